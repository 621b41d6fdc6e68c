"""Narrowband modes of the residual across the array: detected up to Nyquist, located, described, modelled.

A structural mode of the board (or any narrowband disturbance outside the sensor
model's library) leaves, in the normalised residuals r (N, K, 6) of a fitted
model, a spectral line that several IMUs and axes share with fixed amplitude
ratios and phases: the mode shape.  :func:`detect_modes` finds such lines.

**Spectra.** Welch (Hann, 50 % overlap) of every channel (IMU x axis) as a
relative PSD (:func:`~imu_array_ros.discovery.spectra.relative_psd`: white noise
of variance v gives v), at two resolutions: segment lengths giving bins of
about each of ``RESOLUTIONS_HZ`` (0.25 Hz for lines and low frequencies, 1 Hz
for resonances a few tenths of a Hz to 2 Hz wide; at least 8 segments), each
searched at alpha / 2; a line found at both is reported once (the smaller p).
Each channel's **local floor** is the larger of two
running medians of its PSD, over the bins below and over the bins above the
bin tested (``HALF_WINDOW`` bins each side, the ``GUARD`` bins next to it left
out), divided by the median of chi^2_nu / nu: a line must stand out of both
sides, so a broadband misfit (coloured noise, drift, a steep low-frequency
end) raises the floor with the PSD and is no line.

**Tests** (every bin from max(``MIN_FREQ_HZ``, 2 bins) to the last bin below Nyquist):

* *pooled*: the mean over channels of PSD / floor.  Channels are correlated
  (the fitted motion couples the IMUs), so its null law is taken as a scaled
  chi-square whose mean and variance are those of the statistic over the bins
  tested (sigma-clipped, so lines do not inflate them): Satterthwaite's
  moment match; tested at ``alpha / 4`` Bonferroni over the bins;
* *per channel*: PSD / floor against F(nu, nu_floor), nu = 2 L / 1.056 Welch's
  equivalent degrees of freedom of L segments, nu_floor those of the floor
  estimate (median of HALF_WINDOW - GUARD bins, adjacent bins correlated:
  ``FLOOR_EFFICIENCY``; the larger of two medians only raises the floor); at
  ``alpha / 4`` Bonferroni over bins x channels.

* *coherent* (with the IMUs' positions and rotations, >= 4 IMUs): the largest eigenvalue of the
  cross-spectrum of the accelerometer field no rigid motion makes, over windows of 1-8 fine bins
  (:mod:`~imu_array_ros.discovery.coherent`): a mode spread thinly over many IMUs and a resonance
  a few bins wide, too weak in every channel for the two tests above; its channels from their
  coherence with the mode's reference process (:func:`~imu_array_ros.discovery.coherent.mode_channels`).
* *matched* (same condition): the largest eigenvalue of the Lorentzian-weighted cross-spectrum of the field
  channels on the full-length DFT, resonances 0.25-2 Hz wide (:mod:`~imu_array_ros.discovery.matched`): a
  resonance's tails count, and its widest templates are tested down to a few Hz; its band mapped on the fine
  Welch bins, its channels as the coherent test's.

  The array-wide tests run are ``coherent`` ("welch", "matched", "bank", joined by "+"; default
  ``COHERENT_TEST`` = "welch+matched"); "bank" is the template bank of :mod:`~imu_array_ros.discovery.bank`
  (not in the default: benchmarks/results/discovery_vibration_bank.md, no more found, more false modes).  Their
  field basis keeps the quadratic directions of at least ``SMOOTH_SCALE`` of the largest
  (:func:`~imu_array_ros.discovery.coherent.field_basis` ``min_scale``): the 8 corner IMUs, stacked 2 mm apart
  across 19 mm, have 3 field channels, not 9 (a smooth mode puts ~0.1 of its size on the others).

Family-wise false-alarm rate of the detector on a recording: <= ``alpha`` (:data:`MODE_ALPHA`): Bonferroni over
the resolutions and the array-wide tests, alpha / (2 + tests) each (alpha / 4 by default; without positions and
rotations alpha / 2), each resolution's two tests half of its share; measured on null recordings by
``benchmarks/discovery_modes.py`` and ``benchmarks/discovery_generalisation.py``.

**Each mode** (runs of significant bins, 2-bin gaps merged): frequency (the
peak bin), band (the run +- half a bin), per channel the RMS of the in-band
excess (noise stds; m/s^2 or rad/s when the stds are given) and its phase
relative to the strongest channel (Welch cross-spectrum over the band), the
channels significant in the band (chi-square at ``alpha`` / channels; when the
pooled test found it and no channel passes: those beyond 1 % each, else the
strongest; a mode an array-wide test found and no channel's coherence confirms
alone: the IMUs its pooled shape estimate cannot tell from the one of largest
amplitude, :func:`~imu_array_ros.discovery.coherent.shape_estimate`), a shape
description (:func:`~imu_array_ros.discovery.modeshape.describe_shape`), when it
is present (:func:`~imu_array_ros.discovery.modeshape.presence`) and the
empirical model with its held-out gain
(:func:`~imu_array_ros.discovery.modeshape.heldout_model`).

A line that follows the motion (hand twisting is a sum of sinusoids; a misfit
of a library term then leaves lines or a band in the residual at the motion's
frequencies) is not a mode: when the residual's linear relation to the motion
features, learnt with each fold of the band (``FOLD_HZ``, 0.25 Hz) left out,
predicts more than ``MOTION_SHARE`` (half) of the in-band power
(:func:`~imu_array_ros.discovery.motioncheck.motion_check`), the line is kept in
``motion_lines`` (a misfit for the library terms) and not reported as a mode.
When the motion has no content outside a fold the relation cannot be learnt and
the line is reported as a mode, its ``motion.explained_share`` low.

Before the library search (discover's ``localization``) a mode is only a
narrowband excess the fitted model leaves (``MODE_KIND``): it may still be the
misfit of a library term the search then finds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import signal, stats

from imu_array_ros.discovery.bank import bank_scan
from imu_array_ros.discovery.coherent import LEAD_LEVEL, coherent_scan, field_basis, field_channels, mode_channels
from imu_array_ros.discovery.matched import matched_scan
from imu_array_ros.discovery.modeshape import bandpass, describe_shape, heldout_model, presence
from imu_array_ros.discovery.motioncheck import motion_check
from imu_array_ros.discovery.spectra import FLOOR_GUARD, FLOOR_HALF_WINDOW, local_floor, relative_psd, welch_dof, \
    welch_segments
from imu_array_ros.fusion.residuals import AXES
from imu_array_ros.util.jsontools import json_safe

__all__ = ["MODE_ALPHA", "MODE_KIND", "MIN_FREQ_HZ", "RESOLUTIONS_HZ", "Mode", "ModeSearch", "detect_modes", "mode_segment"]

#: family-wise false-alarm rate of the mode detector per recording
MODE_ALPHA = 0.01
#: lowest frequency tested (below it a mode cannot be told from drift and the motion)
MIN_FREQ_HZ = 0.5
#: target bin widths of the spectra: a fine one (lines, low frequencies) and a coarse one (resonances a few
#: bins wide), each searched at alpha / 2
RESOLUTIONS_HZ = (0.25, 1.0)
#: bins either side of the tested one left out of its floor / used for it
GUARD, HALF_WINDOW = FLOOR_GUARD, FLOOR_HALF_WINDOW
#: effective share of the floor's bins (adjacent Hann bins are correlated; the median is 64 % efficient)
FLOOR_EFFICIENCY = 0.5 * 0.64
#: the array-wide tests: "welch" (coherent.py), "matched" (matched.py), "bank" (bank.py), joined by "+"
COHERENT_TEST = "welch+matched"
#: field basis: the quadratic directions of at least this share of the largest (coherent.field_basis min_scale)
SMOOTH_SCALE = 0.25
#: what a mode is known to be when found (before the library search too: not yet "outside the library")
MODE_KIND = "narrowband excess (not explained by the fitted model)"
#: at most this many modes per recording (the strongest)
MAX_MODES = 8
#: a weak mode's attribution by its shape estimate: an IMU's axes carrying at least this share of its largest
SHAPE_AXIS_SHARE = 0.5


def mode_segment(n: int, fs: float, resolution_hz: float = 0.25) -> int:
    """Welch segment length: the power of 2 giving bins of about ``resolution_hz``, at most n / 4 (>= 7
    segments)."""
    want = 2 ** int(np.ceil(np.log2(max(fs / resolution_hz, 16.0))))
    cap = 2 ** int(np.floor(np.log2(max(n / 4.0, 16.0))))
    return int(max(32, min(want, cap)))


@dataclass
class Mode:
    """A narrowband mode (see the module docstring).  amplitude (K, 6) in-band RMS in noise stds, amplitude_si
    the same in m/s^2 / rad/s (NaN without stds), phase (K, 6) rad relative to the reference channel,
    coherence (K, 6) with it, channels: significant (k, a) pairs strongest first; p_value: the detection's
    (Bonferroni-corrected); shape: describe_shape(); presence: presence(); model: heldout_model()."""

    frequency_hz: float
    band_hz: tuple[float, float]
    p_value: float
    test: str
    amplitude: np.ndarray
    amplitude_si: np.ndarray
    phase: np.ndarray
    coherence: np.ndarray
    channels: list[tuple[int, int]]
    share_of_excess: float = 0.0
    shape: dict = field(default_factory=dict)
    presence: dict = field(default_factory=dict)
    model: dict = field(default_factory=dict)
    motion: dict = field(default_factory=dict)
    attribution: str = "the channels significant alone"

    @property
    def follows_motion(self) -> bool:
        return bool(self.motion.get("follows_motion", False))

    @property
    def imus(self) -> list[int]:
        """IMUs of the significant channels, largest in-band amplitude first."""
        out = []
        for k, _ in self.channels:
            if k not in out:
                out.append(k)
        return out

    @property
    def axes(self) -> list[int]:
        return sorted({a for _, a in self.channels})

    def entry(self, names) -> dict:
        """A localisation entry (keys of Localization.entries) with the mode's detail under "mode"."""
        imus = self.imus
        amp = [float(np.sqrt(np.sum(self.amplitude[k, self.axes] ** 2))) for k in imus]
        tot = sum(amp)
        return {"sensors": [str(names[k]) for k in imus], "sensor_shares": [a / tot if tot > 0 else 0.0 for a in amp],
                "axes": [AXES[a] for a in self.axes], "regime": self.presence.get("regime", "all"),
                "band_hz": [float(self.band_hz[0]), float(self.band_hz[1])],
                "share_of_excess": float(self.share_of_excess), "mode": self.to_dict(names)}

    def to_dict(self, names) -> dict:
        return json_safe({
            "kind": MODE_KIND, "frequency_hz": self.frequency_hz,
            "band_hz": list(self.band_hz), "p_value": self.p_value, "test": self.test,
            "channels": [[str(names[k]), AXES[a]] for k, a in self.channels], "attribution": self.attribution,
            "amplitude_noise_std": self.amplitude, "amplitude_si": self.amplitude_si, "phase_rad": self.phase,
            "coherence": self.coherence, "shape": self.shape, "presence": self.presence,
            "empirical_model": self.model, "motion": self.motion})


