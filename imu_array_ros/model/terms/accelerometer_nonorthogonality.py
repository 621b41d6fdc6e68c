"""``accelerometer_nonorthogonality``: non-orthogonal sensing axes (nilsson2014 L)."""

from imu_array_ros.model.terms.base import Field, register
from imu_array_ros.model.terms.triad import ANGLE_PLAUSIBLE, Nonorthogonality


@register
class AccelerometerNonorthogonality(Nonorthogonality):
    name = "accelerometer_nonorthogonality"
    hint = "turn the array so that large specific forces act along every accelerometer axis"
    sensors = ("accelerometer",)
    fields = (Field(("accelerometer", "nonorthogonality"), (3,), "rad", plausible=ANGLE_PLAUSIBLE),)
