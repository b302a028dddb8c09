"""Candidates by shared structure (solid_ros.core.candidates.covisibility): what a keyframe saw
counts."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from planar_poses import planar_pose as _pose

from solid_ros.core.candidates.covisibility import (
    StructureIndex,
    coarse_structure,
    shared_keyframes,
)
from solid_ros.core.candidates.position import GraphHint
from solid_ros.core.config import SolidConfig
from solid_ros.core.geometry import rot_z

CFG = SolidConfig(graph_candidates=2, graph_candidate_min_path_m=10.0, exclude_recent_frames=5,
                  verify_coarse_voxel_size=1.5, verify_min_overlap=0.35)
SEC = 10**9


def _facade(x0: float, x1: float, y: float) -> npt.NDArray[np.float64]:
    """A building front along x at ``y`` (world frame), on a 1 m grid, 0-4 m high."""
    xs, zs = np.meshgrid(np.arange(x0, x1, 1.0), np.arange(0.0, 4.0, 1.0))
    return np.c_[xs.ravel(), np.full(xs.size, y), zs.ravel()]


def _seen_from(world: npt.NDArray[np.float64], pose: npt.NDArray[np.float64]
               ) -> npt.NDArray[np.float64]:
    out: npt.NDArray[np.float64] = (world - pose[:3, 3]) @ pose[:3, :3]
    return out


def _index(structures: dict[int, npt.NDArray[np.float64]]) -> StructureIndex:
    index = StructureIndex(1000)
    for k, v in structures.items():
        index.add(k, v)
    return index


def _world() -> tuple[GraphHint, StructureIndex, npt.NDArray[np.float64]]:
    """Keyframes 0-39 along x, 2 m apart, looking east (+x) at the facade ahead of them on
    their left (y = 10); keyframes 40-79 drive on to x = 400 and back to x = 160 (nothing of
    theirs kept); the query then stands at x = 120, y = -30, looking north (+y) across the
    street onto the stretch of that facade that keyframes 33-39 saw ahead."""
    xs = [2.0 * i for i in range(40)] + [80.0 + 16.0 * i for i in range(20)] + [
        400.0 - 12.0 * i for i in range(20)]
    poses = np.array([_pose(x) for x in xs])
    structures = {}
    for i in range(40):
        seen = _facade(2.0 * i + 10.0, 2.0 * i + 40.0, 10.0)  # the block ahead, on the left
        structures[i] = _seen_from(seen, poses[i])
    hint = GraphHint.of(np.arange(80), np.arange(80) * SEC, poses, poses, np.eye(4),
                        np.diag([0.01] * 6))
    query = _pose(120.0, -30.0, math.pi / 2)
    return hint, _index(structures), query


def test_the_keyframes_that_saw_the_query_s_structure_are_proposed_best_first() -> None:
    hint, structures, query = _world()
    # The query sees the facade at y = 10 between x = 100 and 130, 40 m ahead of it.
    mine = _seen_from(_facade(100.0, 130.0, 10.0), query)
    got = shared_keyframes(hint, 100, 100 * SEC, query, mine, structures, CFG)
    # Keyframes 35-39 (x = 70-78) saw up to x = 110-118 of it, at least verify_min_overlap
    # of it; the one that saw most comes first, at most graph_candidates of them.
    assert [c.index for c in got] == [39, 38]
    more = shared_keyframes(hint, 100, 100 * SEC, query, mine, structures,
                            CFG.replace(graph_candidates=10))
    assert [c.index for c in more] == [39, 38, 37, 36, 35]
    assert all(c.share >= CFG.verify_min_overlap for c in more)
    assert more[0].share > more[-1].share
    # Placed by the graph: the query 42 m east and 30 m south of keyframe 39, turned left.
    np.testing.assert_allclose(got[0].T_mq[:3, 3], [42.0, -30.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(got[0].T_mq[:3, :3], rot_z(math.pi / 2), atol=1e-12)
    assert got[0].distance_m == math.hypot(42.0, 30.0)
    # None of them stands within 40 m of the query: neither position nor view centre finds
    # them, what they saw does.


def test_excluded_recent_and_unseen_keyframes_are_not_proposed() -> None:
    hint, structures, query = _world()
    mine = _seen_from(_facade(100.0, 130.0, 10.0), query)
    assert [c.index for c in shared_keyframes(hint, 100, 100 * SEC, query, mine, structures,
                                              CFG, exclude=[39])] == [38, 37]
    # Too recent (the exclusion window: 37-39 for query 42), or without a structure kept:
    # not proposed.
    assert [c.index for c in shared_keyframes(hint, 42, 42 * SEC, query, mine, structures,
                                              CFG)] == [36, 35]
    fewer = StructureIndex(39)  # room for 39: keyframe 0 goes when 39 comes
    for k in range(1, 39):
        fewer.add(k, _seen_from(_facade(2.0 * k + 10.0, 2.0 * k + 40.0, 10.0), _pose(2.0 * k)))
    assert 39 not in fewer and len(fewer) == 38
    assert [c.index for c in shared_keyframes(hint, 100, 100 * SEC, query, mine, fewer,
                                              CFG)] == [38, 37]
    # Structure elsewhere (a facade nobody saw): under the coarse overlap bar, nothing.
    elsewhere = _seen_from(_facade(300.0, 330.0, 10.0), query)
    assert shared_keyframes(hint, 100, 100 * SEC, query, elsewhere, structures, CFG) == []
    # Nothing when none is wanted, the query shows no structure or the graph is empty.
    assert shared_keyframes(hint, 100, 100 * SEC, query, mine, structures,
                            CFG.replace(graph_candidates=0)) == []
    assert shared_keyframes(hint, 100, 100 * SEC, query, np.zeros((0, 3)), structures,
                            CFG) == []


def test_a_keyframe_too_far_to_see_the_query_s_structure_is_not_counted() -> None:
    # Two keyframes that saw the same facade: one 20 m from it, one placed 500 m away by a
    # wrong structure of its own (its points reach 30 m): only the first can be counted.
    facade = _facade(0.0, 20.0, 10.0)
    near, far = _pose(0.0, -10.0), _pose(500.0, 0.0)
    poses = np.array([near, far])
    hint = GraphHint.of(np.arange(2), np.arange(2) * SEC, poses, poses, np.eye(4))
    structures = _index({0: _seen_from(facade, near), 1: _seen_from(facade, near)})
    query = _pose(10.0, -10.0)
    got = shared_keyframes(hint, 100, 100 * SEC, query, _seen_from(facade, query), structures,
                           CFG.replace(graph_candidate_min_path_m=0.0))
    assert [c.index for c in got] == [0]


def test_coarse_structure_keeps_the_structure_points_on_the_coarse_grid() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [5.1, 0.0, 0.0], [9.0, 9.0, 0.0]])
    out = coarse_structure(pts, [True, True, True, False], 1.5)
    np.testing.assert_allclose(sorted(out[:, 0]), [0.15, 5.1])
    assert coarse_structure(np.zeros((0, 3)), np.zeros(0, bool), 1.5).shape == (0, 3)


def test_keyframes_just_driven_past_are_left_to_the_odometry() -> None:
    # Keyframes 0-44 along x each saw the facade from 10 m behind to 30 m ahead of them;
    # keyframe 45 (x = 90) sees it from 20 m behind to 5 m ahead. Those of the earlier
    # keyframes that saw it too but lie within two of its view depths (its structure's 90th
    # percentile range) of path are not proposed: the odometry holds them.
    poses = np.array([_pose(2.0 * i) for i in range(46)])
    structures = _index({i: _seen_from(_facade(2.0 * i - 10.0, 2.0 * i + 30.0, 10.0),
                                       poses[i]) for i in range(45)})
    hint = GraphHint.of(np.arange(45), np.arange(45) * SEC, poses[:45], poses[:45],
                        np.eye(4), np.diag([0.01] * 6))
    mine = _seen_from(_facade(70.0, 95.0, 10.0), poses[45])
    depth = float(np.percentile(np.hypot(mine[:, 0], mine[:, 1]), 90.0))
    got = shared_keyframes(hint, 45, 45 * SEC, poses[45], mine, structures,
                           CFG.replace(graph_candidates=45))
    assert got and max(c.index for c in got) == int((90.0 - 2.0 * depth) // 2.0)
    # Had the odometry driven 100 m between keyframes, the ones just passed would be worth a
    # loop, and they share the most.
    odom = np.array([_pose(100.0 * i) for i in range(46)])
    long_way = GraphHint.of(np.arange(45), np.arange(45) * SEC, poses[:45], odom[:45],
                            poses[45] @ np.linalg.inv(odom[45]), np.diag([0.01] * 6))
    again = shared_keyframes(long_way, 45, 45 * SEC, odom[45], mine, structures,
                             CFG.replace(graph_candidates=45))
    assert max(c.index for c in again) == 39 and len(again) > len(got)  # 40-44: too recent


def test_a_keyframe_s_voxels_are_placed_again_only_when_the_graph_moves_it() -> None:
    index = StructureIndex(10)
    index.add(3, _facade(0.0, 10.0, 5.0))
    index.add(4, np.zeros((0, 3)))  # nothing to keep
    assert 3 in index and 4 not in index and len(index) == 1
    pose = _pose(1.0)
    first = index.keys_at(3, pose, 1.5)
    assert index.keys_at(3, pose.copy(), 1.5) is first  # the same pose: cached
    moved = index.keys_at(3, _pose(20.0), 1.5)
    assert moved is not first and not np.array_equal(moved, first)
    index.clear()
    assert len(index) == 0
