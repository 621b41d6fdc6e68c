"""Kalibr's IMU-set YAML, both ways: an array description <-> ``imu0``, ``imu1``, ... (docs/kalibr.md).

Kalibr (ethz-asl/kalibr, ``kalibr_calibrate_imu_camera``) writes the IMUs of a multi-IMU calibration
as one mapping ``imuN`` per IMU (its ``ImuSetParameters``); each block holds the IMU's own
configuration (the file ``--imu`` takes per IMU) plus the results::

    accelerometer_noise_density  (m/s^2)/sqrt(Hz)   white noise, continuous time
    accelerometer_random_walk    (m/s^3)/sqrt(Hz)   bias random walk (= our K, (m/s^2)/sqrt(s))
    gyroscope_noise_density      (rad/s)/sqrt(Hz)
    gyroscope_random_walk        (rad/s^2)/sqrt(Hz)
    rostopic, update_rate (Hz: the rate the densities are discretised at, sigma = density sqrt(rate))
    model                        calibrated | scale-misalignment
    T_i_b                        4x4: body frame -> IMU frame, [[C_i_b, -C_i_b r_b], [0, 1]]
    time_offset                  s: the sample stamped t was taken at t + time_offset
    accelerometers: {M}, gyroscopes: {M, A, C_gyro_i}   (scale-misalignment only)

Kalibr's scale-misalignment model (its ``IccScaledMisalignedImu``), with f_b, w_b the specific
force at the IMU and the angular rate in the body frame: accelerometer ``M_a C_i_b f_b + b``,
gyroscope ``M_g C_gyro_i C_i_b w_b + A C_gyro_i C_i_b f_b + b``, M_a and M_g lower triangular.
Ours (:mod:`imu_array_ros.model.terms.triad`): accelerometer ``K L (I + [xi]x) R^T f + b``, gyroscope
``K_g L_g (I + [xi_g]x) R^T w + G R^T f + b``.  They map exactly: the LQ factorisation
``K L (I + [xi]x) = M_a Q`` gives ``C_i_b = Q R^T`` (so the accelerometer misalignment is carried by
T_i_b's rotation), then ``M_g C_gyro_i = T_g Q^T`` (LQ again) and ``A = G Q^T C_gyro_i^T``.  Without
an accelerometer misalignment Q = I and ``C_i_b = R^T``.

Kalibr's noise figures are one number per sensor; ours are per axis: the root mean square over the
axes is written (it keeps the trace of the covariance) and read back on every axis.  Biases, bias
drift, nonlinearity, axis offsets, clocks and the accelerometer's own time offset have no place in
the format and are listed in the notes of :func:`kalibr_from_description`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from imu_array_ros.errors import ConfigError
from imu_array_ros.io.rosbag.recording import imu_topic
from imu_array_ros.model.description import ArrayDescription, ImuSpec, term_fields
from imu_array_ros.model.terms.triad import decompose_triad, triad_matrix
from imu_array_ros.util.files import load_yaml_file

__all__ = ["KalibrImu", "MODELS", "IMU_KEYS", "INTRINSICS_KEYS", "kalibr_from_description", "kalibr_to_dict",
           "dump_kalibr", "kalibr_from_dict", "load_kalibr", "description_from_kalibr", "kalibr_transform", "lq"]

#: Kalibr IMU models this module reads and writes
MODELS = ("calibrated", "scale-misalignment")
#: the keys of every ``imuN`` block, in Kalibr's meaning (module docstring)
IMU_KEYS = ("accelerometer_noise_density", "accelerometer_random_walk", "gyroscope_noise_density",
            "gyroscope_random_walk", "rostopic", "update_rate", "model", "T_i_b", "time_offset")
#: the intrinsics sections of a scale-misalignment block and their matrices
INTRINSICS_KEYS = {"accelerometers": ("M",), "gyroscopes": ("M", "A", "C_gyro_i")}
#: our term fields Kalibr's scale-misalignment model carries (position and orientation through T_i_b)
MAPPED_FIELDS = ("accelerometer.gain", "accelerometer.nonorthogonality", "accelerometer.misalignment",
                 "gyroscope.gain", "gyroscope.nonorthogonality", "gyroscope.misalignment", "gyroscope.g_sensitivity")
_SENSORS = ("accelerometer", "gyroscope")
_ROTATION_TOL = 1e-6
_TOPIC = re.compile(r"/([^/]+)/data_raw$")


@dataclass(frozen=True)
class KalibrImu:
    """One ``imuN`` block.  T_i_b (4, 4); densities, random walks scalars (module docstring units);
    ``intrinsics``: for scale-misalignment ``{"accelerometers": {"M": (3, 3)}, "gyroscopes": {"M", "A",
    "C_gyro_i"}}``, else None."""

    T_i_b: np.ndarray
    accelerometer_noise_density: float
    accelerometer_random_walk: float
    gyroscope_noise_density: float
    gyroscope_random_walk: float
    rostopic: str
    update_rate: float
    time_offset: float = 0.0
    model: str = "calibrated"
    intrinsics: dict | None = None


# --------------------------------------------------------------------------- linear algebra


def lq(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(L, Q) with ``L @ Q == x`` (3, 3): L lower triangular with a positive diagonal, Q orthogonal."""
    q, r = np.linalg.qr(np.asarray(x, dtype=float).T)
    d = np.sign(np.diag(r))
    d[d == 0] = 1.0
    return r.T * d[None, :], d[:, None] * q.T


