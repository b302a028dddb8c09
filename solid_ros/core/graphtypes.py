"""What the pose-graph back end hands back: per-keyframe state, loop outcomes, events.

See :mod:`solid_ros.core.posegraph`. Plain frozen dataclasses of numpy arrays, no gtsam.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.detector import LoopCandidate

__all__ = ['ACCEPTED', 'BackendEvent', 'BackendState', 'Keyframe', 'LoopOutcome', 'key_of',
           'loop_name']

FloatArray = npt.NDArray[np.float64]
_KEY_BASE = ord('x') << 56  # gtsam.symbol('x', index)
ACCEPTED = ('added', 'anchor', 'tie')


def key_of(index: int) -> int:
    """gtsam key of this session's keyframe ``index`` (``gtsam.symbol('x', index)``)."""
    return _KEY_BASE | int(index)


@dataclass(frozen=True)
class Keyframe:
    """A keyframe in the graph: enough for another back end to rebuild the chain.

    Attributes:
        index: its index among this session's keyframes.
        stamp_ns: its stamp.
        odom: 4x4 odometry pose ``T_odom_sensor``.
        pose: 4x4 corrected pose ``T_map_sensor``.
        segment: the graph segment (a new one after each odometry jump or reset).
    """

    index: int
    stamp_ns: int
    odom: FloatArray
    pose: FloatArray
    segment: int


@dataclass(frozen=True)
class BackendEvent:
    """Something the caller should log (one line).

    Attributes:
        kind: ``'segment'``, ``'anchor'``, ``'tie'``, ``'rebuild'``, ``'gate'``,
            ``'confirmed'``, ``'unconfirmed'``, ``'odom_covariance'``, ``'no_pose'`` or
            ``'ignored'``.
        message: the line.
    """

    kind: str
    message: str


@dataclass(frozen=True)
class LoopOutcome:
    """What the back end did with one published loop.

    Attributes:
        loop: the loop.
        reason: ``'added'``, ``'anchor'`` (it moved the session into the loaded map),
            ``'tie'`` (it placed a segment that no loop had tied yet),
            ``'gate'`` (refused: too far from the estimate), ``'no_covariance'``,
            ``'no_pose'`` (the query has no odometry pose), ``'unknown_keyframe'`` (the
            match is not in the graph), ``'unknown_session'`` (another robot's keyframe
            without a map pose) or ``'failed'`` (gtsam could not solve with it).
        sigmas: its Mahalanobis distance from the estimate (NaN: not measured).
    """

    loop: LoopCandidate
    reason: str
    sigmas: float = math.nan

    @property
    def accepted(self) -> bool:
        """Whether the loop is a factor of the graph."""
        return self.reason in ACCEPTED


@dataclass(frozen=True)
class BackendState:
    """The back end after one keyframe.

    Attributes:
        index: the keyframe's index (-1: not a keyframe).
        stamp_ns: its stamp.
        added: whether it became a variable of the graph.
        pose: its corrected pose ``T_map_sensor`` (None when not added).
        correction: ``T_map_odom`` of the newest keyframe in the graph (identity before any).
        covariance: 6x6 marginal covariance of ``pose`` (ROS order, right perturbation in the
            sensor frame), None when not added or not available.
        segment: the graph segment of the newest keyframe.
        loops: what happened to each of the keyframe's loops.
        events: lines to log.
        update_ms: time spent in this update, milliseconds.
    """

    index: int
    stamp_ns: int
    added: bool
    pose: FloatArray | None
    correction: FloatArray
    covariance: FloatArray | None
    segment: int
    loops: tuple[LoopOutcome, ...] = ()
    events: tuple[BackendEvent, ...] = ()
    update_ms: float = 0.0


def loop_name(loop: LoopCandidate) -> str:
    """A loop as log lines name it."""
    return f'{loop.query_index} -> session {loop.match_session} keyframe {loop.match_index}'
