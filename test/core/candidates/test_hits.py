"""The pose graph's share of a keyframe's candidates: the known place, the turn check, views,
aligned peers' keyframes by position."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from solid_ros.core.candidates.hits import (
    STRAY_FLOOR_M,
    extent,
    graph_stray,
    graph_turn,
    hit_knows_place,
    hypotheses_kept,
    placed_peer_hits,
    view_centre,
    with_graph_hits,
)
from solid_ros.core.candidates.peers import place_peer
from solid_ros.core.candidates.position import GraphHint
from solid_ros.core.candidates.proposal import Hit, Proposal
from solid_ros.core.candidates.views import KeyframeViews, ViewCentres
from solid_ros.core.config import SolidConfig
from solid_ros.core.database.descriptors import DescriptorDatabase
from solid_ros.core.descriptor.mount import Mount
from solid_ros.core.geometry import matrix_to_vector, rot_z
from solid_ros.core.results import Match

SEC = 1_000_000_000

NO_VIEWS = KeyframeViews(1)  # this session's view centres: none


def test_a_known_place_takes_the_sigma_relative_to_the_match_when_there_is_one() -> None:
    cfg = SolidConfig(verify_coarse_voxel_size=1.5)
    match = Match(0, 3, 0, 3 * SEC, math.nan)
    centre, guess = np.array([15.0, 0.0, 0.0]), np.eye(4)
    # The newest keyframe's own sigma (0.8 m: 3 sigma = 2.4 m) knows no place within 1.5 m ...
    own = Hit(match, math.nan, np.zeros(0, np.float32), 'graph', guess, True, 5.0,
              sigma_m=0.8)
    assert not hit_knows_place(own, centre, cfg, guess)
    # ... the one relative to the match (0.2 m: 0.6 m) does, asked only now.
    asked: list[int] = []
    rel = Hit(match, math.nan, np.zeros(0, np.float32), 'graph', guess, True, 5.0,
              sigma_m=0.8, place_sigma=lambda: asked.append(1) or 0.2)
    assert asked == []
    assert hit_knows_place(rel, centre, cfg, guess)
    assert asked == [1]


def turned_from_guess(hit: Hit, T_mq: np.ndarray) -> bool:
    """The graph_heading rule's refusal."""
    turn, tol = graph_turn(hit, T_mq)
    return not math.isnan(turn) and turn > tol


def test_only_hypotheses_within_the_heading_tolerance_of_the_guess_are_tried() -> None:
    """A start turned farther from the graph's guess could only verify a loop the
    graph_heading rule refuses (or land where the guess, tried first, started)."""
    guess = np.eye(4)
    guess[:3, :3] = rot_z(math.radians(30.0))
    hit = Hit(Match(0, 0, 0, 0, 0.5), math.nan, np.zeros(60, np.float32), 'descriptor', guess,
              True, 10.0)
    yaws = [math.radians(d) for d in (35.0, 210.0, 21.0, -150.0)]
    assert hypotheses_kept(hit, yaws) == [yaws[0], yaws[2]]
    # Without a guess nothing is checked: every hypothesis is a start.
    assert hypotheses_kept(replace(hit, guess=None), yaws) == yaws


def strayed_from_guess(hit: Hit, centre: np.ndarray, cfg: SolidConfig, T_mq: np.ndarray,
                       voxel: float = 0.5) -> bool:
    """The graph_position rule's refusal (``voxel``: the pair's fine grid)."""
    stray, allowed = graph_stray(hit, centre, cfg, T_mq, voxel)
    return not math.isnan(stray) and stray > allowed


def test_a_loop_the_graph_placed_may_not_turn_from_its_guess() -> None:
    """In a symmetric room the registration can fit the place turned by 180 degrees."""
    guess = np.eye(4)
    guess[:3, :3] = rot_z(math.radians(30.0))
    hit = Hit(Match(0, 0, 0, 0, 0.5), math.nan, np.zeros(60, np.float32), 'graph', guess,
               True, 10.0)
    near, flipped = guess.copy(), guess.copy()
    near[:3, :3] = rot_z(math.radians(38.0))
    flipped[:3, :3] = rot_z(math.radians(210.0))
    assert not turned_from_guess(hit, near) and turned_from_guess(hit, flipped)
    # The descriptor's candidates too, where the graph placed them: its heading hypotheses
    # include the turned room (the simulator's room walks, seeds 3 and 6, published a room
    # turned by 90 and by 180 degrees); without a guess nothing is checked.
    desc = replace(hit, source='descriptor')
    assert turned_from_guess(desc, flipped) and not turned_from_guess(desc, near)
    assert not turned_from_guess(replace(desc, guess=None), flipped)


