"""``bias_drift``: biases drifting linearly, bias(t) = bias + drift (t - first stamp of the recording).

Fields ``accelerometer.bias_drift`` (m/s^2)/s and ``gyroscope.bias_drift`` (rad/s)/s, 3 each.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.terms.base import Field, Term, register


@register
class BiasDrift(Term):
    name = "bias_drift"
    hint = "record for longer"
    sensors = ("accelerometer", "gyroscope")
    order = 51
    linear = False
    fields = (Field(("accelerometer", "bias_drift"), (3,), "(m/s^2)/s"),
              Field(("gyroscope", "bias_drift"), (3,), "(rad/s)/s"))

    def _cols(self, sensor: str) -> slice:
        return slice(0, 3) if sensor == "accelerometer" else slice(3, 6)

    def apply(self, x, ctx, sensor):
        return x + ctx.t[:, None, None] * self.values[None, :, self._cols(sensor)]

    def d_params(self, x, ctx, sensor):
        out = np.zeros(x.shape + (6,))
        out[..., self._cols(sensor)] = ctx.t[:, None, None, None] * np.eye(3)
        return out
