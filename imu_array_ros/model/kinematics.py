"""Rigid-body kinematics of an inertial sensor array (skog2016 eq. 1-2).

The specific force sensed at position ``r`` of a rigid body is

    s_r = s + omega x (omega x r) + omega_dot x r                 (skog2016 eq. 1)
        = s + Omega_w^2 r - Omega_r omega_dot                      (eq. 2)

with ``s`` the specific force at the array origin and ``Omega_a`` the skew
matrix of ``a``.  Everything is batched over leading axes.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "skew",
    "specific_force_at",
    "quadratic_monomials",
    "quadratic_monomials_jacobian",
    "centripetal_matrix",
    "euler_matrix",
    "lever_rows_jacobian",
]


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices ``[v]x`` with ``[v]x b = v x b``; (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def specific_force_at(s: np.ndarray, omega: np.ndarray, omega_dot: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Specific force at positions ``r`` (skog2016 eq. 1).

    s, omega, omega_dot: (N, 3) in the array frame; r: (K, 3) m.
    Returns (N, K, 3) m/s^2 in the array frame.
    """
    s = np.asarray(s, dtype=float)[:, None, :]
    w = np.asarray(omega, dtype=float)[:, None, :]
    wd = np.asarray(omega_dot, dtype=float)[:, None, :]
    r = np.asarray(r, dtype=float)[None, :, :]
    wxr = np.cross(w, r)
    return s + np.cross(w, wxr) + np.cross(wd, r)


def quadratic_monomials(omega: np.ndarray) -> np.ndarray:
    """q(omega) = [wx^2, wy^2, wz^2, wx wy, wx wz, wy wz]; (..., 3) -> (..., 6).

    The centripetal term is linear in q: ``Omega_w^2 r = centripetal_matrix(r) @ q``.
    """
    w = np.asarray(omega, dtype=float)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    return np.stack([x * x, y * y, z * z, x * y, x * z, y * z], axis=-1)


def quadratic_monomials_jacobian(omega: np.ndarray) -> np.ndarray:
    """dq/domega, (..., 3) -> (..., 6, 3)."""
    w = np.asarray(omega, dtype=float)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    out = np.zeros(w.shape[:-1] + (6, 3))
    out[..., 0, 0] = 2 * x
    out[..., 1, 1] = 2 * y
    out[..., 2, 2] = 2 * z
    out[..., 3, 0] = y
    out[..., 3, 1] = x
    out[..., 4, 0] = z
    out[..., 4, 2] = x
    out[..., 5, 1] = z
    out[..., 5, 2] = y
    return out


def centripetal_matrix(r: np.ndarray) -> np.ndarray:
    """M(r) with ``Omega_w^2 r = omega x (omega x r) = M(r) q(omega)``; (..., 3) -> (..., 3, 6)."""
    r = np.asarray(r, dtype=float)
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    out = np.zeros(r.shape[:-1] + (3, 6))
    out[..., 0, 1] = -x
    out[..., 0, 2] = -x
    out[..., 0, 3] = y
    out[..., 0, 4] = z
    out[..., 1, 0] = -y
    out[..., 1, 2] = -y
    out[..., 1, 3] = x
    out[..., 1, 5] = z
    out[..., 2, 0] = -z
    out[..., 2, 1] = -z
    out[..., 2, 4] = x
    out[..., 2, 5] = y
    return out


def euler_matrix(r: np.ndarray) -> np.ndarray:
    """G(r) = -Omega_r with ``omega_dot x r = G(r) omega_dot`` (skog2016 eq. 3); (..., 3) -> (..., 3, 3)."""
    return -skew(r)


def lever_rows_jacobian(omega: np.ndarray, u: np.ndarray, r: np.ndarray) -> np.ndarray:
    """d (u . C r) / d [omega, omega_dot, s] with C = [omega]x^2 + [omega_dot]x (the lever-arm part of skog2016
    eq. 1, no s part: zeros), for rows u and points r (K, A, 3) of every sample's omega (N, 3): (N, K, A, 9).

    Closed form, no 3x3 products: omega x (omega x r) = omega (omega . r) - r |omega|^2 gives
    u^T d/d omega = (omega . r) u^T + (omega . u) r^T - 2 (u . r) omega^T, and u . (omega_dot x r) gives
    d/d omega_dot = (r x u)^T, the same for every sample.  Equal to u^T of
    :meth:`~imu_array_ros.model.terms.base.MotionContext.force_jacobian` to rounding."""
    omega = np.asarray(omega, dtype=float)
    k, a = u.shape[:2]
    n = len(omega)
    wr = (omega @ r.reshape(-1, 3).T).reshape(n, k, a, 1)
    wu = (omega @ u.reshape(-1, 3).T).reshape(n, k, a, 1)
    out = np.zeros((n, k, a, 9))
    np.multiply(wr, u, out=out[..., 0:3])
    out[..., 0:3] += wu * r
    out[..., 0:3] -= (2.0 * np.sum(u * r, axis=-1))[..., None] * omega[:, None, None, :]
    out[..., 3:6] = np.cross(r, u)
    return out
