"""A narrowband mode's shape across the array, when it is present, and its empirical model (held out).

Helpers of :mod:`~imu_array_ros.discovery.modes`:

* :func:`bandpass`: zero-phase band-limiting of the columns in the frequency domain;
* :func:`describe_shape`: the mode's amplitude across the array fitted by simple spatial patterns;
* :func:`presence`: the share of time blocks where the line is present, in still and moving blocks, the regime;
* :func:`heldout_model`: the empirical model -- one narrowband process seen by every channel of the mode
  with its own complex gain (the mode shape) -- fitted on half of the time blocks and scored on the other
  half: each channel predicted from the *other* channels' band-limited signals.
"""

from __future__ import annotations

import numpy as np
from scipy import signal, stats

__all__ = ["bandpass", "describe_shape", "presence", "heldout_model", "BLOCK_S", "SHAPE_R2"]

#: time blocks of presence and of the held-out split
BLOCK_S = 2.0
#: a spatial pattern describes the shape when its R^2 reaches this
SHAPE_R2 = 0.8
#: per-block false-alarm level of "present"
PRESENCE_LEVEL = 0.01
#: width of the band edges of the band-limiting (Hz)
EDGE_HZ = 0.1


def _gain(n: int, fs: float, band) -> np.ndarray:
    """(n // 2 + 1,) real gain of :func:`bandpass` on the rFFT bins: 1 in the band, raised-cosine edges of
    EDGE_HZ (at least two FFT bins) outside it."""
    f = np.fft.rfftfreq(n, 1.0 / fs)
    lo, hi = max(float(band[0]), 0.0), min(float(band[1]), fs / 2)
    w = max(EDGE_HZ, 2.0 * fs / max(n, 1))
    dist = np.maximum(lo - f, f - hi)
    return np.where(dist <= 0, 1.0, np.where(dist < w, 0.5 * (1.0 + np.cos(np.pi * dist / w)), 0.0))


def bandpass(y: np.ndarray, fs: float, band) -> np.ndarray:
    """y (N, ...) band-limited to ``band`` (lo, hi) Hz along axis 0 (NaN must be zeroed first): zero phase, in
    the frequency domain (rFFT x :func:`_gain`), exact however narrow the band is against the rate."""
    y = np.asarray(y, dtype=float)
    n = len(y)
    if n < 8:
        return np.zeros_like(y)
    g = _gain(n, fs, band).reshape((-1,) + (1,) * (y.ndim - 1))
    return np.fft.irfft(np.fft.rfft(y, axis=0) * g, n, axis=0)


def noise_bandwidth(n: int, fs: float, band) -> float:
    """Equivalent noise bandwidth (Hz) of :func:`bandpass` on n samples: sum of the squared gain x fs / n."""
    return float(np.sum(_gain(n, fs, band) ** 2) * fs / n)


def _blocks(n: int, fs: float) -> np.ndarray:
    size = max(int(round(BLOCK_S * fs)), 32)
    return np.arange(n) // size


