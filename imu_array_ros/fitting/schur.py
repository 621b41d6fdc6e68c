"""The batched algebra of the Schur step: per-sample Cholesky factors of A_n, the per-IMU blocks of C
and the stacked G_n = L_n^-1 B_n (theory and notation: :mod:`imu_array_ros.fitting`)."""

from __future__ import annotations

import numpy as np

__all__ = ["MOTION_RTOL", "gram", "factor", "inverse_lower", "per_imu", "accumulate_c", "g_per_imu", "stacked_g"]

#: smallest eigenvalue of a sample's scaled motion information (A_n) for its motion to count as identified
MOTION_RTOL = 1e-10


def gram(jx: np.ndarray) -> np.ndarray:
    """(n, K, 6, d) -> A_n = J_x^T J_x (n, d, d)."""
    j = jx.reshape(len(jx), -1, jx.shape[-1])
    return np.matmul(j.transpose(0, 2, 1), j)


def factor(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """L^-1 of A = L L^T for each (n, d, d) matrix, ok (n,): numerically positive definite, and exact (n,): the
    Gauss-Newton step L^-T L^-1 g is the exact one (ok, or ok but for coordinates no reading informs).

    Jacobi-scaled first (A = D An D); where An's smallest eigenvalue is below
    ``MOTION_RTOL`` the sample does not identify its motion: ok is False (such
    samples are dropped after the initial motion fit, weight 0).  A coordinate
    no reading informs (a zero diagonal: e.g. the reading rate of an axis whose
    gyroscopes all saturate) is held, a unit diagonal on it alone, so that the
    sample's other coordinates get their exact step when they identify
    themselves (exact; a sample nothing informs is not); otherwise a ridge (An + I) keeps the factor finite.
    """
    diag = np.einsum("nii->ni", a)
    d = np.sqrt(diag)
    d = np.where(d > 0, d, 1.0)
    an = a / (d[:, :, None] * d[:, None, :])
    empty = diag <= 0
    ok = ~empty.any(axis=1)  # a coordinate no reading informs (e.g. a dropped sample): not identified
    rest = np.flatnonzero(ok)
    if not _all_above(an[rest], MOTION_RTOL):  # some sample is not identified: which ones
        ok[rest] = np.linalg.eigvalsh(an[rest])[:, 0] > MOTION_RTOL
    exact = ok.copy()
    part = np.flatnonzero(empty.any(axis=1) & ~empty.all(axis=1))  # informed, but not on every coordinate
    if part.size:  # the empty coordinates held (a unit diagonal on them alone) where the others identify themselves
        held = an[part] + empty[part][:, :, None] * np.eye(a.shape[-1])
        exact[part] = np.linalg.eigvalsh(held)[:, 0] > MOTION_RTOL
        an[part[exact[part]]] = held[exact[part]]
    an[~exact] += np.eye(a.shape[-1])  # not identified: the ridge
    lower = np.linalg.cholesky(an)
    return inverse_lower(lower) / d[:, None, :], ok, exact


def inverse_lower(low: np.ndarray) -> np.ndarray:
    """L^-1 of every lower-triangular (n, d, d) matrix with a positive diagonal: forward substitution row by row,
    one batched product per row over all n (numpy's inv solves each matrix by LU with its own LAPACK call, ~4x
    slower on discovery's 15 x 15 chunks; equal to rounding)."""
    n, d, _ = low.shape
    out = np.zeros_like(low)
    diag = 1.0 / np.einsum("nii->ni", low)
    for i in range(d):
        out[:, i, i] = diag[:, i]
        if i:
            out[:, i, :i] = -np.matmul(low[:, i:i + 1, :i], out[:, :i, :i])[:, 0] * diag[:, i:i + 1]
    return out


def _all_above(an: np.ndarray, rtol: float) -> bool:
    """Every (d, d) matrix of ``an`` finite with its smallest eigenvalue above ``rtol``: An - rtol I positive
    definite, one batched Cholesky (5x cheaper than eigvalsh)."""
    if not np.isfinite(an).all():
        return False
    try:
        np.linalg.cholesky(an - rtol * np.eye(an.shape[-1]))
    except np.linalg.LinAlgError:
        return False
    return True


def per_imu(jt: np.ndarray) -> np.ndarray:
    """(n, K_fit, 6, P) -> (K_fit, 6 n, P): each IMU's rows over the chunk's samples."""
    return jt.transpose(1, 0, 2, 3).reshape(jt.shape[1], -1, jt.shape[3])


def accumulate_c(cblocks: np.ndarray, gt: np.ndarray, jt: np.ndarray, r: np.ndarray) -> None:
    """C_k += J_t,k^T J_t,k and gt_k += J_t,k^T r_k over the chunk; jt (n, K_fit, 6, P), r (n, K_fit, 6)."""
    jk = per_imu(jt)
    cblocks += np.matmul(jk.transpose(0, 2, 1), jk)
    gt += np.matmul(jk.transpose(0, 2, 1), r.transpose(1, 0, 2).reshape(len(jk), -1, 1))[..., 0]


def g_per_imu(jx: np.ndarray, linv: np.ndarray, jt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, G) per sample and IMU: M_n,k = J_x,k L_n^-T (n, K_fit, 6, d) and G_n,k = M_n,k^T J_t,k
    (n, K_fit, d, P), one batched product over (n, k).

    B_n is block-structured by IMU (B_n,k = J_x,k^T J_t,k), so G_n = L_n^-1 B_n is [G_n,1 ... G_n,K].
    """
    mk = np.matmul(jx, linv.transpose(0, 2, 1)[:, None])  # (n, K_fit, 6, d): rows (L^-1 phi)^T
    gk = np.matmul(mk.transpose(0, 1, 3, 2), jt)  # (n, K_fit, d, P)
    return mk, gk


def stacked_g(jx: np.ndarray, linv: np.ndarray, jt: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """G_n = L_n^-1 B_n stacked over the chunk: (d n, K_fit P), B_n's IMU blocks B_n,k = J_x,k^T J_t,k written side
    by side (n, d, K_fit P), then one (d, d) @ (d, K_fit P) product per sample, already in the stacked layout (the
    :func:`g_per_imu` blocks to rounding, without their transposed copy).  ``out``: a C-contiguous (n, d, K_fit P)
    array to write G into (e.g. the part of :attr:`~imu_array_ros.fitting.problem.Linearization.G` it fills)."""
    n, kf, _, p = jt.shape
    d = jx.shape[-1]
    b = np.empty((n, d, kf, p))
    np.matmul(jx.transpose(0, 1, 3, 2), jt, out=b.transpose(0, 2, 1, 3))
    if out is None:
        out = np.empty((n, d, kf * p))
    np.matmul(linv, b.reshape(n, d, kf * p), out=out)
    return out.reshape(d * n, kf * p)
