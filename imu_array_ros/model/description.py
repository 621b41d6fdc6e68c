"""Array description: the YAML input contract (see README "Array description").

One file describes the array geometry, the noise figures, and optionally each
IMU's values of the sensor-model terms (:mod:`imu_array_ros.model.terms`), all
in the IMU's sensor frame.  The per-IMU schema is *driven by the term
registry*: every :class:`~imu_array_ros.model.terms.Field` of every registered
term is a key (``position`` at the IMU's top level, ``accelerometer.gain`` as
``gain`` in the IMU's ``accelerometer`` mapping, ...), and every field ``F``
may carry ``F_std`` beside it (same shape, >= 0: the standard deviation a
calibration reports).  A new term's fields are therefore parsed, validated and
written with nothing here edited.  Calibrations write this same schema back,
plus a top-level ``calibration:`` block, so a calibrated file is again a
description; fields a file gives are written back as given (``save(load(x))``
keeps every value), fields it omits take the term's identity value.

Per-IMU noise figures (optional, written by ``imu-array calibrate noise``; docs/noise.md): in an
IMU's ``accelerometer`` and ``gyroscope`` mappings, ``noise_std`` (3 numbers > 0: the white-noise
standard deviation per sample, per axis, m/s^2 or rad/s; it replaces the pooled
``imu_array.*_noise_std`` for that IMU), ``bias_random_walk`` (3, >= 0: K, unit/sqrt(s)) and
``bias_instability`` (3, >= 0: B, unit); in the last two an axis may be ``null`` (not determined).

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

from imu_array_ros.util.files import atomic_write_text, parse_yaml
from imu_array_ros.errors import ConfigError
from imu_array_ros.model.terms import REGISTRY, Field, term_names

__all__ = [
    "ImuSpec",
    "ArrayDescription",
    "load_description",
    "save_description",
    "description_from_dict",
    "description_to_dict",
    "NOISE_FIELDS",
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
STD_SUFFIX = "_std"
#: per-IMU noise figures in the ``accelerometer`` / ``gyroscope`` mappings (module docstring); the
#: ones that may hold ``null`` (not determined) per axis are the last two
NOISE_FIELDS = ("noise_std", "bias_random_walk", "bias_instability")
_NOISE_SENSORS = ("accelerometer", "gyroscope")


def term_fields() -> dict[str, Field]:
    """Every registered term's YAML fields by dotted key, in chain order (``position`` first)."""
    out: dict[str, Field] = {}
    for name in term_names():
        for f in REGISTRY[name].fields:
            out[f.key] = f
    return out


@dataclass(frozen=True)
class ImuSpec:
    """One IMU of the array.

    position (3,) m: accelerometer triad in the array frame.
    orientation (3, 3): rotation sensor frame -> array frame (nominal).
    values: term field key (e.g. ``"accelerometer.gain"``) -> value, as the
    file gave it (fields not given take the term's identity value, see
    :meth:`value`); ``position`` lives in its own attribute.
    stds: field key (``"position"`` included) -> standard deviation, same shape.
    noise: ``"<sensor>.<figure>"`` (sensor accelerometer/gyroscope, figure one of
    :data:`NOISE_FIELDS`) -> (3,) per axis; NaN: not determined.  Absent ``noise_std``: the
    array's pooled figure holds.
    """

    name: str
    position: np.ndarray
    orientation: np.ndarray
    values: dict[str, np.ndarray] = field(default_factory=dict)
    stds: dict[str, np.ndarray] = field(default_factory=dict)
    noise: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def position_std(self) -> np.ndarray | None:
        return self.stds.get("position")

    def value(self, key: str) -> np.ndarray:
        """The value of term field ``key`` (its identity value when the file does not give it)."""
        if key == "position":
            return self.position
        if key in self.values:
            return self.values[key]
        return term_fields()[key].default_value()

    def with_values(self, values: dict | None = None, stds: dict | None = None) -> "ImuSpec":
        """A copy with some field values / standard deviations set (``position`` included)."""
        vals = {**self.values, **(values or {})}
        position = vals.pop("position", self.position)
        return replace(self, position=np.asarray(position, dtype=float), values=vals,
                       stds={**self.stds, **(stds or {})})

    def with_noise(self, noise: dict) -> "ImuSpec":
        """A copy with some noise figures (``"<sensor>.<figure>"`` -> (3,), NaN: not determined) set."""
        return replace(self, noise={**self.noise, **{k: np.asarray(v, dtype=float).reshape(3) for k, v in noise.items()}})


