"""A peer's map frame in this robot's map, from inter-robot loops that agree (fleet_scenes:
two robots whose maps differ by a random rigid transform, robot 1's drifting)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from drifting_odometry import Drift
from fleet_scenes import TwoRobots

from solid_ros.core.backend.alignment import AlignmentSettings, FleetAlignment, path_lengths
from solid_ros.core.backend.consistency import moved_by
from solid_ros.core.config import SolidConfig
from solid_ros.core.results import LoopCandidate


def _true_loops(scene: TwoRobots, first: int, count: int, step: int = 2,
                by_peer: bool = False) -> list[LoopCandidate]:
    return [scene.loop(q, scene.matching(q), by_peer=by_peer)
            for q in range(first, first + count * step, step)]


def _solve(fa: FleetAlignment, scene: TwoRobots) -> list[str]:
    return [e.kind for e in fa.solve(scene.own_poses(), {1: scene.peer_poses()})]


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_a_peer_is_aligned_by_agreeing_loops_and_unaligned_before(seed: int) -> None:
    scene = TwoRobots(seed=seed, lead=10)
    fa = FleetAlignment(0)
    loops = _true_loops(scene, 12, 10)
    for loop in loops[:3]:
        assert fa.add(loop)
    assert _solve(fa, scene) == [] and not fa.state(1).aligned  # 3 < min_loops
    for loop in loops[3:]:
        fa.add(loop)
    assert _solve(fa, scene) == ['aligned']
    st = fa.state(1)
    assert st.aligned and st.inliers == 10 and st.loops == 10 and st.rival == 0
    assert st.transform is not None and st.covariance is not None
    assert scene.placement_error(st.transform, list(range(2, 22))) < 0.1
    assert np.all(np.linalg.eigvalsh(st.covariance) > 0)
    assert _solve(fa, scene) == []  # the same loops again: no event


def test_a_false_loop_alone_or_as_a_consistent_burst_does_not_move_the_alignment() -> None:
    scene = TwoRobots(seed=3, lead=10)
    fa = FleetAlignment(0)
    for loop in _true_loops(scene, 12, 8):
        fa.add(loop)
    _solve(fa, scene)
    before = fa.state(1).transform
    assert before is not None
    fa.add(scene.loop(40, scene.matching(40), offset=20.0))  # alone, tight covariance
    assert _solve(fa, scene) == []
    assert np.array_equal(fa.state(1).transform, before)
    for q in (60, 61, 62):  # a burst of three that agree with each other (not with the first)
        fa.add(scene.loop(q, scene.matching(q), offset=-20.0))
    assert _solve(fa, scene) == []
    st = fa.state(1)
    assert np.array_equal(st.transform, before) and st.inliers == 8 and st.rival == 3


def test_a_burst_before_any_true_loop_leaves_the_peer_unaligned() -> None:
    scene = TwoRobots(seed=4, lead=10)
    fa = FleetAlignment(0)
    for q in (60, 61, 62):
        fa.add(scene.loop(q, scene.matching(q), offset=20.0))
    assert _solve(fa, scene) == [] and not fa.state(1).aligned
    for loop in _true_loops(scene, 12, 4):  # four true ones outnumber the burst
        fa.add(loop)
    assert _solve(fa, scene) == ['aligned']
    st = fa.state(1)
    assert st.inliers == 4 and st.rival == 3
    assert st.transform is not None
    assert scene.placement_error(st.transform, list(range(2, 10))) < 0.2


def test_an_ambiguous_choice_holds_and_a_larger_set_is_a_jump() -> None:
    scene = TwoRobots(seed=5, lead=10)
    fa = FleetAlignment(0)
    for q in range(60, 68, 2):  # four false loops that agree: the peer is placed 20 m off
        fa.add(scene.loop(q, scene.matching(q), offset=20.0))
    assert _solve(fa, scene) == ['aligned']
    wrong = fa.state(1).transform
    assert wrong is not None and scene.placement_error(wrong, [50, 52]) > 15.0
    for loop in _true_loops(scene, 12, 6):  # 6 against 4: two placements, none chosen
        fa.add(loop)
    assert _solve(fa, scene) == [] and np.array_equal(fa.state(1).transform, wrong)
    for loop in _true_loops(scene, 13, 6):  # 12 against 4: the true set wins, one jump line
        fa.add(loop)
    events = fa.solve(scene.own_poses(), {1: scene.peer_poses()})
    assert [e.kind for e in events] == ['jump'] and 'robot 1 alignment jumped' in \
        events[0].message
    st = fa.state(1)
    assert st.jumps == 1 and st.transform is not None
    assert scene.placement_error(st.transform, list(range(2, 14))) < 0.2


def test_the_peers_own_loops_align_it_from_this_side_too() -> None:
    scene = TwoRobots(seed=6, lead=10)
    mine, theirs = FleetAlignment(0), FleetAlignment(1)
    for loop in _true_loops(scene, 12, 6, by_peer=True):  # published by robot 1
        assert mine.add(loop, by=1)
        assert theirs.add(loop)
    _solve(mine, scene)
    theirs.solve(scene.peer_poses(), {0: scene.own_poses()})
    a, b = mine.state(1).transform, theirs.state(0).transform
    assert a is not None and b is not None
    dist, deg = moved_by(a, np.linalg.inv(b), scene.peer[:20, :3, 3])
    assert dist < 0.05 and deg < 0.1


@pytest.mark.parametrize('drift, together', [(Drift(scale=0.005, yaw_bias_deg_per_m=0.01), 12),
                                              (Drift(), 6)])
def test_drifting_maps_align_within_their_drift(drift: Drift, together: int) -> None:
    # Loops of two revisits 100 m apart on robot 1's path: within the odometry model (0.5 %,
    # 0.01 deg/m) they agree; at 5 % and 0.055 deg/m they disagree by more than the model
    # allows but place robot 1 within 3 m of each other, so the larger (here the first) set
    # decides: not a rival.
    scene = TwoRobots(seed=7, lead=10, drift=drift)
    fa = FleetAlignment(0, AlignmentSettings.from_config(SolidConfig()))
    for loop in _true_loops(scene, 12, 6) + _true_loops(scene, 110, 6):
        fa.add(loop)
    _solve(fa, scene)
    st = fa.state(1)
    assert st.aligned and st.inliers >= together, st
    assert st.transform is not None
    assert scene.placement_error(st.transform, list(range(2, 112, 10))) < 1.5


def test_bad_loops_are_refused_and_memory_is_bounded() -> None:
    scene = TwoRobots(seed=8, lead=10)
    fa = FleetAlignment(0, AlignmentSettings(max_loops=20))
    good = scene.loop(20, 10)
    assert not fa.add(LoopCandidate(5, 3, 5, 3, 0, 0.1, 0.0, 1.0, True))  # own session
    assert not fa.add(LoopCandidate(5, 3, 5, 3, 1, 0.1, 0.0, 1.0, False))  # not verified
    assert not fa.add(LoopCandidate(5, 3, 5, 3, 1, 0.1, 0.0, 1.0, True))  # NaN covariance
    assert not fa.add(good, by=2)  # robot 2's loop against robot 1: not about this robot
    assert fa.add(good) and not fa.add(good)  # held once
    for q in range(30, 130):
        fa.add(scene.loop(q, scene.matching(q)))
    assert fa.state(1).loops == 20
    assert fa.peers() == [1] and fa.state(7).peer == 7 and not fa.state(7).aligned
    # Paths given for the peer's keyframes (a node gets only those of its loops) stand for
    # the path along its poses; a keyframe without a path is left out.
    linked = {k: scene.peer[k] for k in range(0, 120)}
    paths = {1: {k: float(k) for k in range(0, 120)}}
    assert [e.kind for e in fa.solve(scene.own_poses(), {1: linked}, paths)] == ['aligned']
    # A peer without poses yet stays as it is; one forgotten is gone.
    assert fa.solve(scene.own_poses(), {}) == []
    fa.forget(1)
    assert fa.peers() == [] and fa.states() == []


def test_path_lengths_follow_the_index_order() -> None:
    poses = {i: np.eye(4) for i in (3, 1, 2)}
    for i, x in ((1, 0.0), (2, 3.0), (3, 3.0)):
        poses[i][1, 3] = x
    poses[3][0, 3] = 4.0
    assert path_lengths(poses) == {1: 0.0, 2: 3.0, 3: 7.0}
    assert path_lengths({}) == {}
    assert AlignmentSettings.from_config(SolidConfig(), min_loops=6).min_loops == 6
    assert AlignmentSettings.from_config(SolidConfig()).drift.rot == pytest.approx(
        math.radians(SolidConfig().backend_odom_rot_sigma_deg))