def kalibr_transform(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """T_i_b (4, 4) of an IMU at ``position`` (3,) whose frame the body frame maps into by ``rotation``
    (C_i_b, 3x3): ``[[C, -C p], [0, 1]]``, so the IMU's position maps to the origin."""
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = -rotation @ np.asarray(position, dtype=float)
    return t


def _inverse(t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def _accelerometer_triad(imu: ImuSpec) -> np.ndarray:
    return triad_matrix(*(imu.value(f"accelerometer.{f}") for f in ("gain", "nonorthogonality", "misalignment")))


def _gyroscope_triad(imu: ImuSpec) -> np.ndarray:
    return triad_matrix(*(imu.value(f"gyroscope.{f}") for f in ("gain", "nonorthogonality", "misalignment")))


def _has_intrinsics(imu: ImuSpec) -> bool:
    fields = term_fields()
    return any(key in imu.values and np.any(imu.values[key] != fields[key].default_value()) for key in MAPPED_FIELDS)


def _imu_frame(imu: ImuSpec, model: str, source: str) -> tuple[np.ndarray, np.ndarray]:
    """(C_i_b, M_a): the IMU frame Kalibr sees for ``imu`` (array -> IMU) and its accelerometer matrix."""
    if model == "calibrated":
        return imu.orientation.T, np.eye(3)
    m_a, q = lq(_accelerometer_triad(imu))
    if np.linalg.det(q) <= 0:
        raise ConfigError(f"{source}: imu {imu.name!r}: the accelerometer triad (gain, nonorthogonality, "
                          "misalignment) mirrors the axes, which Kalibr's scale-misalignment model cannot hold")
    return q @ imu.orientation.T, m_a


# --------------------------------------------------------------------------- description -> Kalibr


def _rms(v: np.ndarray) -> float:
    v = np.asarray(v, dtype=float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v * v))) if v.size else math.nan


def _random_walk(imu: ImuSpec, sensor: str, fallback: float | None) -> float | None:
    """The bias random walk Kalibr gets for ``sensor`` of ``imu``: the description's, else ``fallback``; None
    when neither gives one (> 0)."""
    k = _rms(imu.noise.get(f"{sensor}.bias_random_walk", np.full(3, np.nan)))
    if math.isfinite(k) and k > 0:
        return k
    return None if fallback is None else float(fallback)


def _noise_record_has(desc: ArrayDescription, name: str, sensor: str) -> bool:
    """The description's ``calibration:`` record is a noise calibration that looked for ``sensor``'s random walk
    of IMU ``name`` (files written before ``calibrate noise`` kept an all-``null`` figure)."""
    record = desc.calibration if isinstance(desc.calibration, dict) else {}
    entry = (record.get("imus") or {}).get(name) if str(record.get("method", "")).startswith("noise:") else None
    return isinstance(entry, dict) and isinstance(entry.get(sensor), dict) and "bias_random_walk" in entry[sensor]


