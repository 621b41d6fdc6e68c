"""imu_array_ros: inertial sensor arrays as one high-grade IMU.

The core is ROS-free (numpy/scipy only); the ROS 2 nodes live in
:mod:`imu_array_ros.nodes` and are the only modules that import rclpy.

The small public API (the README's Python example)::

    from imu_array_ros import load_description, read_imu_recording, LinearArrayModel, fuse
"""

from imu_array_ros.version import __version__

from imu_array_ros.errors import ImuArrayError
from imu_array_ros.fusion.ml_fusion import FusionConfig, MLFusion, fuse
from imu_array_ros.fusion.stream import fuse_chunked
from imu_array_ros.io.rosbag.recording import (
    read_fused_recording,
    read_imu_recording,
    read_truth,
    write_fused_recording,
    write_imu_recording,
)
from imu_array_ros.model.description import ArrayDescription, load_description, save_description
from imu_array_ros.model.samples import FusedSamples, ImuSamples, MotionTruth
from imu_array_ros.model.linear import LinearArrayModel

__all__ = [
    "__version__",
    "ImuArrayError",
    "ArrayDescription",
    "load_description",
    "save_description",
    "ImuSamples",
    "FusedSamples",
    "MotionTruth",
    "LinearArrayModel",
    "FusionConfig",
    "MLFusion",
    "fuse",
    "fuse_chunked",
    "read_imu_recording",
    "read_truth",
    "read_fused_recording",
    "write_imu_recording",
    "write_fused_recording",
]
