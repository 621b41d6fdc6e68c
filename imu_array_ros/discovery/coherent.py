"""Coherent search for a board mode: the leading eigenvalue of the non-rigid field's band cross-spectrum.

A board mode is one narrowband process x(t) that every IMU sees with its own gain
(the mode shape).  Spread over many IMUs and a resonance a few bins wide, each
channel holds a small share of its evidence and no single channel, nor the
incoherent mean of all channels' spectra, stands out of the noise (a 3.7 Hz mode
over 32 IMUs of oracle evidence 280 leaves at most 2.2 x the floor in one channel
and bin).  Its cross-spectral matrix over the array, however, is rank one: this
test adds the channels coherently, with the shape they share, as the oracle does.

**Channels.**  The accelerometer residuals (normalised: white, unit variance) on an
orthonormal basis of the fields no rigid motion makes and smooth over the array
(:func:`field_basis`): orthogonal to every field affine in the position, which the
fitted motion absorbs (specific force, angular acceleration, centripetal terms), within
the quadratic ones (3, 9 and 15 channels on the 4 planar, 8 corner and 32 IMUs): the
mode's non-rigid part, in white noise.

**Statistic.**  Welch segments (Hann, 50 % overlap, ~0.25 Hz bins as the fine scan
of :mod:`~imu_array_ros.discovery.modes`), every channel divided by its local floor
(:func:`~imu_array_ros.discovery.spectra.local_floor`, the guard widened by the
window: a resonance does not raise its own floor); for windows of ``WIDTHS`` bins
the largest eigenvalue of the floor-whitened cross-spectral matrix summed over the
window's bins and segments, divided by their number, and then by the larger of the
running medians of that eigenvalue over the windows below and above it
(:func:`_side_floor`): a misfit coherent across channels over a broad band (the
coloured noise of one IMU projects on several channels at once; a drift) raises its
neighbours as much as itself, a line only itself.  The lowest window, whose lower
side is itself, never stands out (the DC end is bias and drift territory).

**Null law**, per width: the same statistic on NULL_RUNS white-noise recordings of
the same channel and segment counts (:func:`null_law`, fixed seed, cached): empirical
up to its 99th percentile, beyond it an exponential tail with its mean excess there
(conservative: the tail of a largest eigenvalue is lighter).  The recording's own bulk
of windows (median, interquartile range) is mapped on the null's when that lowers the
statistic (a misfit that widens the bulk raises the threshold; the bulk's scatter
never lowers it).  Bonferroni over windows and widths.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import stats

from imu_array_ros.discovery.spectra import FLOOR_HALF_WINDOW, local_floor, merge_windows, side_medians

__all__ = ["WIDTHS", "LEAD_LEVEL", "field_basis", "field_channels", "null_law", "coherent_scan", "mode_channels",
           "shape_estimate"]

#: window widths (bins of the fine resolution): a line to a resonance ~2 Hz wide
WIDTHS = (1, 2, 4, 8)
#: quantile of the null sample beyond which its tail is extrapolated (exponential)
TAIL_QUANTILE = 0.99
#: the null law: white-noise recordings simulated per (channels, segments), segments of this length
NULL_RUNS, NULL_NPER = 120, 256
#: channels up to which the largest eigenvalue is computed exactly
EXACT_V = 24
#: power-iteration steps of the largest eigenvalue (block of PROBE vectors)
ITERATIONS, PROBE = 40, 4
#: one-sided level of :func:`shape_estimate`'s confidence set for the IMU of a mode's largest amplitude
LEAD_LEVEL = 0.05


def field_basis(positions: np.ndarray, rotations: np.ndarray, acc_std: np.ndarray | None = None, *,
                smooth: bool = True, min_scale: float = 0.0) -> np.ndarray:
    """(3K, V) orthonormal basis, in the space of the stacked normalised accelerometer residuals (sensor axes,
    each divided by its noise std), of the fields no rigid motion makes: orthogonal to every field affine in
    the position (e_k = s + C p_k, 12 directions, rank-aware: a planar array loses C's third column), and,
    when ``smooth``, within the quadratic fields (e_k = sum_ij c_ij p_ki p_kj, 18 directions): a mode smooth
    over the array.  acc_std (K, 3) m/s^2 (None: equal).  min_scale: only the quadratic directions whose singular
    value (of the quadratic fields of unit coefficients, positions scaled to a largest |coordinate| of 1, beyond the
    affine ones) is at least min_scale x the largest: a field smooth over the array's extent puts at most that
    share of its size along the others (on a thin board: the quadratics in the thickness direction, 0.1 of the
    rest on the 8 corner IMUs stacked 2 mm apart across 19 mm)."""
    p = np.asarray(positions, dtype=float)
    k = len(p)
    rot = np.asarray(rotations, dtype=float)
    sig = np.ones((k, 3)) if acc_std is None else np.asarray(acc_std, dtype=float).reshape(k, 3)
    q = p - p.mean(axis=0)
    q = q / (float(np.max(np.abs(q))) or 1.0)
    i, j = np.triu_indices(3)
    funcs_aff = np.concatenate([np.ones((k, 1)), q], axis=1)                    # (K, 4)
    funcs_quad = q[:, i] * q[:, j]                                              # (K, 6)

    def design(funcs):  # (3K, 3 F): array-frame field e_i f(p_k), whitened in the sensor axes
        a = np.einsum("kf,ij->kijf", funcs, np.eye(3))                           # (K, 3 array, 3 e_i, F)
        b = np.einsum("kji,kjef->kief", rot, a) / sig[:, :, None, None]         # R_k^T e, / sigma
        return b.reshape(3 * k, -1)

    def orth(a):
        u, sv, _ = np.linalg.svd(a, full_matrices=True)
        rank = int(np.sum(sv > 1e-8 * max(float(sv[0]) if len(sv) else 0.0, 1e-300)))
        return u[:, :rank], u[:, rank:]

    _, comp = orth(design(funcs_aff))
    if not smooth:
        return comp
    u, sv, _ = np.linalg.svd(comp @ (comp.T @ design(funcs_quad)), full_matrices=False)
    top = float(sv[0]) if len(sv) else 0.0
    return u[:, sv > max(1e-8, float(min_scale)) * max(top, 1e-300)]


def field_channels(residuals: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """(N, V) the normalised accelerometer residuals (N, K, 3+; NaN -> 0) on the field basis (3K, V): white
    and unit for white unit residuals."""
    r = np.nan_to_num(np.asarray(residuals, dtype=float)[:, :, :3])
    return r.reshape(len(r), -1) @ basis


def _segments(v: np.ndarray, nper: int) -> np.ndarray:
    """(..., L, F, V) Hann-windowed rFFT of the 50 %-overlapping segments of v (..., N, V)."""
    n = v.shape[-2]
    starts = np.arange(0, n - nper + 1, nper // 2)
    win = np.hanning(nper + 1)[:-1]
    idx = starts[:, None] + np.arange(nper)[None]
    return np.fft.rfft(v[..., idx, :] * win[:, None], axis=-2)


def _largest_eigenvalue(g: np.ndarray) -> np.ndarray:
    """(B,) largest eigenvalue of the Hermitian PSD matrices g (B, V, V): exact up to EXACT_V, else block power
    iteration (PROBE vectors, fixed start) with a Rayleigh-Ritz step."""
    v = g.shape[-1]
    if v <= EXACT_V:  # single precision: a statistic, not an estimate
        return np.linalg.eigvalsh(g.astype(np.complex64)).astype(float)[:, -1]
    q = np.random.default_rng(0).normal(size=(g.shape[0], v, PROBE)) + 0j
    for _ in range(ITERATIONS):
        q, _ = np.linalg.qr(g @ q)
    small = np.conj(np.swapaxes(q, 1, 2)) @ g @ q
    return np.linalg.eigvalsh(small)[:, -1]


def _statistics(x: np.ndarray, tested: np.ndarray) -> dict[int, np.ndarray]:
    """Per width w: (..., F) the largest eigenvalue of the floor-whitened cross-spectral matrix of the window of w
    bins starting at each bin (NaN: the window leaves the tested bins).  x (..., L, F, V) segment spectra."""
    *lead, nseg, f_n, c = x.shape
    nu = 2.0 * nseg / 1.056
    power = np.moveaxis(np.mean(np.abs(x) ** 2, axis=-3), -1, -2)  # (..., V, F)
    starts = np.arange(f_n)
    inside = np.concatenate([[0], np.cumsum(~tested)])
    xt = np.moveaxis(x, -3, -1)                                       # (..., F, V, L)
    g0 = (xt @ np.conj(np.swapaxes(xt, -1, -2))) / nseg               # (..., F, V, V)
    out = {}
    for w in WIDTHS:
        floor = local_floor(power.reshape(-1, f_n), nu, guard=3 + w).reshape(power.shape)
        with np.errstate(invalid="ignore", divide="ignore"):
            d = np.nan_to_num(np.swapaxes(1.0 / np.sqrt(np.where(floor > 0, floor, np.nan)), -1, -2))  # (..., F, V)
        g = g0 * d[..., :, None] * d[..., None, :]
        cs = np.concatenate([np.zeros(tuple(lead) + (1, c, c), complex), np.cumsum(g, axis=-3)], axis=-3)
        st = starts[: f_n - w + 1]
        ok = st[(inside[st + w] - inside[st]) == 0]
        stat = np.full(tuple(lead) + (f_n,), np.nan)
        if len(ok):
            gw = (cs[..., ok + w, :, :] - cs[..., ok, :, :]) / w
            lam = _largest_eigenvalue(gw.reshape(-1, c, c)).reshape(tuple(lead) + (len(ok),))
            stat[..., ok] = lam / _side_floor(lam, 3 + w)
        out[w] = stat
    return out


def _side_floor(lam: np.ndarray, guard: int) -> np.ndarray:
    """(..., W) the larger of the running medians of lam (..., W) over the FLOOR_HALF_WINDOW - FLOOR_GUARD windows
    below and above the ``guard`` ones around each (edges: the end window repeated): the eigenvalue a window must
    stand out of.  A misfit coherent across the channels over a broad band (coloured noise of a few IMUs, a
    drift) raises its neighbours' eigenvalues as much as its own; a line raises its own."""
    out = side_medians(lam.reshape(-1, lam.shape[-1]), guard, FLOOR_HALF_WINDOW)
    return np.maximum(out, 1e-300).reshape(lam.shape)


@functools.lru_cache(maxsize=64)
def null_law(channels: int, nseg: int) -> dict[int, np.ndarray]:
    """Per width: the sorted statistic of NULL_RUNS white-noise recordings of ``channels`` channels and ``nseg``
    Welch segments of NULL_NPER samples (the law depends on the channels, the segments and the window, not on
    the rate or the segment length), fixed seed."""
    rng = np.random.default_rng([channels, nseg, 23])
    n = (nseg + 1) * NULL_NPER // 2
    tested = np.ones(NULL_NPER // 2 + 1, dtype=bool)
    tested[:2] = tested[-1:] = False
    acc: dict[int, list] = {w: [] for w in WIDTHS}
    batch = max(1, min(NULL_RUNS, int(4e7 // (n * channels * 16 + channels * channels * NULL_NPER * 16))))
    for lo in range(0, NULL_RUNS, batch):
        x = _segments(rng.normal(size=(min(batch, NULL_RUNS - lo), n, channels)), NULL_NPER)
        for w, st in _statistics(x, tested).items():
            acc[w].append(st[np.isfinite(st)])
    return {w: np.sort(np.concatenate(v)) for w, v in acc.items()}


def _tail_p(s: np.ndarray, law: np.ndarray) -> np.ndarray:
    """P(null >= s) from the sorted null sample ``law``: empirical up to its TAIL_QUANTILE, beyond it an
    exponential tail with the sample's mean excess there (conservative for a tail lighter than exponential)."""
    m = len(law)
    q = float(np.quantile(law, TAIL_QUANTILE))
    beta = float(np.mean(law[law > q] - q))
    emp = (m - np.searchsorted(law, s, side="left") + 1.0) / (m + 1.0)
    with np.errstate(over="ignore", invalid="ignore"):
        ext = (1.0 - TAIL_QUANTILE) * np.exp(-(s - q) / max(beta, 1e-12))
    return np.where(s > q, ext, np.minimum(emp, 1.0))


def coherent_scan(v: np.ndarray, fs: float, nper: int, alpha: float, *, min_hz: float = 0.5) -> dict | None:
    """The coherent test (module docstring) on the field channels v (N, V) at segment length nper, family-wise
    level alpha.  Returns freqs (F,), nseg, per width w ("widths"): stat (F,) (window starting at each bin, NaN:
    not tested) and p (F,) Bonferroni-corrected p-values, and cands: [(p, lo, hi, peak bin, w)] windows
    significant at alpha (overlapping ones merged, the smallest p kept); None when too short."""
    v = np.asarray(v, dtype=float)
    n, c = v.shape
    if c < 2 or n < 2 * nper or nper < 16:
        return None
    x = _segments(v, nper)                                           # (L, F, V)
    nseg = x.shape[0]
    freqs = np.fft.rfftfreq(nper, 1.0 / fs)
    df = freqs[1] - freqs[0]
    tested = (freqs >= max(min_hz, 2 * df)) & (freqs < fs / 2 - 0.5 * df)
    stats_w = _statistics(x, tested)
    nwin = sum(int(np.isfinite(st).sum()) for st in stats_w.values())
    if nwin == 0:
        return None
    law = null_law(c, nseg)
    power = np.sum(np.abs(x) ** 2, axis=(0, 2))                      # (F,) the peak bin of a window
    out = {"freqs": freqs, "nseg": nseg, "widths": {}, "cands": []}
    for w, stat in stats_w.items():
        t = stat[np.isfinite(stat)]
        if len(t) < 8:
            continue
        # the recording's bulk mapped on the null's (median and interquartile range), when that is smaller: a
        # misfit that raises or widens the bulk raises the threshold with it, the bulk's scatter never lowers it
        q25, med, q75 = np.quantile(t, [0.25, 0.5, 0.75])
        n25, nmed, n75 = np.quantile(law[w], [0.25, 0.5, 0.75])
        s = np.fmin(stat, nmed + (stat - med) * (n75 - n25) / max(q75 - q25, 1e-12))
        p = np.where(np.isfinite(stat), np.minimum(1.0, _tail_p(np.nan_to_num(s, nan=-np.inf), law[w]) * nwin),
                     np.nan)
        out["widths"][w] = {"stat": stat, "p": p}
        for lo in np.flatnonzero(np.nan_to_num(p, nan=1.0) < alpha):
            pk = lo + int(np.argmax(power[lo:lo + w]))
            out["cands"].append((float(p[lo]), int(lo), int(lo + w - 1), int(pk), w))
    # significant windows that overlap or have at most 2 bins between them are one line: their union, the smallest p
    out["cands"] = sorted(merge_windows(out["cands"], 2))
    return out


def _hann_bin_dof(w: int, nper: int) -> float:
    """Effective number of independent bins among w adjacent Hann-windowed bins (the squared correlation of
    adjacent bins' coefficients discounted)."""
    win = np.hanning(nper + 1)[:-1]
    spec = np.abs(np.fft.fft(win ** 2))
    rho2 = (spec[1:w] / spec[0]) ** 2
    return w / (1.0 + 2.0 * float(np.sum((1.0 - np.arange(1, w) / w) * rho2)))


def mode_channels(x: np.ndarray, basis: np.ndarray, fs: float, nper: int, lo: int, hi: int, alpha: float) -> dict:
    """The channels of a mode the coherent test found in bins lo..hi: the mode's reference process is the
    leading eigenvector's combination of the field channels (basis (3K, V)) there; channel c (x (N, C),
    C = K x 6, NaN -> 0) is in the mode when its coherence with the reference built *without its own IMU*
    passes Beta(1, M - 1) at alpha / C (M: effective segments x bins).  Returns coherence (C,), p (C,),
    phase (C,) rad, gain (C,) (the channel's coherent in-band RMS, noise stds), significant (C,) bool and the
    pooled shape estimate of :func:`shape_estimate` (``shape``, ``shape_axes``, ``lead_set``)."""
    x = np.nan_to_num(np.asarray(x, dtype=float))
    n, c = x.shape
    k = c // 6
    xs = _segments(x, nper)[:, lo:hi + 1]                              # (L, W, C)
    acc = xs.reshape(xs.shape[:2] + (k, 6))[..., :3].reshape(xs.shape[:2] + (3 * k,))
    fld = acc @ basis                                                   # (L, W, V)
    g = np.einsum("lwa,lwb->ab", fld, np.conj(fld))
    u = np.linalg.eigh(g)[1][:, -1]
    wts = basis @ np.conj(u)                                            # (3K,) the reference's weights
    contrib = acc * wts                                                 # (L, W, 3K)
    ref = contrib.sum(axis=-1)
    own = contrib.reshape(contrib.shape[:2] + (k, 3)).sum(axis=-1)      # (L, W, K)
    ref_c = np.repeat(ref[..., None] - own, 6, axis=2)                  # (L, W, C) without the channel's IMU
    cross = np.sum(xs * np.conj(ref_c), axis=(0, 1))
    pxx = np.sum(np.abs(xs) ** 2, axis=(0, 1))
    prr = np.sum(np.abs(ref_c) ** 2, axis=(0, 1))
    with np.errstate(invalid="ignore", divide="ignore"):
        coh = np.abs(cross) ** 2 / (pxx * prr)
    m = xs.shape[0] / 1.056 * _hann_bin_dof(hi - lo + 1, nper)
    valid = np.isfinite(coh) & (pxx > 0)
    pv = np.where(valid, np.clip(1.0 - coh, 0.0, 1.0) ** max(m - 1.0, 1.0), 1.0)
    ntest = max(int(valid.sum()), 1)
    win = np.hanning(nper + 1)[:-1]
    band_var = pxx / (xs.shape[0] * np.sum(win ** 2)) * (hi - lo + 1) / (nper / 2)   # in-band variance / sample
    gain = np.sqrt(np.clip(np.nan_to_num(coh) - 1.0 / max(m, 1.0), 0.0, None) * band_var)
    return {"coherence": np.where(valid, coh, np.nan), "p": pv, "phase": np.angle(cross), "gain": gain,
            "significant": valid & (pv < alpha / ntest), **shape_estimate(fld, basis)}


def shape_estimate(fld: np.ndarray, basis: np.ndarray, level: float = LEAD_LEVEL) -> dict:
    """The mode's shape across the array from the field channels' spectra ``fld`` (L segments, W bins, V) in its
    band: the leading eigenvector u of their cross-spectral matrix mapped back on the accelerometer channels,
    w = basis u (3K,; the field basis is smooth over the array, so every IMU's estimate pools all of them -- a
    mode too weak for any channel's own coherence test still has a shape).  Returns ``shape`` (K,) |w_k| over the
    IMU's three axes, largest 1; ``shape_axes`` (K, 3) |w_ka|; ``lead_set`` (K,) bool: the IMUs whose shape is not
    below the largest by more than z_level jackknife standard errors of the difference (delete-one Welch segment;
    adjacent segments overlap 50 %, so the errors are a little small): a one-sided ``level`` confidence set for
    the IMU with the largest amplitude."""
    k = basis.shape[0] // 3
    per_seg = np.einsum("lwa,lwb->lab", fld, np.conj(fld))              # (L, V, V)
    g = per_seg.sum(axis=0)

    def magnitudes(mats):
        u = np.linalg.eigh(mats)[1][..., -1]                            # (B, V) unit leading eigenvectors
        w = np.abs(np.einsum("av,bv->ba", basis, u)).reshape(len(mats), k, 3)
        return np.sqrt(np.sum(w ** 2, axis=-1)), w

    full, axes = (a[0] for a in magnitudes(g[None]))
    lead = int(np.argmax(full))
    diff = full[lead] - full
    lead_set = np.zeros(k, dtype=bool)
    lead_set[lead] = True
    if len(per_seg) > 2:
        d = magnitudes(g[None] - per_seg)[0]                              # each Welch segment left out
        d = d[:, lead:lead + 1] - d                                      # (L, K)
        se = np.sqrt((len(d) - 1) / len(d) * np.sum((d - d.mean(axis=0)) ** 2, axis=0))
        lead_set |= diff <= stats.norm.isf(level) * se
    top = max(float(full[lead]), 1e-300)
    return {"shape": full / top, "shape_axes": axes / top, "lead_set": lead_set}
