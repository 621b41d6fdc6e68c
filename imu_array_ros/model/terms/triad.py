"""Physics shared by the accelerometer and gyroscope triad terms (nilsson2014 eq. 1-2).

Not registered itself: ``accelerometer_gain.py``, ``gyroscope_gain.py``, ... each
bind one of these to a sensor and a YAML field.  All act on the sensor-frame
signal x (N, K, 3) of every IMU.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.terms.base import MotionContext, Term

__all__ = ["Gain", "Nonorthogonality", "Misalignment", "Bias", "nonorthogonality_matrix"]


def nonorthogonality_matrix(l: np.ndarray) -> np.ndarray:
    """Unit lower-triangular L of nilsson2014 eq. 1 from ``[l_yz, l_zy, l_zx]``; (..., 3) -> (..., 3, 3).

    ``L = [[1, 0, 0], [l_yz, 1, 0], [l_zy, l_zx, 1]]``.
    """
    l = np.asarray(l, dtype=float)
    out = np.zeros(l.shape[:-1] + (3, 3))
    out[..., 0, 0] = out[..., 1, 1] = out[..., 2, 2] = 1.0
    out[..., 1, 0] = l[..., 0]
    out[..., 2, 0] = l[..., 1]
    out[..., 2, 1] = l[..., 2]
    return out


class Gain(Term):
    """x <- K x, K = diag(gain) (default 1)."""

    order = 40

    def apply(self, x, ctx: MotionContext, sensor):
        return x * self.values[None]

    def d_input(self, x, ctx, sensor):
        return np.broadcast_to(np.eye(3) * self.values[:, None, :], x.shape[:2] + (3, 3))

    def d_params(self, x, ctx, sensor):
        return x[..., :, None] * np.eye(3)


class Nonorthogonality(Term):
    """x <- L x with L unit lower triangular from [l_yz, l_zy, l_zx] rad (default 0)."""

    order = 20

    def apply(self, x, ctx, sensor):
        return np.einsum("kij,nkj->nki", nonorthogonality_matrix(self.values), x)

    def d_input(self, x, ctx, sensor):
        return np.broadcast_to(nonorthogonality_matrix(self.values), x.shape[:2] + (3, 3))

    def d_params(self, x, ctx, sensor):
        out = np.zeros(x.shape + (3,))
        out[..., 1, 0] = x[..., 0]
        out[..., 2, 1] = x[..., 0]
        out[..., 2, 2] = x[..., 1]
        return out


class Misalignment(Term):
    """x <- (I + [xi]x) x, xi (3,) rad: small rotation of the triad vs the reference (default 0)."""

    order = 10

    def apply(self, x, ctx, sensor):
        return x + np.cross(self.values[None], x)

    def d_input(self, x, ctx, sensor):
        return np.broadcast_to(np.eye(3) + skew(self.values), x.shape[:2] + (3, 3))

    def d_params(self, x, ctx, sensor):
        return -skew(x)  # d (xi x x) / d xi = -[x]x


class Bias(Term):
    """x <- x + b (default 0)."""

    order = 50

    def apply(self, x, ctx, sensor):
        return x + self.values[None]

    def d_params(self, x, ctx, sensor):
        return np.broadcast_to(np.eye(3), x.shape + (3,))