def test_a_loop_the_graph_placed_may_not_stray_from_its_guess() -> None:
    """A slide along a room's shelves: the simulator's tilted room walk (seed 6) published a
    loop 2.1 m from where the graph put the query, 0.07 m sure of it (its right loops lay
    within 0.22 m of the guess)."""
    cfg = SolidConfig()
    match = Match(0, 21, 0, 21 * SEC, math.nan)
    centre, guess = np.array([2.0, 0.0, 0.0]), np.eye(4)
    hit = Hit(match, math.nan, np.zeros(0, np.float32), 'graph', guess, False, 5.0,
              sigma_m=0.5, place_sigma=lambda: 0.07)
    slid, near, turned = guess.copy(), guess.copy(), guess.copy()
    slid[:3, 3] = [0.0, 2.1, 0.0]
    near[:3, 3] = [0.0, 0.22, 0.0]
    # Turned 40 deg about the sensor, the view centre 2 m ahead moves 2 x 2 m x sin(20 deg)
    # = 1.37 m.
    turned[:3, :3] = rot_z(math.radians(40.0))
    assert strayed_from_guess(hit, centre, cfg, slid)
    assert not strayed_from_guess(hit, centre, cfg, near)
    assert strayed_from_guess(hit, centre, cfg, turned)
    # The allowance is the floor plus graph_candidate_sigmas of the relative sigma.
    edge = STRAY_FLOOR_M + cfg.graph_candidate_sigmas * 0.07
    for dev, out in ((edge - 0.01, False), (edge + 0.01, True)):
        moved = guess.copy()
        moved[:3, 3] = [dev, 0.0, 0.0]
        assert strayed_from_guess(hit, centre, cfg, moved) is out
    # Descriptor candidates with a guess too; nothing without a guess or a usable sigma.
    desc = replace(hit, source='descriptor', place_sigma=None)
    assert not strayed_from_guess(desc, centre, cfg, slid)  # its own 0.5 m: 2.5 m allowed
    slid[:3, 3] = [0.0, 2.6, 0.0]
    assert strayed_from_guess(desc, centre, cfg, slid)
    assert not strayed_from_guess(replace(desc, guess=None), centre, cfg, slid)
    assert not strayed_from_guess(replace(desc, sigma_m=math.inf), centre, cfg, slid)


def test_two_tight_keyframes_may_stray_less() -> None:
    """In the simulator's rooms (four walks each on 16 seeds) right loops lay within 0.3 m of
    the graph's guess, and two slides along the shelves 1.0 and 1.7 m from it, the graph 0.34
    and 0.38 m sure, inside the 1 m floor: two tight-space keyframes take half of it."""
    cfg = SolidConfig()
    match = Match(0, 38, 0, 38 * SEC, math.nan)
    centre, guess = np.array([2.0, 0.0, 0.0]), np.eye(4)
    hit = Hit(match, math.nan, np.zeros(0, np.float32), 'descriptor', guess, False, 5.0,
              sigma_m=1.0, place_sigma=lambda: 0.38)
    slid = guess.copy()
    slid[:3, 3] = [0.0, 1.68, 0.0]
    assert not strayed_from_guess(hit, centre, cfg, slid)
    assert strayed_from_guess(hit, centre, cfg, slid, voxel=0.25)  # floor: two voxels


def test_view_centre_and_extent_of_a_cloud() -> None:
    cloud = np.array([[10.0, -1.0, 0.0], [12.0, 1.0, 0.0], [10.0, 1.0, 0.0], [12.0, -1.0, 0.0]])
    np.testing.assert_allclose(view_centre(cloud, Mount(SolidConfig())), [11.0, 0.0, 0.0])
    assert extent(cloud) == math.sqrt(2.0)  # every point 1 m off in x and in y


