"""``gyroscope_misalignment``: small rotation of the gyroscope triad vs its nominal orientation (nilsson2014 xi)."""

from imu_array_ros.model.terms.base import Field, register
from imu_array_ros.model.terms.triad import ANGLE_PLAUSIBLE, Misalignment


@register
class GyroscopeMisalignment(Misalignment):
    name = "gyroscope_misalignment"
    hint = "rotate the array fast about all three axes"
    sensors = ("gyroscope",)
    fields = (Field(("gyroscope", "misalignment"), (3,), "rad", plausible=ANGLE_PLAUSIBLE),)
