"""Multi-robot exchange over DDS: robots share keyframe descriptors and fetch clouds on demand.

Topics (absolute, shared by every robot of one ROS domain; remappable), all
``std_msgs/UInt8MultiArray`` carrying the packed messages of :mod:`solid_ros.formats.peers`:

- ``/solid/descriptors``: every stored keyframe's descriptor (440 bytes for 40 x 60 bins).
  Reliable, volatile, history 100.
- ``/solid/cloud_requests``: a robot asks a keyframe's owner for its cloud, or (at start) asks
  every peer for its stored descriptors (the catch-up, at most ``peer_catchup`` each).
  Reliable, history 100.
- ``/solid/clouds``: the owner's reply (the keyframe cloud, ~12 bytes a point, or "no longer
  stored"). Reliable, history 10. Sent from a participant of its own
  (:mod:`solid_ros.ros.bulk_participant`, node ``<name>_bulk``), as the back end's map is.

QoS for a lossy wireless link: reliable delivery with bounded histories retransmits what was
lost without letting a slow link grow memory; volatile durability plus the explicit catch-up
(instead of transient local) means a robot that joins late gets each peer's stored
descriptors on request, not a replay of every sample. The request goes out whenever discovery
matches more robots (a request sent before they match would be lost); a robot answers one
requester at most every 2 s, and repeats are dropped on receipt.

Trust and bounds (:mod:`solid_ros.ros.peer_guard`): with a fleet key every message is sealed
with an HMAC tag and refused without a valid one, played again, or from a robot not on the
allowlist; without a key (a trusted domain) nothing is authenticated. Either way every message
is size-checked before it is decoded, robots are tracked up to ``peer_max_robots`` and each
one's descriptors and requests are rate-limited; a message refused for any of these is counted
(``peer_<why>``) and logged at most every ``_WARN_SEC`` per kind.

Robustness: a message that does not decode, comes from this robot's id, repeats a keyframe
already stored or carries other descriptor settings (its fingerprint) is counted and never
stored. Cloud replies are matched to a pending request by id, owner, index and stamp
(:mod:`solid_ros.ros.peer_fetch`). A cloud that does not come within ``peer_timeout_sec`` (the
peer left, the link dropped it) or that the owner no longer stores leaves the candidate
unverified: it is dropped and counted, never published; a peer that keeps timing out is
skipped for a back-off period.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt8MultiArray

from solid_ros.core.candidates.proposal import Proposal
from solid_ros.core.config import NodeConfig
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.reasons import Reason
from solid_ros.formats.peers import (
    MAX_DESCRIPTOR_BYTES,
    TAG_BYTES,
    CatchUpRequest,
    CloudReply,
    CloudRequest,
    DescriptorMessage,
    Message,
    PeerMessageError,
    decode,
    encode,
    reply_bytes,
    reply_requester,
)
from solid_ros.ros.bulk_participant import BulkParticipant
from solid_ros.ros.memory import LARGE_BYTES, Renewal
from solid_ros.ros.peer_fetch import CloudFetches, Pending
from solid_ros.ros.peer_guard import PeerGuard, Refused, parse_allowlist

__all__ = ['DESCRIPTOR_TOPIC', 'PeerLink', 'REPLY_TOPIC', 'REQUEST_TOPIC', 'can_renew']

DESCRIPTOR_TOPIC = '/solid/descriptors'
REQUEST_TOPIC = '/solid/cloud_requests'
REPLY_TOPIC = '/solid/clouds'
_WARN_SEC = 10.0
_DISCOVERY_SEC = 0.5  # how often the catch-up checks for newly matched robots
_REQUEST_BYTES = 256  # a request is 44 bytes, 100 in an envelope
_ENVELOPE = 64  # envelope header and tag, rounded up
_LISTED_ROBOTS = 16  # robots named on /diagnostics (the rest are counted)

KeyframeRow = tuple[int, int, npt.NDArray[np.float64], npt.NDArray[np.float64],
                    npt.NDArray[np.float64] | None]


def can_renew(node: Node) -> bool:
    """Whether ``node``'s subscriptions can be re-created from its own callbacks: only under a
    single-threaded executor (see :mod:`solid_ros.ros.memory`)."""
    return isinstance(node.executor, SingleThreadedExecutor)


class PeerLink:
    """The peer exchange of one node.

    Args:
        node: the node that owns the publishers and subscriptions.
        robot: this robot's id (its ``session_id``).
        fingerprint: its descriptor settings fingerprint.
        cfg: the node settings (``peer_*``).
        key: the fleet key (None: messages are neither sealed nor authenticated).
        add_keyframe: stores a peer's keyframe (takes the detector's lock); returns False for
            one already stored; raises SolidError.
        own_cloud: this robot's stored cloud of a keyframe index and stamp, or None.
        own_keyframes: this robot's newest stored keyframes (for a catch-up).
        note_size: told the size of every message received (the node trims the heap after
            huge ones).
    """

    def __init__(self, node: Node, robot: int, fingerprint: str, cfg: NodeConfig,
                 key: bytes | None, add_keyframe: Callable[[DescriptorMessage], bool],
                 own_cloud: Callable[[int, int], KeyframeCloud | None],
                 own_keyframes: Callable[[int], list[KeyframeRow]],
                 note_size: Callable[[int], None] | None = None) -> None:
        self.node = node
        self.robot = int(robot)
        self.fingerprint = fingerprint
        self.catchup = int(cfg.peer_catchup)
        self.max_cloud_points = int(cfg.peer_max_cloud_points)
        self._add = add_keyframe
        self._own_cloud = own_cloud
        self._own_keyframes = own_keyframes
        self._note_size = note_size
        self.counts: Counter[str] = Counter()
        self._guard = PeerGuard(
            self.robot, key, allow=parse_allowlist(cfg.peer_allowlist),
            max_robots=cfg.peer_max_robots, window_sec=cfg.peer_replay_window_sec,
            descriptor_rate=cfg.peer_descriptor_rate,
            descriptor_burst=float(self.catchup + 100), request_rate=cfg.peer_request_rate)
        self._fetches = CloudFetches(cfg.peer_timeout_sec, cfg.peer_backoff_sec, self._count)
        self._warned: dict[str, float] = {}
        self._send_locks = {t: threading.Lock()
                            for t in (DESCRIPTOR_TOPIC, REQUEST_TOPIC, REPLY_TOPIC)}
        self._matched = 1  # our own subscription to the request topic
        reliable = ReliabilityPolicy.RELIABLE

        def qos(depth: int) -> QoSProfile:
            return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                              reliability=reliable)

        self._pub_desc = node.create_publisher(UInt8MultiArray, DESCRIPTOR_TOPIC, qos(100))
        self._pub_req = node.create_publisher(UInt8MultiArray, REQUEST_TOPIC, qos(100))
        # Cloud replies (up to MBs) from a participant of their own: from the node's they
        # would overrun its shared-memory segment and take its /tf and loops with them.
        self._bulk = BulkParticipant(node)
        self._pub_reply = self._bulk.create_publisher(UInt8MultiArray, REPLY_TOPIC, qos(10))

        def subscription(topic: str, handle: Callable[[Any], None], depth: int) -> Renewal:
            return Renewal(lambda: node.create_subscription(UInt8MultiArray, topic, handle,
                                                            qos(depth)),
                           node.destroy_subscription, safe=lambda: can_renew(node))

        # Each re-created after an oversized message (frees what its DDS reader keeps).
        self._subs = {DESCRIPTOR_TOPIC: subscription(DESCRIPTOR_TOPIC, self._on_descriptor, 1000),
                      REQUEST_TOPIC: subscription(REQUEST_TOPIC, self._on_request, 100),
                      REPLY_TOPIC: subscription(REPLY_TOPIC, self._on_reply, 10)}

    @property
    def robots(self) -> PeerGuard:
        """The robots heard from recently (``robot in link.robots``; bounded)."""
        return self._guard

    @property
    def authenticated(self) -> bool:
        """Whether messages are sealed and checked with a fleet key."""
        return self._guard.key is not None

    @property
    def timeout_sec(self) -> float:
        """How long a cloud request may wait for its reply."""
        return self._fetches.timeout_sec

    @timeout_sec.setter
    def timeout_sec(self, value: float) -> None:
        self._fetches.timeout_sec = float(value)

    def _count(self, kind: str, n: int = 1) -> None:
        self.counts[kind] += n

    # -- sending -----------------------------------------------------------------------------

    def start(self) -> None:
        """Ask the robots already running for their stored descriptors (the catch-up), each
        time discovery finds more of them (a request sent before they match is lost)."""
        if self.catchup:
            self.node.create_timer(_DISCOVERY_SEC, self._catch_up)
        self.node.create_timer(1.0, self._renew)

    def _renew(self) -> None:
        """Once a second: re-create subscriptions that got an oversized message, and forget
        the liveness of robots no longer tracked."""
        self._fetches.forget(set(self._guard.robots()))
        for topic, sub in self._subs.items():
            if sub.maybe_renew():
                if self._note_size is not None:
                    self._note_size(LARGE_BYTES)
                self.node.get_logger().info(f're-subscribed to {topic} to free the buffers of '
                                            'an oversized message')

    def _catch_up(self) -> None:
        matched = self._pub_req.get_subscription_count()
        if matched > self._matched:
            self._send(self._pub_req, REQUEST_TOPIC, CatchUpRequest(self.robot, self.catchup))
            self.counts['catchup_requests_sent'] += 1
        self._matched = matched

    def share(self, proposal: Proposal) -> None:
        """Publish the descriptor of a keyframe this robot just stored."""
        if proposal.r_solid is None:
            return
        pose = None if proposal.pose is None else tuple(float(v) for v in proposal.pose)
        self._send(self._pub_desc, DESCRIPTOR_TOPIC, DescriptorMessage(
            self.robot, proposal.query_index, proposal.stamp_ns, self.fingerprint,
            _unit(proposal.r_solid), _unit(proposal.heading), pose))
        self.counts['descriptors_sent'] += 1

    def request(self, robot: int, index: int, stamp_ns: int) -> Pending | Reason:
        """Ask ``robot`` for the cloud of its keyframe ``index`` now, without waiting; hand
        the result to :meth:`collect` (no request when the robot left or is backed off)."""
        p = self._fetches.start(int(robot), int(index), int(stamp_ns))
        if not isinstance(p, str):
            self._send_request(p)
        return p

    def _send_request(self, p: Pending) -> None:
        self._send(self._pub_req, REQUEST_TOPIC,
                   CloudRequest(self.robot, p.robot, p.index, p.request_id, p.stamp_ns))

    def collect(self, pending: Pending | Reason) -> KeyframeCloud | Reason:
        """Wait (no lock held) until the reply to :meth:`request` or its deadline.

        Returns:
            The cloud, or the reason there is none: ``'peer_timeout'`` (no answer in time:
            the robot left or the link lost it), ``'peer_gone'`` (backed off after time-outs in
            a row: not asked) or
            ``'peer_evicted'`` (it no longer has it).
        """
        return self._fetches.finish(pending, self._send_request)

    def fetch(self, robot: int, index: int, stamp_ns: int) -> KeyframeCloud | Reason:
        """:meth:`request` and :meth:`collect` in one call (blocks up to the timeout)."""
        return self.collect(self.request(robot, index, stamp_ns))

    def _send(self, pub: Any, topic: str, msg: Message) -> None:
        out = UInt8MultiArray()
        with self._send_locks[topic]:  # sealed stamps must go out in order
            out.data = self._guard.seal(topic, encode(msg))
            pub.publish(out)

    # -- receiving ---------------------------------------------------------------------------

    def _warn(self, kind: str, text: str) -> None:
        """Log ``text`` unless a warning of ``kind`` was logged less than _WARN_SEC ago."""
        now = time.monotonic()
        if now - self._warned.get(kind, -_WARN_SEC) >= _WARN_SEC:
            self._warned[kind] = now
            self.node.get_logger().warning(
                f'peer message refused ({kind}, {self.counts[kind]} so far): {text}')

    def _receive(self, topic: str, msg: UInt8MultiArray, max_bytes: int) -> Message | None:
        """Size check, authentication, decoding, identity and admission of one message."""
        data = msg.data
        if self._note_size is not None:
            self._note_size(len(data))
        if len(data) > max_bytes + _ENVELOPE:
            self.counts['oversized'] += 1
            self._subs[topic].request()
            self._warn('oversized', f'{len(data)} bytes on {topic} (at most {max_bytes})')
            return None
        raw = bytes(data)
        try:
            sender, inner = self._guard.open(topic, raw)
            if sender == self.robot:
                return None  # our own message, back on our own subscription
            m = decode(inner, self.max_cloud_points)
            robot = _robot_of(m)
            if robot == self.robot:
                return None  # this robot's id: our own message, or a forgery
            if sender is not None and sender != robot:
                raise Refused('sender_mismatch', f'robot {sender} sent a message of robot '
                                                 f'{robot}')
            self._guard.admit(robot)
        except Refused as r:
            self.counts[r.kind] += 1
            self._warn(r.kind, f'{r} (on {topic})')
            return None
        except PeerMessageError as err:
            self.counts['malformed'] += 1
            self._warn('malformed', f'{err} (on {topic})')
            return None
        return m

    def _on_descriptor(self, msg: UInt8MultiArray) -> None:
        d = self._receive(DESCRIPTOR_TOPIC, msg, MAX_DESCRIPTOR_BYTES)
        if d is None:
            return
        if not isinstance(d, DescriptorMessage):
            self.counts['malformed'] += 1
            return
        if not self._guard.allow_descriptor(d.robot):
            self.counts['rate_limited'] += 1
            self._warn('rate_limited', f'robot {d.robot} sends descriptors faster than '
                                       'peer_descriptor_rate')
            return
        if d.fingerprint != self.fingerprint:
            self.counts['descriptors_refused'] += 1
            self._warn('descriptors_refused', f'robot {d.robot} describes scans with other '
                                              f'settings (fingerprint {d.fingerprint}, ours '
                                              f'{self.fingerprint}): its keyframes are not '
                                              'stored')
            return
        try:
            stored = self._add(d)
        except Exception as err:  # a bad peer keyframe must not stop the node
            self.counts['malformed'] += 1
            self._warn('malformed', f'peer keyframe of robot {d.robot} refused: {err}')
            return
        self.counts['descriptors_stored' if stored else 'descriptors_repeated'] += 1

    def _on_request(self, msg: UInt8MultiArray) -> None:
        req = self._receive(REQUEST_TOPIC, msg, _REQUEST_BYTES)
        if isinstance(req, CloudRequest):
            if req.owner != self.robot:
                return
            if not self._guard.allow_request(req.requester):
                self.counts['rate_limited'] += 1
                self._warn('rate_limited', f'robot {req.requester} asks for clouds faster '
                                           'than peer_request_rate')
                return
            cloud = self._own_cloud(req.index, req.stamp_ns)
            self._send(self._pub_reply, REPLY_TOPIC, CloudReply(
                self.robot, req.requester, req.index, req.request_id, req.stamp_ns, cloud))
            self.counts['clouds_served' if cloud is not None else 'clouds_missing'] += 1
        elif isinstance(req, CatchUpRequest):
            if not self._guard.allow_catchup(req.requester):
                self.counts['catchups_refused'] += 1
                return
            rows = self._own_keyframes(min(req.limit, self.catchup))
            for index, stamp, r, a, pose in rows:
                self._send(self._pub_desc, DESCRIPTOR_TOPIC, DescriptorMessage(
                    self.robot, index, stamp, self.fingerprint, r.astype(np.float32),
                    a.astype(np.float32), None if pose is None else tuple(pose.tolist())))
            self.counts['catchup_descriptors_sent'] += len(rows)
        elif req is not None:
            self.counts['malformed'] += 1

    def _on_reply(self, msg: UInt8MultiArray) -> None:
        if reply_requester(bytes(msg.data[:TAG_BYTES + 64])) not in (None, self.robot):
            if self._note_size is not None:
                self._note_size(len(msg.data))
            if len(msg.data) > reply_bytes(self.max_cloud_points) + _ENVELOPE:
                self._subs[REPLY_TOPIC].request()
            return  # a reply to another robot: not even authenticated
        rep = self._receive(REPLY_TOPIC, msg, reply_bytes(self.max_cloud_points))
        if not isinstance(rep, CloudReply):
            if rep is not None:
                self.counts['malformed'] += 1
            return
        if rep.requester == self.robot:
            self._fetches.deliver(rep)

    def close(self) -> None:
        """Close the participant of the cloud replies (idempotent)."""
        self._bulk.close()

    def diagnostics(self) -> dict[str, object]:
        """Counters and peers for /diagnostics (keys prefixed ``peer_``; bounded size)."""
        now = time.monotonic()
        out: dict[str, object] = {f'peer_{k}': v for k, v in sorted(self.counts.items())}
        robots = sorted(self._guard.robots().items(), key=lambda rt: -rt[1])
        listed = ','.join(f'{r}({now - t:.0f}s)' for r, t in sorted(robots[:_LISTED_ROBOTS]))
        more = len(robots) - _LISTED_ROBOTS
        out['peer_robots'] = (listed + (f' (+{more} more)' if more > 0 else '')) or 'none'
        out['peer_robots_dropped'] = self._guard.dropped_robots
        out['peer_authenticated'] = 'yes' if self.authenticated else 'no'
        out['peer_requests_pending'] = self._fetches.pending
        return out


def _robot_of(m: Message) -> int:
    """The robot a message speaks for: descriptor's robot, requester or reply owner."""
    if isinstance(m, CloudReply):
        return m.owner
    if isinstance(m, DescriptorMessage):
        return m.robot
    return m.requester


def _unit(v: npt.ArrayLike) -> npt.NDArray[np.float32]:
    arr = np.asarray(v, dtype=np.float64).ravel()
    n = float(np.linalg.norm(arr))
    return (arr / n if n > 0 else arr).astype(np.float32)
