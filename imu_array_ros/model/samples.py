"""In-memory containers passed between readers, simulator, fusion and writers.

All arrays are numpy, SI units.  ``N`` is the number of array samples (one
common ``header.stamp``), ``K`` the number of IMUs in description order.
A NaN in ``accel``/``gyro`` means "not available for this sample" (the IMU's
message was missing, or it was rejected as bad by the reader).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ImuSamples", "MotionTruth", "FusedSamples", "ReadStats"]


@dataclass
class ImuSamples:
    """Raw measurements of every IMU of an array, aligned by array sample.

    Attributes
    ----------
    stamps : (N,) int64
        Sample time, nanoseconds (ROS time, ``header.stamp``).
    accel : (N, K, 3) float64
        Accelerometer triad output in each IMU's own sensor frame, m/s^2.
    gyro : (N, K, 3) float64
        Gyroscope triad output in each IMU's own sensor frame, rad/s.
    names : tuple of K str
        IMU names, in the order of the array description.
    own_stamps : (N, K) int64 or None
        For IMUs that stamp their own messages (own drivers, own clocks): the stamp
        each IMU's message paired with array sample n carried (``stamps`` is then
        the array's grid, by default the reference IMU's stamps).  None: every IMU's
        message carried the array sample's stamp.
    """

    stamps: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray
    names: tuple[str, ...]
    own_stamps: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.stamps = np.asarray(self.stamps, dtype=np.int64)
        self.accel = np.asarray(self.accel, dtype=np.float64)
        self.gyro = np.asarray(self.gyro, dtype=np.float64)
        self.names = tuple(self.names)
        n, k = len(self.stamps), len(self.names)
        for label, arr in (("accel", self.accel), ("gyro", self.gyro)):
            if arr.shape != (n, k, 3):
                raise ValueError(f"{label} has shape {arr.shape}, expected {(n, k, 3)}")
        if self.own_stamps is not None:
            self.own_stamps = np.asarray(self.own_stamps, dtype=np.int64)
            if self.own_stamps.shape != (n, k):
                raise ValueError(f"own_stamps has shape {self.own_stamps.shape}, expected {(n, k)}")

    @property
    def stamp_delays(self) -> np.ndarray | None:
        """(N, K) s: each IMU's own stamp minus the array stamp (None without own stamps)."""
        if self.own_stamps is None:
            return None
        return (self.own_stamps - self.stamps[:, None]).astype(float) * 1e-9

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def present(self) -> np.ndarray:
        """(N, K) bool: the IMU delivered a complete, finite message."""
        return np.isfinite(self.accel).all(axis=2) & np.isfinite(self.gyro).all(axis=2)

    def select(self, index) -> "ImuSamples":
        """Samples picked by a boolean mask or index array (copies)."""
        own = None if self.own_stamps is None else self.own_stamps[index]
        return ImuSamples(self.stamps[index], self.accel[index], self.gyro[index], self.names, own)

    @property
    def readings(self) -> np.ndarray:
        """(N, K, 6) every reading, rows [acc x, y, z, gyro x, y, z] (the sensor model's row order)."""
        return np.concatenate([self.accel, self.gyro], axis=2)

    def valid(self, model) -> np.ndarray:
        """(N, K, 6) True for the readings that carry information under ``model`` (a
        :class:`~imu_array_ros.model.sensor_model.SensorModel`): present, finite and not saturated."""
        return model.valid(self.accel, self.gyro)

    def window(self, start_s: float | None = None, duration_s: float | None = None) -> "ImuSamples":
        """The samples from ``start_s`` to ``start_s + duration_s`` seconds after the first stamp (both
        ends included; None: from the first / to the last); may be empty."""
        if not len(self) or (start_s is None and duration_s is None):
            return self
        t = (self.stamps - self.stamps[0]) / 1e9
        lo = 0.0 if start_s is None else float(start_s)
        hi = np.inf if duration_s is None else lo + float(duration_s)
        return self.select(np.flatnonzero((t >= lo) & (t <= hi)))


@dataclass
class MotionTruth:
    """Ground-truth rigid-body motion of the array frame (simulation only).

    stamps (N,) int64 ns; omega, omega_dot (N, 3) rad/s, rad/s^2; specific_force
    (N, 3) m/s^2 at the array origin, all in the array (body) frame; attitude
    (N, 4) quaternion [w, x, y, z] body -> world, or None when not integrated.
    """

    stamps: np.ndarray
    omega: np.ndarray
    omega_dot: np.ndarray
    specific_force: np.ndarray
    attitude: np.ndarray | None = None


@dataclass
class FusedSamples:
    """Output of the ML fusion (skog2016 eq. 8-15), one row per array sample.

    omega (N,3) rad/s, omega_dot (N,3) rad/s^2, specific_force (N,3) m/s^2 at the
    array origin, all in the array frame; covariance (N,9,9) is the inverse
    Fisher information (Cramér–Rao bound, eq. 14-15) evaluated at the estimate,
    parameter order [omega, omega_dot, specific_force].
    """

    stamps: np.ndarray
    omega: np.ndarray
    omega_dot: np.ndarray
    specific_force: np.ndarray
    covariance: np.ndarray
    iterations: np.ndarray | None = None
    converged: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.stamps)


@dataclass
class ReadStats:
    """What a reader saw and what it rejected; printed by the CLI."""

    messages: int = 0
    samples: int = 0
    bad_messages: int = 0          # non-finite values, wrong layout, unknown encoding
    duplicate_messages: int = 0    # a second message of one IMU at the same stamp
    incomplete_samples: int = 0    # samples where at least one IMU is missing
    notes: list[str] = field(default_factory=list)
