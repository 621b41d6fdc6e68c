"""Physics shared by the accelerometer and gyroscope triad terms (nilsson2014 eq. 1-2).

Not registered itself: ``accelerometer_gain.py``, ``gyroscope_gain.py``, ... each
bind one of these to a sensor and a YAML field.  All act on the sensor-frame
signal x (N, K, 3) of every IMU.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.terms.base import MotionContext, Term

__all__ = ["Gain", "Nonorthogonality", "Misalignment", "Bias", "nonorthogonality_matrix", "triad_matrix",
           "decompose_triad", "triads_in_reference_frame", "GAIN_PLAUSIBLE", "ANGLE_PLAUSIBLE", "BIAS_PLAUSIBLE"]

# What a real triad plausibly has (``Field.plausible``; a calibration beyond is refused,
# :mod:`imu_array_ros.calibration.guards`).  Loose on purpose: a datasheet's worst case is a few
# times inside each, so only a fit that absorbed something else gets there.
#: largest |gain - 1| (MEMS scale-factor errors are a few percent)
GAIN_PLAUSIBLE = 0.2
#: largest misalignment / non-orthogonality angle, rad (5.7 deg; package and die errors are < 1 deg)
ANGLE_PLAUSIBLE = 0.1
#: largest |bias| as a fraction of the full-scale range (consumer parts: +-80 mg at +-2 g, +-20 deg/s at
#: +-250 deg/s, both under 10 % of their smallest range)
BIAS_PLAUSIBLE = 0.1


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


def triad_matrix(gain: np.ndarray, l: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """K L (I + [xi]x) (..., 3, 3): the linear map of a triad's gain, non-orthogonality and misalignment."""
    gain, xi = np.asarray(gain, dtype=float), np.asarray(xi, dtype=float)
    return gain[..., :, None] * nonorthogonality_matrix(l) @ (np.eye(3) + skew(xi))


def decompose_triad(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gain, l, xi), each (..., 3), with ``triad_matrix(gain, l, xi) == matrix`` (..., 3, 3); exact.

    Any matrix with a non-zero leading row splits this way (9 = 3 + 3 + 3
    parameters), in closed form row by row: row 0 of M is k_x [1, -xi_z, xi_y];
    rows 0-1 of M (I + [xi]x)^-1 must be lower triangular, which gives xi_x;
    then K L = M (I + [xi]x)^-1.
    """
    m = np.asarray(matrix, dtype=float)
    z = -m[..., 0, 1] / m[..., 0, 0]
    y = m[..., 0, 2] / m[..., 0, 0]
    den = 1.0 + z * z  # [M_10, M_11] = [T_10, T_11] [[1, -z], [z, 1]]
    t10 = (m[..., 1, 0] - m[..., 1, 1] * z) / den
    t11 = (m[..., 1, 0] * z + m[..., 1, 1]) / den
    x = (t10 * y - m[..., 1, 2]) / t11  # M_12 = T_10 xi_y - T_11 xi_x
    xi = np.stack([x, y, z], axis=-1)
    n = np.eye(3) + skew(xi)
    kl = np.swapaxes(np.linalg.solve(np.swapaxes(n, -1, -2), np.swapaxes(m, -1, -2)), -1, -2)  # M N^-1
    gain = np.diagonal(kl, axis1=-2, axis2=-1).copy()
    low = kl / gain[..., :, None]
    return gain, np.stack([low[..., 1, 0], low[..., 2, 0], low[..., 2, 1]], axis=-1), xi


def triads_in_reference_frame(a: np.ndarray, rotations: np.ndarray, ref: int):
    """Triads re-expressed in the array frame that triad ``ref`` defines (its misalignment 0).

    a (K, 3, 3): each triad's linear map from the array frame to its readings
    (K L (I + [xi]x) R_k^T); rotations (K, 3, 3): nominal sensor -> array.
    Returns (omega, gain, l, xi): omega (3, 3) orthogonal with
    a_k omega R_k = K' L' (I + [xi']x) for every k and xi'[ref] = 0, the new
    quantities being s' = omega^T s.  omega is fixed by making the reference's
    a_ref omega R_ref lower triangular with a positive diagonal (an LQ
    decomposition); the split is :func:`decompose_triad`, exact.
    """
    rot_ref = rotations[ref]
    q_t, r_t = np.linalg.qr((a[ref] @ rot_ref).T)  # a_ref R_ref = (Q R)^T = R^T Q^T
    q = (q_t * np.sign(np.diag(r_t))[None, :]).T
    omega = rot_ref @ q.T @ rot_ref.T
    gain, l, xi = decompose_triad(a @ omega @ rotations)
    xi[ref] = 0.0
    return omega, gain, l, xi


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
        # L x written out (L's zeros and ones skipped): the sums of einsum("kij,nkj->nki", L, x) in their order
        l = self.values
        out = np.empty(np.broadcast_shapes(x.shape, (1, len(l), 3)))
        out[..., 0] = x[..., 0]
        np.multiply(l[:, 0], x[..., 0], out=out[..., 1])
        out[..., 1] += x[..., 1]
        np.multiply(l[:, 1], x[..., 0], out=out[..., 2])
        out[..., 2] += l[:, 2] * x[..., 1]
        out[..., 2] += x[..., 2]
        return out

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
