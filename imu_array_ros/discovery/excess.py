"""Observed against expected squared residual: the statistics, by cell, by motion regime and by time.

Input: the normalised residuals ``r = (y - h(theta_hat)) / sigma`` of a fitted model,
(N, K, 6) for N samples, K IMUs and the axes :data:`~imu_array_ros.fusion.residuals.AXES`
(NaN = masked), and their expectation under the model ``E[r^2] = 1 - leverage``
(same shape, NaN where masked).  Every statistic compares an observed sum
``O = sum r^2`` with its expected value ``E = sum E[r^2]`` over a set of readings:

* ratio ``O / E`` (1: the model explains the readings to the noise level);
* ``z = (O - E) / sqrt(2 E)``, the chi-square approximation (the variance of a
  sum of squared N(0, v) is ``2 sum v^2 <= 2 E``, so z is slightly conservative).
  A cell (IMU k, axis a) is *significant* when ``z > z_threshold`` and ``ratio > 1.05``.

The sums are split

* by **regime** of the fitted motion m = [omega, omega_dot, s] (array frame): still
  (|omega| < still_threshold), moving (the rest), fast_rotation (moving and |omega|
  above the 75th percentile of the moving samples), high_angular_acceleration
  (|omega_dot| above the 75th percentile of the moving samples), high_specific_force
  (| |s| - g | > 0.3 g) and near_saturation (the reading itself flagged near its range);
* by **time**, in windows of ``window_s`` seconds (significant windows merged into spans).

By frequency: :mod:`~imu_array_ros.discovery.spectra`; by geometry:
:mod:`~imu_array_ros.discovery.rigid`; all together: :func:`~imu_array_ros.discovery.locate.localize`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["REGIMES", "MIN_RATIO", "excess_ratio", "excess_z", "is_significant", "regime_masks", "regime_sums",
           "window_sums", "merge_spans"]

REGIMES = ("still", "moving", "fast_rotation", "high_angular_acceleration", "high_specific_force", "near_saturation")

#: a significant cell also needs its ratio above this
MIN_RATIO = 1.05


def excess_ratio(o, e):
    """O / E elementwise (NaN where E <= 0)."""
    o, e = np.asarray(o, dtype=float), np.asarray(e, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(e > 0, o / np.where(e > 0, e, 1.0), np.nan)


def excess_z(o, e):
    """(O - E) / sqrt(2 E) elementwise (NaN where E <= 0)."""
    o, e = np.asarray(o, dtype=float), np.asarray(e, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(e > 0, (o - e) / np.sqrt(2.0 * np.where(e > 0, e, 1.0)), np.nan)


def is_significant(o, e, z_threshold):
    """Bool: z > z_threshold and ratio > MIN_RATIO (False where E = 0)."""
    z, ratio = excess_z(o, e), excess_ratio(o, e)
    return (np.nan_to_num(z, nan=-np.inf) > z_threshold) & (np.nan_to_num(ratio, nan=0.0) > MIN_RATIO)


# --------------------------------------------------------------------------- regimes


def regime_masks(motion: np.ndarray, still_threshold: float, gravity: float) -> dict[str, np.ndarray]:
    """Regime -> (N,) bool from the fitted motion (N, 9); NaN rows belong to no regime."""
    m = np.asarray(motion, dtype=float)
    finite = np.isfinite(m).all(axis=1)
    wn = np.where(finite, np.linalg.norm(np.nan_to_num(m[:, 0:3]), axis=1), np.nan)
    wd = np.where(finite, np.linalg.norm(np.nan_to_num(m[:, 3:6]), axis=1), np.nan)
    sn = np.where(finite, np.linalg.norm(np.nan_to_num(m[:, 6:9]), axis=1), np.nan)
    still = finite & (np.nan_to_num(wn, nan=np.inf) < still_threshold)
    moving = finite & ~still
    if moving.any():
        w75, d75 = np.percentile(wn[moving], 75), np.percentile(wd[moving], 75)
        fast = moving & (np.nan_to_num(wn, nan=-np.inf) > w75)
        angacc = finite & (np.nan_to_num(wd, nan=-np.inf) > d75)
    else:
        fast = angacc = np.zeros(len(m), dtype=bool)
    force = finite & (np.abs(np.nan_to_num(sn, nan=gravity) - gravity) > 0.3 * gravity)
    return {"still": still, "moving": moving, "fast_rotation": fast, "high_angular_acceleration": angacc,
            "high_specific_force": force}


def regime_sums(r2: np.ndarray, ev: np.ndarray, valid: np.ndarray, masks: dict[str, np.ndarray],
                near_saturation: np.ndarray | None) -> tuple[dict, dict, dict]:
    """Per regime: observed (K, 6), expected (K, 6) and number of samples with a valid reading.

    r2, ev: (N, K, 6) squared residuals and E[r^2], 0 where not ``valid``; masks: :func:`regime_masks`;
    near_saturation: (N, K, 6) bool or None (then the near_saturation regime is empty).
    """
    n, k = r2.shape[:2]
    reg_o, reg_e, reg_n = {}, {}, {}
    for regime, m in masks.items():
        reg_o[regime] = np.einsum("n,nka->ka", m.astype(float), r2)
        reg_e[regime] = np.einsum("n,nka->ka", m.astype(float), ev)
        reg_n[regime] = int(np.count_nonzero(m & valid.any(axis=(1, 2))))
    if near_saturation is not None:
        sat = np.asarray(near_saturation, dtype=bool).reshape(n, k, 6) & valid
        reg_o["near_saturation"] = np.where(sat, r2, 0.0).sum(axis=0)
        reg_e["near_saturation"] = np.where(sat, ev, 0.0).sum(axis=0)
        reg_n["near_saturation"] = int(np.count_nonzero(sat.any(axis=(1, 2))))
    else:
        reg_o["near_saturation"] = np.zeros((k, 6))
        reg_e["near_saturation"] = np.zeros((k, 6))
        reg_n["near_saturation"] = 0
    return reg_o, reg_e, reg_n


# --------------------------------------------------------------------------- time windows


def window_sums(t: np.ndarray, r2: np.ndarray, ev: np.ndarray, window_s: float):
    """Sums over windows of ``window_s`` s: (starts (W,) s, observed (W,), expected (W,), observed (W, K),
    expected (W, K)); t (N,) s since the first stamp, r2 and ev as in :func:`regime_sums`."""
    n, k = r2.shape[:2]
    if n:
        widx = np.floor(t / window_s).astype(np.int64)
        widx -= widx.min()
        nw = int(widx.max()) + 1
        o_w = np.bincount(widx, weights=r2.sum(axis=(1, 2)), minlength=nw)
        e_w = np.bincount(widx, weights=ev.sum(axis=(1, 2)), minlength=nw)
        cell = (widx[:, None] * k + np.arange(k)[None]).ravel()
        o_wk = np.bincount(cell, weights=r2.sum(axis=2).ravel(), minlength=nw * k).reshape(nw, k)
        e_wk = np.bincount(cell, weights=ev.sum(axis=2).ravel(), minlength=nw * k).reshape(nw, k)
        starts = np.arange(nw) * float(window_s)
    else:
        o_w = e_w = starts = np.zeros(0)
        o_wk = e_wk = np.zeros((0, k))
    return starts, o_w, e_w, o_wk, e_wk


def merge_spans(starts: np.ndarray, flags: np.ndarray, window_s: float) -> list[tuple[float, float]]:
    """Merge runs of flagged windows into (t0, t1) s."""
    out = []
    idx = np.flatnonzero(flags)
    if len(idx) == 0:
        return out
    breaks = np.flatnonzero(np.diff(idx) > 1)
    first = np.concatenate([[idx[0]], idx[breaks + 1]])
    last = np.concatenate([idx[breaks], [idx[-1]]])
    return [(float(starts[a]), float(starts[b] + window_s)) for a, b in zip(first, last)]
