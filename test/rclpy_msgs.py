"""rclpy messages built from numpy for the tests that publish to solid_node (needs rclpy)."""

from __future__ import annotations

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2

from solid_ros.ros.graph_msgs import cloud_msg, pose_msg


def make_cloud(points: np.ndarray, stamp_ns: int, frame: str = 'lidar') -> PointCloud2:
    """rclpy PointCloud2 of float32 x y z (unorganised, little-endian): the node's own
    encoder (``~/map``), whose layout test/formats/test_pointcloud2.py checks."""
    return cloud_msg(points, frame, int(stamp_ns))


def make_odometry(T: np.ndarray, stamp_ns: int, frame: str = 'odom',
                  child: str = 'lidar') -> Odometry:
    """rclpy Odometry of the 4x4 pose ``T`` of ``child`` in ``frame`` (no covariance)."""
    msg = Odometry()
    msg.header.frame_id, msg.child_frame_id = frame, child
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.pose.pose = pose_msg(T)
    return msg
