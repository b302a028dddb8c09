"""The pose graph's share of a keyframe's candidates: its guesses and the keyframes it proposes.

:mod:`solid_ros.core.candidates.position` says which earlier keyframes lie near the query, or saw
its
place, in the graph's estimate; this module turns that into the detector's :class:`Hit` list
(the descriptor's hits with the graph's relative pose as their first start, then the graph's
own, source ``'graph'``) and holds the two checks a loop at such a hit gets: whether it lands
where the graph predicted it (the known place) and whether it turned away from the graph's
heading. Plain numpy; the joint marginals behind the known place are asked of the graph only
when a test needs them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import replace
from functools import cache, partial

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.covisibility import StructureIndex
from solid_ros.core.candidates.position import (
    GraphCandidate,
    GraphHint,
    MapCandidate,
    PeerCandidate,
    map_keyframes,
    map_view_keyframes,
    near_keyframes,
    peer_keyframes,
    view_keyframes,
)
from solid_ros.core.candidates.proposal import Hit, Proposal
from solid_ros.core.candidates.tolerance import (
    guess_deviation,
    heading_tolerance_deg,
    knows_place,
    position_sigma,
)
from solid_ros.core.candidates.views import KeyframeViews, ViewCentres
from solid_ros.core.config import SolidConfig
from solid_ros.core.database.descriptors import DescriptorDatabase
from solid_ros.core.descriptor.matching import cosine_distance
from solid_ros.core.descriptor.mount import Mount
from solid_ros.core.geometry import rot_z, vector_to_matrix, yaw_of
from solid_ros.core.results import Match

__all__ = ['STRAY_FLOOR_M', 'extent', 'graph_stray', 'graph_turn', 'hit_knows_place',
           'hypotheses_kept', 'placed_peer_hits', 'shared_hits', 'view_centre',
           'with_graph_hits']

FloatArray = npt.NDArray[np.float64]

# Beyond the graph's sigmas, how far a loop may move the query from the graph's guess, metres.
STRAY_FLOOR_M = 1.0


def with_graph_hits(proposal: Proposal, hint: GraphHint, config: SolidConfig,
                    database: DescriptorDatabase, own_seqs: Mapping[int, int],
                    views: KeyframeViews, mount: Mount,
                    map_seqs: Mapping[tuple[int, int], int] | None = None,
                    map_views: ViewCentres | None = None
                    ) -> list[Hit]:
    """The proposal's hits with the graph's guesses, then the keyframes near the query (or
    that saw its place) that the descriptor did not propose, then those of a loaded map near
    it (or that saw its place) once the session is relocalised in that map
    (:func:`map_keyframes`, :func:`map_view_keyframes`). Aligned peers'
    keyframes come apart (:func:`placed_peer_hits`); the descriptor's peer hits get no guess.

    Args:
        proposal: the keyframe's proposal (needs its odometry pose and keyframe cloud, else
            its hits come back unchanged).
        hint: the pose graph after the previous keyframe.
        config: the detector's settings.
        database: the descriptor database (the graph's keyframes' descriptors and headings).
        own_seqs: this session's keyframe index -> database sequence number.
        views: this session's keyframes' view centres (sensor frames).
        mount: the sensor's mount (guesses are registered in the levelled frames).
        map_seqs: a loaded map's ``(session, index)`` -> database sequence number.
        map_views: a loaded map's view centres (sensor frames).
    """
    cfg = config
    if proposal.pose is None or proposal.cloud_points is None:
        return list(proposal.hits)
    odom = vector_to_matrix(proposal.pose)
    near = near_keyframes(hint, proposal.query_index, proposal.stamp_ns, odom, cfg)
    close = {c.index for c in near}
    own = _Placing(proposal, hint, cfg, mount)
    seen: list[GraphCandidate] = []
    if own.centre is not None:
        seen = view_keyframes(hint, proposal.query_index, proposal.stamp_ns, odom, own.centre,
                              extent(proposal.cloud_points), views, cfg, sorted(close))
    viewed = {c.index for c in seen}
    mapped = map_keyframes(hint, odom, cfg)
    mapped_near = {(c.session, c.index) for c in mapped}
    mapped_seen: list[MapCandidate] = []
    if own.centre is not None and map_views is not None and len(map_views):
        mapped_seen = map_view_keyframes(hint, odom, own.centre, extent(proposal.cloud_points),
                                         map_views, cfg)
    hits = []
    for h in proposal.hits:
        T = own.guess(h, viewed)
        if T is not None and h.match.session == cfg.session_id:
            h = replace(h, guess=mount.level_pose(T), near=h.match.index in close,
                        view=h.match.index in viewed, heading_tol_deg=own.tol,
                        sigma_m=own.sigma, place_sigma=own.sigma_to(h.match.index))
        elif T is not None:  # a loaded map's: another session's indices, no joint marginal
            h = replace(h, guess=mount.level_pose(T),
                        near=(h.match.session, h.match.index) in mapped_near,
                        heading_tol_deg=own.tol, sigma_m=own.sigma)
        hits.append(h)
    taken = {h.match.index for h in hits if h.match.session == cfg.session_id}
    out = hits + own.hits([(c, 'near') for c in near] + [(c, 'view') for c in seen], taken,
                          database, own_seqs)
    if (mapped or mapped_seen) and map_seqs:
        taken_map = {(h.match.session, h.match.index) for h in out}  # map_hits adds to it
        out += own.map_hits(mapped, taken_map, database, map_seqs)
        out += own.map_hits(mapped_seen, taken_map, database, map_seqs, near=False)
    return out


def placed_peer_hits(proposal: Proposal, hint: GraphHint, config: SolidConfig,
                     database: DescriptorDatabase, mount: Mount) -> list[Hit]:
    """Aligned peers' keyframes placed near the query (:func:`peer_keyframes`) that are not
    among its hits yet: source ``'graph'``, the placement's guess first. The detector asks
    them only when the descriptor's peer hits verified nothing (each costs a fetched cloud
    and a registration; on the simulated fleet, where the descriptor found every
    inter-robot loop, they found none more).

    Args:
        proposal: the keyframe's proposal with its hits so far (none without its odometry
            pose and keyframe cloud).
        hint: the pose graph after the previous keyframe, with the peers' placement.
        config: the detector's settings.
        database: the descriptor database (the peers' descriptors and headings).
        mount: the sensor's mount.
    """
    if proposal.pose is None or proposal.cloud_points is None or not len(hint.peers.keys):
        return []
    placed = peer_keyframes(hint, vector_to_matrix(proposal.pose), config)
    if not placed:
        return []
    own = _Placing(proposal, hint, config, mount)
    return own.peer_hits(placed, {(h.match.session, h.match.index) for h in proposal.hits},
                         database)


def shared_hits(proposal: Proposal, hint: GraphHint, config: SolidConfig,
                database: DescriptorDatabase, own_seqs: Mapping[int, int], mount: Mount,
                structures: StructureIndex, structure: FloatArray) -> list[Hit]:
    """The keyframes that share the query's coarse structure in the graph's estimate and are
    not among its hits yet (:meth:`~solid_ros.core.candidates.covisibility.StructureIndex.shared`),
    source ``'graph'``, ``shared`` set: asked only when the others verified nothing, and for
    a one-sided view (as by view; a spinning sensor's position stands for its view) of an
    open scene. In a tight space every keyframe shares the same walls, so the share picks
    nothing out; on the simulator's tilted room walks with mixed pixels the extra loops
    (recall 0.46 -> 0.59 over 16 seeds) came with 3 of 745 off by 3.3-3.9 deg in roll.

    Args:
        proposal: the keyframe's proposal with its hits so far.
        hint: the pose graph after the previous keyframe.
        config: the detector's settings.
        database: the descriptor database.
        own_seqs: this session's keyframe index -> database sequence number.
        mount: the sensor's mount.
        structures: this session's keyframes' coarse structure.
        structure: the query's (sensor frame).
    """
    cfg = config
    if (proposal.pose is None or proposal.cloud_points is None or proposal.tight
            or not len(proposal.cloud_points) or not len(structure)):
        return []
    own = _Placing(proposal, hint, cfg, mount)
    assert own.centre is not None
    if not float(np.linalg.norm(own.centre)) > extent(proposal.cloud_points):
        return []
    taken = {h.match.index for h in proposal.hits if h.match.session == cfg.session_id}
    found = structures.shared(hint, proposal.query_index, proposal.stamp_ns,
                              vector_to_matrix(proposal.pose), structure, cfg, sorted(taken))
    return own.hits([(c, 'shared') for c in found], taken, database, own_seqs)


class _Placing:
    """What the graph says of a query: its predicted pose, heading tolerance and sigmas."""

    def __init__(self, proposal: Proposal, hint: GraphHint, config: SolidConfig,
                 mount: Mount) -> None:
        assert proposal.pose is not None and proposal.cloud_points is not None
        odom = vector_to_matrix(proposal.pose)
        self._proposal, self._hint, self._cfg, self._mount = proposal, hint, config, mount
        self._step = np.linalg.solve(hint.odom[-1], odom)
        self.predicted = hint.predict(odom)
        self.centre = (view_centre(proposal.cloud_points, mount)
                       if len(proposal.cloud_points) else None)
        self.sigma = (math.inf if self.centre is None
                      else position_sigma(hint.covariance, config, self._step, self.centre))
        self.tol = heading_tolerance_deg(hint.covariance, config, self._step)

    def sigma_to(self, index: int) -> Callable[[], float] | None:
        return _sigma_to(self._hint, index, self._cfg, self._step, self.centre)

    def guess(self, hit: Hit, viewed: set[int]) -> FloatArray | None:
        """The graph's ``T_mq`` of a descriptor hit it places (within
        ``graph_candidate_max_radius_m``, or proposed by view), else None."""
        cfg = self._cfg
        if hit.match.session == cfg.session_id:
            pose_m = self._hint.pose_of(hit.match.index)
        else:  # a loaded map's keyframe, once the session is placed in that map
            pose_m = self._hint.map_pose_of(hit.match.session, hit.match.index)
        if pose_m is None:
            return None
        T = np.asarray(np.linalg.solve(pose_m, self.predicted), dtype=np.float64)
        if (np.linalg.norm(T[:3, 3]) <= cfg.graph_candidate_max_radius_m
                or (hit.match.session == cfg.session_id and hit.match.index in viewed)):
            return T
        return None

    def hits(self, found: list[tuple[GraphCandidate, str]], taken: set[int],
             database: DescriptorDatabase, own_seqs: Mapping[int, int]) -> list[Hit]:
        """Hits of the graph's own candidates not ``taken`` (which grows)."""
        cfg, proposal, out = self._cfg, self._proposal, []
        for c, kind in found:
            seq = own_seqs.get(c.index)
            if c.index in taken or seq is None or not database.is_stored(seq):
                continue
            taken.add(c.index)
            distance = math.nan if proposal.r_solid is None else cosine_distance(
                proposal.r_solid, database.r_solid(seq))
            match = Match(seq, c.index, cfg.session_id, c.stamp_ns, distance)
            out.append(Hit(match, math.nan, database.heading(seq).copy(), 'graph',
                           self._mount.level_pose(c.T_mq), kind == 'near', self.tol,
                           kind == 'view', self.sigma, self.sigma_to(c.index),
                           kind == 'shared'))
        return out

    def _match(self, session: int, index: int, seq: int | None, taken: set[tuple[int, int]],
               database: DescriptorDatabase) -> Match | None:
        """The match of another session's stored keyframe not ``taken`` (which grows), with
        its descriptor distance to the query; None when taken or not stored."""
        if (session, index) in taken or seq is None or not database.is_stored(seq):
            return None
        taken.add((session, index))
        _, _, stamp = database.match_info(seq)
        r_solid = self._proposal.r_solid
        distance = (math.nan if r_solid is None
                    else cosine_distance(r_solid, database.r_solid(seq)))
        return Match(seq, index, session, stamp, distance)

    def map_hits(self, found: list[MapCandidate], taken: set[tuple[int, int]],
                 database: DescriptorDatabase, map_seqs: Mapping[tuple[int, int], int],
                 near: bool = True) -> list[Hit]:
        """Hits of the loaded map's keyframes near the query (``near``) or that saw its
        place, not ``taken``: source ``'graph'``, the graph's guess first, the query's own
        sigma (the graph holds no joint marginal with the fixed map)."""
        out = []
        for c in found:
            match = self._match(c.session, c.index, map_seqs.get((c.session, c.index)), taken,
                                database)
            if match is not None:
                out.append(Hit(match, math.nan, database.heading(match.seq).copy(), 'graph',
                               self._mount.level_pose(c.T_mq), near, self.tol, not near,
                               self.sigma))
        return out

    def peer_hits(self, found: list[PeerCandidate], taken: set[tuple[int, int]],
                  database: DescriptorDatabase) -> list[Hit]:
        """Hits of aligned peers' placed keyframes near the query not ``taken``: source
        ``'graph'``, the placement's guess first, verified with the peers' hits (not
        ``near``); the query's sigma grows by the placement's (its heading sigma acting over
        the distance to the query's view centre) and the heading tolerance by
        ``graph_candidate_sigmas`` of its heading sigma."""
        cfg, out = self._cfg, []
        view = 0.0 if self.centre is None else float(np.linalg.norm(self.centre))
        for c in found:
            match = self._match(c.session, c.index, database.foreign_seq(c.session, c.index),
                                taken, database)
            if match is None:
                continue
            lever = c.distance_m + view
            sigma = math.sqrt(self.sigma ** 2 + c.sigma_m ** 2
                              + (lever * c.yaw_sigma_rad) ** 2)
            tol = min(180.0, self.tol + cfg.graph_candidate_sigmas
                      * math.degrees(c.yaw_sigma_rad))
            out.append(Hit(match, math.nan, database.heading(match.seq).copy(), 'graph',
                           self._mount.level_pose(c.T_mq), False, tol, False, sigma))
        return out


def _sigma_to(hint: GraphHint, index: int, config: SolidConfig, step: FloatArray,
              centre: FloatArray | None) -> Callable[[], float] | None:
    """The query's position sigma relative to keyframe ``index``, computed once on first
    call (a joint marginal from gtsam: only for the few loops that ask for it)."""
    if hint.relative is None or centre is None:
        return None
    return cache(partial(hint.sigma_to, index, config, step, centre))


def hit_knows_place(hit: Hit, centre: FloatArray, config: SolidConfig,
                    T_mq: FloatArray, coarse_voxel: float | None = None) -> bool:
    """:func:`~solid_ros.core.candidates.tolerance.knows_place` for a hit with a guess, with the
    query's sigma relative to the match keyframe where the graph gives it (``coarse_voxel``:
    the pair's coarse grid, when not the configuration's)."""
    assert hit.guess is not None
    sigma = hit.sigma_m if hit.place_sigma is None else hit.place_sigma()
    return knows_place(hit.guess, T_mq, centre, sigma, hit.heading_tol_deg, config,
                       coarse_voxel)


def graph_turn(hit: Hit, T_mq: FloatArray) -> tuple[float, float]:
    """How far a loop the graph placed (proposed, or the descriptor's with the graph's guess)
    turns from the graph's relative heading, and the hit's tolerance, degrees (levelled
    frames; see :mod:`solid_ros.core.candidates.position`); NaN without a guess."""
    if hit.guess is None:
        return math.nan, math.nan
    turn = math.degrees(abs(yaw_of(np.linalg.solve(hit.guess, T_mq)[:3, :3])))
    return turn, hit.heading_tol_deg


def hypotheses_kept(hit: Hit, yaws: list[float]) -> list[float]:
    """The heading hypotheses (``p_match = Rz(yaw) p_query``, radians) worth a coarse start
    at a hit: all without the graph's guess, else those that turn no farther from it than
    the hit's heading tolerance (:func:`graph_turn`).

    A loop farther off is refused by the graph's heading rule, and a start from there that the
    registration turns back lands where the guess, tried first, started. On hku1 (the bag's
    odometry and KISS-ICP), quickshack and the simulated Avia drives and room walks with
    drifting odometry (the simulator's default and strong drift), 78-94 % of the hypotheses
    beside a guess lay beyond its tolerance (17 % on quickshack with KISS-ICP, lost in the
    tight space, where the tolerance is wide); 14 loops verified from one of them, each with
    the guess's coarse overlap within 0.07 of the winning start's (0.27-0.49). The loops only a
    hypothesis found (strong drift, the graph off by several metres) came from within the
    tolerance."""
    if hit.guess is None:
        return yaws
    return [y for y in yaws if graph_turn(hit, _turned(y))[0] <= hit.heading_tol_deg]


def _turned(yaw: float) -> FloatArray:
    """The 4x4 pose of a heading hypothesis: turned by ``yaw`` about z, no translation."""
    out = np.eye(4)
    out[:3, :3] = rot_z(yaw)
    return out


def graph_stray(hit: Hit, centre: FloatArray, config: SolidConfig, T_mq: FloatArray,
                voxel: float) -> tuple[float, float]:
    """How far a loop the graph placed moves the query's view ``centre`` from the graph's
    guess, and what it allows: ``graph_candidate_sigmas`` of the query's sigma relative to the
    match plus ``STRAY_FLOOR_M``, or two of the pair's fine voxels (``voxel``) where that is
    less (two tight-space keyframes, or a grid set finer by hand: in the simulator's rooms right
    loops lay within 0.3 m of the guess, slides along shelves 0.7-1.7 m); levelled frames, NaN
    without a guess or a finite sigma."""
    if hit.guess is None:
        return math.nan, math.nan
    sigma = hit.sigma_m if hit.place_sigma is None else hit.place_sigma()
    if not math.isfinite(sigma):
        return math.nan, math.nan
    floor = min(STRAY_FLOOR_M, 2.0 * voxel)
    return (guess_deviation(hit.guess, T_mq, centre),
            floor + config.graph_candidate_sigmas * sigma)


def view_centre(cloud: npt.ArrayLike, mount: Mount) -> FloatArray:
    """Centroid of a keyframe cloud (levelled frame) in the sensor frame."""
    centre = np.asarray(cloud, dtype=np.float64)[:, :3].mean(axis=0)
    return mount.to_sensor(centre)


def extent(cloud: FloatArray) -> float:
    """RMS horizontal distance of a cloud's points from their centroid, metres."""
    xy = np.asarray(cloud, dtype=np.float64)[:, :2]
    return math.sqrt(float(np.mean(np.sum((xy - xy.mean(axis=0)) ** 2, axis=1))))
