"""The fusion's fast linear form of the sensor model (:class:`LinearArrayModel`).

The one forward model is :class:`~imu_array_ros.model.sensor_model.SensorModel`
(nominal geometry + noise + ordered terms).  For the fusion it *linearises* to
this form: with z = [q(omega), omega_dot, s] (12; q the quadratic monomials of
omega, skog2016 eq. 5), every accelerometer axis and gyroscope axis of IMU k reads

    accelerometer:  y_a = D_k z + b_a,k + n_a,     D_k (3, 12)
    gyroscope:      y_g = B_k omega + b_g,k + n_g,  B_k (3, 3)

Every term flagged ``linear`` (position, axis_offsets, misalignment,
non-orthogonality, gain, bias) keeps the readings of this form, so
:func:`linear_design` obtains D_k, B_k and the biases *exactly* by evaluating
the model's linear terms on 13 probe motions; a new linear term needs nothing
here.  Per-axis lever arms (``axis_offsets``) thus enter exactly: each
accelerometer row gets the lever arm of its own proof mass.  With only the
nilsson2014 terms, D_k = A_k [M(r_k), -[r_k]x, I] with A_k = K L (I + [xi]x) R_k^T.
Terms that are not linear (nonlinearity, g-sensitivity, time offset, drift)
are compensated on the readings before the linear solve
(:func:`imu_array_ros.fusion.model_fusion.fuse_model`).

``n`` is white Gaussian noise with the description's standard deviations, and
readings at the sensor's clip level are saturated (clipped by the simulator,
dropped by the fusion; see :func:`unsaturated`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.kinematics import centripetal_matrix, euler_matrix
from imu_array_ros.model.saturation import CLIP_RELATIVE_TOLERANCE, clip_tolerance, unsaturated
from imu_array_ros.model.terms.triad import nonorthogonality_matrix

__all__ = ["LinearArrayModel", "nonorthogonality_matrix", "linear_design", "CLIP_RELATIVE_TOLERANCE", "unsaturated"]

@dataclass(frozen=True)
class LinearArrayModel:
    """Array-wide linear measurement model (see module docstring).

    positions (K, 3) m, array frame; acc_matrix (K, 3, 3) sensor <- array incl.
    calibration (the s columns of D); acc_design (K, 3, 12) D_k (default: from
    acc_matrix and positions, one lever arm per IMU); acc_bias (K, 3) m/s^2; gyro_matrix (K, 3, 3); gyro_bias (K, 3)
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
    acc_design: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.acc_design is None:
            d = np.concatenate([centripetal_matrix(self.positions), euler_matrix(self.positions),
                                np.broadcast_to(np.eye(3), (len(self.positions), 3, 3))], axis=2)
            object.__setattr__(self, "acc_design", np.einsum("kij,kjl->kil", self.acc_matrix, d))
        for sensor in ("acc", "gyro"):
            clip = getattr(self, f"{sensor}_clip")
            clip = float(getattr(self, f"{sensor}_range") if clip is None else clip)
            tol = clip_tolerance(clip, getattr(self, f"{sensor}_clip_tolerance"))
            if not (clip > 0 and np.isfinite(tol) and 0 <= tol < clip):
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
        """The linear form of the description's sensor model (see :meth:`from_sensor_model`)."""
        return cls.from_sensor_model(SensorModel.from_description(desc), desc.accelerometer_range,
                                     desc.gyroscope_range)

    @classmethod
    def from_sensor_model(cls, model: SensorModel, acc_range: float | None = None,
                          gyro_range: float | None = None) -> "LinearArrayModel":
        """The exact linear form of ``model``'s linear terms (its other terms are left out)."""
        design, acc_bias, gyro_matrix, gyro_bias = linear_design(model)
        return cls(
            names=model.names,
            frame_id=model.frame_id,
            positions=model.positions.copy(),
            acc_matrix=design[:, :, 9:12].copy(),
            acc_bias=acc_bias,
            gyro_matrix=gyro_matrix,
            gyro_bias=gyro_bias,
            acc_std=model.acc_std.copy(),
            gyro_std=model.gyro_std.copy(),
            acc_range=float(model.acc_clip if acc_range is None else acc_range),
            gyro_range=float(model.gyro_clip if gyro_range is None else gyro_range),
            acc_clip=model.acc_clip,
            gyro_clip=model.gyro_clip,
            acc_clip_tolerance=model.acc_clip_tolerance,
            gyro_clip_tolerance=model.gyro_clip_tolerance,
            acc_design=design,
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
            acc_design=self.acc_design[idx],
        )


def linear_design(model: SensorModel) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(D (K, 3, 12), accelerometer bias (K, 3), B (K, 3, 3), gyroscope bias (K, 3)) of
    ``model``'s linear terms, read off 13 probe motions (see module docstring):
    zero; omega = e_x, e_y, e_z, e_x+e_y, e_x+e_z, e_y+e_z; omega_dot = e_j; s = e_j."""
    lin = model.linear_part()
    eye = np.eye(3)
    omega = np.zeros((13, 3))
    omega[1:4] = eye
    omega[4:7] = [[1, 1, 0], [1, 0, 1], [0, 1, 1]]
    omega_dot = np.zeros((13, 3))
    omega_dot[7:10] = eye
    s = np.zeros((13, 3))
    s[10:13] = eye
    acc, gyr = lin.predict(motion_context(np.arange(13), omega, omega_dot, s, model.rotations))
    b = acc[0]
    d = np.empty((model.n_imus, 3, 12))
    d[:, :, 0:3] = np.moveaxis(acc[1:4] - b, 0, 2)  # q = wx^2, wy^2, wz^2
    for col, (probe, i, j) in enumerate(((4, 1, 2), (5, 1, 3), (6, 2, 3))):  # q = wx wy, wx wz, wy wz
        d[:, :, 3 + col] = acc[probe] - acc[i] - acc[j] + b
    d[:, :, 6:9] = np.moveaxis(acc[7:10] - b, 0, 2)
    d[:, :, 9:12] = np.moveaxis(acc[10:13] - b, 0, 2)
    return d, b.copy(), np.moveaxis(gyr[1:4] - gyr[0], 0, 2), gyr[0].copy()
