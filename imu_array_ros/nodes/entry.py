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
import importlib.util
import sys

__all__ = ["ROS_MODULES", "ROS_INSTALL", "ros_missing", "usage", "driver_node", "fusion_node", "calibration_node"]

#: the top-level ROS 2 modules the nodes import (from rclpy and the message packages)
ROS_MODULES = ("rclpy", "rcl_interfaces", "sensor_msgs", "geometry_msgs", "std_srvs", "diagnostic_msgs", "std_msgs",
               "builtin_interfaces", "tf2_msgs", "rosgraph_msgs", "rosidl_runtime_py", "rosidl_parser", "rpyutils")
#: how to get them (the README's ROS 2 from PyPI, scripts/setup_venv.sh, or a full install)
ROS_INSTALL = ("pip install 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces, or use a ROS 2 Jazzy install "
               "(source /opt/ros/jazzy/setup.bash)")


def ros_missing(err: ImportError) -> str | None:
    """The one-line reason when ``err`` is a ROS 2 module that is not installed, or installed but not loadable in
    this Python (a part of it, e.g. rclpy's C extension ``rclpy._rclpy_pybind11``, fails: a ROS 2 install sourced
    into a venv of another Python version); None for any other ImportError."""
    full = getattr(err, "name", None) or ""
    name = full.split(".")[0]
    if name not in ROS_MODULES:
        return None
    found = full != name and _spec(name)
    if found and (getattr(err, "path", None) or not _spec(full)):  # a part of it, there but not loadable, or absent
        where = (found.submodule_search_locations or [found.origin])[0]
        python = f"{sys.version_info.major}.{sys.version_info.minor}"
        return (f"{name!r} is installed ({where}) but {full!r} does not load in this Python {python}: a ROS 2 install "
                f"works only with the Python it was built for (Jazzy on Ubuntu 24.04: its python3, 3.12) after "
                f"source /opt/ros/jazzy/setup.bash; in a venv of another Python use pip install "
                f"'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces instead")
    return f"the ROS 2 nodes need rclpy and the ROS 2 message packages, and {name!r} is not installed: {ROS_INSTALL}"


def _spec(name: str):
    """``importlib.util.find_spec(name)``, None when it (or its parent package) cannot be imported."""
    try:
        return importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None


def usage(node: str) -> str:
    """``<node> --help``: how to start the node and its parameters with their defaults (ROS 2 not needed)."""
    import textwrap

    from imu_array_ros.nodes.parameters import NODE_PARAMS

    lines = [f"usage: {node} --ros-args -p array_config:=FILE [-p NAME:=VALUE ...] [--params-file FILE]",
             f"       ros2 run imu_array_ros {node} --ros-args ...  (a full ROS 2 install)",
             "", "parameters (default; docs/nodes.md#parameters):"]
    for p in NODE_PARAMS[node]:
        default = "required" if p.required else repr(p.default)
        allowed = (f"; {p.low:g} to {p.high:g}" if p.low is not None else "") + \
            (f"; one of {', '.join(map(str, p.choices))}" if p.choices else "")
        lines.append(f"  {p.name} ({default}{allowed})")
        lines += textwrap.wrap(p.description, 100, initial_indent=" " * 6, subsequent_indent=" " * 6)
    return "\n".join(lines)


def _launch(node: str, args=None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    own = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "-h" in own or "--help" in own:
        print(usage(node))
        return 0
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
