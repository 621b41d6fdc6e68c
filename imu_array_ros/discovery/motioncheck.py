"""Does a narrowband excess follow the motion?  The motion-line check of :mod:`~imu_array_ros.discovery.modes`.

Hand twisting is a sum of sinusoids; a library term left out (a gain, a misalignment, a lever arm) leaves in the
residual a linear function of the motion features (omega, omega_dot, s, omega_i omega_j and a constant) at every
frequency of the motion, which a spectral test sees as lines or a band where the motion is strong.  A board mode
has no such relation: the motion it leaks into does not carry it at the frequencies around it.

**Frequency folds.**  The relation is learnt where it is not scored: the band is split into ``m`` folds of at
least ``FOLD_HZ`` and ``MIN_FOLD_BINS`` bins of the recording's DFT (m = 1 for a band narrower than two folds),
and for each fold the residual of the mode's channels is regressed on the features with that fold removed (the
whole spectrum else, the rest of the band included); that regression predicts the residual in the fold from the
features in the fold.  The predictions of the folds add up to the band's; the excess follows the motion when
they hold more than ``MOTION_SHARE`` of the in-band power.  A board mode's in-fold residual is independent of a
relation learnt at other frequencies (different frequencies of a stationary process are uncorrelated), so its
predicted share stays near 0 (or below: the prediction only adds power) whatever the band's width.

With one fold this is the band left out as a whole, the check until b4592a6: learning the relation only outside a
band 1-3 Hz wide at low frequency (the matched test's widest templates) left out most of a hand-twisting
motion's spectrum, and a missing library term's residual there passed as a mode (fresh seed 733850: on 1 of 40
library nulls, 0 of 40 with the folds, the same 22 of 60 modes below 5 Hz found both ways;
benchmarks/results/discovery_modes_motion_folds.md).  Folds of 0.5 Hz were not narrow enough either: on a
recording whose motion held 98 % of its power in 1.2-3.2 Hz, the relation learnt without 1.2-1.9 Hz mispredicted
that fold (share -0.24 in all, 0.94 with folds of 0.25 Hz; the fine Welch bin, 0.49 Hz at 1 kHz, gave 0.53; ad
hoc, development seed 960060 of benchmarks/discovery_modes.py, not the seed scored).  Narrower folds learn the
relation from more of the spectrum; ``MIN_FOLD_BINS`` keeps a board mode's leakage into the bins next to a fold
(the rectangular window correlates neighbouring DFT bins) a small part of it.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.discovery.modeshape import bandpass

__all__ = ["FOLD_HZ", "MIN_FOLD_BINS", "MOTION_SHARE", "line_features", "motion_check"]

#: the excess follows the motion when the relation learnt outside each fold predicts this share of its power
MOTION_SHARE = 0.5
#: narrowest frequency fold of the motion-line check (Hz; the mode search's fine resolution)
FOLD_HZ = 0.25
#: a fold holds at least this many bins of the recording's DFT
MIN_FOLD_BINS = 4


def line_features(motion: np.ndarray) -> np.ndarray:
    """(N, 16) [omega, omega_dot, s, omega_i omega_j, 1] of the fitted motion (N, 9), 0 on NaN rows (but the
    constant)."""
    m = np.asarray(motion, dtype=float)
    mz = np.where(np.isfinite(m).all(axis=1)[:, None], np.nan_to_num(m), 0.0)
    w = mz[:, 0:3]
    return np.concatenate([mz, w[:, [0, 1, 2, 0, 0, 1]] * w[:, [0, 1, 2, 1, 2, 2]], np.ones((len(m), 1))], axis=1)


def _fold_gains(n: int, fs: float, band, fold_hz: float) -> list[np.ndarray]:
    """Per fold the (n // 2 + 1,) gain on the rFFT bins: the band's gain (:func:`bandpass`'s, edges included) on
    the fold's bins, 0 elsewhere; the folds partition the band's support and their gains add up to its gain."""
    e0 = np.zeros(n)
    e0[0] = 1.0
    g = np.fft.rfft(bandpass(e0, fs, band)).real
    lo, hi = float(band[0]), float(band[1])
    m = max(1, int((hi - lo) / max(fold_hz, MIN_FOLD_BINS * fs / n)))
    f = np.fft.rfftfreq(n, 1.0 / fs)
    fold = np.clip(np.searchsorted(np.linspace(lo, hi, m + 1)[1:-1], f, side="right"), 0, m - 1)
    return [np.where(fold == j, g, 0.0) for j in range(m)]


def motion_check(x: np.ndarray, valid: np.ndarray, motion: np.ndarray, fs: float, band,
                 fold_hz: float = FOLD_HZ) -> dict:
    """The check (module docstring) on the mode's channels x (N, C) (normalised residuals; NaN or invalid -> 0),
    valid (N, C) bool, the fitted motion (N, 9), its band (lo, hi) Hz.  Returns checked, follows_motion,
    explained_share (the share of the in-band power the folds' predictions hold), folds, rule."""
    m = np.asarray(motion, dtype=float)
    ok = np.isfinite(m).all(axis=1) & valid.all(axis=1)
    if ok.sum() < 64:
        return {"checked": False, "follows_motion": False, "reason": "too few samples with a motion"}
    n = len(x)
    xz = np.where(valid, np.nan_to_num(x), 0.0)
    feats = line_features(m)
    xs, fsp = np.fft.rfft(xz, axis=0), np.fft.rfft(feats, axis=0)
    y = np.zeros((int(ok.sum()), xz.shape[1]))
    pred = np.zeros_like(y)
    gains = _fold_gains(n, fs, band, fold_hz)
    for h in gains:
        yj = np.fft.irfft(xs * h[:, None], n, axis=0)
        fj = np.fft.irfft(fsp * h[:, None], n, axis=0)
        fo = (feats - fj)[ok]
        scale = np.maximum(np.sqrt(np.mean(fo ** 2, axis=0)), 1e-12)
        beta = np.linalg.lstsq(fo / scale, (xz - yj)[ok], rcond=None)[0]
        y += yj[ok]
        pred += (fj[ok] / scale) @ beta
    power = float(np.sum(y ** 2))
    share = 1.0 - float(np.sum((y - pred) ** 2)) / power if power > 0 else 0.0
    return {"checked": True, "follows_motion": bool(share > MOTION_SHARE), "explained_share": share,
            "folds": len(gains),
            "rule": f"the excess follows the motion when the residual's relation to the motion features, learnt "
                    f"with each fold of the band ({(band[1] - band[0]) / len(gains):.3g} Hz) left out, predicts more than "
                    f"{MOTION_SHARE:.0%} of its in-band power"}
