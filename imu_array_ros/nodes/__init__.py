"""ROS 2 nodes: thin adapters over the ROS-free core (the only place rclpy is imported)."""
