"""What the detector hands on: the loop candidates, a keyframe's proposal and its result.

:class:`Proposal` is the descriptor stage's output (``LoopDetector.propose``), :class:`Hit`
one candidate in it,
:class:`ScanResult` what verification made of the keyframe and :class:`LoopCandidate` one
loop, published or only attempted (the README's conventions: ``T`` maps the query sensor
frame into the match's; covariance in ROS order with a right perturbation).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from solid_ros.core.database import Match
from solid_ros.core.descriptor import Descriptor
from solid_ros.core.geometry import vector_to_matrix
from solid_ros.core.reasons import Reason
from solid_ros.core.registration import Query

__all__ = ['IDENTITY_POSE', 'NAN_COV', 'Hit', 'LoopCandidate', 'Proposal', 'ScanResult',
           'Source', 'StageTimes']

FloatArray = npt.NDArray[np.float64]
NAN_COV: tuple[float, ...] = (math.nan,) * 36
IDENTITY_POSE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
Source = Literal['descriptor', 'graph', 'step']  # what proposed a candidate


@dataclass(frozen=True)
class LoopCandidate:
    """A loop between the current scan and a stored one, published or only attempted.

    Attributes:
        query_index: index of the query scan among this session's keyframes.
        match_index: index of the matched scan within its session.
        query_stamp_ns: stamp of the query scan, integer nanoseconds.
        match_stamp_ns: stamp of the matched scan, integer nanoseconds.
        match_session: session id of the matched scan.
        distance: cosine distance of the R-SOLiD pair, in [0, 2].
        yaw: heading of the query relative to the match, radians in (-pi, pi], about the
            level +z: p_match = Rz(yaw) p_query. From the verified pose when ``verified``,
            else from A-SOLiD.
        margin: distance of the next-best distinct place minus ``distance``; ``math.inf``
            when there is none.
        verified: registration verified the loop (``reason == 'verified'``).
        pose: ``T`` = pose of the query sensor in the match sensor's frame, ``p_match = T
            p_query``, as ``(tx, ty, tz, qx, qy, qz, qw)``; without verification only the
            descriptor's yaw (no translation).
        fitness: fraction of the match's cloud points supporting the alignment (NaN when no
            registration ran).
        rmse: RMS point-to-plane distance of the supporting points, metres.
        covariance: 6x6 row-major covariance of ``T`` (ROS order x, y, z, roll, pitch, yaw;
            right perturbation in the query sensor frame); NaN unless verified.
        reason: ``'verified'``, ``'descriptor'`` (accepted without verification), the
            verification test that rejected it, or ``'odometry'`` (this session's odometry
            contradicts it).
        overlap: structure overlap of the alignment (NaN when no fine registration ran).
        conflict: free-space conflict of the alignment (NaN: not measured).
        constraint: horizontal constraint per structure point (NaN: not measured).
        spread: the constraint without the strongest object (NaN: not measured).
        source: what proposed it: ``'descriptor'`` (the descriptor's nearest places) or
            ``'graph'`` (a keyframe near the query in the back end's estimate, see
            :mod:`solid_ros.core.proposals`; its ``margin`` is NaN), or ``'step'`` (the
            previous keyframe, :attr:`ScanResult.step`; never published).
    """

    query_index: int
    match_index: int
    query_stamp_ns: int
    match_stamp_ns: int
    match_session: int
    distance: float
    yaw: float
    margin: float
    verified: bool = False
    pose: tuple[float, ...] = IDENTITY_POSE
    fitness: float = math.nan
    rmse: float = math.nan
    covariance: tuple[float, ...] = NAN_COV
    reason: Reason = 'descriptor'
    overlap: float = math.nan
    conflict: float = math.nan
    constraint: float = math.nan
    spread: float = math.nan
    source: Source = 'descriptor'

    def to_dict(self) -> dict[str, Any]:
        """Return the fields as a plain dict."""
        return asdict(self)

    def matrix(self) -> FloatArray:
        """``T`` as a 4x4 matrix."""
        return vector_to_matrix(self.pose)


@dataclass(frozen=True)
class Hit:
    """A candidate to verify: the descriptor's (from ``LoopDetector.propose``) or the
    pose graph's (added by ``verify``); ``guess`` is the graph's ``T_mq`` in the levelled
    frames, the first start of the coarse registration (None: the graph has none); ``near``:
    among the keyframes near the query in the graph's estimate (verified first); ``view``:
    among those whose view centre lies near the query's (verified next); ``shared``: among
    those that share the query's coarse structure in the graph's estimate (verified last);
    ``heading_tol_deg``: how far a loop the graph proposed may turn from the guess;
    ``sigma_m``: the query's position sigma in the graph, its view centre as the lever;
    ``place_sigma``: the same relative to the match keyframe, asked of the graph only when
    :func:`~solid_ros.core.proposals.knows_place` needs it (None: use ``sigma_m``)."""

    match: Match
    margin: float
    heading: npt.NDArray[np.float32]
    source: Source = 'descriptor'
    guess: FloatArray | None = None
    near: bool = False
    heading_tol_deg: float = 180.0
    view: bool = False
    sigma_m: float = math.inf
    place_sigma: Callable[[], float] | None = None
    shared: bool = False


@dataclass(frozen=True)
class StageTimes:
    """Milliseconds per stage of one keyframe (NaN: the stage did not run)."""

    describe: float = math.nan
    search: float = math.nan
    verify: float = math.nan
    step: float = math.nan


@dataclass(frozen=True)
class ScanResult:
    """What one scan gave; ``LoopDetector.process`` and ``LoopDetector.verify``
    return it.

    Attributes:
        stamp_ns: the scan's stamp, integer nanoseconds.
        keyframe: the scan was kept (described, stored and queried); False: gated out.
        query_index: its index among this session's keyframes (-1 when gated out).
        pose: the odometry pose vector ``(x, y, z, qx, qy, qz, qw)`` it came with, if any.
        loops: loops to publish, best first.
        attempts: every candidate looked at, published or not, with its reason.
        best: the nearest stored scan by descriptor, accepted or not (None when none was
            eligible); offline PR curves need it.
        times: milliseconds per stage.
        descriptor: its descriptor (None when gated out or given as a descriptor).
        step: this keyframe registered to the previous one of this session, seeded by the
            odometry step and verified by the loops' tests (``backend_step_registration``
            'on'; source ``'step'``, never published as a loop), or None.
    """

    stamp_ns: int
    keyframe: bool = False
    query_index: int = -1
    pose: FloatArray | None = None
    loops: tuple[LoopCandidate, ...] = ()
    attempts: tuple[LoopCandidate, ...] = ()
    best: LoopCandidate | None = None
    times: StageTimes = StageTimes()
    descriptor: Descriptor | None = None
    step: LoopCandidate | None = None


@dataclass
class Proposal:
    """What ``LoopDetector.propose`` found for one keyframe, for ``verify``.

    Attributes:
        query_index: index of the keyframe in this session.
        stamp_ns: its stamp.
        seq: its database sequence number.
        heading: its heading signature.
        r_solid: its R-SOLiD (shared with peer robots).
        pose: its pose vector ``(x, y, z, qx, qy, qz, qw)``, when known.
        cloud_points: its keyframe cloud points (levelled, gated, clipped, voxelised), or
            None without verification.
        tight: the cloud is on the tight-space grid (see ``verify_tight_range``).
        hits: descriptor candidates, nearest first.
        best: the nearest stored scan by descriptor, accepted or not.
        descriptor: its descriptor (None when given as a descriptor).
        describe_ms: time spent levelling and describing, milliseconds.
        search_ms: time spent searching and storing the descriptor, milliseconds.
        query: its cloud prepared for registration (set by ``LoopDetector.verify``).
    """

    query_index: int
    stamp_ns: int
    seq: int
    heading: FloatArray
    cloud_points: FloatArray | None
    r_solid: FloatArray | None = None
    pose: FloatArray | None = None
    hits: list[Hit] = field(default_factory=list)
    best: LoopCandidate | None = None
    descriptor: Descriptor | None = None
    describe_ms: float = math.nan
    search_ms: float = math.nan
    query: Query | None = None
    tight: bool = False
