"""LoopOutput: a verified keyframe's loops as a candidates message, log lines and edges."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytest.importorskip('std_msgs', reason='ROS 2 message packages are not installed')

from test_stages import LOOP_EVERY_SCAN, Log, scene  # noqa: E402

from solid_ros.core.flow.closure import LoopClosure  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402
from solid_ros.core.odometry.track import OdomSample  # noqa: E402
from solid_ros.formats.candidates import decode_candidates  # noqa: E402
from solid_ros.ros.loop_output import LoopOutput, loop_line, refusal_line  # noqa: E402
from solid_ros.ros.markers import LoopMarkers  # noqa: E402
from solid_ros.ros.shared_detector import SharedDetector  # noqa: E402
from solid_ros.ros.stages import Verified  # noqa: E402
from solid_ros.ros.stats import NodeStats  # noqa: E402

SEC = 1_000_000_000


def at(x: float, stamp: int) -> OdomSample:
    pose = np.eye(4)
    pose[0, 3] = x
    return OdomSample(stamp, pose)


def test_publishes_logs_and_draws_each_loop() -> None:
    shared = SharedDetector(LoopClosure(LoopDetector(LOOP_EVERY_SCAN.replace(verify=False))))
    sent: list[Any] = []
    drawn: list[Any] = []
    markers = LoopMarkers(10, drawn.append, lambda: 'odom', lambda: None)
    stats, log = NodeStats(), Log()
    out = LoopOutput(sent.append, log, stats, shared, markers, session_id=0,
                     peer_robots={7: 0.0})
    pts = scene()
    for i in range(3):
        stamp = (i + 1) * SEC
        proposal = shared.propose(pts, stamp, at(float(i), stamp))
        assert proposal is not None
        result, detector = shared.verify(proposal)
        odom = at(float(i), stamp) if i != 1 else None  # no odometry: no edge
        out.take(Verified(result, odom, proposal, detector))
    assert stats.loops == 2 and stats.inter_robot_loops == 0
    rows = [decode_candidates(m) for m in sent]
    assert [[(r['query_index'], r['match_index']) for r in msg] for msg in rows] == [
        [(1, 0)], [(2, 0)]]
    assert [level for level, _ in log.lines] == ['info', 'info']
    assert log.lines[1][1].startswith('loop: keyframe 2 (3.000000000 s) -> session 0 keyframe 0 '
                                      '(1.000000000 s), descriptor only, yaw ')
    # One edge: keyframe 2 (x = 2) to the stored position of keyframe 0 (x = 0).
    (edges,) = [m.markers[0] for m in drawn]
    assert [(q.x, q.y) for q in edges.points] == [(2.0, 0.0), (0.0, 0.0)]


def test_loop_line_of_a_verified_loop() -> None:
    from solid_ros.core.results import Evidence, LoopCandidate

    c = LoopCandidate(9, 2, 5 * SEC + 7, SEC, 0, 0.1, 0.5, 0.2, verified=True,
                      pose=(1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0), fitness=0.8,
                      evidence=Evidence(rmse=0.05))
    assert loop_line(c) == ('loop: keyframe 9 (5.000000007 s) -> session 0 keyframe 2 '
                            '(1.000000000 s), verified, fitness 0.80, rmse 0.050 m, yaw 28.6 '
                            'deg, t (1.00, 2.00, 3.00) m')


def test_a_refused_candidate_is_logged_with_its_rule_and_reading() -> None:
    from solid_ros.core.results import Evidence, LoopCandidate

    c = LoopCandidate(9, 2, 5 * SEC, SEC, 0, 0.1, 0.5, 0.2, reason='conflict',
                      evidence=Evidence(conflict=0.081), detail='conflict 0.081 > 0.063')
    assert refusal_line(c) == ('candidate: keyframe 9 -> session 0 keyframe 2 (descriptor) '
                               'refused by conflict: conflict 0.081 > 0.063')
