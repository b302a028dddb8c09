"""ROS messages of the back end's results: the ``map -> odom`` transform, corrected odometry,
the corrected keyframe path, the map cloud and LIO-SAM's external-loop message.

Plain functions from numpy values to rclpy messages; the node publishes them. ``tf2_msgs`` is
imported only when a transform is built: a ROS 2 installation has it, and ``./run.sh`` builds
it into its venv (PyPI has no wheel of it).
"""

from __future__ import annotations

import array
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from geometry_msgs.msg import (  # type: ignore[import-untyped]
    Pose,
    PoseStamped,
    TransformStamped,
)
from nav_msgs.msg import Odometry, Path  # type: ignore[import-untyped]
from sensor_msgs.msg import PointCloud2, PointField  # type: ignore[import-untyped]
from std_msgs.msg import Float64MultiArray  # type: ignore[import-untyped]

from solid_ros.core.geometry import matrix_to_vector
from solid_ros.core.stamps import NS_PER_SEC, split_stamp
from solid_ros.formats.pointcloud2 import encode_points

__all__ = ['cloud_msg', 'corrected_odometry', 'covariance_in_parent', 'lio_sam_loop_msg',
           'path_msg', 'pose_msg', 'transform_msg']

FloatArray = npt.NDArray[np.float64]


def _stamp(msg_header: Any, stamp_ns: int) -> None:
    msg_header.stamp.sec, msg_header.stamp.nanosec = split_stamp(stamp_ns)


def pose_msg(T: npt.ArrayLike) -> Pose:
    """geometry_msgs/Pose of a 4x4 pose."""
    x, y, z, qx, qy, qz, qw = (float(v) for v in matrix_to_vector(T))
    out = Pose()
    out.position.x, out.position.y, out.position.z = x, y, z
    out.orientation.x, out.orientation.y, out.orientation.z, out.orientation.w = qx, qy, qz, qw
    return out


def transform_msg(T: npt.ArrayLike, stamp_ns: int, parent: str, child: str) -> Any:
    """A tf2_msgs/TFMessage holding the one transform ``parent <- child``."""
    from tf2_msgs.msg import TFMessage  # type: ignore[import-untyped, unused-ignore]

    x, y, z, qx, qy, qz, qw = (float(v) for v in matrix_to_vector(T))
    tf = TransformStamped()
    _stamp(tf.header, stamp_ns)
    tf.header.frame_id, tf.child_frame_id = parent, child
    tf.transform.translation.x, tf.transform.translation.y = x, y
    tf.transform.translation.z = z
    tf.transform.rotation.x, tf.transform.rotation.y = qx, qy
    tf.transform.rotation.z, tf.transform.rotation.w = qz, qw
    return TFMessage(transforms=[tf])


def covariance_in_parent(T: npt.ArrayLike, cov: npt.ArrayLike) -> FloatArray:
    """A ROS-order pose covariance of a perturbation in the child (sensor) frame, expressed
    along the parent frame's axes (what nav_msgs/Odometry's pose covariance means)."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    block = np.zeros((6, 6))
    block[:3, :3] = block[3:, 3:] = R
    out: FloatArray = block @ np.asarray(cov, dtype=np.float64).reshape(6, 6) @ block.T
    return out


def corrected_odometry(msg: Any, correction: npt.ArrayLike, T_odom_child: npt.ArrayLike,
                       covariance: npt.ArrayLike | None, map_frame: str) -> Odometry:
    """An incoming Odometry moved into the map frame: pose ``correction @ T_odom_child``, the
    covariance of the graph's newest pose (along the map axes; all zero when unknown), the
    message's own twist (it is in the child frame, which the correction does not move)."""
    T = np.asarray(correction, dtype=np.float64) @ np.asarray(T_odom_child, dtype=np.float64)
    out = Odometry()
    out.header.stamp = msg.header.stamp
    out.header.frame_id = map_frame
    out.child_frame_id = msg.child_frame_id
    out.pose.pose = pose_msg(T)
    if covariance is not None:
        out.pose.covariance = covariance_in_parent(T, covariance).ravel().tolist()
    out.twist = msg.twist
    return out


def path_msg(stamps_ns: Sequence[int] | npt.NDArray[np.int64], poses: npt.ArrayLike,
             frame: str, stamp_ns: int) -> Path:
    """nav_msgs/Path of poses (N, 4, 4) with their stamps."""
    out = Path()
    _stamp(out.header, stamp_ns)
    out.header.frame_id = frame
    for s, T in zip(stamps_ns, np.asarray(poses, dtype=np.float64)):
        ps = PoseStamped()
        _stamp(ps.header, int(s))
        ps.header.frame_id = frame
        ps.pose = pose_msg(T)
        out.poses.append(ps)
    return out


def cloud_msg(points: npt.ArrayLike, frame: str, stamp_ns: int) -> PointCloud2:
    """sensor_msgs/PointCloud2 of float32 x, y, z points."""
    layout = encode_points(np.asarray(points)[:, :3])
    out = PointCloud2()
    _stamp(out.header, stamp_ns)
    out.header.frame_id = frame
    out.height, out.width = layout.height, layout.width
    out.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                  for f in layout.fields]
    out.is_bigendian, out.is_dense = layout.is_bigendian, layout.is_dense
    out.point_step, out.row_step = layout.point_step, layout.row_step
    out.data = array.array('B', layout.data.tobytes())
    return out


def lio_sam_loop_msg(query_stamp_ns: int, match_stamp_ns: int) -> Float64MultiArray:
    """LIO-SAM's external loop: ``[query stamp, match stamp]`` in seconds (its ROS 2 branch
    subscribes std_msgs/Float64MultiArray on ``lio_loop/loop_closure_detection``)."""
    return Float64MultiArray(data=[query_stamp_ns / NS_PER_SEC, match_stamp_ns / NS_PER_SEC])
