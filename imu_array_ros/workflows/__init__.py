"""What the command line, the ROS nodes, the Python API and the benchmarks all call.

One function per job, so that offline and live results are the same numbers:

* arrays: :func:`load_array` (a description, optionally its calibrated values), :func:`check_fusable`;
* recordings: :func:`read_recording`, :func:`import_openshoe`, :func:`simulate`;
* fusion: :func:`build_fusion`, :func:`fuse` (samples), :func:`fuse_recording` (a file);
* calibration: :func:`calibrate` (every method, one :class:`~imu_array_ros.calibration.result.Calibration`
  result, one install path), :func:`findings_calibration` (``discover --apply``);
* analysis: :func:`residuals`, :func:`discover`.
"""

from imu_array_ros.calibration.result import Calibration, Installed
from imu_array_ros.workflows.analysis import DiscoveryOptions, discover, residuals
from imu_array_ros.workflows.arrays import as_model, check_fusable, load_array
from imu_array_ros.workflows.calibrate import METHODS, calibrate, findings_calibration, install
from imu_array_ros.workflows.fusion import FusedRecording, build_fusion, fuse, fuse_recording
from imu_array_ros.workflows.recordings import (MOTIONS, Simulated, icosahedron_seconds, import_openshoe, read_recording,
                                                simulate)

__all__ = [
    "load_array", "check_fusable", "as_model",
    "read_recording", "import_openshoe", "simulate", "Simulated", "MOTIONS", "icosahedron_seconds",
    "build_fusion", "fuse", "fuse_recording", "FusedRecording",
    "calibrate", "install", "findings_calibration", "Calibration", "Installed", "METHODS",
    "residuals", "discover", "DiscoveryOptions",
]
