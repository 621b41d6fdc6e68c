"""``gyroscope_gain``: scale factor of each gyroscope axis (nilsson2014 K)."""

from imu_array_ros.model.terms.base import Field, register
from imu_array_ros.model.terms.triad import GAIN_PLAUSIBLE, Gain


@register
class GyroscopeGain(Gain):
    name = "gyroscope_gain"
    hint = "rotate the array fast about all three axes"
    sensors = ("gyroscope",)
    fields = (Field(("gyroscope", "gain"), (3,), "1", default=1.0, positive=True,
                    plausible=GAIN_PLAUSIBLE),)
