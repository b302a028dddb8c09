"""KISS-ICP as solid_node's odometry (``odometry_source: kiss_icp``).

The node's odometry thread (:mod:`solid_ros.ros.stages`) registers each cloud before the
describe thread gets it, never a subscription callback, with
:class:`~solid_ros.core.odometry.kiss.KissOdometry` in a process of its own
(:class:`~solid_ros.core.odometry.kiss_process.KissProcess`: KISS-ICP holds the GIL while it
aligns, which would stall the describe and verify threads). Clouds that carry per-point times
come with them (deskew, ``kiss_deskew``). Each pose goes out as nav_msgs/Odometry
on ``~/kiss/odometry`` and as the ``odom_frame -> sensor`` transform on ``/tf`` (frames from
``odom_frame``, default ``odom``, and ``sensor_frame``, default the cloud's header frame), so
the back end's map -> odom correction and RViz work with the node alone; never one from a
frame to itself (clouds whose frame is ``odom_frame``: no transform, one WARN, see
:mod:`solid_ros.ros.frames`). A reset of the
source (a cloud it cannot register) is logged with its reason; the back end starts a new
graph segment on it. So is a restart of KISS-ICP's process after it ended (killed, crashed):
one ERROR when the end is noticed, then the reset's WARN; the clouds it cannot register until
then raise :class:`~solid_ros.core.errors.OdometryUnavailable` (the stage skips them).
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

import numpy as np
import numpy.typing as npt
from nav_msgs.msg import Odometry
from rclpy.node import Node

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import OdometryUnavailable
from solid_ros.core.odometry.kiss_process import KissProcess
from solid_ros.core.odometry.track import OdomSample
from solid_ros.core.stamps import split_stamp
from solid_ros.ros.frames import DEFAULT_ODOM_FRAME, SelfTransformGuard, odom_sensor_advice
from solid_ros.ros.graph_msgs import pose_msg, transform_msg

__all__ = ['DEFAULT_ODOM_FRAME', 'KissIO']


class KissIO:
    """KISS-ICP odometry with its topic and transform.

    Args:
        node: the node its publishers belong to.
        cfg: the node's settings (``kiss_*``, ``odom_frame``, ``sensor_frame``).

    Raises:
        SolidError: kiss-icp is not installed (the message names the pip package).
    """

    def __init__(self, node: Node, cfg: NodeConfig) -> None:
        self._source = KissProcess(cfg)
        self._log = node.get_logger()
        self._ended = 0  # ends of KISS-ICP's process logged
        # Newest round trips split (to the child, in KISS-ICP there, back), ms: what the
        # hand-over to the process adds to the odometry stage's time.
        self._split: deque[tuple[float, float, float]] = deque(maxlen=1000)
        self._split_lock = threading.Lock()  # appended on the odometry thread, read by timer
        self.frame = cfg.odom_frame or DEFAULT_ODOM_FRAME
        self._sensor_frame = cfg.sensor_frame
        self._frames = SelfTransformGuard(self._log.warning, odom_sensor_advice)
        self._pub = node.create_publisher(Odometry, '~/kiss/odometry', 10)
        self._tf_pub: Any = None
        try:
            from tf2_msgs.msg import TFMessage

            self._tf_pub = node.create_publisher(TFMessage, '/tf', 100)
        except ImportError:
            self._log.error('tf2_msgs is not installed: no odom -> sensor transform on /tf')

    @property
    def resets(self) -> int:
        """Times the source lost track and restarted."""
        return int(self._source.resets)

    def pose_for(self, stamp_ns: int, points: npt.NDArray[np.floating[Any]], cloud_frame: str,
                 point_times: npt.NDArray[np.float64] | None = None) -> OdomSample | None:
        """Register the cloud (with its per-point times, if any); publish and return its pose
        (odometry thread).

        Raises:
            OdometryUnavailable: KISS-ICP's process ended and is not restarted yet.
        """
        try:
            sample = self._source.pose_for(stamp_ns, points, point_times)
        except OdometryUnavailable as err:
            if self._source.ended != self._ended:  # once per end, not per skipped cloud
                self._ended = self._source.ended
                self._log.error(f'{err} ({self._source.restarts} restarts so far)')
            raise
        if sample is None:
            return None
        if self._source.last_ms is not None:
            with self._split_lock:
                self._split.append(self._source.last_ms)
        if sample.reason is not None:
            self._log.warning(f'KISS-ICP odometry reset: {sample.reason} (segment '
                              f'{sample.segment}, {self.resets} resets so far)')
        child = self._sensor_frame or cloud_frame or 'lidar'
        msg = Odometry()
        msg.header.stamp.sec, msg.header.stamp.nanosec = split_stamp(stamp_ns)
        msg.header.frame_id, msg.child_frame_id = self.frame, child
        msg.pose.pose = pose_msg(sample.pose)
        self._pub.publish(msg)
        if self._tf_pub is not None and self._frames.allows(self.frame, child):
            self._tf_pub.publish(transform_msg(sample.pose, stamp_ns, self.frame, child))
        return sample

    def close(self) -> None:
        """End KISS-ICP's process."""
        self._source.close()

    def values(self) -> dict[str, object]:
        """/diagnostics values of the odometry."""
        out: dict[str, object] = {'kiss_registered': self._source.registered,
                                  'kiss_deskewed': self._source.deskewed,
                                  'kiss_resets': self.resets,
                                  'kiss_restarts': self._source.restarts}
        for kind, count in sorted(dict(self._source.reset_counts).items()):
            out[f'kiss_reset_{kind}'] = count
        for kind, count in sorted(dict(self._source.input_counts).items()):
            out[f'kiss_input_{kind}'] = count  # clouds that lost points (NaN rows)
        for guess, count in sorted(dict(self._source.recovered).items()):
            out[f'kiss_recovered_{guess.replace(" ", "_").replace("-", "_")}'] = count
        typical = self._source.typical_overlap
        if typical is not None:
            out['kiss_typical_overlap'] = round(typical, 3)
        return out | self._split_values()

    def _split_values(self) -> dict[str, object]:
        """p50/p95 of the time in KISS-ICP's process (``kiss_icp_ms``: KissOdometry, checks
        included) and of the hand-over to it and back (``kiss_handover_ms``), 'nan' before a
        cloud."""
        with self._split_lock:
            split = np.asarray(self._split, dtype=np.float64).reshape(-1, 3)
        out: dict[str, object] = {}
        for name, ms in (('kiss_icp', split[:, 1]), ('kiss_handover', split[:, 0] + split[:, 2])):
            p50, p95 = np.percentile(ms, [50, 95]) if len(ms) else (np.nan, np.nan)
            out[f'{name}_ms_p50'], out[f'{name}_ms_p95'] = f'{p50:.2f}', f'{p95:.2f}'
        return out
