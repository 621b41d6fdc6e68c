"""``gyroscope_sample_clock``, ``accelerometer_sample_clock``: a free-running sample clock that drives one
sensor of a chip only.

The same sawtooth reading age as :mod:`.sample_clock` (which drives both sensors of a chip), for chips
whose accelerometer and gyroscope do not sample on the same clock.  On the MIMU4444BT captures the
gyroscopes' readings show each chip's ~1 kHz clock as a sawtooth of 0-1 ms, the accelerometers' do not
(they sample faster, or on another schedule): ``gyroscope_sample_clock``.  Fields under the sensor's
section: ``clock_period`` (s; 0: none), ``clock_rate`` (ppm) -- device constants -- and ``clock_phase``
(s), a session state.
"""

from __future__ import annotations

from imu_array_ros.model.terms.base import Field, register
from imu_array_ros.model.terms.sample_clock import CLOCK_RATE_PLAUSIBLE, SampleClock

__all__ = ["GyroscopeSampleClock", "AccelerometerSampleClock"]


def _fields(sensor: str) -> tuple[Field, ...]:
    return (Field((sensor, "clock_period"), (), "s", positive=True, fitted=False),
            Field((sensor, "clock_rate"), (), "ppm", plausible=CLOCK_RATE_PLAUSIBLE),
            Field((sensor, "clock_phase"), (), "s", session=True, fitted=False))


@register
class GyroscopeSampleClock(SampleClock):
    name = "gyroscope_sample_clock"
    sensors = ("gyroscope",)
    fields = _fields("gyroscope")


@register
class AccelerometerSampleClock(SampleClock):
    name = "accelerometer_sample_clock"
    sensors = ("accelerometer",)
    fields = _fields("accelerometer")
