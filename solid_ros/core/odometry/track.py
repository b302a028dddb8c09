"""Odometry of this session: pairing clouds with poses, and the consistency check of loops.

Pairing: every odometry source (a topic, a bag's Odometry topic, a poses file, KISS-ICP over
the clouds: :mod:`solid_ros.core.odometry.kiss`) hands the detector a pose per cloud through
one interface, :class:`OdometrySource`: ``pose_for(stamp_ns, points)`` gives an
:class:`OdomSample` or None.
Stamped sources pair by :func:`nearest_stamp`, the one rule used by the node, the replay and
the fleet replay: the nearest stamp within a tolerance, ties to the earlier one.

Consistency. Odometry drifts, but slowly: a LiDAR(-inertial) odometry is typically off by 0.5-3
% of the path driven. A loop between two keyframes of the same session claims their relative
pose; when the odometry puts the two keyframes far further apart than its drift over the path
driven between them can explain, the loop joins two places that only look alike (a repeated
building, an identical crossing), which the geometry of two scans alone cannot always tell
apart. The check allows ``drift * path + slack`` metres of disagreement between the loop's
translation and the odometry's. It only applies within one session: other robots and loaded
sessions have no odometry in common with this one.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import PoseError
from solid_ros.core.geometry import vector_to_matrix

__all__ = ['OdomSample', 'OdometryPath', 'OdometrySource', 'StampedOdometry', 'disagreement',
           'nearest_stamp', 'usable_covariance']

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
Points = npt.NDArray[np.floating[Any]]


@dataclass(frozen=True)
class OdomSample:
    """One odometry pose.

    Attributes:
        stamp_ns: its stamp, integer nanoseconds.
        pose: 4x4 ``T_odom_sensor`` (finite, a rotation).
        covariance: 6x6 pose covariance (ROS order x, y, z, roll, pitch, yaw) as the source
            gave it (None: none given). It may be unusable (all zero for 'unknown', NaN,
            not positive definite): users check it with :func:`usable_covariance` and fall
            back to a model.
        segment: odometry segment. Poses of one segment are linked by the odometry; a source
            that loses track (a registration-based one resetting on a cloud it cannot
            register) starts the next segment, whose poses nothing links to the earlier ones:
            the back end starts a new graph segment.
        reason: on the first sample of a new segment, why the source reset (one line for the
            caller's log); else None.
    """

    stamp_ns: int
    pose: FloatArray
    covariance: FloatArray | None = None
    segment: int = 0
    reason: str | None = None


class OdometrySource(Protocol):
    """Clouds in, a pose per cloud out: what the detector's callers pair a scan with."""

    name: str

    def pose_for(self, stamp_ns: int, points: Points | None = None) -> OdomSample | None:
        """The sensor pose for the cloud at ``stamp_ns`` (None: no pose for it)."""


def nearest_stamp(stamps_ns: npt.ArrayLike, query_ns: npt.ArrayLike,
                  tolerance_ns: int) -> npt.NDArray[np.intp]:
    """Index of the nearest stamp for every query stamp, -1 beyond ``tolerance_ns``.

    Args:
        stamps_ns: (N,) stamps of the poses (any order).
        query_ns: (M,) stamps to look up.
        tolerance_ns: largest accepted |difference|; ties go to the earlier stamp.
    """
    q = np.atleast_1d(np.asarray(query_ns, dtype=np.int64))
    r = np.asarray(stamps_ns, dtype=np.int64)
    if r.size == 0:
        return np.full(q.shape, -1, dtype=np.intp)
    order = np.argsort(r, kind='stable')
    rs = r[order]
    pos = np.clip(np.searchsorted(rs, q), 1, len(rs) - 1) if len(rs) > 1 else np.zeros_like(q)
    left = pos - 1 if len(rs) > 1 else pos
    dl = np.abs(q - rs[left])
    dr = np.abs(q - rs[pos])
    pick = np.where(dr < dl, pos, left)
    best = np.minimum(dl, dr)
    out: npt.NDArray[np.intp] = order[pick].astype(np.intp)
    out[best > tolerance_ns] = -1
    return out


def usable_covariance(cov: npt.ArrayLike | None) -> FloatArray | None:
    """The 6x6 covariance when it is finite, symmetric and positive definite, else None
    (unset all-zero covariances, NaN, negative variances)."""
    if cov is None:
        return None
    c = np.asarray(cov, dtype=np.float64)
    if c.size != 36:
        return None
    c = c.reshape(6, 6)
    if not np.all(np.isfinite(c)) or not np.allclose(c, c.T, rtol=1e-6, atol=1e-12):
        return None
    try:
        np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        return None
    return c


class StampedOdometry:
    """Poses with stamps (an Odometry topic, a bag's Odometry, a stamped poses file), paired
    with clouds by :func:`nearest_stamp`.

    Args:
        tolerance_ns: largest stamp difference of a pairing.
        capacity: newest poses kept (None: all; a live topic keeps a bounded buffer).
        name: what the source is, for reports and messages.
    """

    def __init__(self, tolerance_ns: int, capacity: int | None = None,
                 name: str = 'odometry') -> None:
        self.name = name
        self.tolerance_ns = int(tolerance_ns)
        self._samples: deque[OdomSample] = deque(maxlen=capacity)
        self._stamps: IntArray | None = None  # cached sorted view, dropped on add

    @classmethod
    def from_track(cls, stamps_ns: npt.ArrayLike, poses: npt.ArrayLike, tolerance_ns: int,
                   name: str = 'odometry',
                   covariances: Sequence[npt.ArrayLike | None] | None = None,
                   ) -> StampedOdometry:
        """A source over a whole recorded track ((N,) stamps, (N, 4, 4) poses)."""
        out = cls(tolerance_ns, name=name)
        covs: Sequence[npt.ArrayLike | None] = (
            [None] * len(np.asarray(stamps_ns)) if covariances is None else covariances)
        for stamp, pose, cov in zip(np.asarray(stamps_ns), np.asarray(poses), covs):
            out.add(int(stamp), pose, cov)
        return out

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def latest_stamp_ns(self) -> int | None:
        """Stamp of the newest pose added (None: none yet)."""
        return self._samples[-1].stamp_ns if self._samples else None

    def add(self, stamp_ns: int, pose: npt.ArrayLike,
            covariance: npt.ArrayLike | None = None) -> OdomSample:
        """Add a pose (4x4 ``T_odom_sensor``) in arrival order.

        Raises:
            PoseError: the pose is not a finite 4x4 matrix; nothing is added.
        """
        T = np.asarray(pose, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise PoseError('odometry pose is not finite')
        cov = None if covariance is None else np.asarray(covariance, dtype=np.float64)
        sample = OdomSample(int(stamp_ns), T, cov.reshape(6, 6) if cov is not None
                            and cov.size == 36 else None)
        self._samples.append(sample)
        self._stamps = None
        return sample

    def pose_for(self, stamp_ns: int, points: Points | None = None) -> OdomSample | None:
        """The pose nearest ``stamp_ns`` within the tolerance, or None."""
        if not self._samples:
            return None
        if self._stamps is None:
            self._stamps = np.fromiter((s.stamp_ns for s in self._samples), np.int64,
                                       len(self._samples))
        k = int(nearest_stamp(self._stamps, stamp_ns, self.tolerance_ns)[0])
        return self._samples[k] if k >= 0 else None

    def nearest_gap_ns(self, stamp_ns: int) -> int | None:
        """``stamp_ns`` minus the nearest pose's stamp, whatever the tolerance (None: no pose);
        a large gap means the clouds and the odometry run on different clocks."""
        if not self._samples:
            return None
        best = min(self._samples, key=lambda s: abs(s.stamp_ns - stamp_ns))
        return stamp_ns - best.stamp_ns

    def clear(self) -> None:
        """Forget every pose."""
        self._samples.clear()
        self._stamps = None


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
    the posed keyframes on either side (a lower bound, so the check only gets stricter). A step
    longer than ``jump_m`` between two posed keyframes is a jump of the odometry (a reset, a
    relocalisation), not a path: the keyframes on either side lie on different segments and
    there is no path between them.

    Args:
        capacity: most keyframes remembered (the oldest is forgotten first).
        jump_m: a longer step between two keyframes starts a new segment (inf: never).
    """

    def __init__(self, capacity: int, jump_m: float = math.inf) -> None:
        self._capacity = max(int(capacity), 1)
        self._jump_m = jump_m
        self._at: dict[int, tuple[int, float]] = {}
        self._last: FloatArray | None = None
        self._total = 0.0
        self._segment = 0

    def add(self, index: int, pose: FloatArray | None, reset: bool = False) -> None:
        """Record keyframe ``index`` (in order) with its pose vector, if any; ``reset``: the
        odometry said it started a new segment (a reset with no jump)."""
        if pose is None:
            return
        if self._last is not None:
            step = float(np.linalg.norm(pose[:3] - self._last[:3]))
            if reset or step > self._jump_m:
                self._segment += 1
            else:
                self._total += step
        self._last = np.asarray(pose, dtype=np.float64).copy()
        self._at[int(index)] = (self._segment, self._total)
        while len(self._at) > self._capacity:
            self._at.pop(next(iter(self._at)))

    def between(self, older: int, newer: int) -> float | None:
        """Path driven from keyframe ``older`` to ``newer``; None when either has no pose or
        they lie on different segments."""
        a, b = self._at.get(int(older)), self._at.get(int(newer))
        if a is None or b is None or a[0] != b[0]:
            return None
        return b[1] - a[1]

    def clear(self) -> None:
        """Forget everything (after a reset)."""
        self._at.clear()
        self._last = None
        self._total = 0.0
        self._segment = 0
