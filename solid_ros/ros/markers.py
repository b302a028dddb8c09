"""The loop edges of ``~/loop_markers`` (visualization_msgs/MarkerArray, latched).

One LINE_LIST of the newest loops whose two positions are known: the query's from paired
odometry, the match's as stored with its scan in the database (this run, a loaded session or
a peer robot). Loops within this session are red; loops against other sessions are blue, at
the position stored in that session's odometry frame, which lines up only when the sessions
share a map frame. The edges are bounded, so neither memory nor the rebuild on every loop
grows with the run. Builds the messages; publishing is the caller's function.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import numpy.typing as npt
from geometry_msgs.msg import Point  # type: ignore[import-untyped]
from std_msgs.msg import ColorRGBA  # type: ignore[import-untyped]
from visualization_msgs.msg import Marker, MarkerArray  # type: ignore[import-untyped]

__all__ = ['Edge', 'LoopMarkers']

NAMESPACE = 'loop_edges'
DEFAULT_FRAME = 'map'  # until odometry names its frame
OWN = ColorRGBA(r=1.0, g=0.2, b=0.2, a=1.0)
OTHER = ColorRGBA(r=0.2, g=0.6, b=1.0, a=1.0)

# (query position, match position, the match is in another session)
Edge = tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], bool]


class LoopMarkers:
    """The newest loop edges, republished whole on every change.

    Args:
        capacity: most edges kept (the oldest go first).
        publish: sends a MarkerArray (a latched publisher's ``publish``).
        frame_id: the frame of the positions now ('' until odometry names it).
        now: the stamp for a message (a ``builtin_interfaces/Time``).
    """

    def __init__(self, capacity: int, publish: Callable[[Any], None],
                 frame_id: Callable[[], str], now: Callable[[], Any]) -> None:
        self._edges: deque[Edge] = deque(maxlen=capacity)
        self._publish, self._frame_id, self._now = publish, frame_id, now
        # The verify thread adds, ~/reset clears: each publishes what it leaves, in order.
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._edges)

    def add(self, edges: Iterable[Edge]) -> None:
        """Append edges and publish all kept ones (nothing when ``edges`` is empty)."""
        new = list(edges)
        if not new:
            return
        with self._lock:
            self._edges.extend(new)
            self._publish(self._message())

    def clear(self) -> None:
        """Forget every edge and publish a DELETEALL, which replaces the latched edges: a
        display that starts later shows none either."""
        with self._lock:
            self._edges.clear()
            clear = Marker(ns=NAMESPACE, action=Marker.DELETEALL)
            clear.header.frame_id = self._frame_id() or DEFAULT_FRAME
            self._publish(MarkerArray(markers=[clear]))

    def _message(self) -> MarkerArray:
        m = Marker()
        m.header.frame_id = self._frame_id() or DEFAULT_FRAME
        m.header.stamp = self._now()
        m.ns, m.id = NAMESPACE, 0
        m.type, m.action = Marker.LINE_LIST, Marker.ADD
        m.pose.orientation.w = 1.0
        m.scale.x = 0.1
        m.color = OWN
        for a, b, foreign in self._edges:
            m.points.append(Point(x=float(a[0]), y=float(a[1]), z=float(a[2])))
            m.points.append(Point(x=float(b[0]), y=float(b[1]), z=float(b[2])))
            m.colors.extend((OTHER, OTHER) if foreign else (OWN, OWN))
        return MarkerArray(markers=[m])
