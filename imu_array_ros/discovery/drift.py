"""Drift vs constant: a bias that drifts is tested *given* a constant bias, and told apart from it.

``bias_drift`` adds drift (t - first stamp) to each bias.  Over a recording whose information is spread
evenly in time, the column t and the constant column of a bias correlate 0.87 (the mean of t over its
RMS): a drift alone explains three quarters of a constant bias, and as ``bias_drift`` holds the drifts of
both sensors (6 parameters), an IMU with an accelerometer *and* a gyroscope bias was explained by a drift
first (a lower BIC than either bias alone).  So:

* :func:`candidate_blocks`: the score and information of a candidate per time block; for a term in
  :data:`GIVEN` (``bias_drift``) with the named terms' columns (the same IMU's biases) *profiled out*: the
  test asks "does the bias change in time?", never "is there a bias?".  A constant bias then gives a
  drift no score; a drift still gives one whatever the bias.
* :func:`drift_confounded`: when a bias is found, whether the recording could have told it from a drift
  at all (the bias adds nothing given the drift, the drift nothing given the bias, while the drift alone
  would explain the data): then they are reported as indistinguishable, with why (the canonical
  correlation of their signatures, the time span holding the bias's information, the recording's length).
"""

from __future__ import annotations

import numpy as np
import scipy.stats

__all__ = ["GIVEN", "candidate_blocks", "drift_confounded"]

#: candidate term -> terms whose columns (same IMU) are profiled out of its test
GIVEN = {"bias_drift": ("accelerometer_bias", "gyroscope_bias")}
#: bias term -> the columns of bias_drift that drift it
_DRIFT_COLUMNS = {"accelerometer_bias": slice(0, 3), "gyroscope_bias": slice(3, 6)}
#: share of a bias's information (central) whose time span is reported
_SPAN_SHARE = 0.9


def _index(sb, terms) -> np.ndarray:
    return np.concatenate([np.arange(sb.columns(t).start, sb.columns(t).stop) for t in terms]) if terms else \
        np.zeros(0, dtype=int)


def _profile(g: np.ndarray, S: np.ndarray, d: np.ndarray, b: np.ndarray):
    """(g (B, |d|), S (B, |d|, |d|)) of the columns d per block with the columns b profiled out (the total
    information's regression of d on b, applied to every block: the block sums are the Schur complement)."""
    St = S.sum(axis=0)
    sbb, sbd = St[np.ix_(b, b)], St[np.ix_(b, d)]
    a = np.linalg.lstsq(sbb, sbd, rcond=1e-10)[0]  # (|b|, |d|)
    gd = g[:, d] - g[:, b] @ a
    sdd = S[:, d][:, :, d]
    sdb = S[:, d][:, :, b]
    sd = sdd - sdb @ a - np.swapaxes(sdb @ a, 1, 2) + np.einsum("ji,bjk,kl->bil", a, S[:, b][:, :, b], a)
    return gd, sd


def candidate_blocks(sb, term: str, k: int):
    """(g (B, P), S (B, P, P)) of ``term`` on IMU k: its own columns, or for a term in :data:`GIVEN` with
    those terms' columns profiled out (when ``sb`` scored them)."""
    cols = sb.columns(term)
    given = [t for t in GIVEN.get(term, ()) if t in sb.offsets]
    if not given:
        return sb.g[:, k, cols], sb.S[:, k, cols, cols]
    d, b = np.arange(cols.start, cols.stop), _index(sb, given)
    return _profile(sb.g[:, k], sb.S[:, k], d, b)


def _stat(g: np.ndarray, S: np.ndarray) -> tuple[float, int]:
    """(g^T S^+ g, rank) on the identified directions of S."""
    if S.size == 0:
        return 0.0, 0
    d = np.sqrt(np.clip(np.diag(S), 0.0, None))
    if not np.any(d > 0):
        return 0.0, 0
    d = np.where(d > 0, d, np.inf)
    lam, vec = np.linalg.eigh(S / np.outer(d, d))
    keep = lam > 1e-8 * max(lam.max(), 0.0)
    q = vec[:, keep] / d[:, None]
    z = q.T @ g
    return float(z @ (z / lam[keep])), int(keep.sum())


