"""The ROS 2 adapter: the ``solid_node`` node and its parameter declarations (imports rclpy)."""
