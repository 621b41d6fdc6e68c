"""``position``: where each accelerometer triad sits in the array frame (skog2016 eq. 1).

The accelerometer chain starts from the specific force at the array origin in
the sensor frame, ``R^T s``; this term adds the lever-arm part, so that
x = R^T f(p) = R^T (s + C p) with C = [omega]x^2 + [omega_dot]x.  Its value is the
position itself (the YAML ``position``), not an offset.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.kinematics import lever_rows_jacobian
from imu_array_ros.model.terms.base import Field, MotionContext, Term, register


@register
class Position(Term):
    name = "position"
    hint = "rotate the array about at least two different axes, with angular acceleration"
    sensors = ("accelerometer",)
    order = 0
    fields = (Field(("position",), (3,), "m"),)

    def apply(self, x, ctx: MotionContext, sensor):
        lever_arm = np.matmul(ctx.lever, self.values.T).transpose(2, 0, 1)  # (K, N, 3): C_n p_k
        return x + np.matmul(lever_arm, ctx.rotations).transpose(1, 0, 2)  # R_k^T C_n p_k

    def d_params(self, x, ctx, sensor):
        return np.matmul(ctx.rot_t[None], ctx.lever[:, None])  # R^T C

    def d_motion(self, x, ctx, sensor):
        # row i of R^T (s + C p) minus the s part (the chain's base): u_i . C p with u_i = R e_i
        p = np.broadcast_to(self.values[:, None, :], ctx.rot_t.shape)
        return lever_rows_jacobian(ctx.omega, ctx.rot_t, p)