def _peer_scene(aligned: bool) -> tuple[list[Hit], np.ndarray, float]:
    """Robot 0 drove keyframes 0..29 along x; peer robot 1's keyframes 0..9 stand along y in
    its own map (its odometry in another frame still), its map put 90 deg turned and 20 m
    off in ours; the query stands near the peer's keyframe 6 (map poses known for 0..4
    only: 6 is placed from 4 by the odometry). Returns the hits, keyframe 6's placement and
    its sigma."""
    def pose(x: float, y: float, yaw: float = 0.0) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = rot_z(yaw)
        T[:2, 3] = (x, y)
        return T

    cfg = SolidConfig(session_id=0, exclude_recent_sec=0.0)
    db = DescriptorDatabase(cfg)
    rng = np.random.default_rng(0)
    own = np.array([pose(float(i), 0.0) for i in range(30)])
    seqs = {i: db.add(rng.random(40), rng.random(60), i * SEC) for i in range(30)}
    odom_frame = pose(5.0, -3.0, 0.7)  # the peer's odometry frame in its map
    peer_map = {k: pose(0.0, 2.0 * k, math.pi / 2) for k in range(10)}
    peer_odom = {k: np.linalg.solve(odom_frame, peer_map[k]) for k in range(10)}
    for k in range(10):
        db.add_foreign(1, k, rng.random(40), rng.random(60), k * SEC,
                       matrix_to_vector(peer_odom[k]))
    T_own_peer = pose(20.0, 0.0, math.pi / 2)
    placed = place_peer(1, T_own_peer, np.diag([1e-4] * 3 + [1e-6] * 3),
                        {k: peer_map[k] for k in range(5)}, peer_odom, cfg)
    hint = GraphHint.of(np.arange(30), np.arange(30) * SEC, own, own, np.eye(4),
                        np.diag([1e-4] * 3 + [1e-6] * 3))
    if aligned:
        hint = replace(hint, peers=placed)
    # Keyframe 6 of the peer: (0, 12) in its map, (8, 0) in ours; the query 1 m beside it.
    query = pose(8.0, 1.0)
    cloud = np.array([[5.0, 0.0, 0.0], [5.0, 1.0, 0.0], [6.0, -1.0, 1.0]])
    prop = Proposal(30, 30 * SEC, 30, np.zeros(60), cloud, pose=matrix_to_vector(query))
    prop = replace(prop, hits=tuple(with_graph_hits(prop, hint, cfg, db, seqs, NO_VIEWS,
                                                    Mount(cfg))))
    assert not [h for h in prop.hits if h.match.session == 1]  # they come apart, asked later
    return (placed_peer_hits(prop, hint, cfg, db, Mount(cfg)), T_own_peer @ peer_map[6],
            float(placed.sigma_m[6]))


def test_an_aligned_peers_keyframe_near_the_query_is_a_graph_hit_with_the_placed_guess() -> None:
    hits, P6, sigma6 = _peer_scene(aligned=True)
    assert hits and all(h.match.session == 1 for h in hits)
    assert hits[0].match.index == 6  # nearest first
    h = hits[0]
    assert h.source == 'graph' and not h.near and not h.view
    query = np.eye(4)
    query[:2, 3] = (8.0, 1.0)
    np.testing.assert_allclose(h.guess, np.linalg.solve(P6, query), atol=1e-9)
    # Its sigma holds the placement's (alignment and the peer's drift over 2 keyframes).
    assert 0.0 < sigma6 < h.sigma_m < 1.0 and h.heading_tol_deg < 180.0


def test_an_unaligned_peer_gives_no_hit_by_position() -> None:
    hits, _, _ = _peer_scene(aligned=False)
    assert hits == []


def test_a_peer_without_a_known_map_pose_or_covariance_is_not_placed() -> None:
    odom = {k: np.eye(4) for k in range(3)}
    assert not len(place_peer(1, np.eye(4), None, {0: np.eye(4)}, odom, SolidConfig()).keys)
    assert not len(place_peer(1, np.eye(4), np.eye(6), {7: np.eye(4)}, odom,
                              SolidConfig()).keys)