@dataclass(frozen=True)
class ArrayDescription:
    """The whole array: frame, noise figures, ranges, IMUs, calibration record.

    Ranges and clip levels are magnitudes of the raw readings: m/s^2 for the
    accelerometers, rad/s for the gyroscopes.  ``*_clip`` (None: the range) is
    where a reading clips, ``*_lsb`` (None: unquantised floats) its
    quantisation step; see :func:`imu_array_ros.model.linear.unsaturated`.
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

    def noise_std(self, sensor: str) -> np.ndarray:
        """(K, 3) white-noise std per IMU and axis of ``sensor`` ("accelerometer" or "gyroscope"): the IMU's own
        ``noise_std`` where it has one, else the array's pooled figure."""
        pooled = float(getattr(self, f"{sensor}_noise_std"))
        return np.array([np.asarray(imu.noise.get(f"{sensor}.noise_std", np.full(3, pooled)), dtype=float)
                         for imu in self.imus]).reshape(len(self.imus), 3)

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


def _field_value(source: str, where: str, value: Any, f: Field, *, std: bool = False) -> np.ndarray:
    """A term field (or its ``_std``) of the shape the field declares; 3x3 as rows or 9 numbers."""
    if f.shape == ():
        x = np.array(_number(source, where, value))
    else:
        if len(f.shape) == 2 and isinstance(value, (list, tuple)) and all(isinstance(r, (list, tuple)) for r in value):
            value = [x for row in value for x in row]
        x = _vector(source, where, value, f.size, positive=f.positive and not std).reshape(f.shape)
    if std and np.any(x < 0):
        raise _fail(source, where, f"a standard deviation must be >= 0, got {value!r}")
    if not std and f.positive and f.default == 0 and np.any(x < 0):
        raise _fail(source, where, f"must be >= 0 (0: not modelled), got {value!r}")
    return x


def _imu_terms(source: str, where: str, m: dict) -> tuple[dict, dict]:
    """(values, stds) of the term fields in one IMU's mapping ``m`` (keys already checked)."""
    values: dict[str, np.ndarray] = {}
    stds: dict[str, np.ndarray] = {}
    for key, f in term_fields().items():
        section = m if len(f.path) == 1 else m.get(f.path[0]) or {}
        leaf = f.path[-1]
        if leaf in section and f.session:
            raise _fail(source, f"{where}.{key}", "is a session state (it changes at every power-up; it is estimated "
                                                  "from each recording), not a device constant: remove it")
        if leaf in section and key != "position":
            values[key] = _field_value(source, f"{where}.{key}", section[leaf], f)
        if leaf + STD_SUFFIX in section:
            stds[key] = _field_value(source, f"{where}.{key}{STD_SUFFIX}", section[leaf + STD_SUFFIX], f, std=True)
    return values, stds


def _imu_schema() -> tuple[set[str], dict[str, set[str]]]:
    """Allowed keys of an IMU mapping and of each of its sections (``accelerometer``, ...)."""
    top = {"name", "orientation"}
    sections: dict[str, set[str]] = {}
    for f in term_fields().values():
        keys = top if len(f.path) == 1 else sections.setdefault(f.path[0], set())
        keys |= {f.path[-1], f.path[-1] + STD_SUFFIX}
    for sensor in _NOISE_SENSORS:
        sections.setdefault(sensor, set()).update(NOISE_FIELDS)
    return top | set(sections), sections


