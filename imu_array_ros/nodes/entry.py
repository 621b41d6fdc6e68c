"""The nodes' console entry points (``driver_node``, ``fusion_node``, ``calibration_node``), ROS-free.

A node module imports rclpy and the message packages when it is imported.  On a core install
(``pip install .``) they are missing, and the bare entry point would die with a traceback;
these import the node module first and turn a missing ROS 2 package into one line
``<node>: error: ...`` naming what is missing and how to get it, exit status 2
(:func:`ros_missing`, also used by :mod:`.probe`).  Anything else propagates.  ``python -m
imu_array_ros.nodes.<node>`` comes here too: a node module run as ``__main__`` calls its entry point
before its own ROS 2 imports.
"""

from __future__ import annotations

import importlib
import sys

__all__ = ["ROS_MODULES", "ROS_INSTALL", "ros_missing", "driver_node", "fusion_node", "calibration_node"]

#: the top-level ROS 2 modules the nodes import (from rclpy and the message packages)
ROS_MODULES = ("rclpy", "rcl_interfaces", "sensor_msgs", "geometry_msgs", "std_srvs", "diagnostic_msgs", "std_msgs",
               "builtin_interfaces", "tf2_msgs", "rosgraph_msgs", "rosidl_runtime_py", "rosidl_parser", "rpyutils")
#: how to get them (the README's ROS 2 from PyPI, scripts/setup_venv.sh, or a full install)
ROS_INSTALL = ("pip install 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces, or use a ROS 2 Jazzy install "
               "(source /opt/ros/jazzy/setup.bash)")


def ros_missing(err: ImportError) -> str | None:
    """The one-line reason when ``err`` is a ROS 2 module that is not installed; None for any other ImportError."""
    name = (getattr(err, "name", None) or "").split(".")[0]
    if name not in ROS_MODULES:
        return None
    return f"the ROS 2 nodes need rclpy and the ROS 2 message packages, and {name!r} is not installed: {ROS_INSTALL}"


def _launch(node: str, args=None) -> int:
    try:
        module = importlib.import_module(f"imu_array_ros.nodes.{node}")
    except ImportError as err:
        why = ros_missing(err)
        if why is None:
            raise
        print(f"{node}: error: {why}", file=sys.stderr)
        return 2
    return module.main(args)


def driver_node(args=None) -> int:
    """``driver_node`` (:mod:`.driver_node`)."""
    return _launch("driver_node", args)


def fusion_node(args=None) -> int:
    """``fusion_node`` (:mod:`.fusion_node`)."""
    return _launch("fusion_node", args)


def calibration_node(args=None) -> int:
    """``calibration_node`` (:mod:`.calibration_node`)."""
    return _launch("calibration_node", args)
