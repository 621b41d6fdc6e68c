"""Driver and fusion node together, and optionally the calibration node (full ROS 2 installs;
`launch` is not on PyPI).

    ros2 launch imu_array_ros imu_array.launch.py                        # serial array on /dev/ttyUSB0
    ros2 launch imu_array_ros imu_array.launch.py port:=/tmp/imu-array   # e.g. `imu-array fake-device --array
        # config/array32.yaml --link /tmp/imu-array`: the same IMUs as array_config (default array32.yaml)
    ros2 launch imu_array_ros imu_array.launch.py mode:=replay bag:=/path/to/recording
    ros2 launch imu_array_ros imu_array.launch.py calibration_file:=/path/cal.yaml calibrate:=true
        # + calibration_node writing cal.yaml, which the fusion node reloads:
        # ros2 service call /calibrate_geometry std_srvs/srv/Trigger

Parameters not given here come from config/driver_node.params.yaml,
config/fusion_node.params.yaml and config/calibration_node.params.yaml of the installed package.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory("imu_array_ros")
    config = os.path.join(share, "config")
    args = {
        "array_config": (os.path.join(config, "array32.yaml"), "array description YAML"),
        "calibration_file": ("", "calibrated description, reloaded by the fusion node when it changes"),
        "mode": ("serial", "serial | replay"),
        "port": ("/dev/ttyUSB0", "serial port of the array"),
        "bag": ("", "recording to replay (mode:=replay)"),
        "rate": ("1.0", "replay speed factor (0 = as fast as possible without loss)"),
        "reliable": ("false", "reliable QoS on every topic"),
        "calibrate": ("false", "also start calibration_node, writing calibration_file (service /calibrate_geometry)"),
    }
    arg = {name: LaunchConfiguration(name) for name in args}
    common = {"array_config": arg["array_config"], "reliable": arg["reliable"]}
    driver = Node(
        package="imu_array_ros", executable="driver_node", name="imu_array_driver", output="screen",
        parameters=[os.path.join(config, "driver_node.params.yaml"),
                    {**common, "mode": arg["mode"], "port": arg["port"], "bag": arg["bag"], "rate": arg["rate"],
                     # the fusion node publishes the frames in use (the calibrated ones after a reload)
                     "publish_frames": False}],
    )
    fusion = Node(
        package="imu_array_ros", executable="fusion_node", name="imu_array_fusion", output="screen",
        parameters=[os.path.join(config, "fusion_node.params.yaml"),
                    {**common, "calibration_file": arg["calibration_file"]}],
    )
    calibration = Node(
        package="imu_array_ros", executable="calibration_node", name="imu_array_calibration", output="screen",
        condition=IfCondition(arg["calibrate"]),
        parameters=[os.path.join(config, "calibration_node.params.yaml"),
                    {**common, "output_file": arg["calibration_file"]}],
    )
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text)
         for name, (default, text) in args.items()] + [driver, fusion, calibration]
    )
