"""Loading the array to work with: a description, optionally its calibrated values."""

from __future__ import annotations

from pathlib import Path

from imu_array_ros.errors import ConfigError
from imu_array_ros.model.description import ArrayDescription, load_description
from imu_array_ros.model.identifiability import check_identifiable
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["load_array", "check_fusable", "as_model"]


def load_array(array: str | Path, calibration: str | Path | None = None) -> tuple[ArrayDescription, Path]:
    """The description to work with, and the file its values came from.

    ``array``: the array description (IMU names and order, nominal geometry, noise); ``calibration``:
    a calibrated description of the same IMUs (same schema, e.g. written by a calibration), used
    instead of ``array``'s values, in ``array``'s IMU order.  ConfigError (one line naming the file)
    for a missing or malformed file or other IMU names."""
    desc = load_description(array)
    if calibration is None:
        return desc, Path(array)
    cal = load_description(calibration)
    if set(cal.names) != set(desc.names):
        extra = sorted(set(cal.names) ^ set(desc.names))
        raise ConfigError(f"{calibration}: IMU names differ from {array} (e.g. {extra[0]!r})")
    by_name = {imu.name: imu for imu in cal.imus}
    return cal.with_imus([by_name[n] for n in desc.names]), Path(calibration)


def check_fusable(desc: ArrayDescription, source: str | Path | None = None) -> None:
    """skog2016 Sec. II-D (at least one gyroscope and three non-collinear accelerometers), with the error
    naming the description file."""
    check_identifiable(desc.positions, len(desc.imus), where=str(source if source is not None else desc.source))


def as_model(desc_or_model: ArrayDescription | SensorModel) -> SensorModel:
    """The sensor model of a description, with every term it gives (a SensorModel passes through)."""
    if isinstance(desc_or_model, SensorModel):
        return desc_or_model
    if isinstance(desc_or_model, ArrayDescription):
        return SensorModel.from_description(desc_or_model)
    raise TypeError(f"expected an ArrayDescription or a SensorModel, got {type(desc_or_model).__name__}")