@dataclass
class ModeSearch:
    """What the detector computed (the finest resolution's spectra): freqs (F,), pooled (F,) statistic and its
    threshold, channel_max (F,) (largest PSD / floor over channels) and its threshold, tested (F,) bool, nu,
    modes, motion_lines,
    positions (K, 3) m of the IMUs (None when not given)."""

    freqs: np.ndarray
    pooled: np.ndarray
    pooled_threshold: float
    channel_max: np.ndarray
    channel_threshold: float
    tested: np.ndarray
    nu: float
    alpha: float
    modes: list[Mode]
    motion_lines: list[Mode]
    positions: np.ndarray | None = None

    def summary(self) -> dict:
        return json_safe({"alpha": self.alpha, "bins_tested": int(self.tested.sum()),
                          "resolution_hz": float(self.freqs[1] - self.freqs[0]) if len(self.freqs) > 1 else None,
                          "pooled_threshold": self.pooled_threshold, "channel_threshold": self.channel_threshold,
                          "welch_dof": self.nu, "modes": len(self.modes), "motion_lines": len(self.motion_lines),
                          "false_alarm_rate": f"family-wise <= {self.alpha:g} per recording (Bonferroni over two "
                                              f"resolutions, each a pooled and a per-channel test, and the "
                                              f"array-wide tests)"})


