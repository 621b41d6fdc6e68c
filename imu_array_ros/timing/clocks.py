"""Finding the sample clocks of a recording's chips from scratch: their rates (device constants) and
this session's phases, for a description that has none yet.

:func:`find_sample_clocks` fuses with the description as it is, reads each sensor's relative reading
delays (:mod:`.delays`; the gyroscopes' and the accelerometers' apart: a chip's two sensors need not
sample on one clock), searches every chip's rate over +-``span_ppm`` around the nominal ``period`` by the
sawtooth's spectrum (:func:`~imu_array_ros.timing.sawtooth.search_rates`; the mirror rate of a read
schedule at a multiple of the period is resolved by the sawtooth's shape), fits the phases, then
re-fuses with the clocks and refines rates and phases (``iterations`` rounds).  A chip's sensor whose
sawtooth is clearly above its delays' noise (``MIN_SNR``) gets a clock (``gyroscope_sample_clock`` /
``accelerometer_sample_clock``); the others are named in the notes.  The constant delay each sawtooth
leaves goes into that sensor's ``time_offset`` (the reference IMU's unchanged: the gauge).  Rates are
relative to the stamps' clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms.time_offset import TimeOffset
from imu_array_ros.timing.delays import reading_delays
from imu_array_ros.timing.sawtooth import fit_phases, refine_rates, sawtooth_delay, search_rates, spectrum
from imu_array_ros.timing.session import MIN_MOVING_S, session_weights

__all__ = ["ClockSearch", "find_sample_clocks", "MIN_SNR", "SENSOR_CLOCKS"]

#: a sawtooth's spectral amplitude must exceed this many times the spectrum's median to count as found
MIN_SNR = 8.0
#: a sawtooth of period T correlates with exp(-2 pi i t / T) by T / 2 pi at most (its fundamental); a peak above
#: that by more than AMPLITUDE_Z noise stds (the spectrum's Rayleigh scale) is not a sample clock
AMPLITUDE_Z = 4.0
#: sensor -> the clock term that delays its readings alone
SENSOR_CLOCKS = {"gyroscope": "gyroscope_sample_clock", "accelerometer": "accelerometer_sample_clock"}


@dataclass
class ClockSearch:
    """model: the input with the clocks found (rates, this session's phases) and time offsets moved by the
    constant delays the sawtooths leave; per sensor: rates (K,) ppm (NaN: none), snr (K,) peak amplitude
    over the spectrum's median, found (K,) bool; rms_before/after (s): weighted RMS of the unexplained
    relative delays; notes; delays: per sensor searched before any clock was found, its reading delays under the
    input model (the search's first look; discovery's evidence plot reuses them)."""

    model: SensorModel
    rates: dict = field(default_factory=dict)
    snr: dict = field(default_factory=dict)
    found: dict = field(default_factory=dict)
    rms_before: dict = field(default_factory=dict)
    rms_after: dict = field(default_factory=dict)
    moving_seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    delays: dict = field(default_factory=dict, repr=False)

    @property
    def count(self) -> int:
        """Sensors (of all IMUs) given a clock."""
        return int(sum(f.sum() for f in self.found.values()))


def _rms(d, w):
    """Weighted RMS of d about each column's weighted mean."""
    c = np.sum(w * d, axis=0) / np.where(w.sum(axis=0) > 0, w.sum(axis=0), 1.0)
    return float(np.sqrt(np.sum(w * (d - c) ** 2) / max(w.sum(), 1e-300)))


def _unexplained(delays) -> float:
    w = session_weights(delays)
    c = delays.correction
    total = w.sum(axis=1)
    return _rms(c - (np.sum(w * c, axis=1) / np.where(total > 0, total, 1.0))[:, None], w)


def _not_a_sawtooth(sensor, names, t, w, period, rates, amp, probe, found, notes) -> np.ndarray:
    """(K,) bool: peaks that cannot be a chip's own sample clock.  A sawtooth of period T has |S| = T / 2 pi
    (:mod:`.sawtooth`; less in the relative delays, which remove the chips' weighted mean), so a peak above
    T / 2 pi by more than AMPLITUDE_Z noise stds (sigma = the spectrum's median / sqrt(2 ln 2), Rayleigh) is
    something else: a misfit that follows the motion (a missing gain or misalignment gives a "delay" that beats
    with the twisting).  The relative delays hand one chip's excess to every other chip as its mirror, at the same
    rate (inverted: with reads at a multiple of the period, a falling sawtooth is the mirror rate's, -rate): a chip
    whose peak lies within one resolution width (1 / span of the moving samples, in ppm) of a chip rejected so, or of
    its mirror, is rejected with it.  A real clock of the same rate is lost with it (device rates are spread
    over thousands of ppm; noted)."""
    sigma = np.median(probe, axis=0) / np.sqrt(2 * np.log(2))
    big = found & (amp > period / (2 * np.pi) + AMPLITUDE_Z * sigma)
    if not big.any():
        return big
    moving = t[w.sum(axis=1) > 0]
    width = 1e6 * period / max(float(np.ptp(moving)) if len(moving) else 0.0, 1e-3)
    near = np.minimum(np.abs(rates[:, None] - rates[None, big]), np.abs(rates[:, None] + rates[None, big]))
    echo = found & ~big & np.any(near <= width, axis=1)
    notes.append(f"{sensor}s: peaks above a sawtooth's amplitude on {', '.join(n for n, b in zip(names, big) if b)} "
                 f"({', '.join(f'{a / (period / (2 * np.pi)):.2f}' for a in amp[big])} x T / 2 pi)"
                 + (f" and their mirror at the same (or mirror) rate on {int(echo.sum())} other IMUs" if echo.any() else "")
                 + ": not sample clocks (a misfit that follows the motion?); rejected")
    return big | echo


def find_sample_clocks(samples: ImuSamples, model: SensorModel, *, period: float = 1e-3, span_ppm: float = 8000.0,
                       iterations: int = 2, t0_ns: int | None = None,
                       sensors: tuple[str, ...] = ("gyroscope", "accelerometer")) -> ClockSearch:
    """Sample clocks of period ``period`` (s) on the ``sensors`` of every IMU of ``model`` from ``samples``
    (module docstring).  ValueError when there is too little motion."""
    t0 = int(samples.stamps[0]) if t0_ns is None else int(t0_ns)
    k = model.n_imus
    current = model
    out = ClockSearch(model)
    fused = ModelFusion(current, t0_ns=t0).fuse(samples)[0]
    for sensor in sensors:
        term = SENSOR_CLOCKS[sensor]
        delays = reading_delays(samples, current, fused, t0_ns=t0, sensor=sensor)
        if current is model:
            out.delays[sensor] = delays
        out.moving_seconds = delays.moving_seconds
        if delays.moving_seconds < MIN_MOVING_S:
            raise ValueError(f"only {delays.moving_seconds:.1f} s of motion: at least {MIN_MOVING_S:.0f} s of "
                             "twisting are needed to find sample clocks")
        w = session_weights(delays)
        d = delays.relative()
        out.rms_before[sensor] = _unexplained(delays)
        clock = np.zeros((k, 3))
        clock[:, 0] = period
        rates, amp = search_rates(delays.t, d, w, clock[:, 0], span_ppm=span_ppm)
        grid = np.linspace(-span_ppm, span_ppm, 257)
        probe = np.abs(spectrum(delays.t, d, w, clock[None, :, 0] / (1.0 + grid[:, None] * 1e-6)))
        snr = amp / np.maximum(np.median(probe, axis=0), 1e-300)
        found = snr >= MIN_SNR
        found &= ~_not_a_sawtooth(sensor, model.names, delays.t, w, period, rates, amp, probe, found, out.notes)
        out.snr[sensor], out.found[sensor] = snr, found
        if not found.any():
            out.rates[sensor] = np.full(k, np.nan)
            out.notes.append(f"{sensor}s: no sample clock of period {period * 1e3:g} ms (largest sawtooth "
                             f"{snr.max():.1f}x the noise, {MIN_SNR:g}x needed"
                             + (", the peaks above it rejected as above" if snr.max() >= MIN_SNR else "") + ")")
            continue
        clock[:, 1] = rates
        clock[~found, 0] = 0.0
        clock[:, 2] = np.where(clock[:, 0] > 0, fit_phases(delays.t, d, w, clock[:, 0], clock[:, 1])[0], 0.0)
        for _ in range(max(0, iterations - 1)):
            trial = current.with_terms(**{term: clock})
            delays = reading_delays(samples, trial, ModelFusion(trial, t0_ns=t0).fuse(samples)[0], t0_ns=t0,
                                    sensor=sensor)
            w = session_weights(delays)
            saw = sawtooth_delay(delays.t, clock[:, 0], clock[:, 1], clock[:, 2])
            d = delays.correction + saw
            total = w.sum(axis=1)
            d = d - (np.sum(w * (d - saw), axis=1) / np.where(total > 0, total, 1.0))[:, None]
            step = 0.25e6 * period / max(float(np.ptp(delays.t[w.sum(axis=1) > 0])), 1e-3)
            clock[found, 1] = refine_rates(delays.t, d[:, found], w[:, found], clock[found, 0], clock[found, 1], step)
            clock[:, 2] = np.where(clock[:, 0] > 0, fit_phases(delays.t, d, w, clock[:, 0], clock[:, 1])[0], 0.0)
        _, _, const = fit_phases(delays.t, d, w, clock[:, 0], clock[:, 1], constants=True)
        offsets = current.terms["time_offset"].values.copy()
        offsets[:, TimeOffset.column(sensor)] += np.where(found, const - const[0], 0.0)
        current = current.with_terms(time_offset=offsets, **{term: clock})
        fused = ModelFusion(current, t0_ns=t0).fuse(samples)[0]
        out.rms_after[sensor] = _unexplained(reading_delays(samples, current, fused, t0_ns=t0, sensor=sensor))
        out.rates[sensor] = np.where(found, clock[:, 1], np.nan)
        named = "" if found.all() else "; none on " + ", ".join(n for n, f in zip(model.names, found) if not f)
        out.notes.append(f"{sensor}s: sample clocks of period {period * 1e3:g} ms on {int(found.sum())} of {k} IMUs "
                         f"(unexplained relative reading delays {out.rms_before[sensor] * 1e6:.0f} -> "
                         f"{out.rms_after[sensor] * 1e6:.0f} us RMS){named}")
    out.model = current
    return out