def _imu_noise(source: str, where: str, m: dict) -> dict[str, np.ndarray]:
    """The noise figures of one IMU's mapping ``m`` (module docstring); ``null`` axes -> NaN."""
    out: dict[str, np.ndarray] = {}
    for sensor in _NOISE_SENSORS:
        section = m.get(sensor) or {}
        for leaf in NOISE_FIELDS:
            if leaf not in section:
                continue
            at, value = f"{where}.{sensor}.{leaf}", section[leaf]
            if leaf == "noise_std":
                out[f"{sensor}.{leaf}"] = _vector(source, at, value, 3, positive=True)
                continue
            if not isinstance(value, (list, tuple)) or len(value) != 3:
                raise _fail(source, at, f"expected a list of 3 numbers (or null), got {value!r}")
            x = np.array([np.nan if v is None else _number(source, f"{at}[{i}]", v) for i, v in enumerate(value)])
            if np.any(x < 0):
                raise _fail(source, at, f"must be >= 0 (null: not determined), got {value!r}")
            out[f"{sensor}.{leaf}"] = x
    return out


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
    imu_keys, section_keys = _imu_schema()
    for i, raw in enumerate(imus_raw):
        where = f"imu_array.imus[{i}]"
        m = _check_keys(source, where, raw, imu_keys, {"name", "position", "orientation"})
        name = m["name"]
        if not isinstance(name, str) or not name or not name.replace("_", "").isalnum() or name[0].isdigit():
            raise _fail(source, f"{where}.name", f"must be a ROS name token (letters, digits, _), got {name!r}")
        if name in seen:
            raise _fail(source, f"{where}.name", f"duplicate IMU name {name!r}")
        seen.add(name)
        where = f"imu {name!r}"
        for sec, allowed in section_keys.items():
            if m.get(sec) is not None:
                _check_keys(source, f"{where}.{sec}", m[sec], allowed, set())
        values, stds = _imu_terms(source, where, m)
        imus.append(
            ImuSpec(
                name=name,
                position=_field_value(source, f"{where}.position", m["position"], term_fields()["position"]),
                orientation=_rotation(source, f"{where}.orientation", m["orientation"]),
                values=values,
                stds=stds,
                noise=_imu_noise(source, where, m),
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
    from imu_array_ros.util.files import load_yaml_file  # YAML read errors are worded in one place

    path = Path(path)
    data = load_yaml_file(path, ConfigError, "array description")
    return description_from_dict(data, source=str(path))


# --------------------------------------------------------------------------- writing


def _floats(v) -> list[float]:
    return [float(x) for x in np.asarray(v, dtype=float).ravel()]


def _imu_dict(imu: ImuSpec) -> dict:
    """One IMU's mapping: name, position(_std), orientation, then each section's fields in chain order."""
    d: dict[str, Any] = {"name": imu.name, "position": _floats(imu.position)}
    if "position" in imu.stds:
        d["position_std"] = _floats(imu.stds["position"])
    d["orientation"] = _floats(imu.orientation)
    for key, f in term_fields().items():
        if key == "position" or f.session or (key not in imu.values and key not in imu.stds):
            continue  # a session state is never written as a device constant
        section = d.setdefault(f.path[0], {})
        for leaf, src in ((f.path[-1], imu.values), (f.path[-1] + STD_SUFFIX, imu.stds)):
            if key in src:
                v = np.asarray(src[key], dtype=float)
                section[leaf] = float(v) if f.shape == () else (
                    [_floats(row) for row in v.reshape(f.shape)] if len(f.shape) == 2 else _floats(v))
    for sensor in _NOISE_SENSORS:
        for leaf in NOISE_FIELDS:
            v = imu.noise.get(f"{sensor}.{leaf}")
            if v is not None:
                d.setdefault(sensor, {})[leaf] = [float(x) if np.isfinite(x) else None for x in np.ravel(v)]
    return d


def description_to_dict(desc: ArrayDescription) -> dict:
    """Plain-data form of a description (inverse of :func:`description_from_dict`)."""
    imus = [_imu_dict(imu) for imu in desc.imus]
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
    flow = all(x is None or isinstance(x, (int, float)) for x in data) or all(
        isinstance(r, list) and all(isinstance(x, (int, float)) for x in r) for r in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_FlowListDumper.add_representer(list, _represent_list)


def dump_description(desc: ArrayDescription) -> str:
    return yaml.dump(description_to_dict(desc), Dumper=_FlowListDumper, sort_keys=False, width=120)


def save_description(desc: ArrayDescription, path: str | Path) -> None:
    """Write a description atomically; the result re-validates before it lands."""
    text = dump_description(desc)
    description_from_dict(parse_yaml(text), source=str(path))  # never write what we can't read
    atomic_write_text(path, text)