def _clipped_moments(t: np.ndarray) -> tuple[float, float]:
    keep = np.isfinite(t)
    for _ in range(6):
        mu, sd = float(np.mean(t[keep])), float(np.std(t[keep]))
        new = np.isfinite(t) & (t < mu + 4.0 * sd)
        if (new == keep).all():
            break
        keep = new
    return mu, sd


def _runs(hit: np.ndarray, gap: int = 2) -> list[tuple[int, int]]:
    idx = np.flatnonzero(hit)
    if not len(idx):
        return []
    out, lo, hi = [], idx[0], idx[0]
    for i in idx[1:]:
        if i - hi <= gap + 1:
            hi = i
        else:
            out.append((lo, hi))
            lo = hi = i
    out.append((lo, hi))
    return out


def _scan(x, chan_ok, fs, nper, alpha) -> dict | None:
    """One resolution: spectra, floors, both tests at alpha / 2 each, candidate runs (p, lo, hi, peak, test)."""
    n = len(x)
    segments = welch_segments(n, nper)
    nu = welch_dof(segments)
    freqs, p = relative_psd(x[:, chan_ok], fs, nperseg=nper)        # (C, F)
    if len(freqs) < 2 * HALF_WINDOW:
        return None
    floor = local_floor(p, nu, GUARD, HALF_WINDOW)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = p / floor
    df = freqs[1] - freqs[0]
    tested = (freqs >= max(MIN_FREQ_HZ, 2 * df)) & (freqs < fs / 2 - 0.5 * df)
    nb, c = int(tested.sum()), int(chan_ok.sum())
    if nb == 0:
        return None
    pooled = np.nanmean(ratio, axis=0)
    mu, sd = _clipped_moments(pooled[tested])
    m_eff = 2.0 * mu * mu / max(sd * sd, 1e-12)
    pooled_thr = mu * stats.chi2.isf(alpha / 2 / nb, m_eff) / m_eff
    nu_floor = nu * (HALF_WINDOW - GUARD) * FLOOR_EFFICIENCY
    chan_thr = float(stats.f.isf(alpha / 2 / (nb * c), nu, nu_floor))
    cmax = np.nanmax(ratio, axis=0)
    cands = []
    for lo, hi in _runs(tested & ((pooled > pooled_thr) | (cmax > chan_thr))):
        sl = slice(lo, hi + 1)
        pk = lo + int(np.nanargmax(pooled[sl] / pooled_thr + cmax[sl] / chan_thr))
        p_pool = min(1.0, stats.chi2.sf(pooled[pk] / mu * m_eff, m_eff) * 2 * nb)
        p_chan = min(1.0, stats.f.sf(cmax[pk], nu, nu_floor) * 2 * nb * c)
        cands.append((min(p_pool, p_chan), lo, hi, pk, "pooled" if p_pool <= p_chan else "channel"))
    return {"nper": nper, "nu": nu, "freqs": freqs, "p": p, "floor": floor, "tested": tested, "pooled": pooled,
            "pooled_thr": float(pooled_thr), "cmax": cmax, "chan_thr": chan_thr, "cands": cands}


