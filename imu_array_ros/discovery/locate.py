"""Where the residuals exceed the noise: by sensor, axis, motion regime, time, frequency and geometry.

Input: the normalised residuals ``r = (y - h(theta_hat)) / sigma`` of a fitted model,
(N, K, 6) for N samples, K IMUs and the axes :data:`~imu_array_ros.fusion.residuals.AXES`
(NaN = masked), and their expectation under the model ``E[r^2] = 1 - leverage``
(same shape, NaN where masked).  Every statistic below compares an observed sum
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
* by **time**, in windows of ``window_s`` seconds (significant windows merged into spans);
* by **frequency**: Welch spectrum of r with masked readings set to 0 and the
  spectrum divided by the cell's valid fraction.  Convention: the *relative*
  one-sided PSD, ``P_rel(f) = P(f) / (2 / fs)`` for 0 < f < fs/2 and ``P(f) / (1 / fs)``
  at 0 and fs/2, so white noise of variance v gives ``P_rel ~ v`` at every
  frequency, and the mean of P_rel over the frequencies is the residual variance
  (a bias shows at f = 0: Welch is run without detrending).  The white floor of a
  cell is its mean ``E[r^2]`` (the mean of 1 - leverage); the band of a finding is
  the narrowest contiguous band holding >= 80 % of its (signed) excess
  ``sum_f (P_rel - floor)``, reported as bin edges (centre +- half a bin).
  A cell is also significant when one frequency bin (DC and Nyquist left out)
  stands out of its floor: with L Welch segments (Hann, 50 % overlap) the
  relative PSD of white noise is floor x chi^2_nu / nu per bin, nu = 2 L / 1.056
  (Welch's equivalent degrees of freedom), tested at ``LINE_ALPHA`` Bonferroni-
  corrected over every bin of every cell: a narrowband mismatch (a board
  vibration) well below the noise in every sample is found there long before
  it shows in the broadband sum.
* by **geometry** (rigid-body test): per sample, the accelerometer residuals in
  SI in the array frame ``e_k = R_k (r_acc,k * sigma_acc,k)`` of a rigid body are an
  affine field of the position, ``e_k = s + C p_k`` with a general 3x3 C (12
  unknowns; the fitted motion only absorbs fields of that form).  The weighted
  least-squares fit of that field, whitened by the sensor noise, leaves a
  non-affine sum of squares that is chi-square with ``m - rank`` degrees of
  freedom (m valid accelerometer axes, rank 12 unless the valid positions are
  degenerate, e.g. coplanar: then the unidentifiable directions of C are dropped).
  Its ratio to the degrees of freedom is 1 for a rigid array; an IMU whose
  accelerometer is off (bias, scale, position, timing) carries most of the excess.

:meth:`Localization.entries` groups the significant cells into findings (see there).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import welch

from imu_array_ros.fusion.residuals import AXES
from imu_array_ros.util.jsontools import json_safe as _json

__all__ = ["REGIMES", "Localization", "RigidTest", "localize", "rigid_body_test", "relative_psd"]

REGIMES = ("still", "moving", "fast_rotation", "high_angular_acceleration", "high_specific_force", "near_saturation")

#: family-wise level of the narrowband line test over every bin of every cell
LINE_ALPHA = 0.01
#: a significant cell also needs its ratio above this
MIN_RATIO = 1.05
#: share of the excess power the reported band must hold
BAND_FRACTION = 0.8
#: a regime needs this fraction of the samples to be reported for a finding
#: a regime is named only when its excess per expected unit is this many times that of the other samples
REGIME_CONTRAST = 2.0
MIN_REGIME_FRACTION = 0.05
#: spectra need at least this many samples
MIN_SPECTRUM_SAMPLES = 64


def _ratio(o, e):
    o, e = np.asarray(o, dtype=float), np.asarray(e, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(e > 0, o / np.where(e > 0, e, 1.0), np.nan)


def _z(o, e):
    o, e = np.asarray(o, dtype=float), np.asarray(e, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(e > 0, (o - e) / np.sqrt(2.0 * np.where(e > 0, e, 1.0)), np.nan)


def _significant(o, e, z_threshold):
    """Bool: z > z_threshold and ratio > MIN_RATIO (False where E = 0)."""
    z, ratio = _z(o, e), _ratio(o, e)
    return (np.nan_to_num(z, nan=-np.inf) > z_threshold) & (np.nan_to_num(ratio, nan=0.0) > MIN_RATIO)


# --------------------------------------------------------------------------- spectra


def _line_significant(psd: np.ndarray, floor: np.ndarray, n: int, nperseg: int = 256) -> np.ndarray:
    """(K, 6) True where one bin (DC and Nyquist excluded) of the relative PSD exceeds the floor beyond what
    white noise gives at LINE_ALPHA, Bonferroni over all bins and cells (module docstring)."""
    from scipy.stats import chi2

    k6 = floor.shape
    if psd.shape[-1] < 3:
        return np.zeros(k6, dtype=bool)
    nper = int(min(nperseg, n))
    segments = 1 + max(0, (n - nper) // (nper // 2))
    nu = 2.0 * segments / 1.056
    inner = psd[..., 1:-1]
    tests = max(1, int(np.isfinite(floor).sum()) * inner.shape[-1])
    limit = chi2.isf(LINE_ALPHA / tests, nu) / nu
    with np.errstate(invalid="ignore"):
        return np.nan_to_num(inner / floor[..., None] > limit).any(axis=-1) & np.isfinite(floor)


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


def _narrowest_band(freqs: np.ndarray, excess: np.ndarray, fraction: float = BAND_FRACTION) -> list[float]:
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


# --------------------------------------------------------------------------- rigid-body test


@dataclass
class RigidTest:
    """Non-affine part of the accelerometer residual field (module docstring).

    ratio: observed / expected non-affine sum of squares over the tested samples;
    z: (O - E) / sqrt(2 E); by_imu (K,): each IMU's share of the observed
    non-affine sum of squares (sums to 1); imu_ratio (K,): per IMU observed /
    expected (expected = sum over its axes of 1 - hat-matrix diagonal);
    statistic (N,): whitened non-affine sum of squares per sample (NaN: not
    tested); dof (N,): its degrees of freedom (0: not tested); samples: tested samples.
    """

    ratio: float
    z: float
    by_imu: np.ndarray
    imu_ratio: np.ndarray
    statistic: np.ndarray
    dof: np.ndarray
    samples: int

    def to_dict(self, names=None) -> dict:
        names = list(names) if names is not None else [str(i) for i in range(len(self.by_imu))]
        return _json({"ratio": self.ratio, "z": self.z, "samples": self.samples,
                      "share_by_imu": dict(zip(names, self.by_imu)), "ratio_by_imu": dict(zip(names, self.imu_ratio))})


def rigid_body_test(acc_residuals: np.ndarray, rotations: np.ndarray, positions: np.ndarray, acc_std: np.ndarray, *,
                    min_imus: int = 5, chunk: int = 2048) -> RigidTest:
    """Whitened non-affine part of the accelerometer residual field (module docstring).

    acc_residuals (N, K, 3) normalised (NaN masked); rotations (K, 3, 3) sensor -> array;
    positions (K, 3) m; acc_std (K, 3) m/s^2.  A sample is tested when at least
    ``min_imus`` IMUs have all three accelerometer axes valid (partially valid IMUs
    still enter the fit with their valid axes).  Batched: weighted normal equations
    (N, 12, 12) solved by eigendecomposition, so a rank-deficient geometry (coplanar
    valid positions) drops the unidentifiable directions instead of failing.
    """
    r = np.asarray(acc_residuals, dtype=float)
    n, k = r.shape[:2]
    rot = np.asarray(rotations, dtype=float)
    p = np.asarray(positions, dtype=float)
    sig = np.asarray(acc_std, dtype=float)
    # affine invariance: centre and scale the positions for conditioning
    p = p - p.mean(axis=0)
    scale = float(np.max(np.linalg.norm(p, axis=1))) or 1.0
    p = p / scale
    # design of the field in the array frame: e_k = [I, p_k0 I, p_k1 I, p_k2 I] theta
    a = np.concatenate([np.broadcast_to(np.eye(3), (k, 3, 3))] + [p[:, j, None, None] * np.eye(3) for j in range(3)],
                       axis=2)                                               # (K, 3, 12)
    # whitened (sensor axes, unit noise): r_k = diag(1/sigma_k) R_k^T e_k
    b = (np.swapaxes(rot, 1, 2) / sig[:, :, None]) @ a                       # (K, 3, 12)
    b = b.reshape(3 * k, 12)
    valid = np.isfinite(r)
    tested = valid.all(axis=2).sum(axis=1) >= min_imus
    w = (valid & tested[:, None, None]).reshape(n, 3 * k).astype(float)
    y = np.where(valid, r, 0.0).reshape(n, 3 * k)
    stat = np.full(n, np.nan)
    dof = np.zeros(n)
    obs_k = np.zeros(k)
    exp_k = np.zeros(k)
    for lo in range(0, n, chunk):
        sl = slice(lo, min(lo + chunk, n))
        ww, yy = w[sl], y[sl]
        if not ww.any():
            continue
        wb = ww[:, :, None] * b[None]                                        # (n, q, 12)
        g = np.swapaxes(wb, 1, 2) @ b                                        # (n, 12, 12)
        vals, vecs = np.linalg.eigh(g)
        keep = vals > 1e-9 * np.maximum(vals[:, -1:], 1e-300)
        inv = np.where(keep, 1.0 / np.where(keep, vals, 1.0), 0.0)
        rhs = (np.swapaxes(wb, 1, 2) @ yy[:, :, None])[..., 0]
        theta = (vecs @ (inv * (np.swapaxes(vecs, 1, 2) @ rhs[:, :, None])[..., 0])[:, :, None])[..., 0]
        res = ww * (yy - theta @ b.T)
        bv = b @ vecs                                                        # (n, q, 12)
        hat = ww * ((bv * bv) @ inv[:, :, None])[..., 0]
        d = ww.sum(axis=1) - keep.sum(axis=1)
        ok = tested[sl] & (d > 0)
        ssq = (res ** 2).sum(axis=1)
        stat[sl] = np.where(ok, ssq, np.nan)
        dof[sl] = np.where(ok, d, 0.0)
        obs_k += (res[ok] ** 2).reshape(-1, k, 3).sum(axis=(0, 2))
        exp_k += (ww[ok] - hat[ok]).reshape(-1, k, 3).sum(axis=(0, 2))
    o, e = float(np.nansum(stat)), float(dof.sum())
    return RigidTest(ratio=float(_ratio(o, e)), z=float(_z(o, e)),
                     by_imu=obs_k / o if o > 0 else np.full(k, np.nan),
                     imu_ratio=_ratio(obs_k, exp_k), statistic=stat, dof=dof,
                     samples=int(np.count_nonzero(dof > 0)))


# --------------------------------------------------------------------------- localisation


@dataclass
class Localization:
    """Where the residual exceeds the noise (module docstring for the statistics).

    names: K IMU names.  observed, expected, ratio, z, significant: (K, 6) over all
    samples.  regime_observed / regime_expected / regime_ratio: regime -> (K, 6);
    regime_samples: regime -> number of samples; n_samples: samples with any valid
    reading.  windows (W,) s since the first stamp (window starts), window_ratio (W,),
    window_ratio_by_imu (W, K), spans: [(t0, t1)] s of merged significant windows.
    freqs (F,) Hz and psd (K, 6, F): relative PSD (white noise of variance v -> v);
    floor (K, 6): the white level (mean E[r^2]).  rigid: :class:`RigidTest` or None.
    line (K, 6): cells significant by the narrowband line test (included in ``significant``).
    """

    names: tuple[str, ...]
    observed: np.ndarray
    expected: np.ndarray
    ratio: np.ndarray
    z: np.ndarray
    significant: np.ndarray
    regime_observed: dict[str, np.ndarray]
    regime_expected: dict[str, np.ndarray]
    regime_ratio: dict[str, np.ndarray]
    regime_samples: dict[str, int]
    n_samples: int
    windows: np.ndarray
    window_ratio: np.ndarray
    window_ratio_by_imu: np.ndarray
    spans: list[tuple[float, float]]
    freqs: np.ndarray
    psd: np.ndarray
    floor: np.ndarray
    rigid: RigidTest | None = None
    window_s: float = 1.0
    z_threshold: float = 5.0
    rate_hz: float = float("nan")
    line: np.ndarray | None = None
    _groups: list | None = field(default=None, repr=False)

    # ---- conveniences
    @property
    def rigid_ratio(self) -> float:
        """Non-affine accelerometer field ratio (NaN when the rigid test was skipped)."""
        return self.rigid.ratio if self.rigid is not None else float("nan")

    @property
    def rigid_by_imu(self) -> np.ndarray:
        """(K,) share of the non-affine sum of squares per IMU (NaN when skipped)."""
        return self.rigid.by_imu if self.rigid is not None else np.full(len(self.names), np.nan)

    def _cells(self, cells) -> np.ndarray:
        """(K, 6) bool from a (K, 6) mask or an iterable of (k, a) pairs."""
        arr = np.asarray(cells)
        if arr.dtype == bool and arr.shape == self.ratio.shape:
            return arr
        mask = np.zeros(self.ratio.shape, dtype=bool)
        for k, a in cells:
            mask[int(k), int(a)] = True
        return mask

    def band_hz(self, cells) -> list[float]:
        """[lo, hi] Hz: narrowest band holding >= 80 % of the summed excess PSD of ``cells``
        ((k, a) pairs or a (K, 6) mask); [0, 0] without spectra or without excess."""
        if len(self.freqs) == 0:
            return [0.0, 0.0]
        m = self._cells(cells)
        excess = np.nansum(np.where(m[..., None], self.psd - self.floor[..., None], 0.0), axis=(0, 1))
        return _narrowest_band(self.freqs, excess)

    def _band_excess(self, imus, axes, band) -> dict | None:
        """IMU -> its excess PSD summed over ``axes`` and the bins of ``band`` (None without spectra): where a
        narrowband mismatch is, the broadband sums are mostly noise."""
        if len(self.freqs) == 0:
            return None
        half = 0.5 * (self.freqs[1] - self.freqs[0]) if len(self.freqs) > 1 else 0.0
        sel = (self.freqs >= band[0] - half) & (self.freqs <= band[1] + half)
        ex = self.psd[:, axes][:, :, sel] - self.floor[:, axes, None]
        return {i: float(np.nansum(ex[i])) for i in imus}

    def regime_of(self, cells) -> str:
        """The regime where the ratio of ``cells`` is largest among regimes with >= 5 % of the samples."""
        m = self._cells(cells)
        best, best_ratio = "moving", -np.inf
        for regime in REGIMES:
            if self.regime_samples[regime] < MIN_REGIME_FRACTION * max(self.n_samples, 1):
                continue
            r = _ratio(self.regime_observed[regime][m].sum(), self.regime_expected[regime][m].sum())
            if np.isfinite(r) and r > best_ratio:
                best, best_ratio = regime, float(r)
        if np.isfinite(best_ratio):  # "all" unless the excess per expected unit is twice that of the other samples
            obs = self.observed[m].sum() - self.regime_observed[best][m].sum()
            exp = self.expected[m].sum() - self.regime_expected[best][m].sum()
            rest = _ratio(obs, exp)
            if np.isfinite(rest) and best_ratio - 1.0 < REGIME_CONTRAST * (rest - 1.0):
                return "all"
        return best

    # ---- findings
    def _findings(self) -> list[dict]:
        """Significant cells grouped (see :meth:`entries`), unsorted, with their cell masks."""
        if self._groups is not None:
            return self._groups
        cands = []
        for k in range(len(self.names)):
            for block in (range(0, 3), range(3, 6)):
                axes = tuple(a for a in block if self.significant[k, a])
                if axes:
                    cands.append({"imus": [k], "axes": axes, "band": self.band_hz([(k, a) for a in axes])})
        groups = []
        for axes in sorted({c["axes"] for c in cands}):
            same = sorted((c for c in cands if c["axes"] == axes), key=lambda c: c["band"][0])
            cur = None
            for c in same:  # merge the IMUs whose bands overlap
                if cur is not None and c["band"][0] <= cur["band"][1]:
                    cur["imus"] += c["imus"]
                    cur["band"] = [cur["band"][0], max(cur["band"][1], c["band"][1])]
                else:
                    cur = {"imus": list(c["imus"]), "axes": axes, "band": list(c["band"])}
                    groups.append(cur)
        exc = self.observed - self.expected
        total = float(np.nansum(np.clip(exc, 0.0, None)))
        out = []
        for g in groups:
            mask = np.zeros(self.ratio.shape, dtype=bool)
            mask[np.ix_(sorted(g["imus"]), list(g["axes"]))] = True
            share = float(np.nansum(exc[mask])) / total if total > 0 else 0.0
            per = self._band_excess(g["imus"], list(g["axes"]), self.band_hz(mask))
            if per is None:
                per = {i: float(np.nansum(exc[i, list(g["axes"])])) for i in g["imus"]}
            imus = sorted(per, key=lambda i: (-per[i], i))  # the IMU carrying most of the excess first
            denom = sum(max(v, 0.0) for v in per.values())
            out.append({"mask": mask, "sensors": [self.names[i] for i in imus],
                        "sensor_shares": [max(per[i], 0.0) / denom if denom > 0 else 0.0 for i in imus],
                        "axes": [AXES[a] for a in g["axes"]], "regime": self.regime_of(mask),
                        "band_hz": self.band_hz(mask), "share_of_excess": share})
        self._groups = out
        return out

    def entries(self, max_entries: int = 10) -> list[dict]:
        """Findings, largest share first: dicts with keys sensors, axes, regime, band_hz, share_of_excess.

        Grouping: the significant cells of one IMU and one sensor (accelerometer
        axes, gyroscope axes) form a candidate; candidates with the same axis set
        whose frequency bands overlap are merged into one finding listing several
        IMUs (e.g. acc_z of imu_02 and imu_07, both at 30 Hz).  Per finding, over
        all its cells: regime = the regime of largest ratio among those with >= 5 %
        of the samples (note: for an excess that does not depend on the motion this
        is whichever regime is largest by chance); band_hz = :meth:`band_hz`;
        share_of_excess = its O - E over the total positive excess of all cells;
        sensors ordered by their own excess power in the finding's axes and band, largest first,
        with sensor_shares (their shares of it): a mismatch on a few IMUs leaks
        into the others through the fitted motion (which averages over all IMUs),
        so the IMUs that carry it come first, the leaks after.
        """
        rows = sorted(self._findings(), key=lambda g: -g["share_of_excess"])[:max_entries]
        return [{"sensors": list(g["sensors"]), "sensor_shares": [float(v) for v in g["sensor_shares"]],
                 "axes": list(g["axes"]), "regime": g["regime"],
                 "band_hz": [float(g["band_hz"][0]), float(g["band_hz"][1])],
                 "share_of_excess": float(g["share_of_excess"])} for g in rows]

    def to_dict(self, *, spectra: bool = False, max_entries: int = 10) -> dict:
        """JSON-serialisable summary (plain floats and lists, None for NaN); ``spectra`` adds freqs and psd."""
        names = list(self.names)
        total_o, total_e = float(np.nansum(self.observed)), float(np.nansum(self.expected))
        out = {
            "names": names, "axes": list(AXES), "n_samples": self.n_samples, "rate_hz": self.rate_hz,
            "z_threshold": self.z_threshold,
            "ratio_all": float(_ratio(total_o, total_e)), "z_all": float(_z(total_o, total_e)),
            "ratio": self.ratio, "z": self.z, "observed": self.observed, "expected": self.expected,
            "significant": [[names[k], AXES[a]] for k, a in zip(*np.nonzero(self.significant))],
            "regime_ratio": {r: self.regime_ratio[r] for r in REGIMES},
            "regime_samples": {r: int(self.regime_samples[r]) for r in REGIMES},
            "window_s": self.window_s, "windows": self.windows, "window_ratio": self.window_ratio,
            "window_ratio_by_imu": self.window_ratio_by_imu, "spans": [list(s) for s in self.spans],
            "rigid": self.rigid.to_dict(names) if self.rigid is not None else None,
            "entries": self.entries(max_entries),
        }
        if spectra:
            out["freqs"] = self.freqs
            out["psd"] = self.psd
            out["floor"] = self.floor
        return _json(out)


def _regimes(motion: np.ndarray, still_threshold: float, gravity: float) -> dict[str, np.ndarray]:
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


def _spans(starts: np.ndarray, flags: np.ndarray, window_s: float) -> list[tuple[float, float]]:
    """Merge runs of flagged windows into (t0, t1) s."""
    out = []
    idx = np.flatnonzero(flags)
    if len(idx) == 0:
        return out
    breaks = np.flatnonzero(np.diff(idx) > 1)
    first = np.concatenate([[idx[0]], idx[breaks + 1]])
    last = np.concatenate([idx[breaks], [idx[-1]]])
    return [(float(starts[a]), float(starts[b] + window_s)) for a, b in zip(first, last)]


def localize(residuals: np.ndarray, expected: np.ndarray, motion: np.ndarray, stamps: np.ndarray, names, *,
             near_saturation: np.ndarray | None = None, rotations: np.ndarray | None = None,
             positions: np.ndarray | None = None, acc_std: np.ndarray | None = None,
             still_threshold: float = 0.2, window_s: float = 1.0, gravity: float = 9.80665,
             z_threshold: float = 5.0) -> Localization:
    """Locate the residual excess of a fitted recording.

    residuals, expected: (N, K, 6) normalised residuals and E[r^2] = 1 - leverage
    (NaN where masked; a reading counts when both are finite).  motion (N, 9) =
    [omega rad/s, omega_dot rad/s^2, s m/s^2] in the array frame (NaN rows:
    dropped samples).  stamps (N,) int64 ns.  names: K IMU names.
    near_saturation: (N, K, 6) bool or None.  rotations (K, 3, 3) sensor -> array,
    positions (K, 3) m and acc_std (K, 3) m/s^2 enable the rigid-body test.
    still_threshold rad/s; window_s s; gravity m/s^2; z_threshold: see module docstring.
    """
    r = np.asarray(residuals, dtype=float)
    e = np.asarray(expected, dtype=float)
    if r.ndim != 3 or r.shape[2] != 6 or e.shape != r.shape:
        raise ValueError(f"residuals and expected must both be (N, K, 6), got {r.shape} and {e.shape}")
    n, k = r.shape[:2]
    names = tuple(str(x) for x in names)
    if len(names) != k:
        raise ValueError(f"{len(names)} names for {k} IMUs")
    motion = np.asarray(motion, dtype=float).reshape(n, 9)
    stamps = np.asarray(stamps, dtype=np.int64).reshape(n)
    valid = np.isfinite(r) & np.isfinite(e)
    r2 = np.where(valid, r, 0.0) ** 2
    ev = np.where(valid, e, 0.0)
    o_all, e_all = r2.sum(axis=0), ev.sum(axis=0)

    # ---- regimes
    masks = _regimes(motion, still_threshold, gravity)
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

    # ---- time windows
    t = (stamps - stamps[0]) * 1e-9 if n else np.zeros(0)
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
    spans = _spans(starts, _significant(o_w, e_w, z_threshold), window_s)

    # ---- spectra (per IMU: bounded memory)
    dt = np.diff(t)
    fs = 1.0 / float(np.median(dt)) if len(dt) and np.median(dt) > 0 else float("nan")
    if n >= MIN_SPECTRUM_SAMPLES and np.isfinite(fs):
        rm = np.where(valid, r, np.nan)
        parts = [relative_psd(rm[:, i], fs) for i in range(k)]
        freqs = parts[0][0]
        psd = np.stack([p for _, p in parts])
    else:
        freqs, psd = np.zeros(0), np.zeros((k, 6, 0))
    nv = valid.sum(axis=0)
    floor = _ratio(e_all, nv)
    significant = _significant(o_all, e_all, z_threshold)
    line = _line_significant(psd, floor, n)
    significant = significant | line

    # ---- rigid body
    rigid = None
    if rotations is not None and positions is not None and acc_std is not None and k >= 5:
        rigid = rigid_body_test(np.where(valid[:, :, :3], r[:, :, :3], np.nan), rotations, positions, acc_std)

    return Localization(
        names=names, observed=o_all, expected=e_all, ratio=_ratio(o_all, e_all), z=_z(o_all, e_all),
        significant=significant, line=line,
        regime_observed=reg_o, regime_expected=reg_e,
        regime_ratio={regime: _ratio(reg_o[regime], reg_e[regime]) for regime in REGIMES},
        regime_samples={regime: reg_n[regime] for regime in REGIMES},
        n_samples=int(np.count_nonzero(valid.any(axis=(1, 2)))),
        windows=starts, window_ratio=_ratio(o_w, e_w), window_ratio_by_imu=_ratio(o_wk, e_wk), spans=spans,
        freqs=freqs, psd=psd, floor=floor, rigid=rigid, window_s=float(window_s), z_threshold=float(z_threshold),
        rate_hz=fs,
    )
