"""The pose graph's share of a keyframe's candidates: its guesses and the keyframes it proposes.

:mod:`solid_ros.core.proposals` says which earlier keyframes lie near the query, or saw its
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

from solid_ros.core.config import SolidConfig
from solid_ros.core.database import DescriptorDatabase, Match
from solid_ros.core.geometry import vector_to_matrix, yaw_of
from solid_ros.core.matching import cosine_distance
from solid_ros.core.mount import Mount
from solid_ros.core.proposals import (
    GraphHint,
    guess_deviation,
    heading_tolerance_deg,
    knows_place,
    near_keyframes,
    position_sigma,
    view_keyframes,
)
from solid_ros.core.results import Hit, Proposal

__all__ = ['STRAY_FLOOR_M', 'extent', 'hit_knows_place', 'strayed_from_guess', 'turned_from_guess',
           'view_centre', 'with_graph_hits']

FloatArray = npt.NDArray[np.float64]

# Beyond the graph's sigmas, how far a loop may move the query from the graph's guess, metres.
STRAY_FLOOR_M = 1.0


def with_graph_hits(proposal: Proposal, hint: GraphHint, config: SolidConfig,
                    database: DescriptorDatabase, own_seqs: Mapping[int, int],
                    views: Mapping[int, FloatArray], mount: Mount) -> list[Hit]:
    """The proposal's hits with the graph's guesses, then the keyframes near the query (or
    that saw its place) that the descriptor did not propose.

    Args:
        proposal: the keyframe's proposal (needs its odometry pose and keyframe cloud, else
            its hits come back unchanged).
        hint: the pose graph after the previous keyframe.
        config: the detector's settings.
        database: the descriptor database (the graph's keyframes' descriptors and headings).
        own_seqs: this session's keyframe index -> database sequence number.
        views: this session's keyframe index -> view centre (sensor frame).
        mount: the sensor's mount (guesses are registered in the levelled frames).
    """
    cfg = config
    if proposal.pose is None or proposal.cloud_points is None:
        return proposal.hits
    odom = vector_to_matrix(proposal.pose)
    near = near_keyframes(hint, proposal.query_index, proposal.stamp_ns, odom, cfg)
    close = {c.index for c in near}
    seen, sigma, centre = [], math.inf, None
    step = np.linalg.solve(hint.odom[-1], odom)
    if len(proposal.cloud_points):
        centre = view_centre(proposal.cloud_points, mount)
        seen = view_keyframes(hint, proposal.query_index, proposal.stamp_ns, odom, centre,
                              extent(proposal.cloud_points), views, cfg, sorted(close))
        sigma = position_sigma(hint.covariance, cfg, step, centre)
    viewed = {c.index for c in seen}
    tol = heading_tolerance_deg(hint.covariance, cfg, step)
    predicted = hint.predict(odom)
    hits = []
    for h in proposal.hits:
        pose_m = hint.pose_of(h.match.index) if h.match.session == cfg.session_id else None
        if pose_m is not None:
            T = np.asarray(np.linalg.solve(pose_m, predicted), dtype=np.float64)
            if (np.linalg.norm(T[:3, 3]) <= cfg.graph_candidate_max_radius_m
                    or h.match.index in viewed):
                h = replace(h, guess=mount.level_pose(T), near=h.match.index in close,
                            view=h.match.index in viewed, heading_tol_deg=tol, sigma_m=sigma,
                            place_sigma=_sigma_to(hint, h.match.index, cfg, step, centre))
        hits.append(h)
    own = {h.match.index for h in hits if h.match.session == cfg.session_id}
    for c, is_near in [(c, True) for c in near] + [(c, False) for c in seen]:
        seq = own_seqs.get(c.index)
        if c.index in own or seq is None or not database.is_stored(seq):
            continue
        distance = math.nan if proposal.r_solid is None else cosine_distance(
            proposal.r_solid, database.r_solid(seq))
        match = Match(seq, c.index, cfg.session_id, c.stamp_ns, distance)
        hits.append(Hit(match, math.nan, database.heading(seq).copy(), 'graph',
                        mount.level_pose(c.T_mq), is_near, tol, not is_near, sigma,
                        _sigma_to(hint, c.index, cfg, step, centre)))
    return hits


def _sigma_to(hint: GraphHint, index: int, config: SolidConfig, step: FloatArray,
              centre: FloatArray | None) -> Callable[[], float] | None:
    """The query's position sigma relative to keyframe ``index``, computed once on first
    call (a joint marginal from gtsam: only for the few loops that ask for it)."""
    if hint.relative is None or centre is None:
        return None
    return cache(partial(hint.sigma_to, index, config, step, centre))


def hit_knows_place(hit: Hit, centre: FloatArray, config: SolidConfig,
                    T_mq: FloatArray, coarse_voxel: float | None = None) -> bool:
    """:func:`~solid_ros.core.proposals.knows_place` for a hit with a guess, with the
    query's sigma relative to the match keyframe where the graph gives it (``coarse_voxel``:
    the pair's coarse grid, when not the configuration's)."""
    assert hit.guess is not None
    sigma = hit.sigma_m if hit.place_sigma is None else hit.place_sigma()
    return knows_place(hit.guess, T_mq, centre, sigma, hit.heading_tol_deg, config,
                       coarse_voxel)


def turned_from_guess(hit: Hit, T_mq: FloatArray) -> bool:
    """Whether a loop the graph placed (proposed, or the descriptor's with the graph's guess)
    turns from the graph's relative heading by more than the hit's tolerance (levelled
    frames; see :mod:`solid_ros.core.proposals`)."""
    if hit.guess is None:
        return False
    turn = math.degrees(abs(yaw_of(np.linalg.solve(hit.guess, T_mq)[:3, :3])))
    return turn > hit.heading_tol_deg


def strayed_from_guess(hit: Hit, centre: FloatArray, config: SolidConfig,
                       T_mq: FloatArray, floor_m: float = STRAY_FLOOR_M) -> bool:
    """Whether a loop the graph placed moves the query's view ``centre`` from the graph's
    guess by more than ``graph_candidate_sigmas`` of the query's sigma relative to the match
    plus ``floor_m`` (levelled frames; two tight-space keyframes pass a smaller one)."""
    if hit.guess is None:
        return False
    sigma = hit.sigma_m if hit.place_sigma is None else hit.place_sigma()
    if not math.isfinite(sigma):
        return False
    return (guess_deviation(hit.guess, T_mq, centre)
            > floor_m + config.graph_candidate_sigmas * sigma)


def view_centre(cloud: FloatArray, mount: Mount) -> FloatArray:
    """Centroid of a keyframe cloud (levelled frame) in the sensor frame."""
    centre = np.asarray(cloud, dtype=np.float64)[:, :3].mean(axis=0)
    return mount.to_sensor(centre)


def extent(cloud: FloatArray) -> float:
    """RMS horizontal distance of a cloud's points from their centroid, metres."""
    xy = np.asarray(cloud, dtype=np.float64)[:, :2]
    return math.sqrt(float(np.mean(np.sum((xy - xy.mean(axis=0)) ** 2, axis=1))))
