"""rclpy messages built from numpy for the tests that publish to solid_node (needs rclpy)."""

from __future__ import annotations

import array

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from solid_ros.formats.pointcloud2 import encode_points


def make_cloud(points: np.ndarray, stamp_ns: int, frame: str = 'lidar') -> PointCloud2:
    """rclpy PointCloud2 of float32 x y z (unorganised, little-endian)."""
    lay = encode_points(np.asarray(points)[:, :3])
    msg = PointCloud2()
    msg.header.frame_id = frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.height, msg.width = lay.height, lay.width
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                  for f in lay.fields]
    msg.is_bigendian, msg.is_dense = lay.is_bigendian, lay.is_dense
    msg.point_step, msg.row_step = lay.point_step, lay.row_step
    msg.data = array.array('B', lay.data.tobytes())
    return msg
