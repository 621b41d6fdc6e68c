"""Array description: the YAML input contract (see README "Array description").

One file describes the array geometry, the noise figures, and optionally each
IMU's calibration in the nilsson2014 model (eq. 1, extended by the
misalignment of eq. 2)::

    y = K · L · (I + [xi]x) · u + b

all in the IMU's sensor frame, where ``u`` is the true specific force
(accelerometer) or angular velocity (gyroscope, ``L = I``) expressed in the
nominal sensor frame.  Calibrations write this same schema back, plus a
top-level ``calibration:`` block, so a calibrated file is again a description.

Parsing is strict: unknown keys, wrong shapes, non-finite numbers and
non-orthonormal orientations are :class:`~imu_array_ros.errors.ConfigError`
with a one-line message naming the file and the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from imu_array_ros.io.atomic import atomic_write_text
from imu_array_ros.errors import ConfigError

__all__ = [
    "TriadCalibration",
    "ImuSpec",
    "ArrayDescription",
    "load_description",
    "save_description",
    "description_from_dict",
    "description_to_dict",
]

_TOP_KEYS = {"imu_array", "calibration"}
_ARRAY_KEYS = {
    "frame_id",
    "accelerometer_noise_std",
    "gyroscope_noise_std",
    "gyroscope_range",
    "accelerometer_range",
    "imus",
}
#: Optional in ``imu_array:`` (SI units, > 0): the magnitude a raw reading clips
#: at (default: the range) and the quantisation step; a reading with
#: |y| >= clip - lsb/2 (no lsb: clip * (1 - 1e-9)) counts as saturated.
_OPTIONAL_ARRAY_KEYS = ("accelerometer_clip", "gyroscope_clip", "accelerometer_lsb", "gyroscope_lsb")
_IMU_KEYS = {"name", "position", "orientation", "position_std", "accelerometer", "gyroscope"}
_ACC_KEYS = {"gain", "nonorthogonality", "misalignment", "bias"}
_GYR_KEYS = {"gain", "misalignment", "bias"}


@dataclass(frozen=True)
class TriadCalibration:
    """Calibration of one sensor triad (nilsson2014 eq. 1-2), sensor frame.

    gain (3,) diagonal of K; nonorthogonality (3,) [l_yz, l_zy, l_zx] rad
    (always zero for gyroscopes); misalignment (3,) small rotation xi, rad;
    bias (3,) in m/s^2 or rad/s.
    """

    gain: np.ndarray = field(default_factory=lambda: np.ones(3))
    nonorthogonality: np.ndarray = field(default_factory=lambda: np.zeros(3))
    misalignment: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def is_identity(self) -> bool:
        return (
            np.all(self.gain == 1.0)
            and not np.any(self.nonorthogonality)
            and not np.any(self.misalignment)
            and not np.any(self.bias)
        )


@dataclass(frozen=True)
class ImuSpec:
    """One IMU of the array.

    position (3,) m: accelerometer triad in the array frame.
    orientation (3, 3): rotation sensor frame -> array frame (nominal).
    position_std (3,) m or None: set by geometry calibrations.
    """

    name: str
    position: np.ndarray
    orientation: np.ndarray
    position_std: np.ndarray | None = None
    accelerometer: TriadCalibration = field(default_factory=TriadCalibration)
    gyroscope: TriadCalibration = field(default_factory=TriadCalibration)


@dataclass(frozen=True)
class ArrayDescription:
    """The whole array: frame, noise figures, ranges, IMUs, calibration record.

    Ranges and clip levels are magnitudes of the raw readings: m/s^2 for the
    accelerometers, rad/s for the gyroscopes.  ``*_clip`` (None: the range) is
    where a reading clips, ``*_lsb`` (None: unquantised floats) its
    quantisation step; see :func:`imu_array_ros.model.sensor_model.unsaturated`.
    """

    frame_id: str
    accelerometer_noise_std: float
    gyroscope_noise_std: float
    gyroscope_range: float
    accelerometer_range: float
    imus: tuple[ImuSpec, ...]
    calibration: dict | None = None
    source: str = "<memory>"
    accelerometer_clip: float | None = None
    gyroscope_clip: float | None = None
    accelerometer_lsb: float | None = None
    gyroscope_lsb: float | None = None

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(imu.name for imu in self.imus)

    @property
    def positions(self) -> np.ndarray:
        """(K, 3) accelerometer positions in the array frame, m."""
        return np.array([imu.position for imu in self.imus], dtype=float).reshape(-1, 3)

    @property
    def orientations(self) -> np.ndarray:
        """(K, 3, 3) rotations sensor -> array."""
        return np.array([imu.orientation for imu in self.imus], dtype=float).reshape(-1, 3, 3)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise ConfigError(f"{self.source}: unknown IMU name {name!r}") from None

    def with_imus(self, imus, **changes) -> "ArrayDescription":
        return replace(self, imus=tuple(imus), **changes)


# --------------------------------------------------------------------------- parsing


def _fail(source: str, where: str, msg: str) -> ConfigError:
    return ConfigError(f"{source}: {where}: {msg}")


def _number(source: str, where: str, value: Any, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(source, where, f"expected a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise _fail(source, where, f"must be finite, got {value!r}")
    if positive and x <= 0:
        raise _fail(source, where, f"must be > 0, got {value!r}")
    return x


def _vector(source: str, where: str, value: Any, n: int, *, positive: bool = False) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise _fail(source, where, f"expected a list of {n} numbers, got {value!r}")
    return np.array([_number(source, f"{where}[{i}]", v, positive=positive) for i, v in enumerate(value)])


def _check_keys(source: str, where: str, mapping: Any, allowed: set[str], required: set[str]) -> dict:
    if not isinstance(mapping, dict):
        raise _fail(source, where, f"expected a mapping, got {type(mapping).__name__}")
    unknown = sorted(set(map(str, mapping)) - allowed)
    if unknown:
        raise _fail(source, where, f"unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")
    missing = sorted(required - set(mapping))
    if missing:
        raise _fail(source, where, f"missing key {missing[0]!r}")
    return mapping


def _triad(source: str, where: str, value: Any, allowed: set[str]) -> TriadCalibration:
    if value is None:
        return TriadCalibration()
    m = _check_keys(source, where, value, allowed, set())
    kw = {}
    for key in allowed:
        if key in m:
            kw[key] = _vector(source, f"{where}.{key}", m[key], 3, positive=(key == "gain"))
    return TriadCalibration(**kw)


def _rotation(source: str, where: str, value: Any) -> np.ndarray:
    if isinstance(value, (list, tuple)) and len(value) == 3 and all(isinstance(r, (list, tuple)) for r in value):
        flat = [x for row in value for x in row]
    else:
        flat = value
    r = _vector(source, where, flat, 9).reshape(3, 3)
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise _fail(source, where, "must be a proper rotation matrix (orthonormal, det +1), row-major")
    return r


def description_from_dict(data: Any, source: str = "<memory>") -> ArrayDescription:
    """Validate a parsed YAML document and build an :class:`ArrayDescription`."""
    top = _check_keys(source, "top level", data, _TOP_KEYS, {"imu_array"})
    arr = _check_keys(source, "imu_array", top["imu_array"], _ARRAY_KEYS | set(_OPTIONAL_ARRAY_KEYS), _ARRAY_KEYS)
    frame_id = arr["frame_id"]
    if not isinstance(frame_id, str) or not frame_id:
        raise _fail(source, "imu_array.frame_id", "expected a non-empty string")
    imus_raw = arr["imus"]
    if not isinstance(imus_raw, list) or not imus_raw:
        raise _fail(source, "imu_array.imus", "expected a non-empty list of IMUs")
    imus = []
    seen: set[str] = set()
    for i, raw in enumerate(imus_raw):
        where = f"imu_array.imus[{i}]"
        m = _check_keys(source, where, raw, _IMU_KEYS, {"name", "position", "orientation"})
        name = m["name"]
        if not isinstance(name, str) or not name or not name.replace("_", "").isalnum() or name[0].isdigit():
            raise _fail(source, f"{where}.name", f"must be a ROS name token (letters, digits, _), got {name!r}")
        if name in seen:
            raise _fail(source, f"{where}.name", f"duplicate IMU name {name!r}")
        seen.add(name)
        where = f"imu {name!r}"
        imus.append(
            ImuSpec(
                name=name,
                position=_vector(source, f"{where}.position", m["position"], 3),
                orientation=_rotation(source, f"{where}.orientation", m["orientation"]),
                position_std=(
                    None
                    if m.get("position_std") is None
                    else _vector(source, f"{where}.position_std", m["position_std"], 3)
                ),
                accelerometer=_triad(source, f"{where}.accelerometer", m.get("accelerometer"), _ACC_KEYS),
                gyroscope=_triad(source, f"{where}.gyroscope", m.get("gyroscope"), _GYR_KEYS),
            )
        )
    calibration = top.get("calibration")
    if calibration is not None and not isinstance(calibration, dict):
        raise _fail(source, "calibration", "expected a mapping")
    clip = {key: _number(source, f"imu_array.{key}", arr[key], positive=True) for key in _OPTIONAL_ARRAY_KEYS
            if key in arr}
    for sensor in ("accelerometer", "gyroscope"):
        level = clip.get(f"{sensor}_clip") or _number(source, f"imu_array.{sensor}_range", arr[f"{sensor}_range"], positive=True)
        if clip.get(f"{sensor}_lsb", 0.0) >= level:
            raise _fail(source, f"imu_array.{sensor}_lsb", f"must be below the clip level {level!r}, got {arr[f'{sensor}_lsb']!r}")
    return ArrayDescription(
        **clip,
        frame_id=frame_id,
        accelerometer_noise_std=_number(source, "imu_array.accelerometer_noise_std", arr["accelerometer_noise_std"], positive=True),
        gyroscope_noise_std=_number(source, "imu_array.gyroscope_noise_std", arr["gyroscope_noise_std"], positive=True),
        gyroscope_range=_number(source, "imu_array.gyroscope_range", arr["gyroscope_range"], positive=True),
        accelerometer_range=_number(source, "imu_array.accelerometer_range", arr["accelerometer_range"], positive=True),
        imus=tuple(imus),
        calibration=calibration,
        source=source,
    )


def load_description(path: str | Path) -> ArrayDescription:
    """Read and validate an array description YAML file."""
    from imu_array_ros.io.yamlfile import load_yaml_file  # YAML read errors are worded in one place

    path = Path(path)
    data = load_yaml_file(path, ConfigError, "array description")
    return description_from_dict(data, source=str(path))


# --------------------------------------------------------------------------- writing


def _floats(v) -> list[float]:
    return [float(x) for x in np.asarray(v, dtype=float).ravel()]


def _triad_dict(cal: TriadCalibration, with_nonorth: bool) -> dict:
    d = {"gain": _floats(cal.gain)}
    if with_nonorth:
        d["nonorthogonality"] = _floats(cal.nonorthogonality)
    d["misalignment"] = _floats(cal.misalignment)
    d["bias"] = _floats(cal.bias)
    return d


def description_to_dict(desc: ArrayDescription) -> dict:
    """Plain-data form of a description (inverse of :func:`description_from_dict`)."""
    imus = []
    for imu in desc.imus:
        d: dict[str, Any] = {
            "name": imu.name,
            "position": _floats(imu.position),
            "orientation": _floats(imu.orientation),
        }
        if imu.position_std is not None:
            d["position_std"] = _floats(imu.position_std)
        if not imu.accelerometer.is_identity:
            d["accelerometer"] = _triad_dict(imu.accelerometer, True)
        if not imu.gyroscope.is_identity:
            d["gyroscope"] = _triad_dict(imu.gyroscope, False)
        imus.append(d)
    out: dict[str, Any] = {
        "imu_array": {
            "frame_id": desc.frame_id,
            "accelerometer_noise_std": float(desc.accelerometer_noise_std),
            "gyroscope_noise_std": float(desc.gyroscope_noise_std),
            "gyroscope_range": float(desc.gyroscope_range),
            "accelerometer_range": float(desc.accelerometer_range),
            **{key: float(getattr(desc, key)) for key in _OPTIONAL_ARRAY_KEYS if getattr(desc, key) is not None},
            "imus": imus,
        }
    }
    if desc.calibration is not None:
        out["calibration"] = desc.calibration
    return out


class _FlowListDumper(yaml.SafeDumper):
    """Write short numeric lists inline ([x, y, z]) and keep key order."""


def _represent_list(dumper, data):
    flow = all(isinstance(x, (int, float)) for x in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_FlowListDumper.add_representer(list, _represent_list)


def dump_description(desc: ArrayDescription) -> str:
    return yaml.dump(description_to_dict(desc), Dumper=_FlowListDumper, sort_keys=False, width=120)


def save_description(desc: ArrayDescription, path: str | Path) -> None:
    """Write a description atomically; the result re-validates before it lands."""
    text = dump_description(desc)
    description_from_dict(yaml.safe_load(text), source=str(path))  # never write what we can't read
    atomic_write_text(path, text)
