"""Finding the sample clocks of a recording's chips from scratch: their rates (device constants) and
this session's phases, for a description that has none yet.

:func:`find_sample_clocks` fuses with the description as it is, reads the relative reading delays
(:mod:`.delays`), searches every chip's rate over +-``span_ppm`` around the nominal ``period`` by the
sawtooth's spectrum (:func:`~imu_array_ros.timing.sawtooth.search_rates`; the mirror rate of a read
schedule at a multiple of the period is resolved by the sawtooth's shape), fits the phases, then
re-fuses with the clocks and refines rates and phases (``iterations`` rounds).  The rates are relative
to the stamps' clock; a chip whose sawtooth is not clearly above the delays' noise (``MIN_SNR``) gets
no clock and is named in the notes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.timing.delays import reading_delays
from imu_array_ros.timing.sawtooth import fit_phases, refine_rates, sawtooth_delay, search_rates, spectrum
from imu_array_ros.timing.session import MIN_MOVING_S, session_weights

__all__ = ["ClockSearch", "find_sample_clocks", "MIN_SNR"]

#: a sawtooth's spectral amplitude must exceed this many times the spectrum's median to count as found
MIN_SNR = 8.0


@dataclass
class ClockSearch:
    """model: the input with the clocks found (rates, this session's phases); rates (K,) ppm;
    phases (K,) s; snr (K,) peak amplitude over the spectrum's median; found (K,) bool;
    rms_before/after (s): weighted RMS of the relative delays before and after; notes."""

    model: SensorModel
    rates: np.ndarray
    phases: np.ndarray
    snr: np.ndarray
    found: np.ndarray
    rms_before: float
    rms_after: float
    moving_seconds: float
    notes: list[str] = field(default_factory=list)


def _rms(d, w):
    """Weighted RMS of d about each column's weighted mean."""
    c = np.sum(w * d, axis=0) / np.where(w.sum(axis=0) > 0, w.sum(axis=0), 1.0)
    return float(np.sqrt(np.sum(w * (d - c) ** 2) / max(w.sum(), 1e-300)))


def find_sample_clocks(samples: ImuSamples, model: SensorModel, *, period: float = 1e-3, span_ppm: float = 8000.0,
                       iterations: int = 2, t0_ns: int | None = None) -> ClockSearch:
    """Sample clocks of period ``period`` (s) on every IMU of ``model`` from ``samples`` (module docstring)."""
    t0 = int(samples.stamps[0]) if t0_ns is None else int(t0_ns)
    k = model.n_imus
    clock = np.zeros((k, 3))
    clock[:, 0] = period
    current = model.with_terms(sample_clock=np.zeros((k, 3)))
    delays = reading_delays(samples, current, ModelFusion(current, t0_ns=t0).fuse(samples)[0], t0_ns=t0)
    if delays.moving_seconds < MIN_MOVING_S:
        raise ValueError(f"only {delays.moving_seconds:.1f} s of motion: at least {MIN_MOVING_S:.0f} s of twisting "
                         "are needed to find sample clocks")
    w = session_weights(delays)
    d = delays.relative()
    before = _rms(d, w)
    rates, amp = search_rates(delays.t, d, w, clock[:, 0], span_ppm=span_ppm)
    probe = np.abs(spectrum(delays.t, d, w, clock[None, :, 0] / (1.0 + np.linspace(-span_ppm, span_ppm, 257)[:, None]
                                                                  * 1e-6)))
    snr = amp / np.maximum(np.median(probe, axis=0), 1e-300)
    found = snr >= MIN_SNR
    clock[:, 1] = rates
    clock[~found, 0] = 0.0
    clock[:, 2], _ = fit_phases(delays.t, d, w, clock[:, 0], clock[:, 1])
    for _ in range(max(0, iterations - 1)):
        current = model.with_terms(sample_clock=clock)
        delays = reading_delays(samples, current, ModelFusion(current, t0_ns=t0).fuse(samples)[0], t0_ns=t0)
        w = session_weights(delays)
        saw = sawtooth_delay(delays.t, clock[:, 0], clock[:, 1], clock[:, 2])
        d = delays.correction + saw
        total = w.sum(axis=1)
        d = d - (np.sum(w * (d - saw), axis=1) / np.where(total > 0, total, 1.0))[:, None]
        step = 0.25e6 * period / max(float(np.ptp(delays.t[w.sum(axis=1) > 0])), 1e-3)
        clock[found, 1] = refine_rates(delays.t, d[:, found], w[:, found], clock[found, 0], clock[found, 1], step)
        clock[:, 2], _ = fit_phases(delays.t, d, w, clock[:, 0], clock[:, 1])
    # the constant delay each sawtooth leaves: into the chip's time offsets (both sensors), the reference's
    # unchanged (the gauge); the clocks' mean age T/2 is part of the sawtooth
    _, _, const = fit_phases(delays.t, d, w, clock[:, 0], clock[:, 1], constants=True)
    offsets = model.terms["time_offset"].values.copy()
    shift = np.where(found, const - const[0], 0.0)
    offsets += shift[:, None]
    current = model.with_terms(sample_clock=clock, time_offset=offsets)
    after_delays = reading_delays(samples, current, ModelFusion(current, t0_ns=t0).fuse(samples)[0], t0_ns=t0)
    c = after_delays.correction
    tot = session_weights(after_delays)
    after = _rms(c - (np.sum(tot * c, axis=1) / np.where(tot.sum(axis=1) > 0, tot.sum(axis=1), 1.0))[:, None], tot)
    notes = [f"sample clocks found on {int(found.sum())} of {k} IMUs from {delays.moving_seconds:.0f} s of motion; "
             f"unexplained relative reading delays {before * 1e6:.0f} -> {after * 1e6:.0f} us RMS"]
    if not found.all():
        notes.append("no clear sawtooth on " + ", ".join(n for n, f in zip(model.names, found) if not f))
    return ClockSearch(current, np.where(found, clock[:, 1], np.nan), np.where(found, clock[:, 2], np.nan), snr,
                       found, before, after, delays.moving_seconds, notes)
