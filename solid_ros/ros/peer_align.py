"""Peers' maps in this robot's map, on solid_node (``peers`` and the back end on).

Each robot keeps its own map; the alignment of every peer's map in it comes from the
inter-robot loops between them (:mod:`solid_ros.core.backend.alignment`). What crosses the
network for it goes on ``/solid/alignment`` (messages of :mod:`solid_ros.formats.fleet_msgs`,
sealed and admitted by the exchange's guard, as every peer message):

- each inter-robot loop this robot publishes, with its keyframe's map pose (192 bytes): the
  peer aligns from it too;
- once a second, the poses of this robot's keyframes that some inter-robot loop names and
  that moved since they were last sent (its graph closed a loop): 36 bytes each;
- on request only (service ``~/peer_paths``), a peer's whole corrected path.

Outputs: ``/tf`` ``map_frame -> <map_frame>/robot<j>`` for every aligned peer ``j`` (a frame
of this robot's tree: on a shared ``/tf`` every robot names its own view of a peer, so no frame
gets two parents); ``/diagnostics`` values ``fleet_*``; one log line when a peer is aligned or
its alignment jumps; ``~/peer_paths/robot<j>`` (nav_msgs/Path in ``map_frame``, latched) after
``~/peer_paths`` is called. A robot's alignment messages draw on its descriptor budget
(``peer_descriptor_rate``). Memory per peer is bounded (``_MAX_POSES`` poses, the core's
loops); a peer the guard no longer tracks is forgotten, one that left keeps its alignment.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict

import numpy as np
import numpy.typing as npt
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt8MultiArray

from solid_ros.core.backend.alignment import path_lengths
from solid_ros.core.flow.closure import Step
from solid_ros.core.geometry import matrix_to_vector, vector_to_matrix
from solid_ros.core.results import LoopCandidate
from solid_ros.formats.fleet_msgs import (
    MAX_ALIGN_BYTES,
    MAX_POSES,
    AlignMessage,
    LoopMessage,
    PathRequest,
    PosesMessage,
    decode_align,
    encode_align,
)
from solid_ros.formats.peers import PeerMessageError
from solid_ros.ros.graph_msgs import transform_msg
from solid_ros.ros.graph_output import GraphOutput
from solid_ros.ros.peer_guard import PeerGuard, Refused
from solid_ros.ros.peer_paths import PeerPaths
from solid_ros.ros.shared_detector import SharedDetector

__all__ = ['ALIGN_TOPIC', 'PeerAlign', 'peer_frame']

ALIGN_TOPIC = '/solid/alignment'
FloatArray = npt.NDArray[np.float64]
_TICK_SEC = 1.0
_MOVED_M = 0.02  # a linked keyframe's pose is sent again once it moved this far
_MAX_POSES = 2000  # poses kept per peer (those its loops name)
_MAX_LINKED = 4000  # own keyframes named by inter-robot loops, newest kept
_LISTED = 16
_ENVELOPE = 64


def peer_frame(map_frame: str, peer: int) -> str:
    """This robot's frame of peer ``peer``'s map."""
    return f'{map_frame}/robot{peer}'


class PeerAlign:
    """The alignment exchange and outputs of one node (module docstring).

    Args:
        node: the node.
        robot: this robot's id.
        shared: the loop closure (its fleet alignment and pose graph).
        guard: the peer exchange's guard (sealing, authentication, admission).
        output: the pose graph's snapshots (this robot's corrected keyframes).
        map_frame: this robot's map frame.
        tf_rate_hz: how often the peers' frames go on /tf (0: never).
    """

    def __init__(self, node: Node, robot: int, shared: SharedDetector, guard: PeerGuard,
                 output: GraphOutput, map_frame: str, tf_rate_hz: float) -> None:
        self._node, self.robot, self._shared = node, int(robot), shared
        self._guard, self._output, self._map_frame = guard, output, map_frame
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._poses: dict[int, OrderedDict[int, tuple[FloatArray, float]]] = {}
        self._linked: OrderedDict[int, FloatArray | None] = OrderedDict()  # -> pose sent
        self._dirty = False
        self.counts: Counter[str] = Counter()
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE)
        self._pub = node.create_publisher(UInt8MultiArray, ALIGN_TOPIC, qos)
        node.create_subscription(UInt8MultiArray, ALIGN_TOPIC, self._on_message, qos)
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:  # BackendIO says so once
            TFMessage = None  # noqa: N806
        self._tf = node.create_publisher(TFMessage, '/tf', 100) if TFMessage else None
        node.create_timer(_TICK_SEC, self._tick)
        if tf_rate_hz > 0.0 and self._tf is not None:
            node.create_timer(1.0 / tf_rate_hz, self._broadcast)
        self._paths = PeerPaths(node, robot, shared, output, map_frame, self._send, self.counts)

    # -- out ---------------------------------------------------------------------------------

    def _send(self, msg: AlignMessage) -> None:
        out = UInt8MultiArray()
        with self._send_lock:  # sealed stamps go out in order
            out.data = self._guard.seal(ALIGN_TOPIC, encode_align(msg))
            self._pub.publish(out)

    def keyframe(self, step: Step) -> None:
        """A keyframe the graph took (verify thread): its inter-robot loops go out."""
        loops = [c for c in step.scan.loops if c.match_session != self.robot and c.verified]
        if not loops or step.backend is None or step.backend.pose is None:
            return
        snap = self._output.snapshot
        path = path_lengths(dict(zip(snap.indices.tolist(), snap.poses)))
        q = step.scan.query_index
        pose = tuple(float(v) for v in matrix_to_vector(step.backend.pose))
        for c in loops:
            self._send(LoopMessage(self.robot, q, c.query_stamp_ns, c.match_session,
                                   c.match_index, c.match_stamp_ns, c.pose, c.covariance,
                                   pose, path.get(q, 0.0)))
            self.counts['loops_sent'] += 1
        with self._lock:
            self._link(q, step.backend.pose)
            self._dirty = True

    def _link(self, index: int, sent: FloatArray | None) -> None:
        self._linked[index] = sent
        self._linked.move_to_end(index)
        while len(self._linked) > _MAX_LINKED:
            self._linked.popitem(last=False)

    def _tick(self) -> None:
        """Once a second: send moved linked poses, forget untracked peers, align again."""
        snap = self._output.snapshot
        own = dict(zip(snap.indices.tolist(), snap.poses))
        path = path_lengths(own)
        with self._lock:
            moved = [i for i, sent in self._linked.items() if i in own and (
                sent is None or float(np.linalg.norm(own[i][:3, 3] - sent[:3, 3])) > _MOVED_M)]
            for i in moved:
                self._linked[i] = own[i]
            tracked = set(self._guard.robots())
            gone = [p for p in self._poses if p not in tracked]
            for p in gone:
                del self._poses[p]
                self._paths.forget(p)
            dirty, self._dirty = self._dirty or bool(moved), False
            peers = {p: {i: v[0] for i, v in d.items()} for p, d in self._poses.items()}
            paths = {p: {i: v[1] for i, v in d.items()} for p, d in self._poses.items()}
        for p in gone:
            self._shared.forget_peer(p)
        for k in range(0, len(moved), MAX_POSES):
            self._send(PosesMessage(self.robot, tuple(
                (i, tuple(float(v) for v in matrix_to_vector(own[i])), path.get(i, 0.0))
                for i in moved[k:k + MAX_POSES])))
            self.counts['poses_sent'] += len(moved[k:k + MAX_POSES])
        if dirty:
            for event in self._shared.align(peers, paths):
                self._node.get_logger().info(f'fleet: {event.message}')

    def _broadcast(self) -> None:
        from tf2_msgs.msg import TFMessage

        now = int(self._node.get_clock().now().nanoseconds)
        out = TFMessage()
        for st in self._shared.alignments():
            if st.aligned and st.transform is not None:
                out.transforms += transform_msg(st.transform, now, self._map_frame,
                                                peer_frame(self._map_frame, st.peer)).transforms
        if out.transforms and self._tf is not None:
            self._tf.publish(out)

    # -- in ----------------------------------------------------------------------------------

    def _on_message(self, msg: UInt8MultiArray) -> None:
        data = msg.data
        if len(data) > MAX_ALIGN_BYTES + _ENVELOPE:
            self.counts['refused_oversized'] += 1
            return
        try:
            sender, inner = self._guard.open(ALIGN_TOPIC, bytes(data))
            if sender == self.robot:
                return
            m = decode_align(inner)
            robot = m.requester if isinstance(m, PathRequest) else m.robot
            if robot == self.robot:
                return
            if sender is not None and sender != robot:
                raise Refused('sender_mismatch', f'robot {sender} sent for robot {robot}')
            self._guard.admit(robot)
            if not self._guard.allow_descriptor(robot):  # the robot's descriptor budget
                raise Refused('rate_limited', f'robot {robot} sends faster than its budget')
        except Refused as r:
            self.counts[f'refused_{r.kind}'] += 1
            return
        except PeerMessageError:
            self.counts['refused_malformed'] += 1
            return
        if isinstance(m, LoopMessage):
            self._on_loop(m)
        elif isinstance(m, PosesMessage):
            self._on_poses(m)
        elif m.owner == self.robot:
            self._paths.answer(m)

    def _keep(self, robot: int, index: int, pose: tuple[float, ...], path: float) -> None:
        store = self._poses.setdefault(robot, OrderedDict())
        store[index] = (vector_to_matrix(pose), path)
        store.move_to_end(index)
        while len(store) > _MAX_POSES:
            store.popitem(last=False)

    def _on_loop(self, m: LoopMessage) -> None:
        if m.match_robot != self.robot:
            return  # between two other robots
        loop = LoopCandidate(m.query_index, m.match_index, m.query_stamp_ns, m.match_stamp_ns,
                             m.match_robot, 0.0, 0.0, 0.0, True, m.pose,
                             covariance=m.covariance, reason='verified')
        self.counts['loops_received'] += 1
        if not self._shared.add_peer_loop(loop, m.robot):
            return
        with self._lock:
            self._keep(m.robot, m.query_index, m.query_pose, m.query_path_m)
            if m.match_index not in self._linked:
                self._link(m.match_index, None)  # its pose goes out at the next tick
            self._dirty = True

    def _on_poses(self, m: PosesMessage) -> None:
        self.counts['poses_received'] += len(m.poses)
        if m.whole:
            self._paths.part(m)
            return
        with self._lock:  # a peer sends only the poses of its keyframes loops name
            for index, pose, path in m.poses:
                self._keep(m.robot, index, pose, path)
            self._dirty = True

    # -- state -------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget this robot's keyframes named by loops (``~/reset``)."""
        with self._lock:
            self._linked.clear()

    def values(self) -> dict[str, object]:
        """/diagnostics: ``fleet_aligned`` (peers placed), ``fleet_robot<j>`` per peer (at
        most 16), ``fleet_*`` counters."""
        states = self._shared.alignments()
        out: dict[str, object] = {f'fleet_{k}': v for k, v in sorted(self.counts.items())}
        out['fleet_aligned'] = ','.join(str(s.peer) for s in states if s.aligned) or 'none'
        for st in states[:_LISTED]:
            out[f'fleet_robot{st.peer}'] = (
                f'aligned by {st.inliers} of {st.loops} loops, rival {st.rival}, jumps '
                f'{st.jumps}' if st.aligned else f'unaligned ({st.loops} loops, rival '
                f'{st.rival})')
        if len(states) > _LISTED:
            out['fleet_robots_unlisted'] = len(states) - _LISTED
        return out