def presence(y: np.ndarray, valid: np.ndarray, floor: np.ndarray, fs: float, band, still=None) -> dict:
    """When the line is there: y (N, C) band-passed residuals of the mode's channels, floor (C,) their relative
    PSD floor at the line.  Per time block of BLOCK_S: sum y^2 over the channels against the noise it would
    hold (floor x noise bandwidth / (fs / 2)), "present" beyond the chi-square at PRESENCE_LEVEL (2 B T
    degrees of freedom per channel).  still (N,) bool: blocks >= 80 % still are "still", <= 20 % "moving".
    regime: still / moving when the in-band excess per block there is >= 2x the other's, else all."""
    n, c = y.shape
    blocks = _blocks(n, fs)
    nb = int(blocks[-1]) + 1 if n else 0
    enbw = noise_bandwidth(n, fs, band)
    expect_per = np.nan_to_num(floor, nan=1.0) * enbw / (fs / 2)                  # (C,) variance per sample
    y2 = np.where(valid, y, 0.0) ** 2 / np.where(expect_per > 0, expect_per, 1.0)[None]
    obs = np.bincount(blocks, weights=y2.sum(axis=1), minlength=nb)
    cnt = np.bincount(blocks, weights=valid.sum(axis=1).astype(float), minlength=nb)
    secs = np.bincount(blocks, minlength=nb) / fs
    dof = np.maximum(2.0 * enbw * secs * c, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = obs / cnt
    limit = stats.chi2.isf(PRESENCE_LEVEL, dof) / dof
    present = (cnt > 0) & (ratio > limit)
    out = {"block_s": BLOCK_S, "blocks": nb, "fraction_present": float(present[cnt > 0].mean()) if (cnt > 0).any()
           else 0.0, "in_band_ratio": float(np.nansum(obs) / max(np.nansum(cnt), 1.0))}
    regime = "all"
    if still is not None:
        s = np.bincount(blocks, weights=np.asarray(still, dtype=float)[:n], minlength=nb) / np.maximum(
            np.bincount(blocks, minlength=nb), 1)
        sb, mb = (s >= 0.8) & (cnt > 0), (s <= 0.2) & (cnt > 0)
        ex = {}
        for name, sel in (("still", sb), ("moving", mb)):
            out[f"blocks_{name}"] = int(sel.sum())
            out[f"fraction_present_{name}"] = float(present[sel].mean()) if sel.any() else None
            ex[name] = float(np.nanmean(ratio[sel]) - 1.0) if sel.any() else None
            out[f"in_band_ratio_{name}"] = ex[name] + 1.0 if ex[name] is not None else None
        if ex["still"] is not None and ex["moving"] is not None:
            if ex["moving"] > 0 and ex["moving"] >= 2.0 * max(ex["still"], 0.0):
                regime = "moving"
            elif ex["still"] > 0 and ex["still"] >= 2.0 * max(ex["moving"], 0.0):
                regime = "still"
    out["regime"] = regime
    return out


def describe_shape(mode, positions, rotations) -> dict:
    """The mode's amplitude across the array: per IMU, the accelerometer (else gyroscope) complex amplitude
    rotated to the array frame (needs rotations; else the sensor frames), projected on its dominant direction
    and phase -> a signed scalar s_k; fitted by least squares with uniform (1), distance from the centre (|p|),
    rigid / affine (1, x, y, z) and quadratic plate (1, x, y, x^2, xy, y^2) patterns (only patterns with fewer
    parameters than IMUs - 2); R^2 of each (share of sum s_k^2 explained), "best": among those reaching
    SHAPE_R2 the one of least AICc (K log(RSS / K) + 2 p + 2 p (p + 1) / (K - p - 1)), else "irregular"."""
    amp = np.nan_to_num(mode.amplitude_si if np.isfinite(mode.amplitude_si[:, :3]).any() else mode.amplitude)
    z = amp * np.exp(1j * np.nan_to_num(mode.phase))
    k = z.shape[0]
    sensor = "accelerometer" if np.sum(np.abs(mode.amplitude[:, :3]) ** 2) >= np.sum(np.abs(mode.amplitude[:, 3:]) ** 2) \
        else "gyroscope"
    v = z[:, :3] if sensor == "accelerometer" else z[:, 3:]
    if rotations is not None:
        v = np.einsum("kij,kj->ki", np.asarray(rotations, dtype=float), v)
    cov = np.real(np.einsum("ki,kj->ij", v, np.conj(v)))
    d = np.linalg.eigh(cov)[1][:, -1]
    proj = v @ d                                                    # (K,) complex
    phi = 0.5 * np.angle(np.sum(proj ** 2))                          # the phase making it most real
    s = np.real(proj * np.exp(-1j * phi))
    s = s * np.sign(s[np.argmax(np.abs(s))]) if np.any(s) else s
    out = {"sensor": sensor, "direction_array_frame": d.tolist(), "signed_amplitude": s.tolist(),
           "real_fraction": float(np.sum(s ** 2) / max(np.sum(np.abs(proj) ** 2), 1e-300)), "fits": {}, "best": None}
    if positions is None or k < 3:
        return out
    p = np.asarray(positions, dtype=float) - np.mean(positions, axis=0)
    x, y, zc = p[:, 0], p[:, 1], p[:, 2]
    one = np.ones(k)
    pats = [("uniform", [one]), ("distance from centre", [np.linalg.norm(p, axis=1)]),
            ("rigid / affine", [one, x, y, zc]), ("quadratic plate", [one, x, y, x * x, x * y, y * y])]
    ss0 = float(np.sum(s ** 2))
    best, best_aic = None, np.inf
    for name, cols in pats:
        a = np.column_stack(cols)
        rank = int(np.linalg.matrix_rank(a))
        if rank > k - 3 or ss0 <= 0:
            continue
        coef = np.linalg.lstsq(a, s, rcond=None)[0]
        res = float(np.sum((s - a @ coef) ** 2))
        r2 = 1.0 - res / ss0
        out["fits"][name] = {"r2": float(r2), "parameters": rank}
        aic = k * np.log(max(res, 1e-12 * ss0) / k) + 2 * rank + 2 * rank * (rank + 1) / max(k - rank - 1, 1)
        if r2 >= SHAPE_R2 and aic < best_aic:
            best, best_aic = name, aic
    out["best"] = best
    out["best"] = out["best"] or "irregular"
    return out


def heldout_model(x: np.ndarray, y: np.ndarray, valid: np.ndarray, fs: float, n: int) -> dict:
    """Empirical model of the mode and its held-out gain.  x (N, C) residuals of the mode's channels (0 where
    masked), y (N, C) the same band-passed.  The analytic signal Z = y + i H(y); on the training blocks the
    mode shape g = leading eigenvector of Z^H Z; on the held-out blocks channel c is predicted as
    Re(g_c x_-c), x_-c = the projection of the other channels on g (leave-one-channel-out).  Two folds (even /
    odd time blocks of BLOCK_S); sum of squared residuals before and after on the held-out blocks."""
    c = x.shape[1]
    if c < 2:
        return {"method": "none: a single channel carries the mode (nothing to predict it from)",
                "improves_heldout": False}
    z = signal.hilbert(y, axis=0)
    half = (_blocks(n, fs) % 2).astype(bool)
    before = after = 0.0
    for train in (half, ~half):
        test = ~train
        g = np.linalg.eigh(z[train].conj().T @ z[train])[1][:, -1]
        proj = z[test] @ g.conj()                                   # (Nt,)
        others = proj[:, None] - z[test] * g.conj()[None]
        w = 1.0 - np.abs(g) ** 2
        pred = np.real(np.where(w > 0.05, g[None] * others / np.where(w > 0.05, w, 1.0)[None], 0.0))
        v = valid[test]
        before += float(np.sum(np.where(v, x[test], 0.0) ** 2))
        after += float(np.sum(np.where(v, x[test] - pred, 0.0) ** 2))
    n_read = float(valid.sum())
    return {"method": "one narrowband process seen by every channel of the mode with its own complex gain (the "
                      "mode shape), fitted on alternate 2 s blocks, each channel predicted from the other channels' "
                      "band-limited signals on the held-out blocks",
            "heldout_sum_r2_before": before, "heldout_sum_r2_after": after,
            "ratio_after_before": after / before if before > 0 else None,
            "heldout_delta_loglik": 0.5 * (before - after), "readings": n_read,
            "improves_heldout": bool(after < before)}
