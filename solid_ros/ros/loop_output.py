"""A verified keyframe's loops out of solid_node: one ``~/loop_candidates`` message (see
:mod:`solid_ros.formats.candidates`), one log line per loop and their edges on
``~/loop_markers``. No ROS import beyond the message types: the node passes its publisher's
``publish`` and its logger in.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Container, Sequence
from typing import Any

from std_msgs.msg import Float64MultiArray, MultiArrayDimension  # type: ignore[import-untyped]

from solid_ros.core.results import LoopCandidate
from solid_ros.core.stamps import format_stamp
from solid_ros.formats.candidates import layout_dims, to_rows
from solid_ros.ros.markers import Edge, LoopMarkers
from solid_ros.ros.shared_detector import SharedDetector
from solid_ros.ros.stages import Log, Verified
from solid_ros.ros.stats import NodeStats

__all__ = ['LoopOutput', 'candidates_msg', 'loop_line', 'refusal_line']


class LoopOutput:
    """Publishes, logs and draws each verified keyframe's loops.

    Args:
        publish: sends a Float64MultiArray of candidate rows.
        log: where each loop is logged.
        stats: counts the loops (and those with other robots).
        shared: where the matched scans' positions are stored.
        markers: the loop edges, or None without markers.
        session_id: this run's session (edges to other sessions are drawn blue).
        peer_robots: the other robots heard from (kept current by the peer link).
    """

    def __init__(self, publish: Callable[[Any], None], log: Log, stats: NodeStats,
                 shared: SharedDetector, markers: LoopMarkers | None, session_id: int,
                 peer_robots: Container[int] = ()) -> None:
        self._publish, self._log, self._stats = publish, log, stats
        self._shared, self._markers = shared, markers
        self._session_id, self._peer_robots = session_id, peer_robots

    def take(self, verified: Verified) -> None:
        """Output a keyframe's loops, if it has any; log why each other candidate was refused
        (debug: the rule and the evidence it read)."""
        loops = verified.result.loops
        for c in verified.result.attempts:
            if c.detail:
                self._log.debug(refusal_line(c))
        if not loops:
            return
        self._stats.loops += len(loops)
        self._stats.inter_robot_loops += sum(1 for c in loops
                                             if c.match_session in self._peer_robots)
        self._publish(candidates_msg(loops))
        for c in loops:
            self._log.info(loop_line(c))
        if self._markers is not None and verified.odom is not None:
            self._markers.add(self._edges(verified))

    def _edges(self, verified: Verified) -> list[Edge]:
        """Edges from the keyframe's odometry position to each match whose position is
        stored."""
        assert verified.odom is not None
        here = verified.odom.pose[:3, 3]
        edges = []
        for c in verified.result.loops:
            there = self._shared.match_position(c, verified.detector)
            if there is not None:
                edges.append((here.copy(), there, int(c.match_session) != self._session_id))
        return edges


def candidates_msg(cands: Sequence[LoopCandidate]) -> Float64MultiArray:
    """The ``~/loop_candidates`` message of ``cands``."""
    rows = to_rows(cands)
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=label, size=size, stride=stride)
                      for label, size, stride in layout_dims(len(rows))]
    msg.data = rows.reshape(-1).tolist()
    return msg


def refusal_line(c: LoopCandidate) -> str:
    """The log line of one refused candidate: the rule that refused it and its reading."""
    return (f'candidate: keyframe {c.query_index} -> session {c.match_session} keyframe '
            f'{c.match_index} ({c.source}) refused by {c.reason}: {c.detail}')


def loop_line(c: LoopCandidate) -> str:
    """The log line of one published loop."""
    t = ', '.join(f'{v:.2f}' for v in c.pose[:3])
    state = (f'verified, fitness {c.fitness:.2f}, rmse {c.rmse:.3f} m' if c.verified
             else 'descriptor only')
    return (f'loop: keyframe {c.query_index} ({format_stamp(c.query_stamp_ns)}) -> session '
            f'{c.match_session} keyframe {c.match_index} ({format_stamp(c.match_stamp_ns)}), '
            f'{state}, yaw {math.degrees(c.yaw):.1f} deg, t ({t}) m')
