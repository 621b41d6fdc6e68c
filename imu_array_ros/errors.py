"""Exception hierarchy of imu_array_ros.

Every error a user can cause derives from :class:`ImuArrayError`; its message is
one line naming the problem (file, topic, field).  The command line prints
``imu-array: error: <message>`` and exits non-zero instead of a traceback.
"""

from __future__ import annotations

__all__ = [
    "ImuArrayError",
    "ConfigError",
    "RecordingError",
    "CaptureError",
    "IdentifiabilityError",
    "FusionError",
    "CalibrationError",
    "OutputError",
    "MissingDependencyError",
]


class ImuArrayError(Exception):
    """Root of every error this package raises on purpose."""


class ConfigError(ImuArrayError):
    """An array description or calibration YAML file is missing or malformed."""


class RecordingError(ImuArrayError):
    """A recording (rosbag2 MCAP directory or bare .mcap file) cannot be used."""


class CaptureError(ImuArrayError):
    """A raw serial capture (OpenShoe byte stream) cannot be used."""


class IdentifiabilityError(ImuArrayError):
    """The array geometry cannot determine angular velocity, angular acceleration
    and specific force (skog2016 Sec. II-D): fewer than one gyroscope triad or
    fewer than three non-collinear accelerometer triads."""


class FusionError(ImuArrayError):
    """Samples handed to the fusion cannot be fused (wrong shapes, nothing identifiable)."""


class CalibrationError(ImuArrayError):
    """A calibration cannot run on the data given (too little motion, too few poses, ...)."""


class OutputError(ImuArrayError):
    """An output path is unsafe to write: it exists, is an input, or holds other files."""


class MissingDependencyError(ImuArrayError):
    """A command needs an optional dependency (an extra of the package) that is not installed."""
