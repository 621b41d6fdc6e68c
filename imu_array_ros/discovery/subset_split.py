"""Candidate carrier sets of a term shared by an unknown set of IMUs, on scopes too large for every subset
(more than :data:`.subset.GAUGE_SEARCH_MAX` IMUs).

With one value v shared by an unknown set C (in each sensor's own frame) and a gauge (the values move together
along the directions B: a value common to the IMUs, absorbed by the motion) or a near-gauge (such a value only
weakly observed: the values' covariance is dominated by it), each IMU's value is, up to the gauge and noise,
either v or 0: once the gauge is taken out, the IMUs form two clusters along v.  So the values are taken across
the exact gauge (their components orthogonal to B) and whitened by their covariance (its symmetric inverse
square root on the identified directions: a near-gauge, a direction of large variance, is shrunk away, each
IMU's noise put to one unit), mapped back to one vector per IMU, projected on their leading direction of
spread (the first principal direction of the centred vectors), sorted, and every contiguous split is a
candidate: G - 1 splits, each side a set (2 (G - 1) candidates, no duplicates).  A projection onto one line
reaches only the sets the clusters separate along it; the candidates are only proposed here, each is then
tested by the same shared-value, gauge-profiled statistic as the exhaustive search
(:func:`.subset.shared_statistics`)."""

from __future__ import annotations

import numpy as np

__all__ = ["split_sets", "whitened_values"]


def whitened_values(d: np.ndarray, cov: np.ndarray, basis: np.ndarray, n_imus: int, p: int, *,
                    rtol: float) -> np.ndarray:
    """(G, p): the changes ``d`` (G p,) across the gauge ``basis`` (G p, r), whitened by their covariance
    ``cov``: Q (Q^T C Q)^{+1/2} Q^T d with Q an orthonormal basis orthogonal to B, parameters first put in a
    common unit per parameter (the median variance over the IMUs that estimate it); directions whose eigenvalue is
    below ``rtol`` times the largest are not identified (the caller's :data:`.subset.EIG_RTOL`)."""
    g = n_imus
    var = np.clip(np.diag(cov), 0.0, None).reshape(g, p)
    known = var > 0
    typical = np.array([np.median(var[known[:, i], i]) if known[:, i].any() else 1.0 for i in range(p)])
    scale = np.tile(np.sqrt(np.where(typical > 0, typical, 1.0)), g)
    x, c = d / scale, cov / np.outer(scale, scale)
    r = basis.shape[1]
    q = np.linalg.svd(basis / scale[:, None], full_matrices=True)[0][:, r:] if r else np.eye(len(d))
    lam, vec = np.linalg.eigh(q.T @ c @ q)
    if lam.size == 0 or lam.max() <= 0:
        return np.zeros((g, p))
    ok = lam > rtol * lam.max()
    y = vec[:, ok] @ ((vec[:, ok].T @ (q.T @ x)) / np.sqrt(lam[ok]))
    return (q @ y).reshape(g, p)


def split_sets(d: np.ndarray, cov: np.ndarray, basis: np.ndarray, n_imus: int, p: int, *, rtol: float) -> np.ndarray:
    """Candidate sets (S, G) bool of "one value shared by C, up to the gauge": both sides of every contiguous
    split of the IMUs sorted along the leading principal direction of their whitened, gauge-free values
    (:func:`whitened_values`)."""
    g = n_imus
    e = whitened_values(d, cov, basis, g, p, rtol=rtol)
    c = e - e.mean(axis=0)
    t = c @ np.linalg.eigh(c.T @ c)[1][:, -1]
    order = np.argsort(t, kind="stable")
    sets = np.zeros((2 * (g - 1), g), dtype=bool)
    for k in range(1, g):
        sets[2 * (k - 1), order[:k]] = True
        sets[2 * (k - 1) + 1, order[k:]] = True
    return np.unique(sets, axis=0)
