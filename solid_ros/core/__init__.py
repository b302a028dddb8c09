"""The ROS-free core: configuration, descriptor, matching, database, detector, persistence.

Pure numpy (and scipy); nothing here imports rclpy or the adapter subpackages.
"""
