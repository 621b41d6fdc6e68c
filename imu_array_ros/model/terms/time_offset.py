"""``time_offset``: the sample stamped t was taken at t + offset (per sensor of each IMU).

First order in the offset: x(t + d) = x(t) + d * dx/dt.  Gyroscope: dx/dt = R^T omega_dot
(omega_dot is part of the motion, so this is exact to first order).  Accelerometer:
dx/dt = R^T (s_dot + C_dot p), C_dot = [w_dot]x[w]x + [w]x[w_dot]x + [w_ddot]x, with s_dot
and omega_ddot taken from the motion context (time derivatives of the motion, held fixed
in the Jacobians).  Offsets of a few ms on hand motion keep the neglected second-order
term far below the noise.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.terms.base import Field, MotionContext, Term, register


@register
class TimeOffset(Term):
    name = "time_offset"
    hint = "twist the array with quickly changing angular rate and specific force"
    sensors = ("accelerometer", "gyroscope")
    order = 2
    linear = False  # the accelerometer part needs d s / dt, which is not in the motion
    fields = (Field(("accelerometer", "time_offset"), (), "s"), Field(("gyroscope", "time_offset"), (), "s"))

    def _rate(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        """(N, K, 3) dx/dt in the sensor frame."""
        if sensor == "gyroscope":
            v = np.broadcast_to(ctx.omega_dot[:, None, :], (ctx.n, ctx.k, 3))
        else:
            sd = ctx.specific_force_dot if ctx.specific_force_dot is not None else np.zeros_like(ctx.specific_force)
            v = sd[:, None, :] + np.einsum("nij,kj->nki", ctx.lever_dot, ctx.positions)
        return np.einsum("kji,nkj->nki", ctx.rotations, v)

    def _column(self, sensor: str) -> int:
        return 0 if sensor == "accelerometer" else 1

    def apply(self, x, ctx, sensor):
        return x + self.values[None, :, self._column(sensor), None] * self._rate(ctx, sensor)

    def d_params(self, x, ctx, sensor):
        out = np.zeros(x.shape + (2,))
        out[..., self._column(sensor)] = self._rate(ctx, sensor)
        return out

    def d_positions(self, x, ctx, sensor):
        if sensor == "gyroscope":
            return None
        d = self.values[:, 0]
        return d[None, :, None, None] * np.einsum("kji,njl->nkil", ctx.rotations, ctx.lever_dot)  # d R^T C_dot p / d p

    def d_motion(self, x, ctx, sensor):
        d = self.values[:, self._column(sensor)]
        out = np.zeros(x.shape + (9,))
        rt = ctx.rot_t
        if sensor == "gyroscope":
            out[..., 3:6] = d[None, :, None, None] * rt[None]
            return out
        p = ctx.positions
        sw, swd, sp = skew(ctx.omega)[:, None], skew(ctx.omega_dot)[:, None], skew(p)[None]
        # d(C_dot p)/d omega = -[w_dot]x[p]x - [w_dot x p]x ; d/d omega_dot = -[w x p]x - [w]x[p]x
        d_w = -swd @ sp - skew(np.cross(ctx.omega_dot[:, None], p[None]))
        d_wd = -skew(np.cross(ctx.omega[:, None], p[None])) - sw @ sp
        out[..., 0:3] = d[None, :, None, None] * (rt[None] @ d_w)
        out[..., 3:6] = d[None, :, None, None] * (rt[None] @ d_wd)
        return out
