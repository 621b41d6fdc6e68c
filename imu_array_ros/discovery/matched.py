"""Matched-resonance search for a board mode: Lorentzian-weighted coherent statistic on the full-length DFT.

A board mode is one narrowband process that every IMU sees with its own gain (the mode shape), a resonance
of some width B (a few tenths of a Hz to ~2 Hz).  :mod:`~imu_array_ros.discovery.coherent` adds the channels
coherently over top-hat windows of Welch bins at most ~2 Hz wide, each field channel against short running-median
floors and the eigenvalue against its neighbours; :mod:`~imu_array_ros.discovery.bank` over top-hat bands of the
full-length DFT.  Both spend the evidence of a resonance's tails on noise and, near DC, test their widest windows
not at all.  This test weights the bins as the likelihood ratio of a Lorentzian line does and whitens each
accelerometer channel, not each field channel, against its own colour (docs/discovery.md; benchmarks/results/
discovery_generalisation_vibration_64024.md).

**Whitening.**  One DFT of the whole recording per accelerometer channel (IMU x axis, normalised residuals;
Tukey taper ``TAPER``: white unit noise gives E|y|^2 = 1 per bin), divided by the square root of its colour:
its running median of |y|^2 over +- ``FLOOR_HZ`` (every other bin, evaluated every quarter window; symmetric,
shrunk towards DC and Nyquist: the median over a symmetric window is the centre's value for any monotone
spectrum) over its median over the tested bins, where above 1 (not the floor itself: the motion fit's leverage
lowers a channel's level, 0.6-0.9 of the noise, without colouring it).  Whitening only where the colour exceeded
1.5 left a step where a coloured IMU's spectrum crossed 1.5, which passed as a 2 Hz wide mode at 7.4 Hz
(p = 0.0017) on a broadband null of benchmarks/discovery_modes (seed 70513013: 3 of 4 IMUs with Gauss-Markov
noise).  One IMU's coloured
noise is whitened where it is coloured, before it can look coherent across the field channels.

**Channels.**  The whitened spectra on the field basis of :func:`~imu_array_ros.discovery.coherent.field_basis`
(the accelerometer fields no rigid motion makes, smooth over the array; orthonormal), each divided by the square
root of its median |z|^2 over the tested bins / ln 2 (the motion fit's leverage leaves them a little below
unit): white, independent, unit.

**Templates.**  Per full width at half maximum B in ``WIDTHS_HZ`` (at least ``MIN_HWHM_BINS`` bins per half
width), weights w_k = S_k / (S_k + 1) over the bins k within ``SPAN`` half widths of the centre, S_k the
Lorentzian of unit peak (the likelihood-ratio weights of a line at SNR 1 per bin); centres every half a half
width (at least one bin), the template inside [``min_hz``, the last bin below Nyquist].

**Statistic.**  The largest eigenvalue of sum_k w_k z_k z_k^H / sum_k w_k (z: the field channels' spectra; the
mode's channels added with the shape they share), divided by its **local level**: the median of the statistic
over the centres whose templates do not overlap its own, within max(4 B, ``FLOOR_HZ``) of it (near DC and
Nyquist the side there shrinks; at least ``LEVEL_CENTRES`` in all), relative to the null's median, when above
1 -- a misfit coherent over a broad band raises its neighbours as much as itself; a resonance raises itself.

**Null law** (:func:`null_laws`): ``NULL_DRAWS`` white-noise recordings of the same length and accelerometer
channels through the same whitening, basis and scan (fixed seed, cached).  Two laws from the same draws
(:func:`family_p`).  *Bonferroni* (discover's, ``JOINT_LAW`` False): per width a Gumbel law fitted to the draws'
maxima of the scan (its family-wise law: not a count of correlated templates), Bonferroni over the widths; ~5x
conservative on white residuals of 3-field-channel arrays (0-0.25 % realised at 1 %: benchmarks/results/
matched_null_calibration.md, matched_null_calibration_65808.md), from the Bonferroni factor over heavily
overlapping templates and a Gumbel on the raw maxima whose upper tail is heavier than theirs.  *Joint*
(``bonferroni=False``): per width a gamma law matched to the mean and variance of the standardised statistic
(statistic / local level) pooled over the draws' tested centres maps each centre to y = -ln P(gamma >= it),
which puts the widths on one scale and lightens that tail; one Gumbel law fitted to the draws' largest y over all
widths and centres is the family-wise law of the whole scan.  On fresh white draws of 4500 samples it is at
nominal (4, 8 and 32 IMUs: 0.9-1.3 % at 1 %, 0.25-0.5 % at 0.25 %), but on the short nulls of benchmarks/
discovery_modes (motion fitted, 635 and 854 samples) it gave p 0.0015 and 0.0018 (2 of 30 white and broadband
nulls below discover's share 0.0025, the Bonferroni law 0 of 30): liberal on short recordings (a Gumbel from 50
draws of few centres), so not discover's law yet (matched_null_calibration_65808.md).
"""

