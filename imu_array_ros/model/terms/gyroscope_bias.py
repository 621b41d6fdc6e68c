"""``gyroscope_bias``: constant offset of each gyroscope axis (nilsson2014 b)."""

from imu_array_ros.model.terms.base import Field, register
from imu_array_ros.model.terms.triad import BIAS_PLAUSIBLE, Bias


@register
class GyroscopeBias(Bias):
    name = "gyroscope_bias"
    hint = "rotate the array fast about several axes"
    sensors = ("gyroscope",)
    fields = (Field(("gyroscope", "bias"), (3,), "rad/s", plausible=BIAS_PLAUSIBLE, plausible_of_range=True),)
