"""The pose graph's share of a keyframe's candidates: the known place, the turn check, views."""

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
    view_centre,
)
from solid_ros.core.candidates.proposal import Hit
from solid_ros.core.config import SolidConfig
from solid_ros.core.descriptor.mount import Mount
from solid_ros.core.geometry import rot_z
from solid_ros.core.results import Match

SEC = 1_000_000_000


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
