"""Template-bank search for a board mode on the full-length DFT, with the family-wise law of its maximum simulated.

The alternative to :mod:`~imu_array_ros.discovery.coherent` (Welch segments, nested short running-median
floors, Bonferroni over every overlapping window): the same channels (the accelerometer fields no rigid motion
makes, :func:`~imu_array_ros.discovery.coherent.field_basis`), a different statistic and null law.

**Spectrum.**  One DFT of the whole recording per channel (Tukey taper ``TAPER``; white unit noise gives
E|y|^2 = 1 per bin, adjacent bins nearly independent).

**Templates.**  Top-hat bands of ``WIDTHS_HZ`` (the narrowest ``LINE_BINS`` bins: a line; then resonances up to
a few Hz wide), band starts every ``max(1, w // 3)`` bins from ``min_hz`` to the last bin below Nyquist.

**Floor.**  Per template, one wide two-sided floor per channel: the median of |y|^2 over ``L = max(4 w,
MIN_FLOOR_BINS)`` bins on each side beyond a guard of w bins (the band's own tails left out), divided by ln 2.
Both sides hold equally many bins, so near DC and Nyquist the window shrinks (down to ``max(MIN_FLOOR_BINS / 3,
w)`` bins a side; a template with less is not tested): the median over a symmetric window is the centre's
value for any monotone spectrum (coloured noise, the tail of a drift).

**Statistic.**  The largest eigenvalue of the band's cross-spectral matrix, each channel divided by its floor's
square root, per bin of the band; divided by its **local level** (:func:`local_level`): the median of the same
statistic over the templates in the floor window, both sides, relative to the null's median, when above it.
A misfit coherent across the channels over a broad band (one IMU's coloured noise projects on several channels
at once) raises its neighbours as much as itself; a line raises itself.

**Null law** (:func:`null_maxima`): ``NULL_DRAWS`` white-noise recordings of the same length and channel count
through the same scan (fixed seed, cached per length, channels and templates); per width the scan is cut into
at most ``CHUNKS`` contiguous parts, a Gumbel law fitted to the parts' maxima pooled over the draws, and the
scan's maximum exceeds t with probability 1 - (1 - sf(t)) ** parts: the family-wise law of the maximum over the
whole scan, not a count of correlated windows.  Bonferroni over the widths only.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import signal, stats

from imu_array_ros.discovery.spectra import merge_windows

__all__ = ["WIDTHS_HZ", "LINE_BINS", "NULL_DRAWS", "bank_statistic", "local_level", "null_maxima", "family_sf",
           "bank_scan"]

#: template widths (Hz); 0: the narrowest, LINE_BINS bins (a line)
WIDTHS_HZ = (0.0, 0.3, 1.0, 3.0)
#: bins of the narrowest template (a sinusoid between two bins)
LINE_BINS = 2
#: floor bins on each side (at most max(4 w, this); near DC and Nyquist at least a third of it)
MIN_FLOOR_BINS = 48
#: templates each side at least in a statistic's local level (:func:`local_level`)
LEVEL_STARTS = 4
#: Tukey taper fraction of the full-length DFT
TAPER = 0.1
#: white-noise recordings simulated for the null law of the maximum
NULL_DRAWS = 24
#: at most this many parts of a scan whose maxima are pooled (:func:`null_maxima`)
CHUNKS = 16


def _spectrum(v: np.ndarray) -> np.ndarray:
    """(F, V) tapered rFFT of v (N, V): white unit noise gives E|y|^2 = 1."""
    n = len(v)
    win = signal.windows.tukey(n, TAPER, sym=False)
    return np.fft.rfft(v * win[:, None], axis=0) / np.sqrt(np.sum(win ** 2))


def _grid(avail: np.ndarray, full: int, least: int) -> np.ndarray:
    """(M,) int: per entry the largest of full, full / sqrt 2, full / 2, ... (>= least) not above avail; 0 where
    avail < least.  Few distinct window lengths, so the medians run on a few plain blocks."""
    levels = sorted({max(least, int(full * 2.0 ** (-j / 2))) for j in range(64)})
    out = np.zeros(len(avail), dtype=int)
    for lv in levels:
        out[avail >= lv] = lv
    return out


def _design(n: int, f_n: int, lo_bin: int, widths_bins: tuple[int, ...]) -> list[dict]:
    """Per width: band length w, guard g, floor bins L per side (at most), band starts (M,) and each start's
    floor bins per side Ls (M,) (module docstring: symmetric, between DC and Nyquist, both left out)."""
    out = []
    top = f_n - 2 if n % 2 == 0 else f_n - 1      # the last bin below Nyquist
    for w in widths_bins:
        g, L = w, max(4 * w, MIN_FLOOR_BINS)
        starts = np.arange(lo_bin, top - w + 2, max(1, w // 3))
        ls = _grid(np.minimum(starts - g - 1, top - (starts + w - 1 + g)), L, max(MIN_FLOOR_BINS // 3, w))
        keep = ls > 0
        if keep.sum() >= 2 * (int(np.ceil(2 * w / max(1, w // 3))) + LEVEL_STARTS) + 2:  # a template has a level
            out.append({"w": w, "g": g, "L": L, "starts": starts[keep], "Ls": ls[keep]})
    return out


def _floor(pw: np.ndarray, s: np.ndarray, w: int, g: int, ls: np.ndarray, every: int) -> np.ndarray:
    """(M, V) per band start s the median of pw (F, V) over Ls bins each side beyond the guard, / ln 2;
    evaluated every ``every`` starts and repeated in between."""
    sub = np.arange(0, len(s), every)
    out = np.empty((len(sub), pw.shape[1]))
    for lv in np.unique(ls[sub]):
        sel = ls[sub] == lv
        offs = np.concatenate([np.arange(-g - lv, -g), np.arange(w + g, w + g + lv)])
        out[sel] = np.median(pw[s[sub][sel][:, None] + offs[None]], axis=1)
    return out[np.arange(len(s)) // every] / np.log(2.0)


def bank_statistic(y: np.ndarray, design: list[dict]) -> list[np.ndarray]:
    """Per width of ``design``: (M,) the largest eigenvalue per bin of each band's floor-whitened cross-spectral
    matrix (before the local level); y (F, V) spectrum.  The floors are evaluated every ``L // 8`` bins (their
    windows of up to 2 L bins barely move in between)."""
    c = y.shape[1]
    pw = np.abs(y) ** 2
    cs = None
    out = []
    for d in design:
        w, g, L, s = d["w"], d["g"], d["L"], d["starts"]
        step = max(1, int(s[1] - s[0]))
        scale = 1.0 / np.sqrt(_floor(pw, s, w, g, d["Ls"], max(1, (L // 8) // step)))   # (M, V)
        if w < c:  # rank <= w: the Gram matrix of the whitened band
            z = y[s[:, None] + np.arange(w)[None]] * scale[:, None, :]              # (M, w, V)
            a = np.conj(z) @ np.swapaxes(z, -1, -2)
        else:
            if cs is None:
                prod = y[:, :, None] * np.conj(y[:, None, :])
                cs = np.concatenate([np.zeros((1, c, c), complex), np.cumsum(prod, axis=0)])
            a = (cs[s + w] - cs[s]) * scale[:, :, None] * scale[:, None, :]
        out.append(np.linalg.eigvalsh(a)[:, -1] / w)
    return out


def local_level(lam: np.ndarray, d: dict, null_median: float) -> tuple[np.ndarray, np.ndarray]:
    """((M,) the factor >= 1 a width's statistic lam (M,) is divided by, (M,) bool: tested).  The factor: lam's
    median over the templates whose bands start in the floor window, equally many each side (shrunk near the
    ends of the scan, at least LEVEL_STARTS a side, else the template is not tested), over the null's median,
    when above 1."""
    m = len(lam)
    st = max(1, int(d["starts"][1] - d["starts"][0]))
    k0 = int(np.ceil((d["w"] + d["g"]) / st))
    k1 = max(k0 + LEVEL_STARTS, int((d["w"] + d["g"] + d["L"]) // st))
    idx = np.arange(m)
    ks = _grid(np.minimum(idx, m - 1 - idx) - k0 + 1, k1 - k0 + 1, LEVEL_STARTS)
    level = np.ones(m)
    for lv in np.unique(ks[ks > 0]):
        sel = ks == lv
        offs = np.concatenate([np.arange(-k0 - lv + 1, -k0 + 1), np.arange(k0, k0 + lv)])
        level[sel] = np.median(lam[idx[sel][:, None] + offs[None]], axis=1)
    return np.maximum(1.0, level / null_median), ks > 0


def _widths_bins(n: int, fs: float) -> tuple[int, ...]:
    t = n / fs
    return tuple(sorted({max(LINE_BINS, int(round(wh * t))) for wh in WIDTHS_HZ}))


def _chunk_maxima(t: np.ndarray, chunks: int) -> np.ndarray:
    """(chunks,) the maxima of t over ``chunks`` contiguous, nearly equal parts."""
    edges = np.linspace(0, len(t), chunks + 1).astype(int)
    return np.maximum.reduceat(t, edges[:-1])


@functools.lru_cache(maxsize=32)
def null_maxima(n: int, channels: int, lo_bin: int, widths_bins: tuple[int, ...], draws: int = NULL_DRAWS
                ) -> dict:
    """The null law of the scan on ``channels`` white channels of n samples (fixed seed; module docstring):
    the design, and per width the Gumbel fit (loc, scale) to the pooled maxima of the scan's ``chunks`` parts
    (at most CHUNKS, at least 4 templates each) and the null's median statistic (pooled over the draws)."""
    design = _design(n, n // 2 + 1, lo_bin, widths_bins)
    rng = np.random.default_rng([n, channels, lo_bin, 41])
    raw = [bank_statistic(_spectrum(rng.normal(size=(n, channels))), design) for _ in range(draws)]
    laws = []
    for i, d in enumerate(design):
        med = float(np.median(np.concatenate([st[i] for st in raw])))
        maxima, parts = [], 1
        for st in raw:
            level, tested = local_level(st[i], d, med)
            parts = max(1, min(CHUNKS, int(tested.sum()) // 4))
            maxima.append(_chunk_maxima((st[i] / level)[tested], parts))
        loc, scale = stats.gumbel_r.fit(np.concatenate(maxima))
        laws.append({"w": d["w"], "loc": float(loc), "scale": float(scale), "chunks": parts, "median": med})
    return {"design": design, "laws": laws}


def family_sf(t: np.ndarray, law: dict) -> np.ndarray:
    """P(the scan's maximum >= t) for one width's null law (:func:`null_maxima`)."""
    sf = stats.gumbel_r.sf(t, law["loc"], law["scale"])
    return -np.expm1(law["chunks"] * np.log1p(-np.minimum(sf, 1.0 - 1e-16)))


def bank_scan(v: np.ndarray, fs: float, alpha: float, *, min_hz: float = 0.5, draws: int = NULL_DRAWS
              ) -> dict | None:
    """The bank test (module docstring) on the field channels v (N, V) sampled at fs Hz, family-wise level
    alpha.  Returns freqs (F,) of the full-length DFT, per width ("widths": w bins -> {"starts", "stat",
    "level", "p"}; p = 1 where not tested), and cands: [(p, band lo Hz, band hi Hz, peak Hz, width Hz)]
    significant at alpha (overlapping or touching bands merged, the smallest p kept), sorted by p; None when
    too short or fewer than 2 channels."""
    v = np.nan_to_num(np.asarray(v, dtype=float))
    n, c = v.shape
    if c < 2 or n < 256 or not np.isfinite(fs) or fs <= 0:
        return None
    df = fs / n
    law = null_maxima(n, c, max(1, int(np.ceil(min_hz / df))), _widths_bins(n, fs), draws)
    design = law["design"]
    if not design:
        return None
    y = _spectrum(v)
    power = np.sum(np.abs(y) ** 2, axis=1)
    nw = len(design)
    out = {"freqs": np.arange(n // 2 + 1) * df, "widths": {}, "cands": []}
    raw = []
    for d, t, lw in zip(design, bank_statistic(y, design), law["laws"]):
        level, tested = local_level(t, d, lw["median"])
        p = np.where(tested, np.minimum(1.0, nw * family_sf(t / level, lw)), 1.0)
        out["widths"][d["w"]] = {"starts": d["starts"], "stat": t, "level": level, "p": p}
        for i in np.flatnonzero(p < alpha):
            s = int(d["starts"][i])
            raw.append((float(p[i]), s, s + d["w"] - 1, s + int(np.argmax(power[s:s + d["w"]])), d["w"]))
    merged = merge_windows(raw, 0)
    out["cands"] = sorted((pv, (lo - 0.5) * df, (hi + 0.5) * df, pk * df, w * df) for pv, lo, hi, pk, w in merged)
    return out
