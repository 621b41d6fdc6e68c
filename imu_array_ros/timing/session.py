"""The session states of one recording: sample-clock phases and each clock family's common rate, the
offsets and skews of IMUs that stamp their own messages.

:func:`estimate_session` alternates fusion and estimation (``iterations`` rounds): fuse with the
current states, read every IMU's relative reading delays off the residuals
(:func:`~imu_array_ros.timing.delays.reading_delays`; per sensor for a clock that drives one sensor),
then

* sample clocks (``sample_clock``, ``gyroscope_sample_clock``, ``accelerometer_sample_clock`` with a
  ``period``): the chips' rates relative to each other are device constants, but the whole board's
  clock drifts between sessions (tens to ~100 ppm): one common rate shift per clock term is searched
  (+-``COMMON_SPAN_PPM``) on the sawtooths' spectra; then each chip's own rate within +-``CHIP_SPAN_PPM`` of
  that (on the MIMU4444BT captures the chips' rates relative to each other moved by up to ~20 ppm between
  sessions, beyond the common shift: over a 100 s recording 1 ppm moves a 1 ms sawtooth by a tenth of its
  period, so a rate carried over from another session, even shifted in common, put the sawtooths in the
  wrong place and fitted worse than no clock at all); then each chip's phase is fitted
  (:func:`~imu_array_ros.timing.sawtooth.fit_phases`);
* stamp clocks (samples with own stamps): each IMU's delay relative to the reference IMU is a straight
  line in time, offset + skew t, fitted by weighted least squares (the reference's held at 0: the
  array's time is the reference IMU's clock).

Only moving samples carry timing information.  With less than ``MIN_MOVING_S`` seconds of motion the
states are not estimated: a sample clock is then replaced by its mean age (a constant delay of half a
period, exact on average, wrong by up to half a period at each sample) and stamps are trusted as they
are; a note says so.  While the array is still, timing does not change the readings, so nothing is lost
there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.reference import reference_index
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.timing.delays import ReadingDelays, reading_delays
from imu_array_ros.timing.sawtooth import fit_phases, sawtooth_delay, spectrum

__all__ = ["SessionStates", "estimate_session", "needs_session", "session_weights", "active_clocks", "CLOCK_TERMS",
           "MIN_MOVING_S", "COMMON_SPAN_PPM", "CHIP_SPAN_PPM", "MAX_CORRECTION_S"]

#: seconds of motion below which the session states are not estimated
MIN_MOVING_S = 2.0
#: the board's common clock rate is searched within +- this (ppm) of the description's rates
COMMON_SPAN_PPM = 400.0
#: each chip's rate is then searched within +- this (ppm) of its rate with the common shift
CHIP_SPAN_PPM = 60.0
#: ... and kept only where it moves the sawtooth by at least this share of its period over the recording
CHIP_MIN_DRIFT = 0.1
#: a per-sample delay correction beyond this (s) is outside the first-order estimate: left out
MAX_CORRECTION_S = 3e-3
#: sample-clock terms -> the sensor whose readings they delay (None: both sensors of the chip)
CLOCK_TERMS = {"sample_clock": None, "gyroscope_sample_clock": "gyroscope",
               "accelerometer_sample_clock": "accelerometer"}
_OFFSET_COLUMNS = {None: [0, 1], "accelerometer": [0], "gyroscope": [1]}


@dataclass
class SessionStates:
    """model: the input model with this recording's session states; phases: clock term -> (K,) s (NaN: no
    clock); common_rate_ppm: clock term -> the shift of every chip's rate found for this session;
    chip_rate_ppm: clock term -> (K,) each chip's further shift found for this session (0: no clock);
    stamp_offset (K,) s, stamp_skew (K,) ppm and their stds (None without own stamps); moving_seconds;
    estimated: False when there was too little motion; notes: what was done and why; delays: the last
    delays seen."""

    model: SensorModel
    phases: dict = field(default_factory=dict)
    common_rate_ppm: dict = field(default_factory=dict)
    chip_rate_ppm: dict = field(default_factory=dict)
    stamp_offset: np.ndarray | None = None
    stamp_skew: np.ndarray | None = None
    stamp_offset_std: np.ndarray | None = None
    stamp_skew_std: np.ndarray | None = None
    moving_seconds: float = 0.0
    estimated: bool = True
    notes: list[str] = field(default_factory=list)
    delays: ReadingDelays | None = field(default=None, repr=False)

    def summary(self) -> dict:
        """JSON-ready session states, for reports and diagnostics."""
        names = self.model.names
        out: dict = {"moving_seconds": round(self.moving_seconds, 1), "estimated": self.estimated,
                     "notes": list(self.notes)}
        for term, phases in self.phases.items():
            out[f"{term}_phase_s"] = {n: float(p) for n, p in zip(names, phases) if np.isfinite(p)}
            out[f"{term}_common_rate_ppm"] = self.common_rate_ppm.get(term)
            if term in self.chip_rate_ppm:
                out[f"{term}_chip_rate_ppm"] = {n: float(r) for n, r, p in zip(names, self.chip_rate_ppm[term], phases)
                                                if np.isfinite(p)}
        if self.stamp_offset is not None:
            out["stamp_clock_offset_s"] = dict(zip(names, map(float, self.stamp_offset)))
            out["stamp_clock_skew_ppm"] = dict(zip(names, map(float, self.stamp_skew)))
        return out


def active_clocks(model: SensorModel) -> list[str]:
    """The sample-clock terms of ``model`` with a period on some IMU."""
    return [t for t in CLOCK_TERMS if np.any(model.terms[t].values[:, 0] > 0)]


def needs_session(samples: ImuSamples, model: SensorModel) -> bool:
    """True when ``model`` has sample clocks or ``samples`` have own stamps (session states to estimate)."""
    return bool(active_clocks(model)) or samples.own_stamps is not None


def estimate_session(samples: ImuSamples, model: SensorModel, *, iterations: int = 2, reference=None,
                     t0_ns: int | None = None, search_common: bool = True) -> SessionStates:
    """The session states of ``samples`` under ``model`` (see module docstring); ``model`` is returned
    unchanged when it has no sample clock and the samples no own stamps."""
    if not needs_session(samples, model):
        return SessionStates(model, notes=["no sample clocks or own stamps: nothing to estimate"])
    t0 = int(samples.stamps[0]) if t0_ns is None else int(t0_ns)
    clocks = {t: model.terms[t].values.copy() for t in active_clocks(model)}
    ref = reference_index(model.names, reference)
    own = samples.own_stamps is not None
    out = SessionStates(model)
    stamp = model.terms["stamp_clock"].values.copy()
    current = model
    for it in range(max(1, int(iterations))):
        fused, _ = ModelFusion(current, t0_ns=t0).fuse(samples)
        for term, clock in clocks.items():
            delays = reading_delays(samples, current, fused, t0_ns=t0, sensor=CLOCK_TERMS[term])
            out.delays, out.moving_seconds = delays, delays.moving_seconds
            if delays.moving_seconds < MIN_MOVING_S:
                return _too_still(out, model, clocks, own, delays.moving_seconds)
            has = clock[:, 0] > 0
            w, t = session_weights(delays), delays.t
            saw = sawtooth_delay(t, clock[:, 0], clock[:, 1], clock[:, 2])
            d = delays.correction + saw  # the sawtooth part, up to a constant per IMU and a common part
            d = d - _common(d, saw, w)
            if it == 0 and search_common:
                shift = _search_common(t, d, w, clock, has)
                clock[has, 1] += shift
                out.common_rate_ppm[term] = shift
                own_shift = _search_each(t, d, w, clock, has)
                clock[:, 1] += own_shift
                out.chip_rate_ppm[term] = own_shift
            phases, _ = fit_phases(t, d, w, clock[:, 0], clock[:, 1])
            clock[:, 2] = np.where(has, np.nan_to_num(phases), 0.0)
            out.phases[term] = np.where(has, phases, np.nan)
        if own:
            delays = reading_delays(samples, current, fused, t0_ns=t0)
            out.delays, out.moving_seconds = delays, delays.moving_seconds
            if delays.moving_seconds < MIN_MOVING_S:
                return _too_still(out, model, clocks, own, delays.moving_seconds)
            stamp, out.stamp_offset_std, out.stamp_skew_std = _stamp_clocks(delays, stamp, session_weights(delays), ref)
            out.stamp_offset, out.stamp_skew = stamp[:, 0].copy(), stamp[:, 1].copy()
        current = model.with_terms(stamp_clock=stamp, **clocks)
    out.model = current
    out.notes.append(f"session states estimated from {out.moving_seconds:.0f} s of motion")
    return out


def session_weights(delays: ReadingDelays) -> np.ndarray:
    """Information weights of the moving samples, capped at their 90th percentile (a few extreme samples
    do not dominate), 0 where the correction leaves the first-order range."""
    w = delays.weights
    pos = w[w > 0]
    cap = np.quantile(pos, 0.9) if len(pos) else 0.0
    w = np.minimum(w, cap)
    return np.where(np.abs(delays.relative()) < MAX_CORRECTION_S, w, 0.0)


def _common(d: np.ndarray, saw: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(N, 1) the per-sample common part of d that the current sawtooths do not explain."""
    total = w.sum(axis=1)
    return (np.sum(w * (d - saw), axis=1) / np.where(total > 0, total, 1.0))[:, None]


