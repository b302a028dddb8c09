"""The back end on solid_node: its topics, the map -> odom TF, its timers and its services.

Each verified keyframe goes to the loop closure's pose graph through
:class:`~solid_ros.ros.graph_output.GraphOutput` (the same update the replay makes); what is
published here is read from its newest snapshot.

Outputs (with ``backend`` on and odometry to build the graph from):

- ``/tf``: ``map_frame -> odom_frame`` at ``tf_rate_hz``, the newest correction; identity
  until loops move it. Never ``map -> map``: an odometry whose frame is ``map_frame`` gets no
  transform and one WARN (:mod:`solid_ros.ros.frames`).
- ``~/odometry`` (nav_msgs/Odometry): every incoming odometry message in the map frame, with
  the covariance of the graph's newest pose.
- ``~/path`` (nav_msgs/Path, latched): the corrected keyframe poses, at most every
  ``path_period_sec`` and only after a change.
- ``~/map`` (PointCloud2, latched): the kept keyframe clouds at their corrected poses,
  voxel-thinned and bounded (``map_voxel_size``, ``map_max_points``), built on a thread of its
  own at most every ``map_period_sec`` and only after a change: never on the cloud -> loop
  path.
- ``lio_sam_loop_topic``: each loop as LIO-SAM's external loop message, when set.

``~/map`` and ``~/path`` (megabytes, and growing) go out of a participant of their own
(:mod:`solid_ros.ros.bulk_participant`): from the node's, they overran its shared-memory
segment on Fast DDS's default transport and took ``/tf`` and ``~/odometry`` samples with them.
- Services ``~/save_map`` (``map.pcd``) and ``~/save_trajectory`` (``trajectory.tum`` and
  ``trajectory.kitti``: the corrected pose of the odometry's child frame at each keyframe)
  write under ``output_directory``; no path comes from the caller, a file is written to a
  temporary name and renamed, and an existing file is replaced only when it is a regular file
  of the same kind (a PCD, a TUM or a KITTI trajectory), never a link or something else.
"""

from __future__ import annotations

import os
import stat
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from solid_ros.core.backend.mapping import MapCloud, build_map
from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import SolidError
from solid_ros.core.flow.closure import Step
from solid_ros.core.results import LoopCandidate
from solid_ros.formats.pointfiles import read_pcd, write_pcd
from solid_ros.formats.poses import (
    read_kitti_poses,
    read_tum_poses,
    write_kitti_poses,
    write_tum_poses,
)
from solid_ros.ros.bulk_participant import BulkParticipant
from solid_ros.ros.frames import SelfTransformGuard, map_odom_advice
from solid_ros.ros.graph_msgs import (
    cloud_msg,
    corrected_odometry,
    lio_sam_loop_msg,
    path_msg,
    transform_msg,
)
from solid_ros.ros.graph_output import GraphOutput
from solid_ros.ros.shared_detector import SharedDetector
from solid_ros.ros.stages import Verified
from solid_ros.ros.worker import Worker

__all__ = ['BackendIO']

_LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
_TF_QOS = 100  # as tf2_ros.TransformBroadcaster


