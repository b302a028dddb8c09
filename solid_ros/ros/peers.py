"""Multi-robot exchange over DDS: robots share keyframe descriptors and fetch clouds on demand.

Topics (absolute, shared by every robot of one ROS domain; remappable), all
``std_msgs/UInt8MultiArray`` carrying the packed messages of :mod:`solid_ros.formats.peers`:

- ``/solid/descriptors``: every stored keyframe's descriptor (440 bytes for 40 x 60 bins).
  Reliable, volatile, history 100.
- ``/solid/cloud_requests``: a robot asks a keyframe's owner for its cloud, or (at start) asks
  every peer for its stored descriptors (the catch-up, at most ``peer_catchup`` each).
  Reliable, history 100.
- ``/solid/clouds``: the owner's reply (the keyframe cloud, ~12 bytes a point, or "no longer
  stored"). Reliable, history 10.

QoS for a lossy wireless link: reliable delivery with bounded histories retransmits what was
lost without letting a slow link grow memory; volatile durability plus the explicit catch-up
(instead of transient local) means a robot that joins late gets each peer's stored
descriptors on request, not a replay of every sample. The request goes out whenever discovery
matches more robots (a request sent before they match would be lost); a robot answers one
requester at most every 2 s, and repeats are dropped on receipt.

Robustness: a message that does not decode, comes from this robot, repeats a keyframe
already stored or carries other descriptor settings (its fingerprint; one warning per robot)
is counted and never stored. A cloud that does not come within ``peer_timeout_sec`` (the peer
left, the link dropped it) or that the owner no longer stores leaves the candidate unverified:
it is dropped and counted, never published.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt8MultiArray

from solid_ros.core.detector import Proposal
from solid_ros.core.keyframes import KeyframeCloud
from solid_ros.formats.peers import (
    CatchUpRequest,
    CloudReply,
    CloudRequest,
    DescriptorMessage,
    PeerMessageError,
    decode,
    encode,
)

__all__ = ['DESCRIPTOR_TOPIC', 'PeerLink', 'REPLY_TOPIC', 'REQUEST_TOPIC']

DESCRIPTOR_TOPIC = '/solid/descriptors'
REQUEST_TOPIC = '/solid/cloud_requests'
REPLY_TOPIC = '/solid/clouds'
_SEEN_LIMIT = 1_000_000  # (robot, index) pairs remembered to drop repeats
_WARN_SEC = 10.0
_DISCOVERY_SEC = 0.5  # how often the catch-up checks for newly matched robots
_CATCHUP_GAP_SEC = 2.0  # one catch-up answer per requester within this time

KeyframeRow = tuple[int, int, npt.NDArray[np.float64], npt.NDArray[np.float64],
                    npt.NDArray[np.float64] | None]


class PeerLink:
    """The peer exchange of one node.

    Args:
        node: the node that owns the publishers and subscriptions.
        robot: this robot's id (its ``session_id``).
        fingerprint: its descriptor settings fingerprint.
        timeout_sec: how long :meth:`fetch` waits for a cloud.
        catchup: most descriptors sent to (and asked of) a late joiner.
        add_keyframe: stores a peer's keyframe (takes the detector's lock); raises SolidError.
        own_cloud: this robot's stored cloud of a keyframe index, or None.
        own_keyframes: this robot's newest stored keyframes (for a catch-up).
    """

    def __init__(self, node: Node, robot: int, fingerprint: str, timeout_sec: float,
                 catchup: int, add_keyframe: Callable[[DescriptorMessage], None],
                 own_cloud: Callable[[int], KeyframeCloud | None],
                 own_keyframes: Callable[[int], list[KeyframeRow]]) -> None:
        self.node = node
        self.robot = int(robot)
        self.fingerprint = fingerprint
        self.timeout_sec = float(timeout_sec)
        self.catchup = int(catchup)
        self._add = add_keyframe
        self._own_cloud = own_cloud
        self._own_keyframes = own_keyframes
        self.counts: Counter[str] = Counter()
        self.robots: dict[int, float] = {}  # peer robot id -> monotonic time of last message
        self._refused: set[int] = set()
        self._seen: OrderedDict[tuple[int, int], None] = OrderedDict()
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._pending: dict[int, tuple[threading.Event, list[CloudReply]]] = {}
        self._matched = 1  # our own subscription to the request topic
        self._answered: dict[int, float] = {}  # requester -> monotonic time of last catch-up
        self._silent: dict[int, float] = {}  # robot -> time its last cloud request timed out
        reliable = ReliabilityPolicy.RELIABLE
        self._pub_desc = node.create_publisher(
            UInt8MultiArray, DESCRIPTOR_TOPIC,
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=reliable))
        self._pub_req = node.create_publisher(
            UInt8MultiArray, REQUEST_TOPIC,
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=reliable))
        self._pub_reply = node.create_publisher(
            UInt8MultiArray, REPLY_TOPIC,
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=reliable))
        node.create_subscription(
            UInt8MultiArray, DESCRIPTOR_TOPIC, self._on_descriptor,
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=reliable))
        node.create_subscription(
            UInt8MultiArray, REQUEST_TOPIC, self._on_request,
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=reliable))
        node.create_subscription(
            UInt8MultiArray, REPLY_TOPIC, self._on_reply,
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=reliable))

    # -- sending -----------------------------------------------------------------------------

    def start(self) -> None:
        """Ask the robots already running for their stored descriptors (the catch-up), each
        time discovery finds more of them (a request sent before they match is lost)."""
        if self.catchup:
            self.node.create_timer(_DISCOVERY_SEC, self._catch_up)

    def _catch_up(self) -> None:
        matched = self._pub_req.get_subscription_count()
        if matched > self._matched:
            self._send(self._pub_req, CatchUpRequest(self.robot, self.catchup))
            self.counts['catchup_requests_sent'] += 1
        self._matched = matched

    def share(self, proposal: Proposal) -> None:
        """Publish the descriptor of a keyframe this robot just stored."""
        if proposal.r_solid is None:
            return
        pose = None if proposal.pose is None else tuple(float(v) for v in proposal.pose)
        self._send(self._pub_desc, DescriptorMessage(
            self.robot, proposal.query_index, proposal.stamp_ns, self.fingerprint,
            _unit(proposal.r_solid), _unit(proposal.heading), pose))
        self.counts['descriptors_sent'] += 1

    def fetch(self, robot: int, index: int, stamp_ns: int) -> KeyframeCloud | str:
        """Ask ``robot`` for the cloud of its keyframe ``index``; wait up to the timeout.

        Returns:
            The cloud, or the reason there is none: ``'peer_timeout'`` (no answer in time:
            the robot left or the link lost it), ``'peer_gone'`` (it timed out before and has
            not been heard of since: not asked again, so a departed robot costs one timeout)
            or ``'peer_evicted'`` (it no longer has it).
        """
        silent_since = self._silent.get(int(robot))
        if silent_since is not None and self.robots.get(int(robot), -math.inf) <= silent_since:
            self.counts['clouds_peer_gone'] += 1  # no word from it since it last timed out
            return 'peer_gone'
        rid = next(self._ids)
        done = threading.Event()
        box: list[CloudReply] = []
        with self._lock:
            self._pending[rid] = (done, box)
        self.counts['clouds_requested'] += 1
        t0 = time.monotonic()
        self._send(self._pub_req, CloudRequest(self.robot, int(robot), int(index), rid))
        try:
            if not done.wait(self.timeout_sec):
                self.counts['clouds_timed_out'] += 1
                self._silent[int(robot)] = time.monotonic()
                return 'peer_timeout'
        finally:
            with self._lock:
                self._pending.pop(rid, None)
        reply = box[0]
        if reply.cloud is None:
            self.counts['clouds_evicted'] += 1
            return 'peer_evicted'
        self.counts['clouds_received'] += 1
        self.counts['cloud_bytes_received'] += 12 * len(reply.cloud.points) + 36
        self.counts['cloud_wait_ms_total'] += int((time.monotonic() - t0) * 1e3)
        return reply.cloud

    def _send(self, pub: Any, msg: Any) -> None:
        raw = encode(msg)
        out = UInt8MultiArray()
        out.data = raw
        pub.publish(out)

    # -- receiving ---------------------------------------------------------------------------

    def _decode(self, msg: UInt8MultiArray) -> Any:
        try:
            return decode(bytes(msg.data))
        except PeerMessageError as err:
            self.counts['malformed'] += 1
            self.node.get_logger().warning(f'peer message ignored: {err}',
                                           throttle_duration_sec=_WARN_SEC)
            return None

    def _on_descriptor(self, msg: UInt8MultiArray) -> None:
        d = self._decode(msg)
        if d is None:
            return
        if not isinstance(d, DescriptorMessage):
            self.counts['malformed'] += 1
            return
        if d.robot == self.robot:
            return
        self.robots[d.robot] = time.monotonic()
        if d.fingerprint != self.fingerprint:
            self.counts['descriptors_refused'] += 1
            if d.robot not in self._refused:
                self._refused.add(d.robot)
                self.node.get_logger().warning(
                    f'robot {d.robot} describes scans with other settings (fingerprint '
                    f'{d.fingerprint}, ours {self.fingerprint}): its keyframes are not stored')
            return
        key = (d.robot, d.index)
        if key in self._seen:
            self.counts['descriptors_repeated'] += 1
            return
        try:
            self._add(d)
        except Exception as err:  # a bad peer keyframe must not stop the node
            self.counts['malformed'] += 1
            self.node.get_logger().warning(f'peer keyframe of robot {d.robot} refused: {err}',
                                           throttle_duration_sec=_WARN_SEC)
            return
        self._seen[key] = None
        if len(self._seen) > _SEEN_LIMIT:
            self._seen.popitem(last=False)
        self.counts['descriptors_stored'] += 1

    def _on_request(self, msg: UInt8MultiArray) -> None:
        req = self._decode(msg)
        if isinstance(req, (CloudRequest, CatchUpRequest)) and req.requester != self.robot:
            self.robots[req.requester] = time.monotonic()
        if isinstance(req, CloudRequest):
            if req.owner != self.robot:
                return
            cloud = self._own_cloud(req.index)
            self._send(self._pub_reply, CloudReply(self.robot, req.requester, req.index,
                                                   req.request_id, cloud))
            self.counts['clouds_served' if cloud is not None else 'clouds_missing'] += 1
        elif isinstance(req, CatchUpRequest):
            now = time.monotonic()
            if req.requester == self.robot or now - self._answered.get(
                    req.requester, -math.inf) < _CATCHUP_GAP_SEC:
                return
            self._answered[req.requester] = now
            rows = self._own_keyframes(min(req.limit, self.catchup))
            for index, stamp, r, a, pose in rows:
                self._send(self._pub_desc, DescriptorMessage(
                    self.robot, index, stamp, self.fingerprint, r.astype(np.float32),
                    a.astype(np.float32), None if pose is None else tuple(pose.tolist())))
            self.counts['catchup_descriptors_sent'] += len(rows)
        elif req is not None:
            self.counts['malformed'] += 1

    def _on_reply(self, msg: UInt8MultiArray) -> None:
        rep = self._decode(msg)
        if not isinstance(rep, CloudReply):
            if rep is not None:
                self.counts['malformed'] += 1
            return
        if rep.requester != self.robot:
            return
        self.robots[rep.owner] = time.monotonic()
        with self._lock:
            waiting = self._pending.get(rep.request_id)
        if waiting is None:
            self.counts['late_replies'] += 1
            return
        done, box = waiting
        box.append(rep)
        done.set()

    def diagnostics(self) -> dict[str, object]:
        """Counters and peers for /diagnostics (keys prefixed ``peer_``)."""
        now = time.monotonic()
        out: dict[str, object] = {f'peer_{k}': v for k, v in sorted(self.counts.items())}
        out['peer_robots'] = ','.join(
            f'{r}({now - t:.0f}s)' for r, t in sorted(self.robots.items())) or 'none'
        return out


def _unit(v: npt.ArrayLike) -> npt.NDArray[np.float32]:
    arr = np.asarray(v, dtype=np.float64).ravel()
    n = float(np.linalg.norm(arr))
    return (arr / n if n > 0 else arr).astype(np.float32)