def _span_step(t, w, clock, has) -> tuple[float, float]:
    """The moving samples' span (s) and the rate-search step (ppm): a quarter of the spectrum's resolution
    over at most 60 s."""
    span = float(np.ptp(t[w.sum(axis=1) > 0]))
    return span, 0.25e6 * float(np.min(clock[has, 0])) / max(min(span, 60.0), 1e-3)


def _peak(best_of, grid: np.ndarray, step: float):
    """The best of ``grid`` (R,) or (R, k) by ``best_of`` (candidates -> the best of each column), then three
    rounds of 21 candidates around it, each ten times finer."""
    best = best_of(grid)
    width = step
    for _ in range(3):
        fine = np.linspace(-width, width, 21).reshape((21,) + (1,) * np.ndim(best))
        best = best_of(best + fine)
        width /= 10.0
    return best


def _search_common(t, d, w, clock, has) -> float:
    """The common rate shift (ppm) maximising the sawtooths' summed spectral power."""
    _, step = _span_step(t, w, clock, has)
    shifts = np.arange(-COMMON_SPAN_PPM, COMMON_SPAN_PPM + step, step)

    def best_of(cand):
        rates = clock[None, :, 1] + cand[:, None]
        periods = np.where(has, clock[:, 0], 1.0)[None] / (1.0 + rates * 1e-6)
        return cand[np.argmax(np.sum(np.abs(spectrum(t, d[:, has], w[:, has], periods[:, has])) ** 2, axis=1))]

    return float(_peak(best_of, shifts, step))


