"""Odometry consistency of loops within one session.

Odometry drifts, but slowly: a LiDAR(-inertial) odometry is typically off by 0.5-3 % of the
path driven. A loop between two keyframes of the same session claims their relative pose; when
the odometry puts the two keyframes far further apart than its drift over the path driven
between them can explain, the loop joins two places that only look alike (a repeated building,
an identical crossing), which the geometry of two scans alone cannot always tell apart. The
check allows ``drift * path + slack`` metres of disagreement between the loop's translation and
the odometry's. It only applies within one session: other robots and loaded sessions have no
odometry in common with this one.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from solid_ros.core.geometry import vector_to_matrix

__all__ = ['OdometryPath', 'disagreement']

FloatArray = npt.NDArray[np.float64]


def disagreement(T_mq: npt.ArrayLike, pose_query: npt.ArrayLike,
                 pose_match: npt.ArrayLike) -> float:
    """Distance between the loop's translation and the odometry's, metres.

    Args:
        T_mq: 4x4 loop pose, ``p_match = T_mq p_query``.
        pose_query: odometry pose vector of the query keyframe.
        pose_match: odometry pose vector of the match keyframe.
    """
    odom = np.linalg.inv(vector_to_matrix(pose_match)) @ vector_to_matrix(pose_query)
    T = np.asarray(T_mq, dtype=np.float64)
    return float(np.linalg.norm(odom[:3, 3] - T[:3, 3]))


class OdometryPath:
    """Path length driven up to each keyframe of this session, from the keyframes' poses.

    Keyframes without a pose get none; the path over such a gap is the straight line between
    the posed keyframes on either side (a lower bound, so the check only gets stricter).

    Args:
        capacity: most keyframes remembered (the oldest is forgotten first).
    """

    def __init__(self, capacity: int) -> None:
        self._capacity = max(int(capacity), 1)
        self._at: dict[int, float] = {}
        self._last: FloatArray | None = None
        self._total = 0.0

    def add(self, index: int, pose: FloatArray | None) -> None:
        """Record keyframe ``index`` (in order) with its pose vector, if any."""
        if pose is None:
            return
        if self._last is not None:
            self._total += float(np.linalg.norm(pose[:3] - self._last[:3]))
        self._last = np.asarray(pose, dtype=np.float64).copy()
        self._at[int(index)] = self._total
        while len(self._at) > self._capacity:
            self._at.pop(next(iter(self._at)))

    def between(self, older: int, newer: int) -> float | None:
        """Path driven from keyframe ``older`` to ``newer``; None when either has no pose."""
        a, b = self._at.get(int(older)), self._at.get(int(newer))
        return None if a is None or b is None else b - a

    def clear(self) -> None:
        """Forget everything (after a reset)."""
        self._at.clear()
        self._last = None
        self._total = 0.0