from __future__ import annotations

import numpy as np
from scipy import signal, special, stats

from imu_array_ros.discovery.spectra import merge_windows

__all__ = ["WIDTHS_HZ", "NULL_DRAWS", "JOINT_LAW", "whitened_fields", "templates", "matched_statistic", "null_laws",
           "family_p", "matched_scan"]

#: resonance widths searched (full width at half maximum, Hz)
WIDTHS_HZ = (0.25, 0.5, 1.0, 2.0)
#: a template reaches this many half widths either side of its centre
SPAN = 3.0
#: at least this many bins per half width (a narrower template is the line tests' business)
MIN_HWHM_BINS = 1.5
#: half width of a channel's running-median floor (its colour), Hz
FLOOR_HZ = 4.0
#: half width of a statistic's local level (at least 4 B), Hz
LEVEL_HZ = 10.0
#: bins either side at least in a channel's running-median floor
MIN_FLOOR_BINS = 8
#: centres at least in a statistic's local level
LEVEL_CENTRES = 8
#: Tukey taper fraction of the full-length DFT
TAPER = 0.1
#: white-noise recordings simulated for the null law of the scan's maximum
NULL_DRAWS = 50
#: discover's law: False the Bonferroni law over widths, True the joint one (module docstring: liberal on short
#: recordings, not the default)
JOINT_LAW = False
#: a line's band: its centre +- this many widths of its smallest-p template (56 % of a Lorentzian's power)
BAND = 0.6

_LAWS: dict = {}


def _spectrum(v: np.ndarray) -> np.ndarray:
    """(F, C) tapered rFFT of v (N, C): white unit noise gives E|y|^2 = 1."""
    win = signal.windows.tukey(len(v), TAPER, sym=False)
    return np.fft.rfft(v * win[:, None], axis=0) / np.sqrt(np.sum(win ** 2))


def _tested_bins(n: int, fs: float, min_hz: float) -> tuple[int, int]:
    f_n = n // 2 + 1
    return max(1, int(np.ceil(min_hz * n / fs))), (f_n - 2 if n % 2 == 0 else f_n - 1)


