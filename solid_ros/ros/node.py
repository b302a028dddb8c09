"""``solid_node``: PointCloud2 in, SOLiD loop candidates with yaw out.

Topics (relative names, remappable): subscribes ``points`` (sensor_msgs/PointCloud2) and,
with ``use_odom``, ``odom`` (nav_msgs/Odometry); publishes ``~/loop_candidates``
(std_msgs/Float64MultiArray, see :mod:`solid_ros.formats.candidates`), ``~/loop_markers``
(visualization_msgs/MarkerArray, latched: transient local, depth 1; see
:mod:`solid_ros.ros.markers`) and ``/diagnostics``. Services ``~/save_database`` and
``~/reset`` (std_srvs/Trigger).

Health (logged as throttled warnings and raised to WARN on /diagnostics while it lasts; the
windows are wall-clock seconds; see :mod:`solid_ros.ros.health`): no cloud on the resolved
points topic, or with ``use_odom`` no odometry, for ``SILENCE_SEC``; odometry on another
clock; clouds rejected, dropped or failed recently; odometry refused (not finite) or cloud
stamps that cannot be trusted (zero, repeated, going back: :mod:`solid_ros.ros.stamp_guard`
then keeps the detector in arrival order).

Bounds on what any participant can send: a cloud beyond ``max_points_per_cloud`` is thinned
(counted); memory a huge message took is given back (:mod:`solid_ros.ros.memory`); runtime
parameter changes that weaken the node are refused unless ``allow_runtime_weakening``
(:mod:`solid_ros.ros.params`), and every accepted one is logged with its old and new value.

Threading (:mod:`solid_ros.ros.stages`): the subscription callback only decodes (zero-copy)
or rejects a cloud and hands it to a bounded queue; when the queue is full the oldest waiting
cloud is dropped (keep newest) and counted as skipped. With ``odometry_source: kiss_icp`` an
odometry thread registers each cloud first (KISS-ICP itself in a process of its own,
:mod:`solid_ros.ros.kiss_io`), with its per-point times when it has them. A describe thread
pairs odometry, describes, searches and stores; a verify thread verifies keyframes and
hands each on (with ``verify`` off the describe thread does that too), so the executor is
never blocked by descriptor computation or registration.

The per-scan flow is the product's :class:`~solid_ros.core.flow.closure.LoopClosure`, the one
the replay and the demo run; the node wires ROS to it. Where a keyframe's result goes:
:meth:`SolidNode._hand_on` gets every verified keyframe, in keyframe order, as one
:class:`~solid_ros.ros.stages.Verified` (its :class:`~solid_ros.core.results.ScanResult` and
paired :class:`~solid_ros.core.odometry.track.OdomSample`), publishes, logs and draws its
loops, then commits it to the loop closure's pose graph (:mod:`solid_ros.ros.backend_io`).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from solid_ros.core.backend.mapping import mount_rotation
from solid_ros.core.config import NodeConfig, SolidConfig
from solid_ros.core.database.atomic import remove_stale_temporaries
from solid_ros.core.database.persistence import check_save_target
from solid_ros.core.errors import CloudError, ConfigError, DatabaseError, SolidError
from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.odometry.track import OdomSample
from solid_ros.core.stamps import join_stamp, seconds_to_ns
from solid_ros.formats.peers import key_id
from solid_ros.formats.pointcloud2 import cloud_point_times, cloud_to_xyz
from solid_ros.formats.poses import PoseError, odometry_to_pose
from solid_ros.ros.backend_io import BackendIO
from solid_ros.ros.cli import check_parameter_files, scan_arguments, usage
from solid_ros.ros.graph_output import GraphOutput
from solid_ros.ros.health import WARN_THROTTLE_SEC, InputHealth
from solid_ros.ros.kiss_io import KissIO
from solid_ros.ros.loop_output import LoopOutput
from solid_ros.ros.markers import LoopMarkers
from solid_ros.ros.memory import LARGE_BYTES, HeapTrim, Renewal
from solid_ros.ros.odom_wait import OdometryWait
from solid_ros.ros.params import apply_changes, changed, declare_all
from solid_ros.ros.peer_align import PeerAlign
from solid_ros.ros.peer_guard import key_file_is_private, load_fleet_key
from solid_ros.ros.peers import PeerLink, can_renew
from solid_ros.ros.sensor_watch import SensorWatch
from solid_ros.ros.shared_detector import SharedDetector
from solid_ros.ros.stages import Stages, Verified
from solid_ros.ros.stamp_guard import StampGuard
from solid_ros.ros.stats import NodeStats
from solid_ros.runtime import tune_allocator, tune_thread_switching

__all__ = ['NodeStats', 'SolidNode', 'main']

_HEALTH_PERIOD_SEC = 1.0
_JOIN_SEC = 10.0


class SolidNode(Node):
    """The SOLiD loop-closure node; see the module docstring for its interface.

    Raises:
        ConfigError: a parameter is invalid (message names it and its allowed range).
        DatabaseError: ``database_load_path`` cannot be loaded.
    """

    def __init__(self, *, context: Any = None, cli_args: list[str] | None = None,
                 parameter_overrides: list[Parameter] | None = None) -> None:
        super().__init__('solid_node', context=context, cli_args=cli_args,
                         parameter_overrides=parameter_overrides)
        try:
            solid, self._node_cfg = declare_all(self)
            self._solid_cfg = solid.for_odometry(self._node_cfg.odometry_source == 'kiss_icp')
            self._shared = SharedDetector(self._new_closure())
        except BaseException:
            super().destroy_node()
            raise
        self._prepare_save_path()
        cfg = self._node_cfg
        self._kiss = KissIO(self, cfg) if cfg.odometry_source == 'kiss_icp' else None
        self._odom = (OdometryWait(seconds_to_ns(cfg.odom_tolerance_sec))
                      if cfg.use_odom and self._kiss is None else None)
        self._cloud_frame = ''
        self._stamps = StampGuard()
        self._trim = HeapTrim(busy=lambda: not self._stages.wait_idle(0.0))
        self._create_topics()
        self._health = InputHealth(
            self._points.current.topic_name,
            self._odom_sub.topic_name if self._odom is not None else None,
            cfg.qos_reliability, cfg.odom_tolerance_sec, self.count_publishers)
        self.stats = self._health.stats
        self._markers = (LoopMarkers(cfg.marker_max_loops, self._pub_markers.publish,
                                     self._odom_frame, lambda: self.get_clock().now().to_msg())
                         if self._pub_markers is not None else None)
        self.create_service(Trigger, '~/save_database', self._on_save)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_timer(cfg.diagnostics_period_sec, self._publish_diagnostics)
        self.create_timer(_HEALTH_PERIOD_SEC, self._check_health)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        try:
            self._peers = self._start_peers() if cfg.peers else None
        except BaseException:
            super().destroy_node()
            raise
        self._backend = self._start_backend()
        self._align = self._start_align()
        self._loop_output = LoopOutput(
            self._pub_cands.publish, self.get_logger(), self.stats, self._shared, self._markers,
            self._solid_cfg.session_id, self._peers.robots if self._peers is not None else ())
        self._stages = Stages(
            self._shared, self._health, self._pose_for, self._hand_on, self.get_logger(),
            queue_size=cfg.queue_size, verify=self._solid_cfg.verify,
            use_odom=self._odom is not None or self._kiss is not None,
            share=self._peers.share if self._peers is not None else None,
            sensor=SensorWatch(self._solid_cfg, self.get_logger()),
            register=self._register if self._kiss is not None else None)
        self._stages.start()
        self.get_logger().info(
            f'ready: database {self._shared.size} scans, FOV {self._solid_cfg.fov_width_deg} '
            f'deg, threshold {self._solid_cfg.distance_threshold}, queue {cfg.queue_size} '
            f'(keep newest), points QoS {cfg.qos_reliability}/{cfg.qos_depth}')

    def _create_topics(self) -> None:
        cfg = self._node_cfg
        reliability = (ReliabilityPolicy.RELIABLE if cfg.qos_reliability == 'reliable'
                       else ReliabilityPolicy.BEST_EFFORT)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=cfg.qos_depth,
                         reliability=reliability)
        # Deep history: a reliable writer drops unacknowledged samples beyond it, and a back
        # end must not miss a loop when a burst of candidates meets a slow subscriber.
        self._pub_cands = self.create_publisher(Float64MultiArray, '~/loop_candidates', 100)
        # Latched: a display that starts late still gets the current edges.
        self._pub_markers = (self.create_publisher(MarkerArray, '~/loop_markers', QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL)) if cfg.marker_max_loops else None)
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        # Re-created after a cloud over max_points_per_cloud: frees what its reader keeps.
        self._points = Renewal(
            lambda: self.create_subscription(PointCloud2, 'points', self._on_points, qos),
            self.destroy_subscription, safe=lambda: can_renew(self))
        if self._odom is not None:
            # Deep enough that a burst of odometry is not dropped before pairing.
            odom_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST,
                                  depth=max(100, cfg.qos_depth), reliability=reliability)
            self._odom_sub = self.create_subscription(Odometry, 'odom', self._on_odom,
                                                      odom_qos)

    def _start_peers(self) -> PeerLink:
        """The peer exchange; raises ConfigError for a fleet key file it cannot use."""
        cfg, solid = self._node_cfg, self._solid_cfg
        key = load_fleet_key(cfg.peer_key_file) if cfg.peer_key_file else None
        log = self.get_logger()
        if key is None:
            log.warning('peers: no peer_key_file, so peer messages are not authenticated: any '
                        'participant on this ROS domain can send descriptors and clouds in '
                        "another robot's name (fine on a trusted domain; see "
                        'doc/multi_robot.md, Trust: the fleet key)')
        else:
            log.info(f'peers: messages authenticated with the fleet key in '
                     f'{cfg.peer_key_file} (key id {key_id(key)})')
            if not key_file_is_private(cfg.peer_key_file):
                log.warning(f'peers: {cfg.peer_key_file} can be read by other users; '
                            f'chmod 600 {cfg.peer_key_file}')
        peers = PeerLink(self, solid.session_id, solid.fingerprint(), cfg, key,
                         add_keyframe=self._shared.add_peer_keyframe,
                         own_cloud=self._shared.own_cloud,
                         own_keyframes=self._shared.own_keyframes, note_size=self._trim.note)
        self._shared.set_cloud_source(peers)
        peers.start()
        return peers

    def _start_backend(self) -> BackendIO | None:
        """The pose graph's outputs, when the loop closure has one (``backend`` on and
        odometry)."""
        solid, cfg = self._solid_cfg, self._node_cfg
        if not solid.backend:
            return None
        if self._shared.closure.graph is None:
            self.get_logger().info('back end off: no odometry (use_odom is false and '
                                   'odometry_source is topic); loops are still published')
            return None
        output = GraphOutput(self._shared, self.get_logger(), self._stamps.headers)
        return BackendIO(self, cfg, output, self._shared, mount_rotation(solid),
                         self._odom_frame_now)

    def _start_align(self) -> PeerAlign | None:
        """Peers' maps in this robot's, with peers and the back end on."""
        if self._peers is None or self._backend is None:
            return None
        return PeerAlign(self, self._solid_cfg.session_id, self._shared, self._peers.robots,
                         self._backend.output, self._node_cfg.map_frame,
                         self._node_cfg.tf_rate_hz)

    def _odom_frame_now(self) -> str:
        """The odometry frame: the parameter, KISS-ICP's, or the odometry messages'."""
        if self._node_cfg.odom_frame:
            return self._node_cfg.odom_frame
        if self._kiss is not None:
            return self._kiss.frame
        return self._odom.frame_id if self._odom is not None else ''

    # -- configuration -----------------------------------------------------------------------

    @property
    def solid_config(self) -> SolidConfig:
        """The detector settings in force."""
        return self._solid_cfg

    @property
    def node_config(self) -> NodeConfig:
        """The node settings in force."""
        return self._node_cfg

    def _new_closure(self) -> LoopClosure:
        """The loop closure: the database to load, if any; the pose graph with ``backend``
        and odometry to build it from (KISS-ICP's, or the odometry topic's)."""
        cfg = self._node_cfg
        graph = self._solid_cfg.backend and (cfg.odometry_source == 'kiss_icp'
                                             or cfg.use_odom)
        path = cfg.database_load_path
        if not path:
            return LoopClosure(LoopDetector(self._solid_cfg), backend=graph)
        closure = LoopClosure.load(path, self._solid_cfg, backend=graph)
        self.get_logger().info(f'loaded database {path}')
        return closure

    def _prepare_save_path(self) -> None:
        """Remove temporaries a killed save left; warn now when saving would be refused."""
        if not self._node_cfg.database_save_path:
            return
        target = Path(self._node_cfg.database_save_path).expanduser()
        for stale in remove_stale_temporaries(target):
            self.get_logger().info(f'removed {stale}, left by an interrupted save')
        try:
            check_save_target(target)
        except DatabaseError as err:
            self.get_logger().warning(f'~/save_database will refuse: {err}')

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        try:
            solid, node_cfg = apply_changes(self._solid_cfg, self._node_cfg, params,
                                            self._node_cfg.allow_runtime_weakening)
            if solid != self._solid_cfg:
                self._shared.reconfigure(solid)
        except ConfigError as err:
            self.get_logger().warning(f'parameter change refused: {err}',
                                      throttle_duration_sec=WARN_THROTTLE_SEC)
            return SetParametersResult(successful=False, reason=str(err))
        for name, old, new in changed(self._solid_cfg, self._node_cfg, solid, node_cfg):
            self.get_logger().info(f'parameter {name} changed at runtime: {old!r} -> {new!r}')
        self._solid_cfg, self._node_cfg = solid, node_cfg
        self._health.odom_tolerance_sec = node_cfg.odom_tolerance_sec
        if self._odom is not None:
            self._odom.tolerance_ns = seconds_to_ns(node_cfg.odom_tolerance_sec)
        if self._peers is not None:
            self._peers.timeout_sec = node_cfg.peer_timeout_sec
        return SetParametersResult(successful=True)

    # -- input -------------------------------------------------------------------------------

    def _on_points(self, msg: PointCloud2) -> None:
        self._health.cloud_received()
        self._trim.note(len(msg.data))
        try:
            points = cloud_to_xyz(msg)
            if points.shape[0] == 0:
                raise CloudError('cloud has no points')
        except CloudError as err:
            self._stages.reject(str(err))
            return
        # Only clouds that are used move the stamp guard: a malformed one with an old stamp
        # must not make the next good cloud look as if the clock went back.
        header = _header_ns(msg)
        stamp, problem = self._stamps.take(
            header, self._odom.newest if self._odom is not None else None)
        if problem is not None:
            line = self._health.untrusted_stamp(problem, header)
            if line is not None:
                self.get_logger().warning(line)
        times = self._point_times(msg, points.shape[0])
        cap = self._node_cfg.max_points_per_cloud
        if points.shape[0] > cap:
            step = -(-points.shape[0] // cap)
            points = self._thin(points, cap, step)
            times = None if times is None else times[::step]
        self._cloud_frame = msg.header.frame_id
        self._stages.put((points, stamp), times)

    def _point_times(self, msg: PointCloud2, count: int) -> Any:
        """The cloud's per-point times in [0, 1] for KISS-ICP's deskew (``kiss_deskew``,
        ``kiss_time_field``), or None (no KISS-ICP, no deskew, no usable time field)."""
        cfg = self._node_cfg
        if self._kiss is None or not cfg.kiss_deskew:
            return None
        found = cloud_point_times(msg, cfg.kiss_time_field)
        return None if found is None or len(found[0]) != count else found[0]

    def _thin(self, points: Any, cap: int, step: int) -> Any:
        """Every ``step``-th point of a cloud beyond ``max_points_per_cloud`` (a copy, so the
        huge message is freed when the callback returns)."""
        self.stats.downsampled += 1
        self._points.request()
        self.get_logger().warning(
            f'PointCloud2 of {points.shape[0]} points on {self._health.points_topic} thinned '
            f'to every {step}th point (max_points_per_cloud {cap}; {self.stats.downsampled} '
            'so far)', throttle_duration_sec=WARN_THROTTLE_SEC)
        return points[::step].copy()

    def _on_odom(self, msg: Odometry) -> None:
        assert self._odom is not None
        covariance: Any = msg.pose.covariance
        if not all(math.isfinite(v) for v in covariance):
            # Refused alone: the pose is good, and the back end takes its noise model (a
            # covariance it cannot use), so one bad field does not starve the node.
            line = self._health.odom_rejected('odometry covariance is not finite (refused; '
                                              "the pose is used with the back end's model)")
            if line is not None:
                self.get_logger().warning(line)
            covariance = None
        try:
            sample = self._odom.add(_header_ns(msg), odometry_to_pose(msg), covariance,
                                    msg.header.frame_id)
        except PoseError as err:
            line = self._health.odom_rejected(str(err))
            if line is not None:
                self.get_logger().warning(line)
            return
        self._health.odom_received()
        if self._backend is not None:
            self._backend.odometry(msg, sample.pose)

    def _odom_frame(self) -> str:
        return self._odom.frame_id if self._odom is not None else ''

    def _register(self, stamp_ns: int, points: Any, times: Any) -> OdomSample | None:
        """KISS-ICP's registration of the cloud (odometry thread)."""
        assert self._kiss is not None
        # The detector's stamp: monotonic even when the header's is not.
        return self._kiss.pose_for(stamp_ns, points, self._cloud_frame, times)

    def _pose_for(self, stamp_ns: int, points: Any) -> OdomSample | None:
        """The cloud's pose: the odometry within ``odom_tolerance_sec`` of it (waits briefly
        if it lags, while someone publishes odometry); for a cloud whose stamp cannot be
        trusted, the odometry that was newest when it arrived."""
        if self._odom is None:
            return None
        header_ns, trusted = self._stamps.source(stamp_ns)
        if not trusted:
            sample: OdomSample | None = self._stamps.hint(stamp_ns)
            return sample
        publishing = self.count_publishers(self._odom_sub.topic_name) > 0
        sample, gap_ns = self._odom.pair(header_ns, wait=publishing)
        if gap_ns is not None:
            self._health.odom_paired(gap_ns)
        return sample

    def _check_health(self) -> None:
        """Log a problem when it appears and every ``REPEAT_SEC`` while it lasts (and give
        back the memory of a huge message)."""
        if self._points.maybe_renew(idle=self._stages.wait_idle(0.0)):
            self._trim.note(LARGE_BYTES)
            self.get_logger().info('re-subscribed to the points topic to free the buffers of a '
                                   'cloud over max_points_per_cloud')
        self._trim.maybe_trim()
        warnings, recovered = self._health.check()
        for line in warnings:
            self.get_logger().warning(line)
        for line in recovered:
            self.get_logger().info(line)

    # -- output ------------------------------------------------------------------------------

    def _hand_on(self, verified: Verified) -> None:
        """Every verified keyframe, in keyframe order, on the verify thread (the describe
        thread with ``verify`` off): the one place where each keyframe's result and paired
        odometry go: the loops out first (with the clouds' header stamps again, see
        :mod:`~solid_ros.ros.stamp_guard`), then the loop closure's registered step and pose
        graph, so that the loops wait for neither.
        """
        restored = verified
        if self._stamps.shifted:
            restored = dataclasses.replace(verified, result=self._stamps.restore(
                verified.result, self._solid_cfg.session_id))
        self._loop_output.take(restored)
        if self._backend is None:
            return
        step = self._backend.take(verified, restored.result.loops)
        if step is not None and math.isfinite(step.scan.times.step):  # registered steps on
            self._stages.timings.add('step', step.scan.times.step)
        if step is not None and self._align is not None:
            self._align.keyframe(step)

    # -- services and diagnostics -----------------------------------------------------------

    def _on_save(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        path = self._node_cfg.database_save_path
        if not path:
            response.success, response.message = False, 'database_save_path is empty'
            return response
        try:
            size, backup = self._shared.save(path)
        except (SolidError, OSError) as err:
            response.success, response.message = False, f'save failed: {err}'
            self.get_logger().error(response.message)
            return response
        response.success, response.message = True, f'saved {size} scans to {path}'
        if backup is not None:
            response.message += (f'; it replaced a database with more scans, kept as '
                                 f'{backup}')
            self.get_logger().warning(response.message)
        else:
            self.get_logger().info(response.message)
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        self._stages.clear()
        self._shared.reset(LoopDetector(self._solid_cfg))
        if self._markers is not None:
            self._markers.clear()
        if self._backend is not None:
            self._backend.reset()
        if self._align is not None:
            self._align.reset()
        response.success, response.message = True, 'database cleared'
        self.get_logger().info('database cleared by ~/reset')
        return response

    def wait_idle(self, timeout: float) -> bool:
        """Block until both stages are idle with nothing waiting; return False on timeout."""
        return self._stages.wait_idle(timeout)

    def _publish_diagnostics(self) -> None:
        problems = self._health.problems()
        status = DiagnosticStatus(name=f'{self.get_fully_qualified_name()}: loop detector',
                                  hardware_id='solid_ros')
        status.level = DiagnosticStatus.WARN if problems else DiagnosticStatus.OK
        status.message = self._health.summary(problems)
        values = self._health.values(problems)
        clouds_waiting, keyframes_waiting = self._stages.waiting()
        values.update({'database_size': self._shared.size, 'queue_length': clouds_waiting})
        values.update(self._stages.timings.values())
        values.update({'verify_queue_length': keyframes_waiting,
                       'verify_skipped': self.stats.verify_skipped})
        odometry_waiting = self._stages.odometry_waiting
        if odometry_waiting is not None:
            values.update({'odometry_queue_length': odometry_waiting,
                           'odometry_skipped': self.stats.odometry_skipped})
        values.update(self._shared.values())
        values['inter_robot_loops'] = self.stats.inter_robot_loops
        if self._peers is not None:
            values.update(self._peers.diagnostics())
        if self._backend is not None:
            values.update(self._backend.values())
        if self._align is not None:
            values.update(self._align.values())
        if self._kiss is not None:
            values.update(self._kiss.values())
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(msg)

    def destroy_node(self) -> None:
        """Stop and join the worker threads, then destroy the node."""
        if self._odom is not None:
            self._odom.close()  # a describe thread waiting for odometry returns now
        self._stages.stop(_JOIN_SEC)
        if self._kiss is not None:
            self._kiss.close()
        if self._backend is not None:
            self._backend.stop(_JOIN_SEC)
        if self._peers is not None:
            self._peers.close()
        super().destroy_node()


def _header_ns(msg: Any) -> int:
    return join_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec)


