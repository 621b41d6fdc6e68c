"""imu_array_ros: inertial sensor arrays as one high-grade IMU.

The package root is ROS-free (numpy/scipy only); the ROS 2 nodes live in
:mod:`imu_array_ros.nodes` and import rclpy lazily.
"""

__version__ = "0.1.0"
