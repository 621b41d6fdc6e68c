"""``accelerometer_nonlinearity``: each axis reads u + q u^2 of its input u (before the gain).

Field ``accelerometer.quadratic`` [qx, qy, qz] in 1/(m/s^2).
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.terms.base import Field, Term, register


@register
class AccelerometerNonlinearity(Term):
    name = "accelerometer_nonlinearity"
    hint = "turn the array so that large specific forces of both signs act along every accelerometer axis"
    sensors = ("accelerometer",)
    order = 30
    linear = False
    fields = (Field(("accelerometer", "quadratic"), (3,), "1/(m/s^2)"),)

    def apply(self, x, ctx, sensor):
        return x + self.values[None] * x * x

    def d_input(self, x, ctx, sensor):
        return (1.0 + 2.0 * self.values[None] * x)[..., :, None] * np.eye(3)

    def d_params(self, x, ctx, sensor):
        return (x * x)[..., :, None] * np.eye(3)