class BackendIO:
    """Publishers, timers and services of the back end on ``node``.

    Args:
        node: the node they belong to.
        cfg: the node's settings.
        output: the pose graph and its newest snapshot.
        shared: the detector (its kept keyframe clouds make the map).
        mount: the sensor mounting rotation that levelled the stored clouds.
        odom_frame: the odometry frame now (the parameter, else the odometry's header).
    """

    def __init__(self, node: Node, cfg: NodeConfig, output: GraphOutput,
                 shared: SharedDetector, mount: npt.ArrayLike,
                 odom_frame: Callable[[], str]) -> None:
        self._node, self._cfg, self._output, self._shared = node, cfg, output, shared
        self._mount = np.asarray(mount, dtype=np.float64)
        self._odom_frame = odom_frame
        self._log = node.get_logger()
        self._tf_pub = self._tf_publisher()
        self._frames = SelfTransformGuard(self._log.warning, map_odom_advice)
        self._odom_pub = node.create_publisher(Odometry, '~/odometry', 10)
        self._bulk = BulkParticipant(node)
        self._path_pub = self._bulk.create_publisher(PathMsg, '~/path', _LATCHED)
        self._map_pub = (self._bulk.create_publisher(PointCloud2, '~/map', _LATCHED)
                         if cfg.map_period_sec > 0.0 else None)
        self._lio_pub = (node.create_publisher(Float64MultiArray, cfg.lio_sam_loop_topic, 10)
                         if cfg.lio_sam_loop_topic else None)
        self._path_version = 0
        self._map_lock = threading.Lock()  # the newest map and the version it shows
        self._map: tuple[int, MapCloud] | None = None
        self._map_worker: Worker[int] = Worker('solid_map', self._publish_map, 1,
                                               self._map_failed)
        self._map_worker.start()
        if self._tf_pub is not None and cfg.tf_rate_hz > 0.0:
            node.create_timer(1.0 / cfg.tf_rate_hz, self._broadcast)
        node.create_timer(cfg.path_period_sec, self._publish_path)
        if self._map_pub is not None:
            node.create_timer(cfg.map_period_sec, self._request_map)
        node.create_service(Trigger, '~/save_map', self._on_save_map)
        node.create_service(Trigger, '~/save_trajectory', self._on_save_trajectory)

    def _tf_publisher(self) -> Any:
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self._log.error('tf2_msgs is not installed: no map -> odom transform on /tf '
                            '(install ros-jazzy-tf2-msgs)')
            return None
        return self._node.create_publisher(TFMessage, '/tf', _TF_QOS)

    @property
    def output(self) -> GraphOutput:
        """The pose graph's newest snapshot and its updates."""
        return self._output

    # -- from the verify thread and the odometry callback ----------------------------------

    def take(self, verified: Verified, loops: tuple[LoopCandidate, ...]) -> Step | None:
        """A verified keyframe: its ``loops`` (header stamps) to LIO-SAM when asked, then its
        step and graph update (see :meth:`GraphOutput.take`)."""
        if self._lio_pub is not None:
            for c in loops:
                self._lio_pub.publish(lio_sam_loop_msg(c.query_stamp_ns, c.match_stamp_ns))
        return self._output.take(verified)

    def odometry(self, msg: Any, T_odom_child: npt.ArrayLike) -> None:
        """An incoming odometry message, corrected into the map frame on ``~/odometry``."""
        snap = self._output.snapshot
        self._odom_pub.publish(corrected_odometry(msg, snap.correction, T_odom_child,
                                                  snap.covariance, self._cfg.map_frame))

    # -- timers ------------------------------------------------------------------------------

    def _now_ns(self) -> int:
        return int(self._node.get_clock().now().nanoseconds)

    def _broadcast(self) -> None:
        child = self._odom_frame()
        if not child or self._tf_pub is None:
            return  # no odometry frame known yet
        if not self._frames.allows(self._cfg.map_frame, child):
            return
        self._tf_pub.publish(transform_msg(self._output.snapshot.correction, self._now_ns(),
                                           self._cfg.map_frame, child))

    def _publish_path(self) -> None:
        snap = self._output.snapshot
        if snap.version == self._path_version:
            return
        self._path_version = snap.version
        self._path_pub.publish(path_msg(snap.stamps_ns, snap.poses, self._cfg.map_frame,
                                        self._now_ns()))

    def _request_map(self) -> None:
        version = self._output.snapshot.version
        with self._map_lock:
            if self._map is not None and self._map[0] == version:
                return
        if version and self._map_worker.idle:
            self._map_worker.put(version)

    def _publish_map(self, version: int) -> None:
        built = self._build(version)
        if self._map_pub is not None:
            self._map_pub.publish(cloud_msg(built.points, self._cfg.map_frame, self._now_ns()))

    def _build(self, version: int) -> MapCloud:
        """The map of the snapshot ``version`` (the newest, when it is not older)."""
        with self._map_lock:
            if self._map is not None and self._map[0] >= version:
                return self._map[1]
        snap = self._output.snapshot
        clouds = self._shared.keyframe_clouds(dict(zip(snap.indices.tolist(), snap.poses)))
        built = build_map(clouds, self._mount, self._cfg.map_voxel_size,
                          self._cfg.map_max_points)
        with self._map_lock:
            self._map = (snap.version, built)
        return built

    def _map_failed(self, err: Exception) -> None:
        self._log.error(f'map building failed: {type(err).__name__}: {err}')

    # -- services ----------------------------------------------------------------------------

    def _on_save_map(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        def write(directory: Path) -> str:
            built = self._build(self._output.snapshot.version)
            target = directory / 'map.pcd'
            _check_target(target, read_pcd)
            write_pcd(target, built.points)
            return (f'saved {len(built.points)} map points of {built.keyframes} keyframes '
                    f'to {target}')
        return self._save(response, write)

    def _on_save_trajectory(self, request: Trigger.Request,
                            response: Trigger.Response) -> Any:
        def write(directory: Path) -> str:
            snap = self._output.snapshot
            tum, kitti = directory / 'trajectory.tum', directory / 'trajectory.kitti'
            _check_target(tum, read_tum_poses)
            _check_target(kitti, read_kitti_poses)
            write_tum_poses(tum, snap.stamps_ns, snap.poses)
            write_kitti_poses(kitti, snap.poses)
            return f'saved {len(snap.poses)} keyframe poses to {tum} and {kitti}'
        return self._save(response, write)

    def _save(self, response: Trigger.Response, write: Callable[[Path], str]) -> Any:
        if not self._cfg.output_directory:
            response.success, response.message = False, 'output_directory is empty'
            return response
        directory = Path(self._cfg.output_directory).expanduser()
        try:
            directory.mkdir(parents=True, exist_ok=True)
            response.message = write(directory)
            response.success = True
            self._log.info(response.message)
        except (SolidError, OSError) as err:
            response.success, response.message = False, f'save failed: {err}'
            self._log.error(response.message)
        return response

    # -- the rest ----------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget this session's keyframes (``~/reset``)."""
        self._output.reset()
        with self._map_lock:
            self._map = None

    def values(self) -> dict[str, object]:
        """/diagnostics values of the back end."""
        return self._output.values()

    def stop(self, join_sec: float) -> None:
        """End the map thread, then the participant of the map and path."""
        self._map_worker.stop()
        self._map_worker.join(join_sec)
        self._bulk.close()


def _check_target(path: Path, read: Callable[[Path], Any]) -> None:
    """Refuse a target that exists and is not a regular file of the kind written there.

    Raises:
        SolidError: a link, a directory or another non-regular file, or a file ``read``
            cannot read (not ours to replace).
    """
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISREG(st.st_mode):
        raise SolidError(f'{path} exists and is not a regular file; it is not replaced')
    try:
        read(path)
    except (SolidError, OSError, ValueError) as err:
        raise SolidError(f'{path} exists and is not a file of this kind ({err}); it is not '
                         'replaced (remove it or set another output_directory)') from err
