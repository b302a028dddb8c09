"""Peers' whole corrected paths in this robot's map, on request (part of
:mod:`solid_ros.ros.peer_align`).

Calling ``~/peer_paths`` (std_srvs/Trigger) asks every aligned peer for its whole path; each
answers with its graph's keyframe poses in parts of at most ``MAX_POSES`` (36 bytes a pose)
and the path goes out, moved into this robot's map by the peer's alignment, on
``~/peer_paths/robot<j>`` (nav_msgs/Path in ``map_frame``, latched; the poses carry the
time the path arrived: the messages hold keyframe indices, not stamps). A robot answers a
requester at most once per ``_ANSWER_SEC``, and a path of more than ``_MAX_PATH`` poses is
refused (counted) before its parts are held, so neither side's memory nor its uplink grows
with requests.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from solid_ros.core.backend.alignment import path_lengths
from solid_ros.core.geometry import matrix_to_vector, vector_to_matrix
from solid_ros.formats.fleet_msgs import MAX_POSES, AlignMessage, PathRequest, PosesMessage
from solid_ros.ros.graph_msgs import path_msg
from solid_ros.ros.graph_output import GraphOutput
from solid_ros.ros.shared_detector import SharedDetector

__all__ = ['PeerPaths']

_MAX_PATH = 100_000  # poses of a peer's whole path held at once
_ANSWER_SEC = 2.0  # a requester gets this robot's path at most this often
_LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
Row = tuple[int, tuple[float, ...], float]


class PeerPaths:
    """Path requests and answers of one node (module docstring).

    Args:
        node: the node (service, publishers, clock).
        robot: this robot's id.
        shared: the loop closure (the peers' alignments).
        output: the pose graph's snapshots (this robot's path).
        map_frame: this robot's map frame.
        send: seals and publishes one alignment message.
        counts: the exchange's counters (``paths_*``).
    """

    def __init__(self, node: Node, robot: int, shared: SharedDetector, output: GraphOutput,
                 map_frame: str, send: Callable[[AlignMessage], None],
                 counts: Counter[str]) -> None:
        self._node, self.robot, self._shared, self._output = node, int(robot), shared, output
        self._map_frame, self._send, self.counts = map_frame, send, counts
        self._lock = threading.Lock()
        self._parts: dict[int, dict[int, tuple[Row, ...]]] = {}
        self._pubs: dict[int, Any] = {}
        self._answered: dict[int, float] = {}
        node.create_service(Trigger, '~/peer_paths', self._on_request_service)

    def _on_request_service(self, request: Trigger.Request,
                            response: Trigger.Response) -> Any:
        aligned = [st.peer for st in self._shared.alignments() if st.aligned]
        for peer in aligned:
            self._send(PathRequest(self.robot, peer))
        response.success = bool(aligned)
        response.message = (f'asked robots {", ".join(map(str, aligned))} for their paths: on '
                            '~/peer_paths/robot<id> as they come' if aligned
                            else 'no peer is aligned yet')
        return response

    def answer(self, request: PathRequest) -> None:
        """A peer asked for this robot's path: send it, unless sent to it just now."""
        now = time.monotonic()
        with self._lock:
            if now - self._answered.get(request.requester, -math.inf) < _ANSWER_SEC:
                self.counts['paths_refused_rate'] += 1
                return
            self._answered[request.requester] = now
            for r in [r for r, t in self._answered.items() if now - t > _ANSWER_SEC]:
                del self._answered[r]  # bounded by the requesters of the last seconds
        snap = self._output.snapshot
        own = dict(zip(snap.indices.tolist(), snap.poses))
        path = path_lengths(own)
        rows = [(i, tuple(float(v) for v in matrix_to_vector(T)), path[i])
                for i, T in own.items()][-_MAX_PATH:]
        parts = max(1, -(-len(rows) // MAX_POSES))
        for k in range(parts):
            self._send(PosesMessage(self.robot, tuple(rows[k * MAX_POSES:(k + 1) * MAX_POSES]),
                                    True, k, parts))
        self.counts['paths_sent'] += 1

    def part(self, m: PosesMessage) -> None:
        """One part of a peer's path: once all are in, publish it in this robot's map."""
        if m.parts * MAX_POSES > _MAX_PATH:
            self.counts['paths_refused_oversized'] += 1
            return
        with self._lock:
            parts = self._parts.setdefault(m.robot, {})
            if m.part == 0:
                parts.clear()
            parts[m.part] = m.poses
            if len(parts) < m.parts:
                return
            rows = [row for k in range(m.parts) for row in parts.get(k, ())]
            del self._parts[m.robot]
        state = next((st for st in self._shared.alignments() if st.peer == m.robot), None)
        if state is None or state.transform is None or not rows:
            return
        poses = state.transform @ np.array([vector_to_matrix(p) for _, p, _ in rows])
        now = int(self._node.get_clock().now().nanoseconds)
        pub = self._pubs.get(m.robot)
        if pub is None:
            pub = self._node.create_publisher(PathMsg, f'~/peer_paths/robot{m.robot}', _LATCHED)
            self._pubs[m.robot] = pub
        pub.publish(path_msg([now] * len(poses), poses, self._map_frame, now))
        self.counts['paths_received'] += 1

    def forget(self, robot: int) -> None:
        """Drop a peer's partial path (it is no longer tracked)."""
        with self._lock:
            self._parts.pop(robot, None)

