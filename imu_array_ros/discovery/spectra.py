"""Where the residuals exceed the noise by frequency: relative PSD, the narrowband line test, the band of an excess.

Welch spectrum of the normalised residuals r (:mod:`~imu_array_ros.discovery.excess`)
with masked readings set to 0 and the spectrum divided by the cell's valid fraction.
Convention: the *relative* one-sided PSD, ``P_rel(f) = P(f) / (2 / fs)`` for
0 < f < fs/2 and ``P(f) / (1 / fs)`` at 0 and fs/2, so white noise of variance v
gives ``P_rel ~ v`` at every frequency, and the mean of P_rel over the frequencies
is the residual variance (a bias shows at f = 0: Welch is run without detrending).
The white floor of a cell is its mean ``E[r^2]`` (the mean of 1 - leverage); the
band of a finding is the narrowest contiguous band holding >= 80 % of its (signed)
excess ``sum_f (P_rel - floor)``, reported as bin edges (centre +- half a bin).

A cell is also significant when one frequency bin (DC and Nyquist left out)
stands out of its floor, tested at ``LINE_ALPHA`` Bonferroni-corrected over
every bin of every cell: a narrowband mismatch (a board vibration) well below
the noise in every sample is found there long before it shows in the
broadband sum.  With L Welch segments (Hann, 50 % overlap) the relative PSD of
white noise at an inner bin is floor x (1/L) sum_j mu_j E_j, E_j ~ Exp(1),
mu_j = 1 + 2 rho cos(j pi / (L + 1)) the eigenvalues of the segments'
correlation (rho = 1/6: neighbours overlap by half a Hann window); its tail
at the Bonferroni level (~1e-6) is taken by the Lugannani-Rice saddlepoint
approximation (:func:`welch_line_limit`).  Welch's equivalent degrees of freedom
(chi^2_nu / nu, nu = 2 L / 1.056), used before, match its mean and variance
but not that tail: the test fired on 1.5-1.7 % of null recordings at a
nominal 1 % (benchmarks/results/discovery_nulls_703302.md).

Narrowband lines shared across the array (board modes) are located, with their
band and shape, by :mod:`~imu_array_ros.discovery.modes` against each channel's
*local* floor (against the white floor every coloured misfit is a line).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy import ndimage, optimize, stats
from scipy.signal import get_window, welch

__all__ = ["LINE_ALPHA", "BAND_FRACTION", "MIN_SPECTRUM_SAMPLES", "FLOOR_GUARD", "FLOOR_HALF_WINDOW", "relative_psd",
           "imu_spectra", "welch_segments", "welch_dof", "welch_line_limit", "line_bins", "line_significant", "local_floor", "narrowest_band",
           "merge_windows"]

#: family-wise level of the narrowband line test over every bin of every cell
LINE_ALPHA = 0.01
#: share of the excess power the reported band must hold
BAND_FRACTION = 0.8
#: spectra need at least this many samples
MIN_SPECTRUM_SAMPLES = 64
#: bins either side of the tested one left out of its local floor / used for it (:func:`local_floor`)
FLOOR_GUARD, FLOOR_HALF_WINDOW = 3, 24


def relative_psd(r: np.ndarray, fs: float, nperseg: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Relative one-sided Welch PSD of r (N, ...) along samples: (freqs (F,) Hz, psd (..., F)).

    NaN readings are set to 0 and each series' PSD is divided by its valid
    fraction; white noise of variance v gives ~v at every frequency (module
    docstring).  No detrending, Hann window, 50 % overlap.  N < 64: empty spectra.
    """
    r = np.asarray(r, dtype=float)
    n = len(r)
    if n < MIN_SPECTRUM_SAMPLES or not np.isfinite(fs) or fs <= 0:
        return np.zeros(0), np.zeros(r.shape[1:] + (0,))
    valid = np.isfinite(r)
    frac = valid.mean(axis=0)
    nper = int(min(nperseg, n))
    freqs, p = welch(np.where(valid, r, 0.0), fs=fs, window="hann", nperseg=nper, detrend=False, axis=0)
    p = np.moveaxis(p, 0, -1) * (fs / 2.0)
    p[..., 0] *= 2.0  # scipy doubles all but the DC (and an even-length Nyquist) bin
    if nper % 2 == 0:
        p[..., -1] *= 2.0
    with np.errstate(invalid="ignore", divide="ignore"):
        p = np.where(frac[..., None] > 0, p / np.where(frac > 0, frac, 1.0)[..., None], np.nan)
    return freqs, p


