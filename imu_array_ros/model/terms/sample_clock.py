"""``sample_clock``: a free-running internal sample clock read by the host (per IMU).

Many MEMS IMUs sample on their own oscillator (e.g. ~1 kHz) and keep the latest
sample in a register; the host reads the register on its own schedule and
stamps the read.  The reading is then older than its stamp by the time since
the chip's last internal sample, its *age*, a sawtooth in [0, T)::

    T = period / (1 + rate * 1e-6),   age(t) = (t - phase) mod T,   delay = -age(t)

with t the stamp in seconds since the recording's first stamp.  ``period``
(the chip's nominal internal sample period, e.g. 1e-3 s; 0: not modelled) and
``rate`` (the chip's clock error, ppm; by the gauge of time relative to the
reference IMU's clock) are device constants; ``phase`` (s, in [0, T): when the
chip sampled first after the recording's start) changes at every power-up: a
session state, estimated from each recording (:mod:`imu_array_ros.timing`) and
never written into a description.  The chip's constant delays (filter delay,
read order) are ``time_offset``.

Jacobians (away from a wrap, where the sawtooth jumps by T): d delay / d phase =
1, d delay / d rate = -m period 1e-6 / (1 + rate 1e-6)^2 with m the number of
whole periods since the phase, d delay / d period = m / (1 + rate 1e-6).  The
phase is not fitted by the engine: to first order it is indistinguishable from a
constant time offset (only the wraps tell them apart), so it is found by search.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.terms.base import Field, MotionContext, register
from imu_array_ros.model.terms.timing import TimingTerm

#: largest plausible |clock rate error|, ppm (``Field.plausible``): crystals are tens of ppm, a chip's internal
#: RC oscillator up to a few percent
CLOCK_RATE_PLAUSIBLE = 5e4

__all__ = ["SampleClock", "clock_ticks", "CLOCK_RATE_PLAUSIBLE"]


def clock_ticks(t: np.ndarray, period: np.ndarray, rate: np.ndarray, phase: np.ndarray):
    """(m, age, T): whole periods since the phase, the age (s) and the period, each broadcast over
    t (N, 1) and the per-IMU values (K,); the age is 0 where period is 0."""
    period = np.asarray(period, dtype=float)
    on = period > 0
    big_t = np.where(on, period, 1.0) / (1.0 + np.asarray(rate, dtype=float) * 1e-6)
    u = (t - phase) / big_t
    m = np.floor(u)
    age = np.where(on, (u - m) * big_t, 0.0)
    return np.where(on, m, 0.0), age, big_t


@register
class SampleClock(TimingTerm):
    name = "sample_clock"
    same_for_sensors = True  # the chip's clock: one age for its accelerometer and gyroscope
    hint = "twist the array for a minute or more, with fast changes of angular rate"
    fields = (Field(("sample_clock", "period"), (), "s", positive=True, fitted=False),
              Field(("sample_clock", "rate"), (), "ppm", plausible=CLOCK_RATE_PLAUSIBLE),
              Field(("sample_clock", "phase"), (), "s", session=True, fitted=False))

    def __init__(self, values: np.ndarray) -> None:
        super().__init__(values)
        if np.any(self.values[:, 0] < 0) or not np.all(np.isfinite(self.values)):
            raise ValueError("sample_clock: period must be >= 0 (0: no sample clock) and every value finite")

    def _ticks(self, ctx: MotionContext):
        v = self.values
        return clock_ticks(ctx.t[:, None], v[None, :, 0], v[None, :, 1], v[None, :, 2])

    def delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        # -age of clock_ticks, its arithmetic in place (one (N, K) array and the whole periods)
        v = self.values
        on = v[:, 0] > 0
        big_t = np.where(on, v[:, 0], 1.0) / (1.0 + v[:, 1] * 1e-6)
        u = ctx.t[:, None] - v[None, :, 2]
        u /= big_t
        u -= np.floor(u)
        u *= big_t
        if not on.all():
            u[:, ~on] = 0.0
        return np.negative(u, out=u)

    def d_delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        m, _, _ = self._ticks(ctx)
        v = self.values
        on = (v[:, 0] > 0)[None, :]
        scale = 1.0 + v[None, :, 1] * 1e-6
        out = np.zeros((ctx.n, ctx.k, 3))
        out[..., 0] = m / scale
        out[..., 1] = -m * v[None, :, 0] * 1e-6 / scale ** 2
        out[..., 2] = np.where(on, 1.0, 0.0)
        return out