def whitened_fields(acc: np.ndarray, basis: np.ndarray, fs: float, min_hz: float = 0.5) -> np.ndarray:
    """(F, V) the field channels' spectra of the accelerometer residuals acc (N, 3K; NaN -> 0), each channel
    whitened against its own floor before the projection on ``basis`` (3K, V) (module docstring)."""
    a = np.nan_to_num(np.asarray(acc, dtype=float))
    n = len(a)
    y = _spectrum(a)
    pw = np.abs(y) ** 2
    lo, top = _tested_bins(n, fs, min_hz)
    glob = np.median(pw[lo:top + 1], axis=0)                              # (C,)
    w = max(MIN_FLOOR_BINS, int(FLOOR_HZ * n / fs))
    grid = np.unique(np.concatenate([np.arange(1, top + 1, max(1, w // 4)), [top]]))
    half = np.clip(np.minimum(grid - 1, top - grid), MIN_FLOOR_BINS, w)
    run = np.empty((len(grid), a.shape[1]))
    for m in np.unique(half):  # a symmetric window, shrunk towards DC and Nyquist; every other bin (the taper
        sel = half == m        # correlates neighbours)
        idx = np.clip(grid[sel][:, None] + np.arange(-m, m + 1, 2)[None], 1, top)
        run[sel] = np.median(pw[idx], axis=1)
    bins = np.arange(len(pw))
    floor = np.stack([np.interp(bins, grid, run[:, c]) for c in range(a.shape[1])], axis=1)
    colour = np.maximum(floor / np.maximum(glob[None], 1e-300), 1.0)
    z = (y / np.sqrt(colour)) @ basis
    scale = np.median(np.abs(z[lo:top + 1]) ** 2, axis=0) / np.log(2.0)  # the motion fit's leverage: a bit < 1
    return z / np.sqrt(np.maximum(scale, 1e-300))


def templates(n: int, fs: float, min_hz: float) -> list[dict]:
    """Per width (module docstring): fwhm (Hz), g (span, bins), weights (2 g + 1,), centres (M,) bins, reach
    (level window, bins); widths with too few centres left out."""
    df = fs / n
    lo, top = _tested_bins(n, fs, min_hz)
    out = []
    for fwhm in WIDTHS_HZ:
        hw = 0.5 * fwhm / df
        if hw < MIN_HWHM_BINS:
            continue
        g = int(np.ceil(SPAN * hw))
        k = np.arange(-g, g + 1)
        s = 1.0 / (1.0 + (k / hw) ** 2)
        centres = np.arange(lo + g, top - g + 1, max(1, int(hw // 2)))
        if len(centres) > 2 * LEVEL_CENTRES:
            out.append({"fwhm": fwhm, "g": g, "weights": s / (s + 1.0), "centres": centres,
                        "reach": int(max(4 * fwhm, LEVEL_HZ) / df)})
    return out


def matched_statistic(z: np.ndarray, tmpl: list[dict]) -> list[np.ndarray]:
    """Per template width: (M,) the largest eigenvalue of the weighted cross-spectral matrix of the field
    spectra z (F, V) at each centre, / the weights' sum (before the local level)."""
    g0 = z[:, :, None] * np.conj(z[:, None, :])                         # (F, V, V)
    out = []
    for t in tmpl:
        c, g, w = t["centres"], t["g"], t["weights"]
        a = np.zeros((len(c),) + g0.shape[1:], dtype=complex)
        for j, wk in enumerate(w):
            a += wk * g0[c + j - g]
        out.append(np.linalg.eigvalsh(a)[:, -1] / float(w.sum()))
    return out


def _level(lam: np.ndarray, t: dict, null_median: float) -> tuple[np.ndarray, np.ndarray]:
    """((M,) factor >= 1 the statistic is divided by, (M,) bool tested): the median of lam over the centres whose
    templates do not overlap, within the reach (near DC and Nyquist the side there shrinks; at least
    LEVEL_CENTRES in all), over the null's median, when above 1."""
    m = len(lam)
    st = max(1, int(t["centres"][1] - t["centres"][0]))
    k0 = int(np.ceil((2 * t["g"] + 1) / st))                                  # templates apart
    k1 = k0 + max(t["reach"] // st, LEVEL_CENTRES // 2) - 1
    idx = np.arange(m)
    lo_a, lo_b = np.maximum(idx - k1, 0), np.maximum(idx - k0 + 1, 0)        # [lo_a, lo_b) below
    hi_a, hi_b = np.minimum(idx + k0, m), np.minimum(idx + k1 + 1, m)         # [hi_a, hi_b) above
    count = (lo_b - lo_a) + (hi_b - hi_a)
    tested = count >= LEVEL_CENTRES
    # every window at once: its centres' values (+inf beyond its ends), partitioned (full windows) or sorted
    # (shrunk ones); the median from its own count
    half = k1 - k0 + 1
    full = count == 2 * half
    level = np.ones(m)
    if full.any():
        i = np.flatnonzero(full)
        win = lam[np.concatenate([i[:, None] - k1 + np.arange(half), i[:, None] + k0 + np.arange(half)], axis=1)]
        level[i] = np.mean(np.partition(win, [half - 1, half], axis=1)[:, half - 1:half + 1], axis=1)
    i = np.flatnonzero(tested & ~full)
    if len(i):
        j = np.arange(half)
        below, above = i[:, None] - k1 + j, i[:, None] + k0 + j
        ok = np.concatenate([below >= lo_a[i, None], above < hi_b[i, None]], axis=1)
        vals = np.sort(np.where(ok, lam[np.clip(np.concatenate([below, above], axis=1), 0, m - 1)], np.inf), axis=1)
        c = count[i]
        level[i] = 0.5 * (vals[np.arange(len(i)), (c - 1) // 2] + vals[np.arange(len(i)), c // 2])
    return np.maximum(1.0, level / null_median), tested


def _marginal_y(s: np.ndarray, law: dict) -> np.ndarray:
    """-ln P(one centre's statistic >= s) under a width's marginal gamma law (:func:`null_laws`); where the sf
    underflows, its leading asymptotic term."""
    s = np.asarray(s, dtype=float)
    a, x = law["shape"], s / law["theta"]
    ls = stats.gamma.logsf(s, a, scale=law["theta"])
    far = ~np.isfinite(ls) & (x > 0)
    ls = np.where(far, (a - 1.0) * np.log(np.where(far, x, 1.0)) - x - special.gammaln(a), ls)
    return -ls


def null_laws(n: int, fs: float, basis: np.ndarray, min_hz: float, draws: int = NULL_DRAWS) -> dict:
    """The templates and the null law of the scan's maximum on white accelerometer residuals of n samples through
    the same whitening and basis (3K, V) (fixed seed, cached; module docstring): per width ("laws") the null's
    median statistic, the gamma (shape, theta) of its standardised statistic, the Gumbel (loc, scale) of its
    draws' maxima (the Bonferroni law); "joint": the Gumbel (loc, scale) of the draws'
    largest y over widths and centres."""
    basis = np.ascontiguousarray(basis, dtype=float)
    key = (n, float(fs), float(min_hz), draws, basis.shape, hash(basis.tobytes()))
    if key in _LAWS:
        return _LAWS[key]
    tmpl = templates(n, fs, min_hz)
    rng = np.random.default_rng([n, basis.shape[0], basis.shape[1], 57])
    raw = [matched_statistic(whitened_fields(rng.normal(size=(n, basis.shape[0])), basis, fs, min_hz), tmpl)
           for _ in range(draws)]
    laws, joint = [], np.full(draws, -np.inf)
    for i, t in enumerate(tmpl):
        med = float(np.median(np.concatenate([r[i] for r in raw])))
        std = []
        for r in raw:
            level, tested = _level(r[i], t, med)
            std.append((r[i] / level)[tested])
        pooled = np.concatenate(std)
        mean, var = float(np.mean(pooled)), float(np.var(pooled))
        law = {"fwhm": t["fwhm"], "median": med, "shape": mean * mean / var, "theta": var / mean}
        law["loc"], law["scale"] = (float(v) for v in stats.gumbel_r.fit(np.array([np.max(x) for x in std])))
        joint = np.maximum(joint, [float(np.max(_marginal_y(x, law))) for x in std])
        laws.append(law)
    loc, scale = stats.gumbel_r.fit(joint) if tmpl else (np.nan, np.nan)
    if len(_LAWS) > 32:
        _LAWS.clear()
    _LAWS[key] = {"templates": tmpl, "laws": laws, "joint": {"loc": float(loc), "scale": float(scale)}}
    return _LAWS[key]


def family_p(s: np.ndarray, law: dict, joint: dict | None, widths: int) -> np.ndarray:
    """Family-wise p of standardised statistics s of one width (:func:`null_laws`' "laws" entry): P(the scan's
    largest y over all widths >= y(s)) under the joint law; joint None: the Bonferroni law, the width's own
    Gumbel, Bonferroni over the ``widths`` widths."""
    if joint is None:
        return np.minimum(1.0, widths * stats.gumbel_r.sf(s, law["loc"], law["scale"]))
    return stats.gumbel_r.sf(_marginal_y(s, law), joint["loc"], joint["scale"])


def matched_scan(acc: np.ndarray, basis: np.ndarray, fs: float, alpha: float, *, min_hz: float = 0.5,
                 draws: int = NULL_DRAWS, bonferroni: bool | None = None) -> dict | None:
    """The matched test (module docstring) on the accelerometer residuals acc (N, 3K) sampled at fs Hz, field
    basis (3K, V), family-wise level alpha (bonferroni: the law, :func:`family_p`; None: not ``JOINT_LAW``).  Returns
    freqs (F,) of the full-length DFT, per width ("widths": fwhm -> {"centres", "stat", "level", "p"}; p = 1 where
    not tested) and cands: [(p, band lo Hz, band hi Hz,
    peak Hz, fwhm Hz)] significant at alpha (overlapping or touching templates are one line, with the centre
    +- ``BAND`` x the width of its smallest-p template), sorted by p; None when too short or fewer than 2 field
    channels."""
    acc = np.asarray(acc, dtype=float)
    n = len(acc)
    bonferroni = not JOINT_LAW if bonferroni is None else bonferroni
    if basis.shape[1] < 2 or n < 256 or not np.isfinite(fs) or fs <= 0:
        return None
    law = null_laws(n, float(fs), basis, float(min_hz), draws)
    if not law["templates"]:
        return None
    df = fs / n
    z = whitened_fields(acc, basis, fs, min_hz)
    nw = len(law["templates"])
    out = {"freqs": np.arange(n // 2 + 1) * df, "widths": {}, "cands": []}
    raw = []
    for t, lam, lw in zip(law["templates"], matched_statistic(z, law["templates"]), law["laws"]):
        level, tested = _level(lam, t, lw["median"])
        p = np.where(tested, family_p(lam / level, lw, None if bonferroni else law["joint"], nw), 1.0)
        out["widths"][t["fwhm"]] = {"centres": t["centres"], "stat": lam, "level": level, "p": p}
        hw = int(round(0.5 * t["fwhm"] / df))
        for i in np.flatnonzero(p < alpha):
            ce = int(t["centres"][i])
            raw.append((float(p[i]), ce - hw, ce + hw, ce, t["fwhm"]))
    # overlapping significant templates are one line; its band: centre +- BAND widths of its smallest-p template
    out["cands"] = sorted((pv, max(0.0, (pk - 0.5) * df - BAND * w), (pk + 0.5) * df + BAND * w, pk * df, w)
                          for pv, _, _, pk, w in merge_windows(raw, 0))
    return out
