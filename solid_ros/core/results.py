"""The records that flow between the rooms of the core: every result type is imported from here.

A scan's :class:`Descriptor`; a stored scan a search returned (:class:`Match`); one loop,
published or only attempted (:class:`LoopCandidate`: ``T`` maps the query sensor frame into
the match's, covariance in ROS order with a right perturbation; see doc/conventions.md);
what one scan gave (:class:`ScanResult`, with :class:`StageTimes`); and what the pose-graph
back end did with a keyframe (:class:`Keyframe`, :class:`LoopOutcome`, :class:`BackendEvent`,
:class:`BackendState`). Plain frozen dataclasses of numbers and numpy arrays: this module
imports nothing of the core beyond the base modules.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass, fields
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from solid_ros.core.geometry import vector_to_matrix
from solid_ros.core.reasons import Reason

__all__ = ['ACCEPTED', 'EVIDENCE_FIELDS', 'IDENTITY_POSE', 'NAN_COV', 'BackendEvent',
           'BackendState', 'Descriptor', 'Evidence', 'Keyframe', 'LoopCandidate', 'LoopOutcome',
           'Match', 'PeerAlignment', 'ScanResult', 'Source', 'StageTimes', 'loop_name']

FloatArray = npt.NDArray[np.float64]
NAN_COV: tuple[float, ...] = (math.nan,) * 36
IDENTITY_POSE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
Source = Literal['descriptor', 'graph', 'step']  # what proposed a candidate


@dataclass(frozen=True)
class Descriptor:
    """SOLiD descriptor of one scan.

    Attributes:
        r_solid: R-SOLiD, shape (N_r,): place signature, compared by cosine distance.
        a_solid: A-SOLiD, shape (N_a,): azimuth signature, used for the heading.
        rec: range-elevation counts, shape (N_r, N_e).
        aec: azimuth-elevation counts, shape (N_a, N_e).
        iev: min-max normalised elevation counts (the weights), shape (N_e,).
        num_points: points left after preprocessing.
        heading: signature used for the heading, shape (N_a,): ``a_solid`` itself with
            ``heading_weight='count'``; with ``'range'`` the same sum with each point
            weighted by its squared horizontal range (about the surface it stands for), so
            near objects, whose azimuth shifts most when the sensor moves, count less.
    """

    r_solid: FloatArray
    a_solid: FloatArray
    rec: FloatArray
    aec: FloatArray
    iev: FloatArray
    num_points: int
    heading: FloatArray

    @property
    def ec(self) -> FloatArray:
        """Elevation counts EC[k] = sum_i REC[i, k]."""
        ec: FloatArray = self.rec.sum(axis=0)
        return ec


@dataclass(frozen=True)
class Match:
    """One stored scan returned by :meth:`DescriptorDatabase.search`.

    Attributes:
        seq: insertion sequence number (valid while the scan is stored).
        index: index of the scan within its own session.
        session: session id of the scan.
        stamp_ns: stamp of the scan, integer nanoseconds.
        distance: exact cosine distance to the query, in [0, 2].
    """

    seq: int
    index: int
    session: int
    stamp_ns: int
    distance: float


@dataclass(frozen=True)
class Evidence:
    """Everything measured about one loop candidate: what the judge's rules read
    (:mod:`solid_ros.core.verification.judge`). NaN: not measured, because an earlier rule
    refused the candidate or no rule needed it; flags are 1.0 or 0.0.

    Attributes:
        cloud: the candidate has a stored keyframe cloud (1) or none (0).
        usable: both clouds hold enough points and structure to register (1) or not (0).
        coarse_overlap: fraction of coarse structure points that the coarse stage aligned.
        converged: the fine stage converged (1) or not (0).
        overlap: structure overlap of the alignment, the smaller of the two directions.
        known_place: the pose puts the query where the pose graph predicted it, within one
            coarse voxel counting its sigmas (1) or not (0).
        rmse: RMS point-to-plane distance of the supporting points, metres.
        conflict: fraction of one scan's points in space the other sensor saw through, in
            coherent patches (at least 3 points in a cell of two voxels).
        conflict_points: the same point by point, scattered points counted too.
        constraint: least horizontal constraint per structure point (10 m heading lever).
        constraint_near: the same with the supporting structure's own range as the lever.
        spread: the constraint left without the strongest object.
        drift_m: largest translation of the two consistency restarts from the pose, metres.
        drift_deg: their largest rotation from it, degrees.
        drift_turn_deg: the turn they were started with, degrees.
        pinned_m: two sigmas of the loop covariance's least pinned translation, metres.
        pinned_deg: two sigmas of its least pinned rotation, degrees.
        odom_error_m: how far the loop's translation is from the odometry's, metres.
        odom_allowed_m: what the odometry's drift over the path between them allows, metres.
        graph_turn_deg: how far the loop turns from the pose graph's relative heading.
        graph_turn_tol_deg: the heading tolerance the graph allows.
        graph_stray_m: how far the loop moves the query's view from the graph's guess.
        graph_stray_allowed_m: what the graph's sigmas allow, metres.
        graph: the candidate was proposed by the pose graph (1) or the descriptor (0).
        step: a registered step to the previous keyframe (1), not a loop (0).
    """

    cloud: float = math.nan
    usable: float = math.nan
    coarse_overlap: float = math.nan
    converged: float = math.nan
    overlap: float = math.nan
    known_place: float = math.nan
    rmse: float = math.nan
    conflict: float = math.nan
    conflict_points: float = math.nan
    constraint: float = math.nan
    constraint_near: float = math.nan
    spread: float = math.nan
    drift_m: float = math.nan
    drift_deg: float = math.nan
    drift_turn_deg: float = math.nan
    pinned_m: float = math.nan
    pinned_deg: float = math.nan
    odom_error_m: float = math.nan
    odom_allowed_m: float = math.nan
    graph_turn_deg: float = math.nan
    graph_turn_tol_deg: float = math.nan
    graph_stray_m: float = math.nan
    graph_stray_allowed_m: float = math.nan
    graph: float = math.nan
    step: float = math.nan

    def __iter__(self) -> Iterator[float]:
        """The values in field order (one CSV column each): read directly, not by
        ``astuple``, which deep-copies each float (a third of writing hku1's candidates.csv)."""
        return (getattr(self, name) for name in EVIDENCE_FIELDS)


EVIDENCE_FIELDS: tuple[str, ...] = tuple(f.name for f in fields(Evidence))


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
        covariance: 6x6 row-major covariance of ``T`` (ROS order x, y, z, roll, pitch, yaw;
            right perturbation in the query sensor frame); NaN unless verified.
        reason: ``'verified'``, ``'descriptor'`` (accepted without verification) or the
            judge's rule that refused it (:data:`~solid_ros.core.verification.judge.RULES`).
        evidence: what was measured about it, as the judge read it.
        detail: the refusing rule's reading, e.g. ``'conflict 0.057 > 0.030'`` (empty when
            accepted).
        source: what proposed it: ``'descriptor'`` (the descriptor's nearest places) or
            ``'graph'`` (a keyframe near the query in the back end's estimate, see
            :mod:`solid_ros.core.candidates.position`; its ``margin`` is NaN), or ``'step'`` (the
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
    covariance: tuple[float, ...] = NAN_COV
    reason: Reason = 'descriptor'
    evidence: Evidence = Evidence()
    source: Source = 'descriptor'
    detail: str = ''

    @property
    def rmse(self) -> float:
        """RMS point-to-plane distance of the supporting points, metres (NaN: not measured)."""
        return self.evidence.rmse

    @property
    def overlap(self) -> float:
        """Structure overlap of the alignment (NaN: no fine registration ran)."""
        return self.evidence.overlap

    @property
    def conflict(self) -> float:
        """Free-space conflict of the alignment (NaN: not measured)."""
        return self.evidence.conflict

    @property
    def constraint(self) -> float:
        """Horizontal constraint per structure point (NaN: not measured)."""
        return self.evidence.constraint

    @property
    def spread(self) -> float:
        """The constraint without the strongest object (NaN: not measured)."""
        return self.evidence.spread

    def to_dict(self) -> dict[str, Any]:
        """Return the fields as a plain dict."""
        return asdict(self)

    def matrix(self) -> FloatArray:
        """``T`` as a 4x4 matrix."""
        return vector_to_matrix(self.pose)


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


# -------------------------------------------------------------------------------------- the back e

ACCEPTED = ('added', 'anchor', 'tie')


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
            ``'confirmed'``, ``'unconfirmed'``, ``'odom_covariance'``, ``'no_pose'``,
            ``'ignored'``, or of a peer's alignment ``'aligned'`` and ``'jump'``.
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


@dataclass(frozen=True)
class PeerAlignment:
    """Where a peer robot's map frame sits in this robot's map frame
    (:mod:`solid_ros.core.backend.alignment`).

    Attributes:
        peer: the peer's robot id (its session id).
        aligned: a set of at least ``min_loops`` mutually consistent inter-robot loops placed
            it (it stays so, with the last transform, while no such set decides otherwise).
        transform: ``T_own_map_peer_map`` (4x4; peer map coordinates into this robot's map),
            None while unaligned.
        covariance: 6x6 covariance of ``transform`` (ROS order, right perturbation), None while
            unaligned.
        loops: inter-robot loops held for this peer (both robots' loops between the two).
        inliers: loops of the consistent set that decided ``transform``.
        rival: size of the largest set of loops that disagrees with it (0: none).
        jumps: times the transform moved by more than the jump bounds after aligning.
    """

    peer: int
    aligned: bool = False
    transform: FloatArray | None = None
    covariance: FloatArray | None = None
    loops: int = 0
    inliers: int = 0
    rival: int = 0
    jumps: int = 0


def loop_name(loop: LoopCandidate) -> str:
    """A loop as log lines name it."""
    return f'{loop.query_index} -> session {loop.match_session} keyframe {loop.match_index}'
