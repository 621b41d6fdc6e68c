"""``stamp_clock``: the clock of an IMU that stamps its own messages (its own driver).

When every IMU's message carries the stamp of its own driver's clock, the true
sample time of IMU k's reading is its own stamp corrected by that clock's
offset and skew relative to the array's time::

    delay = (own stamp - array stamp) + offset + skew * 1e-6 * t

with t in seconds since the recording's first stamp.  The first part is known
(``MotionContext.stamp_delays``, from pairing the messages to the array's
samples); ``offset`` (s) and ``skew`` (ppm) are session states: clocks are set
and drift anew at every start, so they are estimated from each recording and
never written into a description.  By the gauge of time the reference IMU's are
held at 0 (the array's time is the reference IMU's clock).
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.terms.base import Field, MotionContext, register
from imu_array_ros.model.terms.timing import TimingTerm

__all__ = ["StampClock"]


@register
class StampClock(TimingTerm):
    name = "stamp_clock"
    hint = "twist the array with quickly changing angular rate for ten seconds or more"
    fields = (Field(("stamp_clock", "offset"), (), "s", session=True),
              Field(("stamp_clock", "skew"), (), "ppm", session=True))

    def delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        return self.values[None, :, 0] + self.values[None, :, 1] * 1e-6 * ctx.t[:, None]

    def d_delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        out = np.empty((ctx.n, ctx.k, 2))
        out[..., 0] = 1.0
        out[..., 1] = 1e-6 * ctx.t[:, None]
        return out
