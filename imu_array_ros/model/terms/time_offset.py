"""``time_offset``: the sample stamped t was taken at t + offset (per sensor of each IMU).

A device constant: the sensor's filter delay and its place in the read order, e.g.
an accelerometer sampled 1.6 ms before its gyroscope.  Applied with the other
timing terms (:mod:`.timing`): exactly along a trajectory, else to first order,
x(t + d) = x(t) + d * dx/dt.  Offsets of a few ms on hand motion keep the neglected
second-order term far below the noise.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.terms.base import Field, MotionContext, register
from imu_array_ros.model.terms.timing import TimingTerm

#: largest plausible |time offset|, s (``Field.plausible``): filter delays and read orders are ms; 0.1 s is
#: six samples at 62.5 Hz
TIME_OFFSET_PLAUSIBLE = 0.1


@register
class TimeOffset(TimingTerm):
    name = "time_offset"
    candidate = True
    hint = "twist the array with quickly changing angular rate and specific force"
    fields = (Field(("accelerometer", "time_offset"), (), "s", plausible=TIME_OFFSET_PLAUSIBLE),
              Field(("gyroscope", "time_offset"), (), "s", plausible=TIME_OFFSET_PLAUSIBLE))

    @staticmethod
    def column(sensor: str) -> int:
        """The column of ``sensor``'s ("accelerometer" or "gyroscope") offset in the (K, 2) values."""
        return 0 if sensor == "accelerometer" else 1

    def delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        return np.broadcast_to(self.values[None, :, self.column(sensor)], (ctx.n, ctx.k))

    def d_delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        out = np.zeros((ctx.n, ctx.k, 2))
        out[..., self.column(sensor)] = 1.0
        return out
