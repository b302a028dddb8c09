"""``solid_node``: PointCloud2 in, SOLiD loop candidates with yaw out.

Topics (relative names, remappable): subscribes ``points`` (sensor_msgs/PointCloud2) and,
with ``use_odom``, ``odom`` (nav_msgs/Odometry); publishes ``~/loop_candidates``
(std_msgs/Float64MultiArray, see :mod:`solid_ros.formats.candidates`), ``~/loop_markers``
(visualization_msgs/MarkerArray, latched: transient local, depth 1) and ``/diagnostics``.
Services ``~/save_database`` and ``~/reset`` (std_srvs/Trigger).

Loop markers: one LINE_LIST of the newest ``marker_max_loops`` loops whose two positions are
known: the query's from paired odometry, the match's as stored with its scan in the database
(this run, a loaded session or a peer robot). Loops against other sessions are drawn in blue
at the position stored in that session's odometry frame, which lines up only when the
sessions share a map frame.

Health (logged as throttled warnings and raised to WARN on /diagnostics while it lasts; the
windows are wall-clock seconds): no cloud on the resolved points topic for ``_SILENCE_SEC``
since start or since the last one; with ``use_odom``, no odometry for as long, or odometry
whose stamps lie more than ``max(_CLOCK_GAP_SEC, 10 x odom_tolerance_sec)`` from the cloud
stamps (another clock); clouds rejected, dropped because processing or verification falls
behind, or failed with an error in the last ``_SILENCE_SEC`` (their counters stay on
/diagnostics; the WARN clears once they stop). Each distinct reason
for a rejection (numbers aside) is logged when it first occurs, repeats at most every
``_WARN_THROTTLE_SEC``.

Threading: the subscription callback only decodes (zero-copy) or rejects a cloud and appends
it to a bounded queue; when the queue is full the oldest waiting cloud is dropped (keep newest)
and counted as skipped. A worker thread describes, searches and stores; a second thread
verifies keyframes and publishes their loops (with ``verify`` off the worker publishes too), so
the executor is never blocked by descriptor computation or registration.
"""

from __future__ import annotations

import importlib
import math
import re
import sys
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import ColorRGBA, Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from solid_ros.core.config import NodeConfig, SolidConfig
from solid_ros.core.detector import LoopCandidate, LoopDetector, Proposal
from solid_ros.core.errors import CloudError, ConfigError, DatabaseError, SolidError
from solid_ros.core.persistence import check_save_target, remove_stale_temporaries
from solid_ros.core.registration import KeyframeCloud
from solid_ros.core.stamps import NS_PER_SEC, format_stamp, join_stamp, seconds_to_ns
from solid_ros.formats.candidates import layout_dims, to_rows
from solid_ros.formats.peers import DescriptorMessage
from solid_ros.formats.pointcloud2 import cloud_to_xyz
from solid_ros.formats.poses import PoseError, odometry_to_pose
from solid_ros.ros.cli import check_parameter_files, scan_arguments, usage
from solid_ros.ros.params import apply_changes, declare_all
from solid_ros.ros.peers import PeerLink
from solid_ros.runtime import tune_allocator, tune_thread_switching

__all__ = ['NodeStats', 'SolidNode', 'main']

_ODOM_BUFFER = 512
_ODOM_WAIT_SEC = 0.25
_ODOM_MAX_MISSES = 3  # waits in a row that saw no odometry before the node stops waiting
_WARN_THROTTLE_SEC = 5.0
_SILENCE_SEC = 5.0  # no cloud / no odometry this long (since start or the last one) is a problem
_REPEAT_SEC = 30.0  # a lasting problem is logged again this often
_HEALTH_PERIOD_SEC = 1.0
_CLOCK_GAP_SEC = 1.0  # least cloud-odometry stamp gap taken for another clock
_REASON_KINDS = 32  # distinct rejection reasons remembered for throttling
_MIN_PROPOSALS = 20  # keyframes that may wait for verification (at least queue_size)


