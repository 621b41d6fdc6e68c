"""Small batched linear algebra on stacks of matrices, with one matrix per sample.

* symmetric 3x3 matrices (..., 3, 3): :func:`inv_sym3`, :func:`solve_sym3` by
  cofactors, with a flag for where the matrix is not numerically positive definite;
* symmetric 6x6 matrices (M, 6, 6): :func:`inv_spd6`, a Cholesky written out
  entry by entry over all M matrices at once, with a conditioning test;
* rows times shared-or-stacked matrices: :func:`row_times`, :func:`take_rows`;
* :data:`BLOCK`, the rows per block of the blocked products (their buffers stay in cache).

No Python loop over the matrices: every function works on the whole stack.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BLOCK", "inv_sym3", "solve_sym3", "inv_spd6", "row_times", "take_rows"]

#: rows per block of the blocked products (masked sums, covariance): their buffers stay in cache
BLOCK = 512


def _cofactors_sym3(h: np.ndarray):
    """Cofactors ``(c00, c01, c02, c11, c12, c22)`` and determinant of symmetric 3x3 ``h`` (..., 3, 3), each (...)."""
    a, b, c = h[..., 0, 0], h[..., 0, 1], h[..., 0, 2]
    d, e, f = h[..., 1, 1], h[..., 1, 2], h[..., 2, 2]
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    c11 = a * f - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    det = a * c00 + b * c01 + c * c02
    return (c00, c01, c02, c11, c12, c22), det


def _positive_definite(h: np.ndarray, det: np.ndarray) -> np.ndarray:
    """True where symmetric 3x3 ``h`` is numerically positive definite: det > 1e-12 * diagonal product."""
    diag = h[..., 0, 0] * h[..., 1, 1] * h[..., 2, 2]
    return (det > 1e-12 * diag) & (diag > 0) & np.isfinite(det)


def inv_sym3(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of symmetric 3x3 matrices (..., 3, 3) by cofactors.

    Returns ``(inverse, ok)``; ``ok`` is False where ``h`` is not numerically
    positive definite (the inverse there is inf/nan and must not be used).
    """
    (c00, c01, c02, c11, c12, c22), det = _cofactors_sym3(h)
    out = np.empty_like(h)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / det
        out[..., 0, 0] = c00 * inv_det
        out[..., 0, 1] = out[..., 1, 0] = c01 * inv_det
        out[..., 0, 2] = out[..., 2, 0] = c02 * inv_det
        out[..., 1, 1] = c11 * inv_det
        out[..., 1, 2] = out[..., 2, 1] = c12 * inv_det
        out[..., 2, 2] = c22 * inv_det
    return out, _positive_definite(h, det)


def solve_sym3(h: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``h x = r`` for symmetric 3x3 ``h`` (..., 3, 3), ``r`` (..., 3).

    Returns ``(x, ok)`` with ``ok`` as in :func:`inv_sym3` (x is 0 where not ok).
    """
    (c00, c01, c02, c11, c12, c22), det = _cofactors_sym3(h)
    ok = _positive_definite(h, det)
    safe = np.where(ok, det, 1.0)
    r0, r1, r2 = r[..., 0], r[..., 1], r[..., 2]
    x = np.stack(
        [c00 * r0 + c01 * r1 + c02 * r2, c01 * r0 + c11 * r1 + c12 * r2, c02 * r0 + c12 * r1 + c22 * r2], axis=-1
    ) / safe[..., None]
    x[~ok] = 0.0
    return x, ok


def row_times(x: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Row vectors times matrices: x (n, i) @ a, with a (i, j) shared or (n, i, j) per row -> (n, j)."""
    if a.ndim == 2:
        return x @ a
    return np.matmul(x[:, None, :], a)[:, 0]


def take_rows(a: np.ndarray, idx) -> np.ndarray:
    """``a`` itself if shared (2-D, (i, j)), else its rows ``idx`` of the stack (n, i, j)."""
    return a if a.ndim == 2 else a[idx]


def inv_spd6(fpp: np.ndarray, max_cond: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of M symmetric 6x6 matrices F_pp (M, 6, 6) and which of them are well conditioned.

    Cholesky ``F_pp = L L^T`` and ``F_pp^-1 = L^-T L^-1`` written out entry by
    entry, each entry a length-M vector (loops over the 6 rows and columns only).
    Well conditioned means: positive diagonal and ``cond(Fn) < max_cond`` for
    ``Fn`` = F_pp scaled to unit diagonal (the test of the fusion's shared
    geometry, there with a dense ``np.linalg.cond``).  That is
    decided from ``max diag(Fn^-1) <= cond(Fn) <= 6 trace(Fn^-1)`` (the largest
    eigenvalue of Fn lies in [1, 6], the smallest in [1/trace(Fn^-1), 1/max diag(Fn^-1)]);
    only samples between the bounds get an exact (SVD) condition number.
    Returns ``(inverse (M, 6, 6), ok (M,) bool)``; the inverse is garbage where not ok.
    """
    a = np.ascontiguousarray(np.moveaxis(fpp, 0, -1))  # (6, 6, M): each entry contiguous over samples
    ok = np.ones(a.shape[-1], dtype=bool)
    lo = [[None] * 6 for _ in range(6)]  # L
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for j in range(6):
            piv = a[j, j] - sum(lo[j][k] * lo[j][k] for k in range(j)) if j else a[j, j].copy()
            ok &= piv > 0
            lo[j][j] = np.sqrt(np.where(piv > 0, piv, 1.0))
            rd = 1.0 / lo[j][j]
            for i in range(j + 1, 6):
                lo[i][j] = (a[i, j] - sum(lo[i][k] * lo[j][k] for k in range(j)) if j else a[i, j]) * rd
        ni = [[None] * 6 for _ in range(6)]  # N = L^-1, lower triangular
        for i in range(6):
            ni[i][i] = 1.0 / lo[i][i]
            for j in range(i):
                ni[i][j] = -sum(lo[i][k] * ni[k][j] for k in range(j, i)) * ni[i][i]
        inv = np.empty((6, 6) + a.shape[2:])
        for i in range(6):
            for j in range(i + 1):
                inv[i, j] = inv[j, i] = sum(ni[k][i] * ni[k][j] for k in range(i, 6))
        d = np.stack([a[i, i] for i in range(6)])  # (6, M)
        inv_n = np.stack([inv[i, i] for i in range(6)]) * d  # diagonal of Fn^-1
        ok &= (d > 0).all(axis=0) & np.isfinite(inv_n).all(axis=0) & (inv_n > 0).all(axis=0)
        lower, upper = inv_n.max(axis=0), 6.0 * inv_n.sum(axis=0)
    unsure = np.flatnonzero(ok & (upper >= max_cond) & (lower < max_cond))
    ok &= lower < max_cond
    if unsure.size:
        scale = np.sqrt(d[:, unsure].T)
        ok[unsure] = np.linalg.cond(fpp[unsure] / (scale[:, :, None] * scale[:, None, :])) < max_cond
    return np.ascontiguousarray(np.moveaxis(inv, -1, 0)), ok