def test_a_loaded_maps_descriptor_hit_is_judged_by_the_map_not_by_own_keyframes() -> None:
    """Session 1 drove keyframes 0..29 along x and stands at x = 29.5; the loaded map
    (session 0) has keyframe 40 beside it and keyframe 29 far off. The descriptor proposes
    both: their indices are the map's, so own keyframe 29 (near, with a joint marginal to the
    query) says nothing of them. Map 40 is near because the map's near keyframes hold it,
    map 29 is not, and neither asks the graph for a sigma relative to an own keyframe."""
    cfg = SolidConfig(session_id=1, exclude_recent_sec=0.0, graph_candidate_max_radius_m=50.0)
    db = DescriptorDatabase(cfg)
    rng = np.random.default_rng(1)

    def pose(x: float, y: float = 0.0) -> np.ndarray:
        T = np.eye(4)
        T[:2, 3] = (x, y)
        return T

    own = np.array([pose(float(i)) for i in range(30)])
    seqs = {i: db.add(rng.random(40), rng.random(60), i * SEC) for i in range(30)}
    asked: list[int] = []

    def relative(j: int) -> np.ndarray:
        asked.append(j)
        return np.diag([1e-6] * 6)

    placed = {(0, 40): pose(29.5, 1.0), (0, 29): pose(29.5, 40.0)}
    hint = GraphHint.of(np.arange(30), np.arange(30) * SEC, own, own, np.eye(4),
                        np.diag([0.04] * 3 + [1e-4] * 3), relative, placed)
    cloud = np.array([[5.0, 0.0, 0.0], [5.0, 1.0, 0.0], [6.0, -1.0, 1.0]])
    prop = Proposal(30, 30 * SEC, 30, np.zeros(60), cloud, pose=matrix_to_vector(pose(29.5)))
    prop = replace(prop, hits=tuple(Hit(Match(100 + k, k, 0, k * SEC, 0.1), math.nan,
                                        np.zeros(60, np.float32), 'descriptor')
                                    for k in (40, 29)))
    hits = {h.match.index: h for h in with_graph_hits(prop, hint, cfg, db, seqs, NO_VIEWS,
                                                        Mount(cfg)) if h.match.session == 0}
    assert hits[40].guess is not None and hits[40].near and not hits[40].view
    assert hits[29].guess is not None and not hits[29].near and not hits[29].view
    assert hits[40].place_sigma is None and hits[29].place_sigma is None
    assert hits[40].sigma_m == hits[29].sigma_m < 1.0
    for h in hits.values():
        hit_knows_place(h, np.array([5.0, 0.0, 0.0]), cfg, h.guess)
    assert asked == []


def test_a_loaded_maps_keyframe_that_saw_the_place_joins_by_view() -> None:
    """Session 1 stands at x = 29.5 looking along +x (its view centre about 5 m ahead). The
    loaded map's keyframe 40 stands beside it (by position); keyframe 7 stands 30 m on,
    turned round, and saw the same spot (by view): both join, 7 with the graph's guess."""
    cfg = SolidConfig(session_id=1, exclude_recent_sec=0.0)
    db = DescriptorDatabase(cfg)
    rng = np.random.default_rng(2)

    def pose(x: float, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = rot_z(yaw)
        T[:2, 3] = (x, y)
        return T

    own = np.array([pose(float(i)) for i in range(30)])
    seqs = {i: db.add(rng.random(40), rng.random(60), i * SEC) for i in range(30)}
    placed = {(0, 40): pose(29.5, 1.0), (0, 7): pose(60.0, 0.0, math.pi)}
    hint = GraphHint.of(np.arange(30), np.arange(30) * SEC, own, own, np.eye(4),
                        np.diag([0.04] * 3 + [1e-4] * 3), None, placed)
    cloud = np.array([[5.0, 0.0, 0.0], [5.0, 1.0, 0.0], [6.0, -1.0, 1.0]])
    prop = Proposal(30, 30 * SEC, 30, np.zeros(60), cloud, pose=matrix_to_vector(pose(29.5)))
    mount = Mount(cfg)
    map_seqs = {(0, 40): seqs[3], (0, 7): seqs[4]}  # stored scans standing in for the map's
    views = {(0, 40): view_centre(cloud, mount), (0, 7): view_centre(cloud, mount)}
    views[(0, 7)] = np.array([60.0 - 29.5 - views[(0, 7)][0], 0.0, views[(0, 7)][2]])
    hits = {h.match.index: h for h in with_graph_hits(prop, hint, cfg, db, seqs, NO_VIEWS, mount,
                                                        map_seqs, ViewCentres.of(views))
            if h.match.session == 0}
    assert sorted(hits) == [7, 40]
    assert hits[40].near and not hits[40].view
    assert hits[7].view and not hits[7].near and hits[7].source == 'graph'
    assert hits[7].guess is not None
    np.testing.assert_allclose(hits[7].guess[:2, 3], [30.5, 0.0], atol=1e-9)
    # Without the map's view centres only keyframe 40 comes.
    assert [h.match.index for h in with_graph_hits(prop, hint, cfg, db, seqs, NO_VIEWS, mount,
                                                   map_seqs) if h.match.session == 0] == [40]