@dataclass
class NodeStats:
    """Counters reported on /diagnostics."""

    received: int = 0
    processed: int = 0
    skipped: int = 0
    rejected: int = 0
    failed: int = 0
    loops: int = 0
    without_odom: int = 0
    verify_skipped: int = 0
    inter_robot_loops: int = 0


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
            self._solid, self._cfg = declare_all(self)
            self._detector = self._new_detector(load=True)
        except BaseException:
            super().destroy_node()
            raise
        self._prepare_save_path()
        self.stats = NodeStats()
        self._times_ms: deque[float] = deque(maxlen=1000)
        self._stage_ms: dict[str, deque[float]] = {k: deque(maxlen=1000)
                                                    for k in ('describe', 'search', 'verify')}
        # Stage 1 (describe, search, store) and stage 2 (verify, publish) each hold their lock
        # while they use the detector; save and reset take both.
        self._det_lock = threading.Lock()
        self._verify_lock = threading.Lock()
        self._cv = threading.Condition()
        self._queue: deque[tuple[npt.NDArray[np.floating], int]] = deque(
            maxlen=self._cfg.queue_size)
        self._proposals: deque[tuple[Proposal, npt.NDArray[np.float64] | None]] = deque()
        self._busy = False
        self._verifying = False
        self._stop = False
        self._odom: deque[tuple[int, npt.NDArray[np.float64]]] = deque(maxlen=_ODOM_BUFFER)
        self._odom_frame = ''
        self._odom_misses = 0
        # Health: wall-clock (monotonic) times of the last cloud / odometry / rejections, the
        # stamp gap to the nearest odometry at the last pairing, the problems logged.
        self._started = time.monotonic()
        self._last_cloud: float | None = None
        self._last_odom: float | None = None
        self._odom_gap: tuple[float, int] | None = None
        self._rejected_at: deque[float] = deque(maxlen=10_000)
        # Latest time a cloud was dropped (falling behind) or failed, by kind: a WARN while
        # recent, not for the rest of the run.
        self._trouble_at: dict[str, float] = {}
        self._reject_lock = threading.Lock()
        self._reasons: OrderedDict[str, list[float]] = OrderedDict()
        self._last_reason = ''
        self._problems_logged: dict[str, float] = {}
        # Newest loop edges (query position, match position, other session): bounded, so
        # neither memory nor the rebuild on every loop grows with the run.
        self._edges: deque[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], bool]] = (
            deque(maxlen=self._cfg.marker_max_loops))
        self._edges_lock = threading.Lock()  # the verify thread adds, ~/reset clears

        reliability = (ReliabilityPolicy.RELIABLE if self._cfg.qos_reliability == 'reliable'
                       else ReliabilityPolicy.BEST_EFFORT)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self._cfg.qos_depth,
                         reliability=reliability)
        # Deep history: a reliable writer drops unacknowledged samples beyond it, and a back
        # end must not miss a loop when a burst of candidates meets a slow subscriber.
        self._pub_cands = self.create_publisher(Float64MultiArray, '~/loop_candidates', 100)
        # Latched: a display that starts late still gets the current edges.
        self._pub_markers = (self.create_publisher(MarkerArray, '~/loop_markers', QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL)) if self._cfg.marker_max_loops else None)
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._points_sub = self.create_subscription(PointCloud2, 'points', self._on_points, qos)
        if self._cfg.use_odom:
            # Deep enough that a burst of odometry is not dropped before pairing.
            odom_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST,
                                  depth=max(100, self._cfg.qos_depth), reliability=reliability)
            self._odom_sub = self.create_subscription(Odometry, 'odom', self._on_odom,
                                                      odom_qos)
        self.create_service(Trigger, '~/save_database', self._on_save)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_timer(self._cfg.diagnostics_period_sec, self._publish_diagnostics)
        self.create_timer(_HEALTH_PERIOD_SEC, self._check_health)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._peers: PeerLink | None = None
        if self._cfg.peers:
            self._peers = PeerLink(
                self, self._solid.session_id, self._solid.fingerprint(),
                self._cfg.peer_timeout_sec, self._cfg.peer_catchup,
                add_keyframe=self._peer_add, own_cloud=self._peer_cloud,
                own_keyframes=self._peer_keyframes)
            self._detector.fetch_cloud = self._peers.fetch
            self._peers.start()
        self._worker = threading.Thread(target=self._run, name='solid_describe', daemon=True)
        self._verifier = threading.Thread(target=self._run_verify, name='solid_verify',
                                          daemon=True)
        self._worker.start()
        self._verifier.start()
        self.get_logger().info(
            f'ready: database {self._db_size()} scans, FOV {self._solid.fov_width_deg} deg, '
            f'threshold {self._solid.distance_threshold}, queue {self._cfg.queue_size} '
            f'(keep newest), points QoS {self._cfg.qos_reliability}/{self._cfg.qos_depth}')

    # -- configuration -----------------------------------------------------------------------

    @property
    def solid_config(self) -> SolidConfig:
        """The detector settings in force."""
        return self._solid

    @property
    def node_config(self) -> NodeConfig:
        """The node settings in force."""
        return self._cfg

    def _new_detector(self, *, load: bool) -> LoopDetector:
        path = self._cfg.database_load_path
        if load and path:
            det = LoopDetector.load(path, self._solid)
            self.get_logger().info(f'loaded database {path}')
            return det
        return LoopDetector(self._solid)

    def _prepare_save_path(self) -> None:
        """Remove temporaries a killed save left; warn now when saving would be refused."""
        if not self._cfg.database_save_path:
            return
        target = Path(self._cfg.database_save_path).expanduser()
        for stale in remove_stale_temporaries(target):
            self.get_logger().info(f'removed {stale}, left by an interrupted save')
        try:
            check_save_target(target)
        except DatabaseError as err:
            self.get_logger().warning(f'~/save_database will refuse: {err}')

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        try:
            solid, node_cfg = apply_changes(self._solid, self._cfg, params)
            if solid != self._solid:
                with self._det_lock, self._verify_lock:
                    _update_detector_config(self._detector, solid)
        except ConfigError as err:
            return SetParametersResult(successful=False, reason=str(err))
        self._solid, self._cfg = solid, node_cfg
        if self._peers is not None:
            self._peers.timeout_sec = node_cfg.peer_timeout_sec
        return SetParametersResult(successful=True)

    # -- input -------------------------------------------------------------------------------

    def _on_points(self, msg: PointCloud2) -> None:
        self.stats.received += 1
        self._last_cloud = time.monotonic()
        try:
            points = cloud_to_xyz(msg)
            if points.shape[0] == 0:
                raise CloudError('cloud has no points')
        except CloudError as err:
            self._reject(str(err))
            return
        item = (points, _header_ns(msg))
        with self._cv:
            if len(self._queue) == self._queue.maxlen:
                self.stats.skipped += 1
                self._trouble('skipped')
                self.get_logger().warning(
                    f'processing falls behind: dropped the oldest waiting cloud '
                    f'({self.stats.skipped} skipped so far)',
                    throttle_duration_sec=_WARN_THROTTLE_SEC)
            self._queue.append(item)
            self._cv.notify_all()

    def _on_odom(self, msg: Odometry) -> None:
        try:
            pose = odometry_to_pose(msg)
        except PoseError as err:
            self.get_logger().warning(f'odometry message skipped: {err}',
                                      throttle_duration_sec=_WARN_THROTTLE_SEC)
            return
        self._last_odom = time.monotonic()
        with self._cv:
            self._odom.append((_header_ns(msg), pose))
            self._odom_frame = msg.header.frame_id
            self._odom_misses = 0
            self._cv.notify_all()

    def _pose_for(self, stamp_ns: int) -> npt.NDArray[np.float64] | None:
        """Nearest odometry pose within ``odom_tolerance_sec`` (waits briefly if odom lags)."""
        if not self._cfg.use_odom:
            return None
        tol = seconds_to_ns(self._cfg.odom_tolerance_sec)
        deadline = time.monotonic() + _ODOM_WAIT_SEC
        # Odometry often arrives just after its cloud: wait for one at or past it, but only
        # when someone publishes odometry (an unused odom topic must not slow every scan),
        # and not while a silent publisher has let several waits pass without a message.
        publishing = self.count_publishers(self._odom_sub.topic_name) > 0
        with self._cv:
            waited = False
            while (publishing and self._odom_misses < _ODOM_MAX_MISSES
                   and (not self._odom or self._odom[-1][0] < stamp_ns)
                   and not self._stop and time.monotonic() < deadline):
                waited = True
                self._cv.wait(deadline - time.monotonic())
            if waited and (not self._odom or self._odom[-1][0] < stamp_ns):
                self._odom_misses += 1
            best = min(self._odom, key=lambda sp: abs(sp[0] - stamp_ns), default=None)
        if best is not None:
            self._odom_gap = (time.monotonic(), stamp_ns - best[0])
        if best is None or abs(best[0] - stamp_ns) > tol:
            return None
        return best[1]

    def _trouble(self, kind: str) -> None:
        with self._reject_lock:
            self._trouble_at[kind] = time.monotonic()

    def _reject(self, reason: str) -> None:
        """Count a rejected cloud; log each distinct reason at once, its repeats throttled."""
        now = time.monotonic()
        kind = re.sub(r'\d+', '#', reason)  # the same reason for clouds of other sizes
        with self._reject_lock:
            self.stats.rejected += 1
            self._rejected_at.append(now)
            self._last_reason = reason
            seen = self._reasons.get(kind)
            if seen is None:
                seen = self._reasons[kind] = [now, 0.0]
                while len(self._reasons) > _REASON_KINDS:
                    self._reasons.popitem(last=False)
                text = 'first of its kind'
            else:
                self._reasons.move_to_end(kind)
                seen[1] += 1
                if now - seen[0] < _WARN_THROTTLE_SEC:
                    return
                text = f'{int(seen[1])} more like it since it was last logged'
                seen[:] = [now, 0.0]
            total = self.stats.rejected
        self.get_logger().warning(f'rejected PointCloud2 on {self._points_sub.topic_name}: '
                                  f'{reason} ({text}; {total} rejected so far)')

    def _problems(self) -> dict[str, str]:
        """The input problems now, by kind, each as one line naming the topic."""
        now = time.monotonic()
        out: dict[str, str] = {}
        points = self._points_sub.topic_name
        if self._last_cloud is None and now - self._started > _SILENCE_SEC:
            pubs = self.count_publishers(points)
            hint = (f'{pubs} publisher(s): check their QoS against qos_reliability '
                    f'{self._cfg.qos_reliability!r}' if pubs else
                    'no publisher: check the topic name or remap points:=<your topic>')
            out['no_clouds'] = (f'no PointCloud2 received on {points} in the '
                                f'{now - self._started:.0f} s since start ({hint})')
        elif self._last_cloud is not None and now - self._last_cloud > _SILENCE_SEC:
            out['no_clouds'] = (f'no PointCloud2 received on {points} for the last '
                                f'{now - self._last_cloud:.0f} s ({self.stats.received} before)')
        if self._cfg.use_odom:
            odom = self._odom_sub.topic_name
            since = self._last_odom if self._last_odom is not None else self._started
            if now - since > _SILENCE_SEC:
                when = (f'for {now - since:.0f} s' if self._last_odom is not None
                        else f'in the {now - since:.0f} s since start')
                out['no_odom'] = (f'use_odom is on but no nav_msgs/Odometry received on {odom} '
                                  f'{when} ({self.count_publishers(odom)} publisher(s)); '
                                  'clouds are processed without pose')
            gap = self._odom_gap
            limit = max(_CLOCK_GAP_SEC, 10.0 * self._cfg.odom_tolerance_sec)
            if (gap is not None and now - gap[0] <= _SILENCE_SEC
                    and abs(gap[1]) > limit * NS_PER_SEC):
                out['odom_clock'] = (f'odometry on {odom} is stamped '
                                     f'{-gap[1] / NS_PER_SEC:+.3f} s from '
                                     f'the clouds on {points} (tolerance '
                                     f'{self._cfg.odom_tolerance_sec:g} s): another clock? '
                                     '(use_sim_time, the bag clock, the driver time source); '
                                     'clouds are processed without pose')
        with self._reject_lock:
            while self._rejected_at and now - self._rejected_at[0] > _SILENCE_SEC:
                self._rejected_at.popleft()
            recent, reason = len(self._rejected_at), self._last_reason
            trouble = {k: t for k, t in self._trouble_at.items() if now - t <= _SILENCE_SEC}
        if recent:
            out['rejected'] = (f'{recent} PointCloud2 rejected on {points} in the last '
                               f'{_SILENCE_SEC:.0f} s (latest: {reason})')
        counts = {'skipped': self.stats.skipped, 'verify_skipped': self.stats.verify_skipped,
                  'failed': self.stats.failed}
        for kind, t in trouble.items():
            out[kind] = _TROUBLE[kind].format(n=counts[kind], ago=now - t)
        return out

    def _check_health(self) -> None:
        """Log a problem when it appears and every ``_REPEAT_SEC`` while it lasts."""
        now = time.monotonic()
        problems = self._problems()
        for kind, text in problems.items():
            if kind in _SELF_LOGGED:
                continue  # logged where they happen
            last = self._problems_logged.get(kind)
            if last is None or now - last >= _REPEAT_SEC:
                self._problems_logged[kind] = now
                self.get_logger().warning(text)
        for kind in [k for k in self._problems_logged if k not in problems]:
            del self._problems_logged[kind]
            self.get_logger().info(f'recovered: {_RECOVERED[kind]}')

    # -- processing --------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._queue and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                points, stamp_ns = self._queue.popleft()
                self._busy = True
            try:
                self._process(points, stamp_ns)
            except CloudError as err:  # decoded, but nothing the detector can use
                self._reject(str(err))
            except Exception as err:  # the worker must survive any bad scan
                self.stats.failed += 1
                self._trouble('failed')
                self.get_logger().error(f'processing failed: {type(err).__name__}: {err}',
                                        throttle_duration_sec=_WARN_THROTTLE_SEC)
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def _process(self, points: npt.NDArray[np.floating], stamp_ns: int) -> None:
        """Stage 1: describe, search and store; hand the keyframe to the verification stage
        (or, descriptor only, finish it here)."""
        t0 = time.perf_counter()
        pose = self._pose_for(stamp_ns)
        with self._det_lock:
            proposal = self._detector.propose(points, stamp_ns, pose=pose)
        self._times_ms.append((time.perf_counter() - t0) * 1e3)
        self.stats.processed += 1
        if pose is None and self._cfg.use_odom:
            self.stats.without_odom += 1
        if proposal is None:
            return
        if self._peers is not None:
            self._peers.share(proposal)
        self._stage_ms['describe'].append(proposal.describe_ms)
        self._stage_ms['search'].append(proposal.search_ms)
        if not self._solid.verify:
            # Descriptor only: what is left takes well under a millisecond, so it runs here
            # instead of waiting for the verify thread to wake up.
            self._verify_and_publish(proposal, pose)
            return
        with self._cv:
            if len(self._proposals) >= max(_MIN_PROPOSALS, self._cfg.queue_size):
                self._proposals.popleft()
                self.stats.verify_skipped += 1
                self._trouble('verify_skipped')
                self.get_logger().warning(
                    'verification falls behind: dropped the oldest waiting keyframe '
                    f'({self.stats.verify_skipped} so far; its cloud is not stored)',
                    throttle_duration_sec=_WARN_THROTTLE_SEC)
            self._proposals.append((proposal, pose))
            self._cv.notify_all()

    def _run_verify(self) -> None:
        """Stage 2 thread: verify keyframes in order, publish their loops."""
        if self._solid.verify:
            # small_gicp and scipy.ndimage take about 0.8 s to import: here, before the
            # first keyframe, not in its latency (where the queue would drop clouds).
            for module in ('small_gicp', 'scipy.ndimage'):
                try:
                    importlib.import_module(module)
                except ImportError as err:
                    self.get_logger().error(f'verification needs {module}: {err} '
                                            '(pip install small-gicp)')
        while True:
            with self._cv:
                while not self._proposals and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                proposal, pose = self._proposals.popleft()
                self._verifying = True
            try:
                self._verify_and_publish(proposal, pose)
            except Exception as err:  # the thread must survive any bad keyframe
                self.stats.failed += 1
                self._trouble('failed')
                self.get_logger().error(f'verification failed: {type(err).__name__}: {err}',
                                        throttle_duration_sec=_WARN_THROTTLE_SEC)
            finally:
                with self._cv:
                    self._verifying = False
                    self._cv.notify_all()

    def _verify_and_publish(self, proposal: Proposal,
                            pose: npt.NDArray[np.float64] | None) -> None:
        with self._verify_lock:
            detector = self._detector
            result = detector.verify(proposal)
        self._stage_ms['verify'].append(result.times.verify)
        self._publish(result.loops, pose, proposal, detector)

    def _publish(self, cands: Sequence[LoopCandidate], pose: npt.NDArray[np.float64] | None,
                 proposal: Proposal, detector: LoopDetector) -> None:
        if not cands:
            return
        self.stats.loops += len(cands)
        self.stats.inter_robot_loops += sum(
            1 for c in cands if self._peers is not None
            and c.match_session in self._peers.robots)
        self._pub_cands.publish(self._candidates_msg(cands))
        for c in cands:
            t = ', '.join(f'{v:.2f}' for v in c.pose[:3])
            state = (f'verified, fitness {c.fitness:.2f}, rmse {c.rmse:.3f} m' if c.verified
                     else 'descriptor only')
            self.get_logger().info(
                f'loop: keyframe {c.query_index} ({format_stamp(c.query_stamp_ns)}) -> session '
                f'{c.match_session} keyframe {c.match_index} ({format_stamp(c.match_stamp_ns)}), '
                f'{state}, yaw {math.degrees(c.yaw):.1f} deg, t ({t}) m')
        self._add_edges(cands, pose, proposal, detector)

    # -- peer robots (see solid_ros.ros.peers) ---------------------------------------------------

    def _peer_add(self, d: DescriptorMessage) -> None:
        with self._det_lock:
            self._detector.add_peer_keyframe(d.robot, d.index, d.stamp_ns, d.r_solid, d.heading,
                                             d.pose)

    def _peer_cloud(self, index: int) -> KeyframeCloud | None:
        # Not under the verification lock: the verify thread may hold it while it waits for
        # a peer's reply, and this runs on the executor that delivers that reply.
        with self._det_lock:
            seq = self._detector.database.own_seq(index)
        return None if seq is None else self._detector.clouds.get(seq)

    def _peer_keyframes(self, limit: int) -> list[Any]:
        with self._det_lock:
            return self._detector.own_keyframes(limit)

    def _candidates_msg(self, cands: Sequence[Any]) -> Float64MultiArray:
        rows = to_rows(cands)
        msg = Float64MultiArray()
        msg.layout.dim = [MultiArrayDimension(label=label, size=size, stride=stride)
                          for label, size, stride in layout_dims(len(rows))]
        msg.data = rows.reshape(-1).tolist()
        return msg

    def _add_edges(self, cands: Sequence[LoopCandidate], pose: npt.NDArray[np.float64] | None,
                   proposal: Proposal, detector: LoopDetector) -> None:
        if pose is None or self._pub_markers is None:
            return
        edges = []
        for c in cands:
            match_pos = self._match_position(c, proposal, detector)
            if match_pos is not None:
                other = int(c.match_session) != self._solid.session_id
                edges.append((pose[:3, 3].copy(), match_pos, other))
        if edges:
            with self._edges_lock:
                self._edges.extend(edges)
                self._pub_markers.publish(self._markers())

    def _match_position(self, cand: LoopCandidate, proposal: Proposal,
                        detector: LoopDetector) -> npt.NDArray[np.float64] | None:
        """Position stored with the matched scan (any session), or None when unknown."""
        seq = next((h.match.seq for h in proposal.hits
                    if (h.match.session, h.match.index) == (cand.match_session,
                                                            cand.match_index)), None)
        if seq is None:
            return None
        # Under the stage-1 lock: it stores scans, and may evict this one meanwhile.
        with self._det_lock:
            db = detector.database
            if (detector is not self._detector or not db.is_stored(seq)
                    or db.match_info(seq)[:2] != (cand.match_index, cand.match_session)):
                return None
            stored = db.pose(seq)
            return None if stored is None else np.asarray(stored[:3], dtype=np.float64)

    def _markers(self) -> MarkerArray:
        m = Marker()
        m.header.frame_id = self._odom_frame or 'map'
        m.header.stamp = self.get_clock().now().to_msg()
        m.ns, m.id = 'loop_edges', 0
        m.type, m.action = Marker.LINE_LIST, Marker.ADD
        m.pose.orientation.w = 1.0
        m.scale.x = 0.1
        m.color.r, m.color.g, m.color.b, m.color.a = 1.0, 0.2, 0.2, 1.0
        own, other = m.color, ColorRGBA(r=0.2, g=0.6, b=1.0, a=1.0)
        for a, b, foreign in self._edges:
            m.points.append(Point(x=float(a[0]), y=float(a[1]), z=float(a[2])))
            m.points.append(Point(x=float(b[0]), y=float(b[1]), z=float(b[2])))
            m.colors.extend((other, other) if foreign else (own, own))
        return MarkerArray(markers=[m])

    # -- services and diagnostics -----------------------------------------------------------

    def _on_save(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        path = self._cfg.database_save_path
        if not path:
            response.success, response.message = False, 'database_save_path is empty'
            return response
        try:
            with self._det_lock, self._verify_lock:
                size = self._db_size()
                _save_atomic(self._detector, path)
        except (SolidError, OSError) as err:
            response.success, response.message = False, f'save failed: {err}'
            self.get_logger().error(response.message)
            return response
        response.success, response.message = True, f'saved {size} scans to {path}'
        self.get_logger().info(response.message)
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        with self._cv:
            self._queue.clear()
            self._proposals.clear()
        with self._det_lock, self._verify_lock:
            self._detector = self._new_detector(load=False)
            if self._peers is not None:
                self._detector.fetch_cloud = self._peers.fetch
        with self._edges_lock:
            self._edges.clear()
            if self._pub_markers is not None:
                # Replaces the latched edges: a display that starts later shows none either.
                clear = Marker(ns='loop_edges', action=Marker.DELETEALL)
                clear.header.frame_id = self._odom_frame or 'map'
                self._pub_markers.publish(MarkerArray(markers=[clear]))
        response.success, response.message = True, 'database cleared'
        self.get_logger().info('database cleared by ~/reset')
        return response

    def _db_size(self) -> int:
        return int(self._detector.database.size)

    def wait_idle(self, timeout: float) -> bool:
        """Block until both stages are idle with nothing waiting; return False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while self._queue or self._busy or self._proposals or self._verifying:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    def _publish_diagnostics(self) -> None:
        s = self.stats
        times = np.asarray(self._times_ms, dtype=np.float64)
        pct = (np.percentile(times, [50, 95, 99]) if times.size else np.full(3, np.nan))
        status = DiagnosticStatus(name=f'{self.get_fully_qualified_name()}: loop detector',
                                  hardware_id='solid_ros')
        problems = self._problems()
        status.level = DiagnosticStatus.WARN if problems else DiagnosticStatus.OK
        status.message = '; '.join([*problems.values(), (
            f'{s.processed} processed, {s.skipped} skipped, {s.rejected} rejected, '
            f'{s.loops} loops')])
        now = time.monotonic()
        gap = self._odom_gap
        values: dict[str, object] = {
            'points_topic': self._points_sub.topic_name,
            'seconds_since_last_cloud': _age(now, self._last_cloud),
            'odom_topic': self._odom_sub.topic_name if self._cfg.use_odom else '',
            'seconds_since_last_odom': _age(now, self._last_odom),
            'odom_stamp_offset_sec': 'nan' if gap is None else f'{-gap[1] / NS_PER_SEC:.3f}',
            'clouds_rejected_recently': len(self._rejected_at),
            'last_reject_reason': self._last_reason,
            'problems': ', '.join(problems) or 'none',
            'clouds_received': s.received, 'clouds_processed': s.processed,
            'clouds_skipped': s.skipped, 'clouds_rejected': s.rejected,
            'clouds_failed': s.failed, 'clouds_without_odom': s.without_odom,
            'loop_candidates': s.loops,
            'database_size': self._db_size(), 'queue_length': len(self._queue),
            'processing_ms_p50': f'{pct[0]:.2f}', 'processing_ms_p95': f'{pct[1]:.2f}',
            'processing_ms_p99': f'{pct[2]:.2f}',
            'processing_ms_max': f'{times.max():.2f}' if times.size else 'nan',
        }
        for stage, ms in self._stage_ms.items():
            arr = np.asarray(ms, dtype=np.float64)
            p50, p95 = np.percentile(arr, [50, 95]) if arr.size else (math.nan, math.nan)
            values[f'{stage}_ms_p50'], values[f'{stage}_ms_p95'] = f'{p50:.2f}', f'{p95:.2f}'
        det = self._detector
        values['verify_queue_length'] = len(self._proposals)
        values['verify_skipped'] = s.verify_skipped
        values['keyframe_clouds'] = len(det.clouds)
        values['keyframe_clouds_mb'] = f'{det.clouds.nbytes / 1e6:.2f}'
        values['keyframe_clouds_dropped'] = det.clouds.dropped
        for reason, count in sorted(dict(det.reasons).items()):
            values[f'verify_{reason}'] = count
        values['inter_robot_loops'] = s.inter_robot_loops
        if self._peers is not None:
            values.update(self._peers.diagnostics())
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(msg)

    def destroy_node(self) -> None:
        """Stop and join the worker threads, then destroy the node."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        for thread in (self._worker, self._verifier):
            if thread.is_alive() and thread is not threading.current_thread():
                thread.join(timeout=10.0)
        super().destroy_node()


_TROUBLE = {
    'skipped': '{n} PointCloud2 dropped so far: processing falls behind (latest {ago:.0f} s ago)',
    'verify_skipped': '{n} keyframes dropped so far: verification falls behind (latest '
                      '{ago:.0f} s ago)',
    'failed': '{n} clouds failed with an error so far (latest {ago:.0f} s ago; see the log)'}
_SELF_LOGGED = ('rejected', *_TROUBLE)
_RECOVERED = {'no_clouds': 'PointCloud2 arriving', 'no_odom': 'odometry arriving',
              'odom_clock': 'odometry stamps match the clouds again'}


def _header_ns(msg: Any) -> int:
    return join_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec)


def _age(now: float, then: float | None) -> str:
    return 'never' if then is None else f'{now - then:.1f}'


def _update_detector_config(detector: LoopDetector, config: SolidConfig) -> None:
    """Apply tunable settings to a running detector (raises ConfigError if refused)."""
    detector.reconfigure(config)


def _save_atomic(detector: LoopDetector, path: str) -> None:
    """Save the database; the core writes a temporary file and renames it over ``path``."""
    Path(path).expanduser().parent.mkdir(parents=True, exist_ok=True)
    detector.save(Path(path).expanduser())


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
