"""``axis_offsets``: each accelerometer sensing axis at its own point (the "size effect").

Row i of the (3, 3) value is the offset of axis i's proof mass from ``position``,
in the sensor frame, m.  Axis i reads the specific force at p + R o_i:
x_i += e_i^T R^T C R o_i, exact because f(r) = s + C r is affine in r.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.kinematics import lever_rows_jacobian
from imu_array_ros.model.terms.base import Field, MotionContext, Term, register


@register
class AxisOffsets(Term):
    name = "axis_offsets"
    hint = "rotate the array fast about all three axes, and do not fit axis offsets together with positions"
    sensors = ("accelerometer",)
    order = 1
    fields = (Field(("accelerometer", "axis_offsets"), (3, 3), "m"),)

    def _m(self, ctx: MotionContext) -> np.ndarray:
        """(N, K, 3, 3) R^T C R."""
        return np.einsum("kji,njl,klm->nkim", ctx.rotations, ctx.lever, ctx.rotations, optimize=True)  # 8x: pairwise

    def apply(self, x, ctx, sensor):
        o = self.values.reshape(-1, 3, 3)
        return x + np.einsum("nkij,kij->nki", self._m(ctx), o)

    def d_params(self, x, ctx, sensor):
        m = self._m(ctx)
        out = np.zeros(x.shape + (3, 3))
        for i in range(3):
            out[..., i, i, :] = m[..., i, :]
        return out.reshape(x.shape + (9,))

    def d_motion(self, x, ctx, sensor):
        o = self.values.reshape(-1, 3, 3)
        r = np.einsum("kij,kaj->kai", ctx.rotations, o)  # (K, 3 axes, 3) array-frame offsets R o_a
        # axis a reads u_a . C r_a, u_a = R e_a (the lever part of f(r_a); s is the chain's base)
        return lever_rows_jacobian(ctx.omega, ctx.rot_t, r)