def local_floor(p: np.ndarray, nu: float, guard: int = FLOOR_GUARD, half_window: int = FLOOR_HALF_WINDOW
                ) -> np.ndarray:
    """(C, F) the larger of the running medians of p (C, F) over the ``half_window - FLOOR_GUARD`` bins below
    and above the ``guard`` bins around the tested one (edges: the end bin repeated), made unbiased for white
    noise of nu degrees of freedom.  A line must stand out of both sides: a steep coloured spectrum is no line.
    A wider guard (a window of several bins tested) moves the same number of floor bins outwards."""
    return side_medians(p, guard, half_window) / (stats.chi2.median(nu) / nu)


def side_medians(p: np.ndarray, guard: int = FLOOR_GUARD, half_window: int = FLOOR_HALF_WINDOW) -> np.ndarray:
    """(C, F) the larger of the running medians of p (C, F) along its last axis over the ``half_window -
    FLOOR_GUARD`` entries below and above the ``guard`` ones around each (edges: the end entry repeated)."""
    span = half_window - FLOOR_GUARD
    half = guard + span
    out = None
    for side in (-1, 1):
        foot = np.zeros(2 * half + 1, dtype=bool)
        if side < 0:
            foot[:span] = True
        else:
            foot[half + guard + 1:] = True
        med = ndimage.median_filter(p, footprint=foot[None, :], mode="nearest")
        out = med if out is None else np.fmax(out, med)
    return out


