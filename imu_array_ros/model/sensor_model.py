"""The one sensor model of the array, built from composable error terms.

Measurement model of IMU k (nilsson2014 eq. 1-2, skog2016 eq. 1-5), in the
IMU's own sensor frame:

    accelerometer:  y_a = A_k s(r_k) + b_a,k + n_a,   A_k = K L (I + [xi]x) R_k^T
    gyroscope:      y_g = B_k omega  + b_g,k + n_g,   B_k = K (I + [xi]x) R_k^T

``R_k`` rotates sensor -> array frame, ``s(r_k)`` is the array-frame specific
force at the accelerometer position (skog2016 eq. 1), ``n`` white Gaussian noise
with the description's standard deviations, and readings at the sensor's clip
level are saturated (clipped by the simulator, dropped by the fusion; see
:func:`unsaturated`).

:class:`LinearArrayModel` holds these matrices as arrays; the fusion estimates
with it, the simulator measures with it.  Error terms (:class:`ErrorTerm`)
compose onto an :class:`~imu_array_ros.model.description.ArrayDescription`: each
term perturbs the fields it owns (positions, gains, ...), so the same terms
describe the truth in simulation and, later, what mismatch discovery adds to
the nominal model and tests.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol, Sequence

import numpy as np

from imu_array_ros.model.description import ArrayDescription, ImuSpec, TriadCalibration
from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.terms.triad import nonorthogonality_matrix

__all__ = [
    "LinearArrayModel",
    "nonorthogonality_matrix",
    "ErrorTerm",
    "PositionOffset",
    "AccelerometerGain",
    "AccelerometerNonorthogonality",
    "AccelerometerMisalignment",
    "AccelerometerBias",
    "GyroscopeGain",
    "GyroscopeMisalignment",
    "GyroscopeBias",
    "apply_terms",
    "random_error_terms",
    "CLIP_RELATIVE_TOLERANCE",
    "unsaturated",
]

#: Quantisation tolerance of a clip level, relative to it, when the description
#: gives no LSB (simulated floats: a clipped reading equals the clip level up to
#: rounding).
CLIP_RELATIVE_TOLERANCE = 1e-9


def unsaturated(values: np.ndarray, clip: float, tolerance: float | None = None) -> np.ndarray:
    """True where a reading is finite and not saturated (NaN and +-inf -> False).

    The one saturation rule of the package: a raw reading is saturated when
    ``|y| >= clip - tolerance``, with ``clip`` the magnitude the sensor clips at
    (same unit as ``values``) and ``tolerance`` half an LSB for quantised
    readings, or ``CLIP_RELATIVE_TOLERANCE * clip`` when None.  Use
    :meth:`LinearArrayModel.acc_unsaturated` / :meth:`~LinearArrayModel.gyro_unsaturated`,
    which pass the description's clip levels.  ``values`` any shape -> bool, same shape.
    """
    if tolerance is None:
        tolerance = CLIP_RELATIVE_TOLERANCE * clip
    level = clip - tolerance
    return (values < level) & (values > -level)  # no float temporary, unlike abs(values) < level


@dataclass(frozen=True)
class LinearArrayModel:
    """Array-wide linear measurement model (see module docstring).

    positions (K, 3) m, array frame; acc_matrix (K, 3, 3) sensor <- array incl.
    calibration; acc_bias (K, 3) m/s^2; gyro_matrix (K, 3, 3); gyro_bias (K, 3)
    rad/s; acc_std, gyro_std (K, 3) noise standard deviations per sensor axis;
    acc_range, gyro_range: nominal full-scale ranges (m/s^2, rad/s);
    acc_clip, gyro_clip: magnitude at which the raw readings clip (default: the
    range); acc_clip_tolerance, gyro_clip_tolerance: a reading with
    ``|y| >= clip - tolerance`` is saturated (default
    ``CLIP_RELATIVE_TOLERANCE * clip``; half an LSB for quantised sensors).
    """

    names: tuple[str, ...]
    frame_id: str
    positions: np.ndarray
    acc_matrix: np.ndarray
    acc_bias: np.ndarray
    gyro_matrix: np.ndarray
    gyro_bias: np.ndarray
    acc_std: np.ndarray
    gyro_std: np.ndarray
    acc_range: float
    gyro_range: float
    acc_clip: float | None = None
    gyro_clip: float | None = None
    acc_clip_tolerance: float | None = None
    gyro_clip_tolerance: float | None = None

    def __post_init__(self) -> None:
        for sensor in ("acc", "gyro"):
            clip = getattr(self, f"{sensor}_clip")
            clip = float(getattr(self, f"{sensor}_range") if clip is None else clip)
            tol = getattr(self, f"{sensor}_clip_tolerance")
            tol = CLIP_RELATIVE_TOLERANCE * clip if tol is None else float(tol)
            if not (np.isfinite(clip) and clip > 0 and 0 <= tol < clip):
                raise ValueError(f"{sensor}: need clip > 0 and 0 <= tolerance < clip, got {clip!r}, {tol!r}")
            object.__setattr__(self, f"{sensor}_clip", clip)
            object.__setattr__(self, f"{sensor}_clip_tolerance", tol)

    @property
    def n_imus(self) -> int:
        return len(self.names)

    def acc_unsaturated(self, values: np.ndarray) -> np.ndarray:
        """Raw accelerometer readings (any shape, m/s^2) that are finite and not clipped (:func:`unsaturated`)."""
        return unsaturated(values, self.acc_clip, self.acc_clip_tolerance)

    def gyro_unsaturated(self, values: np.ndarray) -> np.ndarray:
        """Raw gyroscope readings (any shape, rad/s) that are finite and not clipped (:func:`unsaturated`)."""
        return unsaturated(values, self.gyro_clip, self.gyro_clip_tolerance)

    @classmethod
    def from_description(cls, desc: ArrayDescription) -> "LinearArrayModel":
        rot_t = np.swapaxes(desc.orientations, 1, 2)  # array -> sensor
        acc = []
        gyr = []
        for imu, rt in zip(desc.imus, rot_t):
            a = imu.accelerometer
            acc.append(np.diag(a.gain) @ nonorthogonality_matrix(a.nonorthogonality) @ (np.eye(3) + skew(a.misalignment)) @ rt)
            g = imu.gyroscope
            gyr.append(np.diag(g.gain) @ nonorthogonality_matrix(g.nonorthogonality) @ (np.eye(3) + skew(g.misalignment)) @ rt)
        k = len(desc.imus)
        return cls(
            names=desc.names,
            frame_id=desc.frame_id,
            positions=desc.positions,
            acc_matrix=np.array(acc).reshape(k, 3, 3),
            acc_bias=np.array([imu.accelerometer.bias for imu in desc.imus]).reshape(k, 3),
            gyro_matrix=np.array(gyr).reshape(k, 3, 3),
            gyro_bias=np.array([imu.gyroscope.bias for imu in desc.imus]).reshape(k, 3),
            acc_std=np.full((k, 3), desc.accelerometer_noise_std),
            gyro_std=np.full((k, 3), desc.gyroscope_noise_std),
            acc_range=float(desc.accelerometer_range),
            gyro_range=float(desc.gyroscope_range),
            acc_clip=desc.accelerometer_clip,
            gyro_clip=desc.gyroscope_clip,
            acc_clip_tolerance=None if desc.accelerometer_lsb is None else 0.5 * desc.accelerometer_lsb,
            gyro_clip_tolerance=None if desc.gyroscope_lsb is None else 0.5 * desc.gyroscope_lsb,
        )

    def select(self, index: Sequence[int]) -> "LinearArrayModel":
        """A sub-array of the IMUs at ``index`` (e.g. to test an IMU dropping out)."""
        idx = np.asarray(index)
        return replace(
            self,
            names=tuple(self.names[i] for i in idx),
            positions=self.positions[idx],
            acc_matrix=self.acc_matrix[idx],
            acc_bias=self.acc_bias[idx],
            gyro_matrix=self.gyro_matrix[idx],
            gyro_bias=self.gyro_bias[idx],
            acc_std=self.acc_std[idx],
            gyro_std=self.gyro_std[idx],
        )


# --------------------------------------------------------------------------- error terms


class ErrorTerm(Protocol):
    """One composable error term: perturbs the description fields it owns.

    ``values`` is (K, d) — one row per IMU in description order.
    """

    name: str
    values: np.ndarray

    def apply(self, desc: ArrayDescription) -> ArrayDescription: ...


def _map_imus(desc: ArrayDescription, values: np.ndarray, fn) -> ArrayDescription:
    values = np.asarray(values, dtype=float)
    if values.shape[0] != len(desc.imus):
        raise ValueError(f"error term has {values.shape[0]} rows for {len(desc.imus)} IMUs")
    return desc.with_imus([fn(imu, v) for imu, v in zip(desc.imus, values)])


def _triad_term(sensor: str, field: str, combine):
    def apply(self, desc: ArrayDescription) -> ArrayDescription:
        def one(imu: ImuSpec, v: np.ndarray) -> ImuSpec:
            cal: TriadCalibration = getattr(imu, sensor)
            new = replace(cal, **{field: combine(getattr(cal, field), v)})
            return replace(imu, **{sensor: new})

        return _map_imus(desc, self.values, one)

    return apply


@dataclass(frozen=True)
class PositionOffset:
    """Accelerometer triad displaced by ``values`` (K, 3) m from its nominal position."""

    values: np.ndarray
    name: str = "position_offset"

    def apply(self, desc: ArrayDescription) -> ArrayDescription:
        return _map_imus(desc, self.values, lambda imu, v: replace(imu, position=imu.position + v))


@dataclass(frozen=True)
class AccelerometerGain:
    """Relative gain error: K <- K * (1 + values), values (K, 3)."""

    values: np.ndarray
    name: str = "accelerometer_gain"
    apply = _triad_term("accelerometer", "gain", lambda old, v: old * (1.0 + v))


@dataclass(frozen=True)
class AccelerometerNonorthogonality:
    """Sensitivity-axis non-orthogonality [l_yz, l_zy, l_zx] rad added, values (K, 3)."""

    values: np.ndarray
    name: str = "accelerometer_nonorthogonality"
    apply = _triad_term("accelerometer", "nonorthogonality", lambda old, v: old + v)


@dataclass(frozen=True)
class AccelerometerMisalignment:
    """Small mounting rotation xi (rad) added, values (K, 3)."""

    values: np.ndarray
    name: str = "accelerometer_misalignment"
    apply = _triad_term("accelerometer", "misalignment", lambda old, v: old + v)


@dataclass(frozen=True)
class AccelerometerBias:
    """Bias (m/s^2) added, values (K, 3)."""

    values: np.ndarray
    name: str = "accelerometer_bias"
    apply = _triad_term("accelerometer", "bias", lambda old, v: old + v)


@dataclass(frozen=True)
class GyroscopeGain:
    """Relative gyroscope gain error, values (K, 3)."""

    values: np.ndarray
    name: str = "gyroscope_gain"
    apply = _triad_term("gyroscope", "gain", lambda old, v: old * (1.0 + v))


@dataclass(frozen=True)
class GyroscopeMisalignment:
    """Small gyroscope mounting rotation (rad) added, values (K, 3)."""

    values: np.ndarray
    name: str = "gyroscope_misalignment"
    apply = _triad_term("gyroscope", "misalignment", lambda old, v: old + v)


@dataclass(frozen=True)
class GyroscopeBias:
    """Gyroscope bias (rad/s) added, values (K, 3)."""

    values: np.ndarray
    name: str = "gyroscope_bias"
    apply = _triad_term("gyroscope", "bias", lambda old, v: old + v)


def apply_terms(desc: ArrayDescription, terms: Sequence[ErrorTerm]) -> ArrayDescription:
    """Compose error terms onto a description, in order."""
    for term in terms:
        desc = term.apply(desc)
    return desc


#: Default 1-sigma sizes of seeded error terms: positions per carlsson2017 Sec. IV
#: (sigma_r = 1 mm would be the paper's pessimistic case; 0.1 mm is PCB placement,
#: skog2016 footnote 5); gain/bias/angles of the order of nilsson2014 Table I.
DEFAULT_ERROR_SCALES = {
    "position_offset": 1e-4,
    "accelerometer_gain": 5e-3,
    "accelerometer_nonorthogonality": np.deg2rad(0.2),
    "accelerometer_misalignment": np.deg2rad(0.5),
    "accelerometer_bias": 0.3,
    "gyroscope_bias": np.deg2rad(1.0),
}

_TERM_TYPES = {
    cls.__dataclass_fields__["name"].default: cls
    for cls in (
        PositionOffset,
        AccelerometerGain,
        AccelerometerNonorthogonality,
        AccelerometerMisalignment,
        AccelerometerBias,
        GyroscopeGain,
        GyroscopeMisalignment,
        GyroscopeBias,
    )
}


def random_error_terms(
    n_imus: int, rng: np.random.Generator, scales: dict[str, float] | None = None
) -> list[ErrorTerm]:
    """Seeded error terms: zero-mean Gaussian with the given 1-sigma ``scales``.

    ``scales`` maps term names (see :data:`DEFAULT_ERROR_SCALES`) to sigma; a
    term with scale 0 or absent from ``scales`` is not created.
    """
    scales = DEFAULT_ERROR_SCALES if scales is None else scales
    terms: list[ErrorTerm] = []
    for name, sigma in scales.items():
        if name not in _TERM_TYPES:
            raise ValueError(f"unknown error term {name!r} (known: {', '.join(sorted(_TERM_TYPES))})")
        if sigma:
            terms.append(_TERM_TYPES[name](values=rng.normal(0.0, float(sigma), (n_imus, 3))))
    return terms