def detect_modes(residuals: np.ndarray, fs: float, *, valid: np.ndarray | None = None,
                 positions: np.ndarray | None = None, rotations: np.ndarray | None = None,
                 std: np.ndarray | None = None, still: np.ndarray | None = None, motion: np.ndarray | None = None,
                 alpha: float = MODE_ALPHA, heldout: bool = True, coherent: str | None = None) -> ModeSearch:
    """Narrowband modes of the normalised residuals (N, K, 6) sampled at ``fs`` Hz (module docstring).

    valid (N, K, 6) bool (default: finite); positions (K, 3) m, rotations (K, 3, 3) sensor -> array: the
    shape description; std (K, 6) noise stds: amplitudes in SI units; still (N,) bool: the regime;
    motion (N, 9) fitted [omega, omega_dot, s]: the motion-line check.  heldout: fit the empirical model.
    coherent: the array-wide tests, "welch" (:mod:`~imu_array_ros.discovery.coherent`), "matched"
    (:mod:`~imu_array_ros.discovery.matched`), "bank" (:mod:`~imu_array_ros.discovery.bank`) joined by "+"
    ("" none); None: COHERENT_TEST.
    """
    coherent = COHERENT_TEST if coherent is None else coherent
    r = np.asarray(residuals, dtype=float)
    n, k = r.shape[:2]
    valid = np.isfinite(r) if valid is None else (np.asarray(valid, dtype=bool) & np.isfinite(r))
    x = np.where(valid, r, np.nan).reshape(n, k * 6)
    vx = valid.reshape(n, k * 6)
    chan_ok = vx.mean(axis=0) > 0.5
    empty = ModeSearch(np.zeros(0), np.zeros(0), np.inf, np.zeros(0), np.inf, np.zeros(0, bool), 0.0, alpha, [], [])
    if n < 256 or not np.isfinite(fs) or fs <= 0 or not chan_ok.any():
        return empty
    npers = sorted({mode_segment(n, fs, res) for res in RESOLUTIONS_HZ}, reverse=True)
    basis = None
    if positions is not None and rotations is not None and k >= 4:
        acc_std = None if std is None else np.asarray(std, dtype=float).reshape(k, 6)[:, :3]
        basis = field_basis(positions, rotations, acc_std, min_scale=SMOOTH_SCALE)
        basis = basis if basis.shape[1] >= 2 else None
    arraywide = [t for t in coherent.split("+") if t] if basis is not None else []
    share = alpha / (len(npers) + len(arraywide))
    scans = [sc for sc in (_scan(x, chan_ok, fs, nper, share) for nper in npers) if sc is not None]
    if not scans:
        return empty
    cands = sorted((c + (i,) for i, sc in enumerate(scans) for c in sc["cands"]), key=lambda c: c[0])
    unknown = [t for t in arraywide if t not in ("welch", "bank", "matched")]
    if unknown:
        raise ValueError(f"unknown array-wide mode test {unknown[0]!r} (welch, bank, matched)")
    fine = scans[0]["freqs"][1] - scans[0]["freqs"][0]
    last = len(scans[0]["freqs"]) - 1
    for test in arraywide if scans[0]["nper"] == npers[0] else []:
        if test == "welch":
            co = coherent_scan(field_channels(np.where(valid, r, np.nan), basis), fs, npers[0], share)
            cands += [(pv, lo, hi, pk, f"coherent ({w} bins)", 0) for pv, lo, hi, pk, w in (co or {}).get("cands", [])]
            continue
        co = (bank_scan(field_channels(np.where(valid, r, np.nan), basis), fs, share) if test == "bank" else
              matched_scan(np.where(valid, r, np.nan)[:, :, :3].reshape(n, 3 * k), basis, fs, share))
        name = "coherent bank ({:.2g} Hz template)" if test == "bank" else "coherent matched ({:.2g} Hz wide)"
        for pv, f_lo, f_hi, f_pk, w_hz in (co or {}).get("cands", []):  # the band on the fine Welch bins
            lo, hi = (int(np.clip(np.rint(f / fine), 1, last - 1)) for f in (f_lo, f_hi))
            cands.append((pv, lo, max(lo, hi), int(np.clip(np.rint(f_pk / fine), lo, max(lo, hi))),
                          name.format(w_hz), 0))
    cands.sort(key=lambda c: c[0])
    modes, motion_lines, taken = [], [], []
    for pval, lo, hi, pk, test, i in cands:
        if len(modes) + len(motion_lines) >= MAX_MODES:
            break
        sc = scans[i]
        freqs, df = sc["freqs"], sc["freqs"][1] - sc["freqs"][0]
        band = (max(0.0, float(freqs[lo] - df / 2)), min(fs / 2, float(freqs[hi] + df / 2)))
        if any(band[0] < b[1] and b[0] < band[1] for b in taken):  # the same line at the other resolution
            continue
        full_p = np.full((k * 6, len(freqs)), np.nan)
        full_floor = np.full((k * 6, len(freqs)), np.nan)
        full_p[chan_ok], full_floor[chan_ok] = sc["p"], sc["floor"]
        mode = _describe(x, vx, full_p, full_floor, freqs, lo, hi, pk, band, fs, sc["nper"], sc["nu"], alpha,
                         k, pval, f"{test}, {df:.2g} Hz bins")
        if test.startswith("coherent"):
            _coherent_channels(mode, x, basis, fs, sc["nper"], lo, hi, alpha)
        excess = np.clip(sc["p"] - sc["floor"], 0, None)
        total = float(np.nansum(excess[:, sc["tested"]]))
        mode.share_of_excess = float(np.nansum(excess[:, lo:hi + 1])) / total if total > 0 else 0.0
        if not mode.channels:
            continue
        taken.append(band)
        _finish(mode, x, vx, full_floor[:, pk], fs, positions, rotations, std, still, motion, heldout)
        (motion_lines if mode.follows_motion else modes).append(mode)
    f = scans[0]
    return ModeSearch(f["freqs"], f["pooled"], f["pooled_thr"], f["cmax"], f["chan_thr"], f["tested"], f["nu"],
                      alpha, modes, motion_lines, None if positions is None else np.asarray(positions, dtype=float))


