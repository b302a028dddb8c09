"""rclpy messages built from numpy for the tests that publish to solid_node (needs rclpy)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import PointCloud2

from solid_ros.ros.graph_msgs import cloud_msg


def make_cloud(points: np.ndarray, stamp_ns: int, frame: str = 'lidar') -> PointCloud2:
    """rclpy PointCloud2 of float32 x y z (unorganised, little-endian): the node's own
    encoder (``~/map``), whose layout test/formats/test_pointcloud2.py checks."""
    return cloud_msg(points, frame, int(stamp_ns))
