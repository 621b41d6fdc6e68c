"""``imu-array``: the offline command line (same core functions as the ROS nodes)."""

from imu_array_ros.cli.commands import build_parser, main

__all__ = ["main", "build_parser"]