def _describe(x, valid, p, floor, freqs, lo, hi, pk, band, fs, nper, nu, alpha, k, pval, test) -> Mode:
    """Amplitudes, phases and significant channels of the line in bins lo..hi."""
    sl = slice(lo, hi + 1)
    nbins = hi - lo + 1
    df = freqs[1] - freqs[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        excess = np.nansum(p[:, sl] - floor[:, sl], axis=1)          # (C,)
        q = p[:, sl] / floor[:, sl]
        cnt = np.isfinite(q).sum(axis=1)
        band_ratio = np.where(cnt > 0, np.nansum(q, axis=1) / np.maximum(cnt, 1), np.nan)
    var = np.clip(excess, 0.0, None) * df / (fs / 2)
    amp = np.sqrt(var)
    ok = np.isfinite(band_ratio)
    dof = max(nu * nbins / 2.0, 1.0)                                 # adjacent bins correlated
    limit = stats.chi2.isf(alpha / max(int(ok.sum()), 1), dof) / dof
    sig = ok & (band_ratio > limit)
    if not sig.any():  # found by the pooled test, no channel strong on its own: those beyond 1 % each
        sig = ok & (band_ratio > stats.chi2.isf(0.01, dof) / dof)
    if not sig.any():
        sig = ok & (np.arange(len(ok)) == int(np.nanargmax(np.where(ok, band_ratio, -np.inf))))
    ref = int(np.nanargmax(np.where(ok, amp, -1.0)))
    z = np.nan_to_num(x)
    _, s_xr = signal.csd(z, z[:, ref:ref + 1], fs=fs, window="hann", nperseg=nper, detrend=False, axis=0)
    _, s_rr = signal.welch(z[:, ref], fs=fs, window="hann", nperseg=nper, detrend=False)
    _, s_xx = signal.welch(z, fs=fs, window="hann", nperseg=nper, detrend=False, axis=0)
    cross = s_xr[sl].sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        coh = np.abs(cross) ** 2 / (s_xx[sl].sum(axis=0) * s_rr[sl].sum())
    phase = np.angle(cross)
    order = [int(i) for i in np.argsort(-np.where(sig, amp, -1.0)) if sig[i]]
    shape = (k, 6)
    return Mode(float(freqs[pk]), band, float(pval), test, amp.reshape(shape), np.full(shape, np.nan),
                np.where(ok, phase, np.nan).reshape(shape), np.where(ok, coh, np.nan).reshape(shape),
                [(i // 6, i % 6) for i in order])


def _coherent_channels(mode: Mode, x, basis, fs, nper, lo, hi, alpha) -> None:
    """A mode the coherent test found: its channels, amplitudes, phases and coherences from each channel's
    coherence with the mode's reference process (:func:`~imu_array_ros.discovery.coherent.mode_channels`)."""
    ch = mode_channels(x, basis, fs, nper, lo, hi, alpha)
    shape = mode.amplitude.shape
    mode.amplitude = ch["gain"].reshape(shape)
    mode.phase = np.where(np.isfinite(ch["coherence"]), ch["phase"], np.nan).reshape(shape)
    mode.coherence = ch["coherence"].reshape(shape)
    sig = ch["significant"]
    if sig.any():
        mode.channels = [(int(i) // 6, int(i) % 6) for i in np.argsort(-np.where(sig, ch["gain"], -1.0)) if sig[i]]
        return
    # no channel's own coherence is significant (a weak mode spread over many IMUs): the IMUs the pooled shape
    # estimate cannot tell from the one of largest amplitude, largest first, each on its accelerometer axes
    # carrying at least half of its largest (not the one channel of largest coherence: its noise's pick)
    shape, axes = ch["shape"], ch["shape_axes"]
    lead = [int(i) for i in np.argsort(-shape, kind="stable") if ch["lead_set"][i]]
    mode.channels = [(kk, a) for kk in lead for a in range(3) if axes[kk, a] >= SHAPE_AXIS_SHARE * axes[kk].max()]
    mode.attribution = (f"no channel is significant alone: the IMUs the pooled shape estimate (field basis) "
                        f"cannot tell from the one of largest amplitude ({1 - LEAD_LEVEL:.0%} one-sided, jackknife "
                        f"over the Welch segments), largest first")


def _finish(mode: Mode, x, valid, floor_pk, fs, positions, rotations, std, still, motion, heldout: bool) -> None:
    """SI amplitudes, the motion-line check, shape, presence and held-out model of ``mode``."""
    n = len(x)
    k = mode.amplitude.shape[0]
    if std is not None:
        mode.amplitude_si = mode.amplitude * np.asarray(std, dtype=float).reshape(k, 6)
    cols = [kk * 6 + a for kk, a in mode.channels]
    y = bandpass(np.where(valid[:, cols], np.nan_to_num(x[:, cols]), 0.0), fs, mode.band_hz)
    if motion is not None:
        mode.motion = motion_check(x[:, cols], valid[:, cols], motion, fs, mode.band_hz)
    mode.shape = describe_shape(mode, positions, rotations)
    mode.presence = presence(y, valid[:, cols], floor_pk[cols], fs, mode.band_hz, still)
    if heldout:
        mode.model = heldout_model(np.nan_to_num(x[:, cols]), y, valid[:, cols], fs, n)
