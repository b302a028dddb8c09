"""LoopMarkers: the latched loop edges, built without a node (a list stands for the publisher)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytest.importorskip('visualization_msgs', reason='ROS 2 message packages are not installed')

from builtin_interfaces.msg import Time  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from solid_ros.ros.markers import LoopMarkers  # noqa: E402


def p(*xyz: float) -> np.ndarray:
    return np.array(xyz, dtype=np.float64)


def make(capacity: int, frame: list[str]) -> tuple[LoopMarkers, list[Any]]:
    sent: list[Any] = []
    return LoopMarkers(capacity, sent.append, lambda: frame[0], lambda: Time(sec=7)), sent


def test_one_line_list_of_the_newest_edges_coloured_by_session() -> None:
    frame = ['']
    markers, sent = make(3, frame)
    markers.add([(p(0, 0, 0), p(1, 2, 3), False)])
    (m,) = sent[-1].markers
    assert (m.ns, m.id, m.type, m.action) == ('loop_edges', 0, Marker.LINE_LIST, Marker.ADD)
    assert m.header.frame_id == 'map'  # no odometry frame yet
    assert m.header.stamp.sec == 7 and m.pose.orientation.w == 1.0 and m.scale.x == 0.1
    assert [(q.x, q.y, q.z) for q in m.points] == [(0, 0, 0), (1, 2, 3)]
    frame[0] = 'odom'
    markers.add([(p(1, 0, 0), p(5, 5, 5), True), (p(2, 0, 0), p(6, 6, 6), False)])
    markers.add([(p(3, 0, 0), p(7, 7, 7), True)])
    (m,) = sent[-1].markers
    assert len(sent) == 3 and len(markers) == 3 and m.header.frame_id == 'odom'
    # The oldest edge went; the whole newest three are republished each time.
    assert [q.x for q in m.points] == [1, 5, 2, 6, 3, 7]
    blue = [c.b == 1.0 and c.r < 0.5 for c in m.colors]
    assert blue == [True, True, False, False, True, True]
    assert all(c.a == 1.0 for c in m.colors) and len(m.colors) == len(m.points)


def test_nothing_new_publishes_nothing() -> None:
    markers, sent = make(10, ['odom'])
    markers.add([])
    assert sent == [] and len(markers) == 0


def test_clear_replaces_the_latched_edges_with_a_deleteall() -> None:
    markers, sent = make(10, ['odom'])
    markers.add([(p(0, 0, 0), p(1, 1, 1), False)])
    markers.clear()
    (m,) = sent[-1].markers
    assert (m.ns, m.action, m.header.frame_id) == ('loop_edges', Marker.DELETEALL, 'odom')
    assert len(markers) == 0
    markers.add([(p(2, 2, 2), p(3, 3, 3), False)])
    assert [q.x for q in sent[-1].markers[0].points] == [2, 3]
