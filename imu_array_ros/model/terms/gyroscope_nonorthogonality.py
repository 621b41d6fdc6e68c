"""``gyroscope_nonorthogonality``: non-orthogonal sensing axes (nilsson2014 L)."""

from imu_array_ros.model.terms.base import Field, register
from imu_array_ros.model.terms.triad import ANGLE_PLAUSIBLE, Nonorthogonality


@register
class GyroscopeNonorthogonality(Nonorthogonality):
    name = "gyroscope_nonorthogonality"
    hint = "rotate the array fast about all three axes"
    sensors = ("gyroscope",)
    fields = (Field(("gyroscope", "nonorthogonality"), (3,), "rad", plausible=ANGLE_PLAUSIBLE),)