def _search_each(t, d, w, clock, has) -> np.ndarray:
    """(K,) each chip's rate shift (ppm, within +-CHIP_SPAN_PPM) maximising its own sawtooth's spectral power;
    0 where there is no clock, and for every chip when the span is too short for the spectrum to resolve
    rates CHIP_SPAN_PPM apart (under 1e6 period / CHIP_SPAN_PPM s: 17 s for 1 ms clocks)."""
    span, step = _span_step(t, w, clock, has)
    cols = np.flatnonzero(has)
    if span * CHIP_SPAN_PPM * 1e-6 < float(np.max(clock[cols, 0])):
        return np.zeros(len(has))  # the spectrum cannot resolve rates within the span (a short window)
    grid = np.arange(-CHIP_SPAN_PPM, CHIP_SPAN_PPM + step, step)

    def best_of(cand):  # cand (R, k) shifts per chip -> (k,) the shift with the largest power per chip
        periods = clock[cols, 0][None] / (1.0 + (clock[cols, 1][None] + cand) * 1e-6)
        power = np.abs(spectrum(t, d[:, cols], w[:, cols], periods)) ** 2
        return cand[np.argmax(power, axis=0), np.arange(len(cols))]

    best = _peak(best_of, np.repeat(grid[:, None], len(cols), axis=1), step)
    # a shift that moves the sawtooth by less than CHIP_MIN_DRIFT of its period over the recording is within
    # the search's own noise (a rate carried over exactly, as in a simulation): the common rate stays
    best = np.where(np.abs(best) * 1e-6 * span >= CHIP_MIN_DRIFT * clock[cols, 0], best, 0.0)
    out = np.zeros(len(has))
    out[cols] = best
    return out


def _stamp_clocks(delays: ReadingDelays, stamp: np.ndarray, w: np.ndarray, ref: int):
    """Offset and skew of every IMU's stamp clock relative to the reference's, weighted least squares on
    the moving samples; returns (values (K, 2), offset std (K,), skew std (K,))."""
    cur = stamp[:, 0][None] + stamp[:, 1][None] * 1e-6 * delays.t[:, None]
    y = delays.correction + cur  # offset + skew t of every IMU, plus a part common to all (per sample)
    y = y - y[:, ref:ref + 1]
    k = y.shape[1]
    new, s_off, s_skew = np.zeros((k, 2)), np.full(k, np.nan), np.full(k, np.nan)
    info_ref = w[:, ref]
    a = np.stack([np.ones_like(delays.t), 1e-6 * delays.t], axis=1)
    for j in range(k):
        if j == ref:
            continue
        both = (w[:, j] > 0) & (info_ref > 0)
        wj = np.where(both, 1.0 / (1.0 / np.where(both, w[:, j], 1.0) + 1.0 / np.where(both, info_ref, 1.0)), 0.0)
        m = a.T @ (wj[:, None] * a)
        cond = np.linalg.cond(m)  # unscaled: a window too short to tell an offset from a skew is left out
        if not np.isfinite(cond) or cond > 1e12:
            continue
        cov = np.linalg.inv(m)
        new[j] = cov @ (a.T @ (wj * y[:, j]))
        s_off[j], s_skew[j] = np.sqrt(cov[0, 0]), np.sqrt(cov[1, 1])
    return new, s_off, s_skew


def _too_still(out: SessionStates, model: SensorModel, clocks: dict, own: bool, moving: float) -> SessionStates:
    out.estimated = False
    out.notes.append(f"only {moving:.1f} s of motion (at least {MIN_MOVING_S:.0f} s needed): session states "
                     "not estimated")
    if clocks:
        offsets = model.terms["time_offset"].values.copy()
        reset = {}
        for term in clocks:
            clock = model.terms[term].values.copy()
            has = clock[:, 0] > 0
            half = np.where(has, 0.5 * clock[:, 0] / (1.0 + clock[:, 1] * 1e-6), 0.0)
            for c in _OFFSET_COLUMNS[CLOCK_TERMS[term]]:
                offsets[:, c] -= half
            clock[:, 0] = 0.0
            reset[term] = clock
        out.model = model.with_terms(time_offset=offsets, **reset)
        out.notes.append("sample clocks replaced by their mean age (half a period) for this recording")
    if own:
        out.notes.append("own stamps taken as the sample times")
    return out