def _check_random_walks(desc: ArrayDescription, fallback: dict) -> None:
    """One ConfigError naming every sensor whose bias random walk Kalibr would lack (and its option)."""
    flags = {"accelerometer": "--random-walk-accel", "gyroscope": "--random-walk-gyro"}
    without = {s: [imu.name for imu in desc.imus if _random_walk(imu, s, fallback[s]) is None] for s in flags}
    lacking = [(s, names[0]) for s, names in without.items() if names]
    if lacking:
        what = " and ".join(f"the {s} (imu {name!r} and maybe others)" for s, name in lacking)
        by_name = {imu.name: imu for imu in desc.imus}
        measured = all(f"{s}.bias_random_walk" in by_name[name].noise or _noise_record_has(desc, name, s)
                       for s, name in lacking)
        how = ("the noise calibration it holds did not see one (its still intervals were too short for the "
               "random walk to show): calibrate noise on a longer still recording" if measured else
               "run 'imu-array calibrate noise' on a still recording")
        raise ConfigError(f"{desc.source}: Kalibr requires a bias_random_walk (> 0), which the description does not "
                          f"give for {what}: {how}, or give " + " and ".join(flags[s] for s, _ in lacking))


def kalibr_from_description(desc: ArrayDescription, *, rate: float, topic_prefix: str = "/imu_array",
                            model: str | None = None, random_walk_accel: float | None = None,
                            random_walk_gyro: float | None = None) -> tuple[list[KalibrImu], list[str]]:
    """The Kalibr blocks of every IMU of ``desc`` in its order, and notes on what is not carried over.

    ``rate`` (Hz): the rate the IMUs publish at (a description holds none); the white noise per sample
    (``noise_std``, else the pooled figure) becomes a density ``noise_std / sqrt(rate)``.  ``model``:
    one of :data:`MODELS`; None: scale-misalignment if any IMU gives a gain, nonorthogonality,
    misalignment or g-sensitivity, else calibrated.  ``random_walk_*``: the bias random walk of IMUs
    whose description gives none (Kalibr requires one).  ConfigError (one line) otherwise.
    """
    if not (math.isfinite(rate) and rate > 0):
        raise ConfigError(f"rate must be a positive number of Hz, got {rate!r}")
    for name, v in (("random_walk_accel", random_walk_accel), ("random_walk_gyro", random_walk_gyro)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ConfigError(f"{name} must be > 0 (Kalibr refuses 0), got {v!r}")
    if model is None:
        model = "scale-misalignment" if any(_has_intrinsics(imu) for imu in desc.imus) else "calibrated"
    if model not in MODELS:
        raise ConfigError(f"unknown Kalibr IMU model {model!r} (known: {', '.join(MODELS)})")
    walks = {"accelerometer": random_walk_accel, "gyroscope": random_walk_gyro}
    _check_random_walks(desc, walks)
    noise_std = {s: desc.noise_std(s) for s in _SENSORS}
    out = []
    for k, imu in enumerate(desc.imus):
        c_ib, m_a = _imu_frame(imu, model, desc.source)
        density = {s: _rms(noise_std[s][k]) / math.sqrt(rate) for s in _SENSORS}
        intrinsics = None
        if model == "scale-misalignment":
            q = c_ib @ imu.orientation  # C_i_b = Q R^T
            m_g, c_gi = lq(_gyroscope_triad(imu) @ q.T)
            a_g = imu.value("gyroscope.g_sensitivity").reshape(3, 3) @ q.T @ c_gi.T
            intrinsics = {"accelerometers": {"M": m_a}, "gyroscopes": {"M": m_g, "A": a_g, "C_gyro_i": c_gi}}
        out.append(KalibrImu(
            T_i_b=kalibr_transform(c_ib, imu.position),
            accelerometer_noise_density=density["accelerometer"],
            accelerometer_random_walk=_random_walk(imu, "accelerometer", random_walk_accel),
            gyroscope_noise_density=density["gyroscope"],
            gyroscope_random_walk=_random_walk(imu, "gyroscope", random_walk_gyro),
            rostopic=imu_topic(imu.name, topic_prefix), update_rate=float(rate),
            time_offset=float(imu.value("gyroscope.time_offset")), model=model, intrinsics=intrinsics))
    return out, _export_notes(desc, model)


def _export_notes(desc: ArrayDescription, model: str) -> list[str]:
    """What the description gives that the Kalibr file does not hold."""
    fields = term_fields()
    carried = {"position", "gyroscope.time_offset", *(MAPPED_FIELDS if model == "scale-misalignment" else ())}
    dropped = sorted({key for imu in desc.imus for key, v in imu.values.items()
                      if key not in carried and np.any(v != fields[key].default_value())},
                     key=list(fields).index)
    notes = []
    offsets = [imu.name for imu in desc.imus
               if imu.value("accelerometer.time_offset") != imu.value("gyroscope.time_offset")]
    if offsets:
        notes.append(f"Kalibr has one time_offset per IMU: the gyroscope's is written; the accelerometer's differs "
                     f"for {len(offsets)} IMU(s) (e.g. {offsets[0]})")
        dropped = [k for k in dropped if k != "accelerometer.time_offset"]
    if dropped:
        where = "they stay in the description" if model == "calibrated" else "Kalibr's format has no place for them"
        notes.append(f"not written to the Kalibr file ({where}): {', '.join(dropped)}")
    if any("bias_instability" in k for imu in desc.imus for k in imu.noise):
        notes.append("not written to the Kalibr file (no place for it): bias_instability")
    return notes


def _floats(m: np.ndarray) -> list:
    m = np.asarray(m, dtype=float)
    return [_floats(row) for row in m] if m.ndim > 1 else [float(x) for x in m]


def kalibr_to_dict(imus: list[KalibrImu]) -> dict:
    """The plain-data IMU set: ``{"imu0": {...}, "imu1": {...}}`` with exactly Kalibr's keys."""
    out: dict[str, Any] = {}
    for n, k in enumerate(imus):
        block: dict[str, Any] = {
            "accelerometer_noise_density": float(k.accelerometer_noise_density),
            "accelerometer_random_walk": float(k.accelerometer_random_walk),
            "gyroscope_noise_density": float(k.gyroscope_noise_density),
            "gyroscope_random_walk": float(k.gyroscope_random_walk),
            "rostopic": k.rostopic, "update_rate": float(k.update_rate), "model": k.model,
            "T_i_b": _floats(k.T_i_b), "time_offset": float(k.time_offset),
        }
        for section, mats in (k.intrinsics or {}).items():
            block[section] = {name: _floats(mats[name]) for name in INTRINSICS_KEYS[section]}
        out[f"imu{n}"] = block
    return out


class _Dumper(yaml.SafeDumper):
    """Matrix rows inline ([a, b, c]), key order kept."""


_Dumper.add_representer(list, lambda d, data: d.represent_sequence(
    "tag:yaml.org,2002:seq", data, flow_style=all(isinstance(x, (int, float)) for x in data)))


def dump_kalibr(imus: list[KalibrImu]) -> str:
    """The YAML text of the IMU set (floats written exactly: they read back bit for bit)."""
    return yaml.dump(kalibr_to_dict(imus), Dumper=_Dumper, sort_keys=False, width=120)


# --------------------------------------------------------------------------- Kalibr file -> blocks


def _number(source: str, where: str, value: Any, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{source}: {where}: expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise ConfigError(f"{source}: {where}: must be > 0, got {value!r}")
    return float(value)


def _matrix(source: str, where: str, value: Any, n: int) -> np.ndarray:
    if not (isinstance(value, list) and len(value) == n and all(isinstance(r, list) and len(r) == n for r in value)):
        raise ConfigError(f"{source}: {where}: expected a {n}x{n} matrix (a list of {n} rows), got {value!r}")
    return np.array([[_number(source, f"{where}[{i}][{j}]", x) for j, x in enumerate(r)] for i, r in enumerate(value)])


def _check_rotation(source: str, where: str, r: np.ndarray) -> None:
    if not np.allclose(r @ r.T, np.eye(3), atol=_ROTATION_TOL) or np.linalg.det(r) <= 0:
        raise ConfigError(f"{source}: {where}: must be a proper rotation (orthonormal, det +1)")


def _block(source: str, name: str, raw: Any) -> KalibrImu:
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: {name}: expected a mapping, got {type(raw).__name__}")
    unknown = sorted(set(map(str, raw)) - set(IMU_KEYS) - set(INTRINSICS_KEYS))
    if unknown:
        raise ConfigError(f"{source}: {name}: unknown key {unknown[0]!r} (Kalibr's: {', '.join(IMU_KEYS)}, "
                          f"{', '.join(INTRINSICS_KEYS)})")
    for key in IMU_KEYS[:6] + ("T_i_b",):
        if key not in raw:
            raise ConfigError(f"{source}: {name}: missing key {key!r}"
                              + (" (a Kalibr input file, not a calibration result?)" if key == "T_i_b" else ""))
    model = raw.get("model", "calibrated")
    if model not in MODELS:
        raise ConfigError(f"{source}: {name}: model {model!r} is not imported (only {', '.join(MODELS)})")
    t = _matrix(source, f"{name}.T_i_b", raw["T_i_b"], 4)
    if not np.allclose(t[3], [0, 0, 0, 1], atol=1e-12):
        raise ConfigError(f"{source}: {name}.T_i_b: the last row must be [0, 0, 0, 1]")
    _check_rotation(source, f"{name}.T_i_b", t[:3, :3])
    if not isinstance(raw["rostopic"], str):
        raise ConfigError(f"{source}: {name}.rostopic: expected a string")
    intrinsics = None
    if model == "scale-misalignment":
        intrinsics = {}
        for section, names in INTRINSICS_KEYS.items():
            sec = raw.get(section)
            if not isinstance(sec, dict) or set(sec) != set(names):
                raise ConfigError(f"{source}: {name}.{section}: expected a mapping with {', '.join(names)} "
                                  f"(model scale-misalignment)")
            intrinsics[section] = {m: _matrix(source, f"{name}.{section}.{m}", sec[m], 3) for m in names}
            for m in ("M",):
                mat = intrinsics[section][m]
                if np.any(np.triu(mat, 1) != 0) or np.any(np.diag(mat) <= 0):
                    raise ConfigError(f"{source}: {name}.{section}.M: must be lower triangular with a positive "
                                      "diagonal (Kalibr's scale-misalignment)")
        _check_rotation(source, f"{name}.gyroscopes.C_gyro_i", intrinsics["gyroscopes"]["C_gyro_i"])
    elif any(s in raw for s in INTRINSICS_KEYS):
        raise ConfigError(f"{source}: {name}: intrinsics given but model is {model!r}")
    return KalibrImu(
        T_i_b=t, rostopic=raw["rostopic"], model=model, intrinsics=intrinsics,
        update_rate=_number(source, f"{name}.update_rate", raw["update_rate"], positive=True),
        time_offset=_number(source, f"{name}.time_offset", raw.get("time_offset", 0.0)),
        **{k: _number(source, f"{name}.{k}", raw[k], positive=True) for k in IMU_KEYS[:4]})


def kalibr_from_dict(data: Any, source: str = "<memory>") -> list[KalibrImu]:
    """Validate a parsed Kalibr IMU set (``imu0`` ... ``imu{n-1}``, nothing else); ConfigError (one line)."""
    if not isinstance(data, dict) or not data:
        raise ConfigError(f"{source}: expected a Kalibr IMU set (a mapping imu0, imu1, ...)")
    names = [f"imu{n}" for n in range(len(data))]
    if set(map(str, data)) != set(names):
        odd = sorted(set(map(str, data)) - set(names)) or sorted(set(names) - set(map(str, data)))
        raise ConfigError(f"{source}: expected the keys imu0 ... imu{len(data) - 1} of a Kalibr IMU set, "
                          f"found {odd[0]!r}")
    return [_block(source, n, data[n]) for n in names]


def load_kalibr(path: str | Path) -> list[KalibrImu]:
    """Read and validate a Kalibr IMU-set YAML file."""
    return kalibr_from_dict(load_yaml_file(path, ConfigError, "Kalibr IMU file"), source=str(path))


# --------------------------------------------------------------------------- blocks -> description


def description_from_kalibr(imus: list[KalibrImu], array: ArrayDescription, source: str = "<memory>"
                            ) -> tuple[ArrayDescription, list[str]]:
    """``array`` with the values Kalibr's blocks give, matched by order (imu0 -> the first IMU), and notes.

    Positions and orientations from T_i_b, after placing Kalibr's body frame so that imu0 keeps the
    pose ``array`` gives it (Kalibr's results use imu0 as the body frame; a file written by
    :func:`kalibr_from_description` is left as it is); time offsets likewise relative to imu0's.
    Per IMU: ``noise_std`` = density sqrt(update_rate) and ``bias_random_walk`` on all three axes;
    the gyroscope time offset (the accelerometer's keeps its difference to it); with
    scale-misalignment, the gains, nonorthogonalities, gyroscope misalignment and g-sensitivity (the
    accelerometer misalignment is then 0: T_i_b's rotation holds it).  Everything else stays as
    ``array`` gives it; standard deviations of replaced fields are dropped.
    """
    if len(imus) != len(array.imus):
        raise ConfigError(f"{source}: {len(imus)} IMUs but {array.source} has {len(array.imus)} "
                          "(IMUs are matched by order: imu0 is the first)")
    for n, (k, imu) in enumerate(zip(imus, array.imus)):
        m = _TOPIC.search(k.rostopic)
        if m and m.group(1) in array.names and m.group(1) != imu.name:
            raise ConfigError(f"{source}: imu{n}'s rostopic {k.rostopic!r} names IMU {m.group(1)!r}, but by order "
                              f"imu{n} is {imu.name!r} in {array.source}")
    c0, _ = _imu_frame(array.imus[0], imus[0].model, array.source)
    t_ba = _inverse(imus[0].T_i_b) @ kalibr_transform(c0, array.imus[0].position)
    dt = float(array.imus[0].value("gyroscope.time_offset")) - imus[0].time_offset
    out = [_imu_from_kalibr(k, imu, t_ba, dt) for k, imu in zip(imus, array.imus)]
    notes = []
    moved = np.abs(t_ba - np.eye(4)).max()
    if moved > 1e-9 or abs(dt) > 1e-12:
        notes.append(f"Kalibr's body frame placed on {array.imus[0].name}'s pose in {array.source} "
                     f"(moved by up to {moved:.3g}; time offsets shifted by {dt:+.3g} s)")
    calibration = {"method": "import kalibr", "source": str(source),
                   "models": sorted({k.model for k in imus})}
    return array.with_imus(out, calibration=calibration), notes


def _imu_from_kalibr(k: KalibrImu, imu: ImuSpec, t_ba: np.ndarray, dt: float) -> ImuSpec:
    t_ia = k.T_i_b @ t_ba
    c = t_ia[:3, :3]
    values: dict[str, np.ndarray] = {"position": -c.T @ t_ia[:3, 3]}
    if k.intrinsics is not None:
        m_a = k.intrinsics["accelerometers"]["M"]
        values["accelerometer.gain"] = np.diag(m_a).copy()
        values["accelerometer.nonorthogonality"] = np.array(
            [m_a[1, 0] / m_a[1, 1], m_a[2, 0] / m_a[2, 2], m_a[2, 1] / m_a[2, 2]])
        values["accelerometer.misalignment"] = np.zeros(3)
        g = k.intrinsics["gyroscopes"]
        c_gi = g["C_gyro_i"]
        gain, low, xi = decompose_triad(g["M"] @ c_gi)
        values.update({"gyroscope.gain": gain, "gyroscope.nonorthogonality": low, "gyroscope.misalignment": xi,
                       "gyroscope.g_sensitivity": g["A"] @ c_gi})
    offset = k.time_offset + dt
    offsets = {"accelerometer.time_offset": offset + float(imu.value("accelerometer.time_offset"))
               - float(imu.value("gyroscope.time_offset")), "gyroscope.time_offset": offset}
    values.update({key: np.array(v) for key, v in offsets.items() if v != 0 or key in imu.values})
    stds = {key: v for key, v in imu.stds.items() if key not in values}
    noise = dict(imu.noise)
    for sensor in _SENSORS:
        density, walk = getattr(k, f"{sensor}_noise_density"), getattr(k, f"{sensor}_random_walk")
        noise[f"{sensor}.noise_std"] = np.full(3, density * math.sqrt(k.update_rate))
        noise[f"{sensor}.bias_random_walk"] = np.full(3, walk)
    kept = {key: v for key, v in imu.values.items() if key not in values}
    spec = ImuSpec(name=imu.name, position=imu.position, orientation=c.T.copy(), values=kept, stds=stds, noise=noise)
    return spec.with_values(values)
