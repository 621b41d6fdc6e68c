"""``accelerometer_bias``: constant offset of each accelerometer axis (nilsson2014 b)."""

from imu_array_ros.model.terms.base import Field, register
from imu_array_ros.model.terms.triad import BIAS_PLAUSIBLE, Bias


@register
class AccelerometerBias(Bias):
    name = "accelerometer_bias"
    hint = "turn the array through many orientations"
    sensors = ("accelerometer",)
    fields = (Field(("accelerometer", "bias"), (3,), "m/s^2", plausible=BIAS_PLAUSIBLE, plausible_of_range=True),)