def imu_spectra(r: np.ndarray, valid: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """(freqs (F,) Hz, psd (K, 6, F)): :func:`relative_psd` of the (N, K, 6) residuals where ``valid``, one IMU
    at a time (bounded memory); no spectra (F = 0) below MIN_SPECTRUM_SAMPLES samples or without a rate."""
    n, k = r.shape[:2]
    if n >= MIN_SPECTRUM_SAMPLES and np.isfinite(fs):
        rm = np.where(valid, r, np.nan)
        parts = [relative_psd(rm[:, i], fs) for i in range(k)]
        freqs = parts[0][0]
        psd = np.stack([p for _, p in parts])
    else:
        freqs, psd = np.zeros(0), np.zeros((k, 6, 0))
    return freqs, psd


def welch_segments(n: int, nperseg: int = 256) -> int:
    """How many segments :func:`relative_psd` averages over ``n`` samples (min(nperseg, n) each, 50 % overlap)."""
    nper = int(min(nperseg, n))
    return 1 + max(0, (n - nper) // (nper // 2))


def welch_dof(segments: int) -> float:
    """Welch's equivalent degrees of freedom of ``segments`` Hann segments at 50 % overlap, 2 L / 1.056: a bin's
    mean and variance as chi^2_nu / nu, not its far tail (:func:`welch_line_limit`)."""
    return 2.0 * segments / 1.056


def _welch_eigenvalues(segments: int, nper: int) -> np.ndarray:
    """(L,) eigenvalues of the correlation of L >= 2 Welch segments' DFT values at an inner bin (Hann, 50 %
    overlap): neighbours correlate by rho = sum w_n w_{n+D} / sum w_n^2, the rest not at all (tridiagonal Toeplitz)."""
    w = get_window("hann", nper)
    d = nper - nper // 2
    rho = float(w[:-d] @ w[d:] / (w @ w))
    return 1.0 + 2.0 * rho * np.cos(np.arange(1, segments + 1) * np.pi / (segments + 1))


def _welch_log_sf(x: float, mu: np.ndarray) -> float:
    """ln P((1/L) sum_j mu_j E_j > x), E_j ~ Exp(1), x above the mean 1: Lugannani-Rice saddlepoint
    approximation (cumulant generating function K(s) = -sum ln(1 - mu_j s), s < 1 / max mu)."""
    t = x * len(mu)
    s = optimize.brentq(lambda v: float(np.sum(mu / (1.0 - mu * v))) - t, 0.0, (1.0 - 1e-15) / float(mu.max()))
    k = -float(np.sum(np.log1p(-mu * s)))
    w = np.sqrt(2.0 * max(s * t - k, 0.0))
    u = s * np.sqrt(float(np.sum((mu / (1.0 - mu * s)) ** 2)))
    return float(np.log(stats.norm.sf(w) + stats.norm.pdf(w) * (1.0 / u - 1.0 / w)))


@lru_cache(maxsize=256)
def welch_line_limit(alpha: float, segments: int, nper: int) -> float:
    """The level-``alpha`` upper limit (alpha <= 0.01) of a Welch bin's relative PSD over its white floor, with
    ``segments`` Hann segments of ``nper`` samples at 50 % overlap (module docstring).  One segment: exactly
    Exp(1), -ln alpha."""
    if not 0.0 < alpha <= 0.01:
        raise ValueError(f"welch_line_limit needs 0 < alpha <= 0.01, got {alpha}")
    if segments < 2:
        return float(-np.log(alpha))
    mu = _welch_eigenvalues(segments, nper)
    nu = welch_dof(segments)  # its chi-square brackets the limit from below and above
    lo, hi = stats.chi2.isf(10.0 * alpha, nu) / nu, stats.chi2.isf(alpha / 100.0, nu) / nu
    while _welch_log_sf(hi, mu) > np.log(alpha):
        hi *= 2.0
    return float(optimize.brentq(lambda x: _welch_log_sf(x, mu) - np.log(alpha), max(lo, 1.0 + 1e-6), hi))


def line_bins(psd: np.ndarray, floor: np.ndarray, n: int, nperseg: int = 256) -> np.ndarray:
    """(K, 6, F) True at the bins (never DC nor Nyquist) where the relative PSD exceeds the floor beyond what
    white noise gives at LINE_ALPHA, Bonferroni over all bins and cells (module docstring)."""
    out = np.zeros(psd.shape, dtype=bool)
    if psd.shape[-1] < 3:
        return out
    inner = psd[..., 1:-1]
    tests = max(1, int(np.isfinite(floor).sum()) * inner.shape[-1])
    limit = welch_line_limit(LINE_ALPHA / tests, welch_segments(n, nperseg), int(min(nperseg, n)))
    with np.errstate(invalid="ignore"):
        out[..., 1:-1] = np.nan_to_num(inner / floor[..., None] > limit) & np.isfinite(floor)[..., None]
    return out


def line_significant(psd: np.ndarray, floor: np.ndarray, n: int, nperseg: int = 256) -> np.ndarray:
    """(K, 6) True where one bin (DC and Nyquist excluded) of the relative PSD exceeds the floor beyond what
    white noise gives at LINE_ALPHA, Bonferroni over all bins and cells (module docstring)."""
    if psd.shape[-1] < 3:
        return np.zeros(floor.shape, dtype=bool)
    return line_bins(psd, floor, n, nperseg).any(axis=-1)


def narrowest_band(freqs: np.ndarray, excess: np.ndarray, fraction: float = BAND_FRACTION) -> list[float]:
    """[lo, hi] Hz: the narrowest run of bins whose excess sums to >= fraction of the total."""
    if len(freqs) == 0:
        return [0.0, 0.0]
    excess = np.nan_to_num(excess)
    total = float(excess.sum())
    df = float(freqs[1] - freqs[0]) if len(freqs) > 1 else 0.0
    if not total > 0:
        return [0.0, 0.0]
    c = np.concatenate([[0.0], np.cumsum(excess)])
    s = c[None, 1:] - c[:-1, None]                       # s[i, j]: bins i..j
    i, j = np.indices(s.shape)
    ok = (j >= i) & (s >= fraction * total)
    width = np.where(ok, j - i, np.iinfo(np.int64).max)
    best = width.min()
    cand = np.flatnonzero((width == best).ravel())
    pick = cand[np.argmax(s.ravel()[cand])]              # ties: the band holding the most
    lo, hi = divmod(int(pick), s.shape[1])
    return [max(0.0, float(freqs[lo]) - df / 2), min(float(freqs[-1]), float(freqs[hi]) + df / 2)]


def merge_windows(cands: list[tuple], max_gap: int) -> list[tuple]:
    """Significant windows (p, lo bin, hi bin, peak bin, width, ...) joined into lines: a window starting at most
    ``max_gap`` bins past the end of the line so far (0: touching or overlapping) extends it to their union, and
    the line keeps the fields of its smallest-p window (the first on ties).  Returned by lo."""
    merged: list[tuple] = []
    for cand in sorted(cands, key=lambda c: c[1]):
        if merged and cand[1] <= merged[-1][2] + 1 + max_gap:
            last = merged[-1]
            best = cand if cand[0] < last[0] else last
            merged[-1] = (best[0], last[1], max(last[2], cand[2]), best[3], best[4])
        else:
            merged.append(cand)
    return merged
