"""``gyroscope_g_sensitivity``: the gyroscope reads + G a, a the specific force at that IMU.

Field ``gyroscope.g_sensitivity`` (3, 3) row-major, (rad/s)/(m/s^2); a = R^T f(p) is the
sensor-frame specific force at the IMU's accelerometer position (no time offset), added
after the gain.  The reading depends on the position through a: the model adds that
cross-derivative through :meth:`d_positions`.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.terms.base import Field, MotionContext, Term, register


@register
class GyroscopeGSensitivity(Term):
    name = "gyroscope_g_sensitivity"
    hint = "turn the array through many orientations so the specific force at every gyroscope varies in all directions"
    sensors = ("gyroscope",)
    order = 45
    linear = False
    fields = (Field(("gyroscope", "g_sensitivity"), (3, 3), "(rad/s)/(m/s^2)"),)

    @staticmethod
    def force(ctx: MotionContext) -> np.ndarray:
        """(N, K, 3) a = R^T (s + C p)."""
        return np.einsum("kji,nkj->nki", ctx.rotations, ctx.force_at(ctx.positions))

    def apply(self, x, ctx, sensor):
        return x + np.einsum("kij,nkj->nki", self.values.reshape(-1, 3, 3), self.force(ctx))

    def d_params(self, x, ctx, sensor):
        a = self.force(ctx)
        out = np.zeros(x.shape + (3, 3))
        for i in range(3):
            out[..., i, i, :] = a
        return out.reshape(x.shape + (9,))

    def d_positions(self, x, ctx, sensor):
        """G d a / d p = G R^T C."""
        return np.einsum("kij,kmj,nml->nkil", self.values.reshape(-1, 3, 3), ctx.rotations, ctx.lever,
                         optimize=True)

    def d_motion(self, x, ctx, sensor):
        j = np.einsum("kji,nkjl->nkil", ctx.rotations, ctx.force_jacobian(ctx.positions))
        return np.einsum("kij,nkjl->nkil", self.values.reshape(-1, 3, 3), j)
