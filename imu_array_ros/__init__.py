"""imu_array_ros: inertial sensor arrays as one high-grade IMU.

The core is ROS-free (numpy/scipy only); the ROS 2 nodes live in
:mod:`imu_array_ros.nodes` and are the only modules that import rclpy.

The public API is the workflows layer (:mod:`imu_array_ros.workflows`), which the
command line and the nodes call too, so Python gives the command line's numbers::

    from imu_array_ros import load_array, read_imu_recording, fuse
    desc, _ = load_array("config/array32.yaml")
    samples, _ = read_imu_recording("bags/twist32_sample", desc)
    fused, stats = fuse(samples, desc)      # every term of the description
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from imu_array_ros.errors import ImuArrayError
from imu_array_ros.version import __version__

if TYPE_CHECKING:  # what a type checker (and test_architecture's layer check) sees
    from imu_array_ros.io.rosbag.recording import (read_fused_recording, read_imu_recording, read_truth,
                                                   write_fused_recording, write_imu_recording)
    from imu_array_ros.model.description import ArrayDescription, load_description, save_description
    from imu_array_ros.model.samples import FusedSamples, ImuSamples, MotionTruth
    from imu_array_ros.model.sensor_model import SensorModel
    from imu_array_ros.workflows import (Calibration, DiscoveryOptions, build_fusion, calibrate, discover,
                                         findings_calibration, fuse, fuse_recording, import_openshoe, load_array,
                                         residuals, simulate)

#: public name -> the module that defines it; imported when first used (:pep:`562`), so that importing
#: any part of the package (a node, the command line) does not import every calibration
EXPORTS = {
    **dict.fromkeys(("read_imu_recording", "read_truth", "read_fused_recording", "write_imu_recording",
                     "write_fused_recording"), "imu_array_ros.io.rosbag.recording"),
    **dict.fromkeys(("ArrayDescription", "load_description", "save_description"), "imu_array_ros.model.description"),
    **dict.fromkeys(("ImuSamples", "FusedSamples", "MotionTruth"), "imu_array_ros.model.samples"),
    "SensorModel": "imu_array_ros.model.sensor_model",
    **dict.fromkeys(("Calibration", "DiscoveryOptions", "build_fusion", "calibrate", "discover", "findings_calibration",
                     "fuse", "fuse_recording", "import_openshoe", "load_array", "residuals", "simulate"),
                    "imu_array_ros.workflows"),
}
__all__ = ["__version__", "ImuArrayError", *EXPORTS]


def __getattr__(name: str):
    try:
        module = EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(EXPORTS))