def _correlation(S: np.ndarray, nb: int) -> float:
    def inv_sqrt(a):
        lam, vec = np.linalg.eigh(a)
        keep = lam > 1e-8 * max(lam.max(), 1e-300)
        return vec[:, keep] / np.sqrt(lam[keep])
    a, b = inv_sqrt(S[:nb, :nb]), inv_sqrt(S[nb:, nb:])
    if a.size == 0 or b.size == 0:
        return float("nan")
    return float(np.clip(np.linalg.svd(a.T @ S[:nb, nb:] @ b, compute_uv=False).max(), 0.0, 1.0))


def _span(info: np.ndarray, block_s: float) -> float:
    """Seconds between the blocks holding the first and last (1 - _SPAN_SHARE) / 2 of ``info`` (B,)."""
    total = info.sum()
    if total <= 0:
        return 0.0
    c = np.cumsum(info) / total
    lo = int(np.searchsorted(c, (1 - _SPAN_SHARE) / 2))
    hi = int(np.searchsorted(c, 1 - (1 - _SPAN_SHARE) / 2))
    return (hi - lo + 1) * block_s


def drift_confounded(sb, best, level: float, block_s: float) -> list[dict]:
    """When ``best`` (a Candidate) is a bias: [dict] naming ``bias_drift`` as indistinguishable from it on
    this recording, or [] when the recording tells them apart (or the drift was not scored).

    With T_b (the bias), T_d (its sensor's drift alone, bias held) and T_bd (both), each chi-square under
    its null: indistinguishable when the drift alone would be significant at ``level``, yet neither adds
    significantly to the other (T_bd - T_d and T_bd - T_b both below the level's critical value)."""
    if getattr(best, "scope", "imu") != "imu" or best.effect not in _DRIFT_COLUMNS or "bias_drift" not in sb.offsets or best.effect not in sb.offsets:
        return []
    cb, cd = sb.columns(best.effect), sb.columns("bias_drift")
    dsl = _DRIFT_COLUMNS[best.effect]
    bi = np.arange(cb.start, cb.stop)
    di = np.arange(cd.start, cd.stop)[dsl]
    idx = np.r_[bi, di]
    g = sb.g[:, best.k][:, idx].sum(axis=0)
    S_blocks = sb.S[:, best.k][:, idx][:, :, idx]
    S = S_blocks.sum(axis=0)
    nb = len(bi)
    t_b, q_b = _stat(g[:nb], S[:nb, :nb])
    t_d, q_d = _stat(g[nb:], S[nb:, nb:])
    t_bd, q_bd = _stat(g, S)
    if q_d == 0 or scipy.stats.chi2.sf(t_d, q_d) >= level:
        return []  # a drift alone would not explain the data: nothing to confuse
    bias_adds = scipy.stats.chi2.sf(max(t_bd - t_d, 0.0), max(q_bd - q_d, 1)) < level
    drift_adds = scipy.stats.chi2.sf(max(t_bd - t_b, 0.0), max(q_bd - q_b, 1)) < level
    if bias_adds or drift_adds:
        return []
    corr = _correlation(S, nb)
    info = np.einsum("bii->b", S_blocks[:, :nb, :nb])
    span = _span(info, block_s)
    duration = len(info) * block_s
    why = (f"why: over this recording a constant and a drifting {best.effect.replace('_', ' ')} leave the same "
           f"signature (canonical correlation {corr:.3f}); duration: {int(_SPAN_SHARE * 100)} % of its information "
           f"lies within {span:.1f} s of the {duration:.1f} s recording; motion: the bias is seen only there. "
           f"Still poses or motion spread over a longer recording would separate them")
    gap = (q_d - q_b) * np.log(max(sb.valid_axes, 2)) - (t_d - t_b)  # BIC(drift alone) - BIC(bias)
    return [{"effect": "bias_drift", "delta_bic_gap": float(gap), "added_statistic": float(t_bd - t_b),
             "correlation": corr, "reason": f"indistinguishable ({why}); reported as {best.effect} (the simpler)",
             "statistics": {"bias": t_b, "drift": t_d, "both": t_bd}}]
