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

from imu_array_ros.errors import ImuArrayError
from imu_array_ros.io.rosbag.recording import (
    read_fused_recording,
    read_imu_recording,
    read_truth,
    write_fused_recording,
    write_imu_recording,
)
from imu_array_ros.model.description import ArrayDescription, load_description, save_description
from imu_array_ros.model.samples import FusedSamples, ImuSamples, MotionTruth
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.version import __version__
from imu_array_ros.workflows import (
    Calibration,
    DiscoveryOptions,
    build_fusion,
    calibrate,
    discover,
    findings_calibration,
    fuse,
    fuse_recording,
    import_openshoe,
    load_array,
    residuals,
    simulate,
)

__all__ = [
    "__version__",
    "ImuArrayError",
    "ArrayDescription",
    "SensorModel",
    "load_array",
    "load_description",
    "save_description",
    "ImuSamples",
    "FusedSamples",
    "MotionTruth",
    "Calibration",
    "DiscoveryOptions",
    "build_fusion",
    "fuse",
    "fuse_recording",
    "calibrate",
    "findings_calibration",
    "residuals",
    "discover",
    "simulate",
    "import_openshoe",
    "read_imu_recording",
    "read_truth",
    "read_fused_recording",
    "write_imu_recording",
    "write_fused_recording",
]
