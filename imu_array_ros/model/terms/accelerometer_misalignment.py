"""``accelerometer_misalignment``: small rotation of the accelerometer triad vs its nominal orientation (nilsson2014 xi)."""

from imu_array_ros.model.terms.base import Field, register
from imu_array_ros.model.terms.triad import ANGLE_PLAUSIBLE, Misalignment


@register
class AccelerometerMisalignment(Misalignment):
    name = "accelerometer_misalignment"
    hint = "turn the array through many orientations and rotate it fast about several axes"
    sensors = ("accelerometer",)
    fields = (Field(("accelerometer", "misalignment"), (3,), "rad", plausible=ANGLE_PLAUSIBLE),)