def main(args: list[str] | None = None) -> int:
    """Run ``solid_node`` until SIGINT or ROS shutdown; return the process exit status.

    Args:
        args: the full command line, program name first (default ``sys.argv``).

    Returns:
        0 after SIGINT or shutdown (and for ``--help``), 1 when the database cannot be
        loaded, 2 for a bad parameter file, parameter value or ROS argument.
    """
    argv = list(sys.argv if args is None else args)
    try:
        cli = scan_arguments(argv)
        if cli.help:
            print(usage())
            return 0
        # Before rclpy.init(): rcl would refuse a bad file with a traceback, and would start
        # silently on defaults with an empty file or one for another node.
        check_parameter_files(cli)
    except ConfigError as err:
        print(f'solid_node: error: {err}', file=sys.stderr)
        return 2
    tune_allocator()
    tune_thread_switching()
    try:
        rclpy.init(args=argv)
    except RCLError as err:  # what the check above does not know (log levels, remaps, ...)
        print(f'solid_node: error: invalid ROS arguments: {" ".join(str(err).split())}',
              file=sys.stderr)
        return 2
    logger = rclpy.logging.get_logger('solid_node')
    node: SolidNode | None = None
    status = 0
    try:
        node = SolidNode()
        rclpy.spin(node)
    except ConfigError as err:
        logger.fatal(f'invalid parameter: {err}')
        status = 2
    except SolidError as err:
        logger.fatal(f'cannot start: {err}')
        status = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        # SIGINT shuts the context down from the signal handler; a spin (or start) caught in
        # between fails on the invalid context instead of seeing the shutdown. That is the
        # same clean stop; any other rcl error still fails loudly.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())
