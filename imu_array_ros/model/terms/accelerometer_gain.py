"""``accelerometer_gain``: scale factor of each accelerometer axis (nilsson2014 K)."""

from imu_array_ros.model.terms.base import Field, register
from imu_array_ros.model.terms.triad import GAIN_PLAUSIBLE, Gain


@register
class AccelerometerGain(Gain):
    name = "accelerometer_gain"
    hint = "turn the array so that large specific forces act along every accelerometer axis"
    sensors = ("accelerometer",)
    fields = (Field(("accelerometer", "gain"), (3,), "1", default=1.0, positive=True,
                    plausible=GAIN_PLAUSIBLE),)
