"""Candidates by position (solid_ros.core.candidates.position): eligibility, order, pose."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest
from planar_poses import planar_pose as _pose
from planar_poses import position_cov as _cov

from solid_ros.core.candidates.position import (
    GraphHint,
    map_keyframes,
    map_view_keyframes,
    near_keyframes,
    view_keyframes,
)
from solid_ros.core.candidates.tolerance import position_sigma, search_radius
from solid_ros.core.candidates.views import KeyframeViews, ViewCentres
from solid_ros.core.config import SolidConfig
from solid_ros.core.geometry import rot_z

CFG = SolidConfig(graph_candidates=3, graph_candidate_radius_m=5.0, graph_candidate_sigmas=3.0,
                  graph_candidate_max_radius_m=15.0, graph_candidate_min_path_m=10.0,
                  exclude_recent_frames=5)


def _line(n: int, step: float = 1.0) -> GraphHint:
    """Keyframes 0..n-1 one ``step`` apart along x, odometry = corrected, 1 s apart."""
    poses = np.array([_pose(i * step) for i in range(n)])
    return GraphHint.of(np.arange(n), np.arange(n) * 10**9, poses, poses, np.eye(4), _cov(0.0))


def _loop_hint(sigma_m: float = 0.0, correction: npt.NDArray[np.float64] | None = None,
               ) -> GraphHint:
    """A square drive of 40 keyframes, 2 m apart (80 m around), back near the start."""
    xy = ([(2.0 * i, 0.0) for i in range(10)] + [(20.0, 2.0 * i) for i in range(10)]
          + [(20.0 - 2.0 * i, 20.0) for i in range(10)] + [(0.0, 20.0 - 2.0 * i)
                                                            for i in range(10)])
    poses = np.array([_pose(x, y) for x, y in xy])
    return GraphHint.of(np.arange(40), np.arange(40) * 10**9, poses, poses,
                        np.eye(4) if correction is None else correction, _cov(sigma_m))


def test_nearest_first_within_the_radius_at_most_the_count() -> None:
    hint = _loop_hint()
    # Query 40 at (0.5, 1.0), back at the start: keyframes 0 (1.12 m), 39 (1.12 m, but within
    # exclude_recent_frames, as 35-38 are), 1 (1.80 m), 2 (3.64 m), then 3 (5.59 m, too far).
    near = near_keyframes(hint, 40, 40 * 10**9, _pose(0.5, 1.0), CFG)
    assert [c.index for c in near] == [0, 1, 2]
    np.testing.assert_allclose([c.distance_m for c in near],
                               [math.hypot(0.5, 1.0), math.hypot(1.5, 1.0), math.hypot(3.5, 1.0)])
    # The relative pose is the graph's: the query's predicted pose in the keyframe's frame.
    np.testing.assert_allclose(near[0].T_mq[:3, 3], [0.5, 1.0, 0.0], atol=1e-12)
    assert near_keyframes(hint, 40, 40 * 10**9, _pose(0.5, 1.0),
                          CFG.replace(graph_candidates=1))[0].index == 0
    assert near_keyframes(hint, 40, 40 * 10**9, _pose(0.5, 1.0),
                          CFG.replace(graph_candidates=0)) == []


def test_exclusion_window_and_path_rule() -> None:
    hint = _loop_hint()
    q = _pose(0.5, 1.0)
    everything = CFG.replace(graph_candidates=100, graph_candidate_max_radius_m=1000.0,
                             graph_candidate_radius_m=1000.0)
    # Frames: indices < 40 - 5 only.
    got = {c.index for c in near_keyframes(hint, 40, 40 * 10**9, q, everything)}
    assert max(got) == 34
    # Path: keyframe j is eligible when at least 10 m were driven since it (keyframe 39 at
    # (0, 2) is 78 m of path from the start; the query adds 1.1 m).
    got = {c.index for c in near_keyframes(
        hint, 40, 40 * 10**9, q, everything.replace(exclude_recent_frames=0))}
    assert 34 in got and 35 not in got  # 11.1 m and 9.1 m of path
    # Seconds: the detector's exclude_recent_sec applies too.
    got = {c.index for c in near_keyframes(
        hint, 40, 40 * 10**9, q, everything.replace(exclude_recent_sec=20.0))}
    assert max(got) == 20


def test_the_query_is_placed_by_the_correction() -> None:
    # The odometry drifted 6 m along x: the graph's correction brings the query back home.
    correction = _pose(-6.0)
    hint = _loop_hint(correction=correction)
    near = near_keyframes(hint, 40, 40 * 10**9, _pose(6.5, 1.0), CFG)
    assert near and near[0].index == 0
    # Without the correction the query would be at (6.5, 1): nearest keyframe 3.
    plain = near_keyframes(_loop_hint(), 40, 40 * 10**9, _pose(6.5, 1.0), CFG)
    assert plain[0].index == 3


def test_a_larger_covariance_reaches_farther() -> None:
    q = _pose(0.0, -8.0)  # 8 m beyond keyframe 0
    assert near_keyframes(_loop_hint(0.0), 40, 40 * 10**9, q, CFG) == []
    near = near_keyframes(_loop_hint(1.5), 40, 40 * 10**9, q, CFG)  # radius 9.5 m
    assert [c.index for c in near] == [0, 1, 2]  # 8.0, 8.2 and 8.9 m; 3 is 10 m off


def test_a_turned_keyframe_gets_its_relative_heading() -> None:
    poses = np.array([_pose(0.0, 0.0, math.pi / 2)]
                     + [_pose(2.0 * i + 20.0) for i in range(1, 30)])
    hint = GraphHint.of(np.arange(30), np.arange(30) * 10**9, poses, poses, np.eye(4))
    (c, *_) = near_keyframes(hint, 30, 30 * 10**9, _pose(1.0, 0.0), CFG)
    assert c.index == 0
    # The query (heading 0, 1 m along x) in keyframe 0's frame (heading 90 deg).
    np.testing.assert_allclose(c.T_mq[:3, 3], [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(c.T_mq[:3, :3], rot_z(-math.pi / 2), atol=1e-12)


def test_hint_is_read_only_and_finds_poses_by_index() -> None:
    hint = _line(10)
    with pytest.raises(ValueError):
        hint.poses[0, 0, 3] = 1.0
    assert hint.pose_of(4) is not None and hint.pose_of(4)[0, 3] == 4.0  # type: ignore[index]
    assert hint.pose_of(10) is None
    np.testing.assert_allclose(hint.path_m, np.arange(10.0))
    assert near_keyframes(GraphHint.of([], [], np.zeros((0, 4, 4)), np.zeros((0, 4, 4)),
                                       np.eye(4)), 3, 0, np.eye(4), CFG) == []


def _street_hint() -> tuple[GraphHint, dict[int, npt.NDArray[np.float64]]]:
    """A street driven east, 40 keyframes 2 m apart, by a sensor that sees 20 m ahead."""
    poses = np.array([_pose(2.0 * i) for i in range(40)])
    views = {i: np.array([20.0, 0.0, 0.0]) for i in range(40)}
    return GraphHint.of(np.arange(40), np.arange(40) * 10**9, poses, poses, np.eye(4),
                        _cov(0.0)), views


def test_a_keyframe_that_saw_the_place_from_afar_is_proposed() -> None:
    hint, views = _street_hint()
    own = KeyframeViews.of(views)
    # Driving back west at x = 60: the sensor sees x = 40, which keyframe 10 (x = 20) saw;
    # the keyframes beside the query (28-32) looked the other way.
    q = _pose(60.0, 1.0, math.pi)
    near = near_keyframes(hint, 100, 100 * 10**9, q, CFG)
    assert [c.index for c in near] == [30, 29, 31]  # the position rule: beside the query
    seen = view_keyframes(hint, 100, 100 * 10**9, q, [20.0, 0.0, 0.0], 10.0, own, CFG)
    assert [c.index for c in seen] == [10, 9, 11]
    np.testing.assert_allclose([c.distance_m for c in seen], [1.0, math.hypot(2.0, 1.0),
                                                              math.hypot(2.0, 1.0)])
    # The graph's relative pose: 40 m along keyframe 10's x, turned round.
    np.testing.assert_allclose(seen[0].T_mq[:3, 3], [40.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(seen[0].T_mq[:3, :3], rot_z(math.pi), atol=1e-12)
    # A view all round (its centre within its extent of the sensor, as a spinning sensor's):
    # the position rule stands for it, nothing by view.
    assert view_keyframes(hint, 100, 100 * 10**9, q, [20.0, 0.0, 0.0], 25.0, own, CFG) == []
    # A keyframe without a view centre is not proposed; nor anything when none is wanted.
    assert 10 not in {c.index for c in view_keyframes(
        hint, 100, 100 * 10**9, q, [20.0, 0.0, 0.0], 10.0,
        KeyframeViews.of({**views, 10: np.full(3, np.nan)}), CFG)}
    assert view_keyframes(hint, 100, 100 * 10**9, q, [20.0, 0.0, 0.0], 10.0, own,
                          CFG.replace(graph_candidates=0)) == []


def test_a_loaded_maps_keyframe_that_saw_the_place_is_proposed_beside_those_near() -> None:
    street, views = _street_hint()
    # The street as a loaded map (session 0) this session is relocalised in; its own graph
    # holds one keyframe, 100 m off.
    placed = {(0, int(i)): street.poses[k] for k, i in enumerate(street.indices)}
    hint = GraphHint.of([0], [0], [_pose(100.0)], [_pose(100.0)], np.eye(4), _cov(0.0),
                        placed_map=placed)
    map_views = ViewCentres.of({(0, i): c for i, c in views.items()})
    # Driving east at x = 36.5, 1 m aside, seeing 20 m ahead: keyframes 18 and 19 stand near
    # the sensor and saw what it sees; by view they come back too (those by position do not
    # stand for the others in a map) ...
    q = _pose(36.5, 1.0)
    near = map_keyframes(hint, q, CFG)
    assert [(c.session, c.index) for c in near][:2] == [(0, 18), (0, 19)]
    seen = map_view_keyframes(hint, q, [20.0, 0.0, 0.0], 10.0, map_views, CFG)
    assert [(c.session, c.index) for c in seen] == [(0, 18), (0, 19), (0, 17)]
    np.testing.assert_allclose(seen[0].T_mq[:3, 3], [0.5, 1.0, 0.0], atol=1e-12)
    # ... and when it looks back west from x = 60 it sees x = 40, which keyframe 10 saw: not
    # near by position (20 m off), proposed by view, however many the position rule proposes.
    back = _pose(60.0, 1.0, math.pi)
    assert 10 not in {c.index for c in map_keyframes(hint, back, CFG)}
    seen = map_view_keyframes(hint, back, [20.0, 0.0, 0.0], 10.0, map_views, CFG)
    assert [c.index for c in seen] == [10, 9, 11]
    np.testing.assert_allclose(seen[0].T_mq[:3, 3], [40.0, 1.0, 0.0], atol=1e-12)
    # Nothing before the session is placed in the map, for a view all round, without views.
    unplaced = GraphHint.of([0], [0], [_pose(100.0)], [_pose(100.0)], np.eye(4), _cov(0.0))
    assert map_view_keyframes(unplaced, back, [20.0, 0.0, 0.0], 10.0, map_views, CFG) == []
    assert map_view_keyframes(hint, back, [20.0, 0.0, 0.0], 25.0, map_views, CFG) == []
    assert map_view_keyframes(hint, back, [20.0, 0.0, 0.0], 10.0, ViewCentres.of({}),
                              CFG) == []


def test_view_centres_are_found_by_session_and_index_in_bulk() -> None:
    views = ViewCentres.of({(2, 7): [1.0, 2.0, 3.0], (0, 7): [4.0, 5.0, 6.0],
                            (0, 2**31 + 5): [7.0, 8.0, 9.0]})
    keys = np.array([[0, 7], [1, 7], [2, 7], [0, 2**31 + 5], [0, 5]], dtype=np.int64)
    np.testing.assert_array_equal(views.at(keys), [[4.0, 5.0, 6.0], [np.nan] * 3,
                                                  [1.0, 2.0, 3.0], [7.0, 8.0, 9.0],
                                                  [np.nan] * 3])
    assert len(views) == 3 and len(ViewCentres.of({})) == 0
    assert ViewCentres.of({}).at(keys).shape == (5, 3)


def test_no_view_candidates_when_a_keyframe_by_position_saw_the_place() -> None:
    hint, views = _street_hint()
    own = KeyframeViews.of(views)
    # Driving east again at x = 20.5: the keyframes beside it see what it sees.
    q = _pose(20.5, 1.0)
    near = [c.index for c in near_keyframes(hint, 100, 100 * 10**9, q, CFG)]
    assert near[0] == 10
    assert view_keyframes(hint, 100, 100 * 10**9, q, [20.0, 0.0, 0.0], 10.0, own, CFG,
                          near) == []
    # Without them the same keyframes come back by their view.
    assert [c.index for c in view_keyframes(hint, 100, 100 * 10**9, q, [20.0, 0.0, 0.0],
                                            10.0, own, CFG)] == near


def test_the_view_radius_grows_with_the_heading_uncertainty_at_the_view_centre() -> None:
    cov = _cov(0.0)
    cov[3:, 3:] = np.diag([0.0, 0.0, math.radians(1.0) ** 2])
    # The sensor itself is certain; its view 20 m ahead moves by 20 m x 1 deg per sigma.
    assert search_radius(cov, CFG) == pytest.approx(5.0)
    assert search_radius(cov, CFG, view=[20.0, 0.0, 0.0]) == pytest.approx(
        5.0 + 3.0 * 20.0 * math.radians(1.0))
    # The lever is the view centre's offset from the newest keyframe: the step, then the view.
    from solid_ros.core.backend.noise import model_covariance

    step = _pose(10.0, 0.0, math.pi)  # 10 m on, turned round: the view lies 10 m behind
    odo = float(np.linalg.eigvalsh(model_covariance(step, CFG)[:3, :3])[-1])
    assert search_radius(cov, CFG, step, [20.0, 0.0, 0.0]) == pytest.approx(
        5.0 + 3.0 * math.sqrt(odo + (10.0 * math.radians(1.0)) ** 2))
    assert search_radius(cov, CFG, step) == pytest.approx(
        5.0 + 3.0 * math.sqrt(odo + (10.0 * math.radians(1.0)) ** 2))
    assert search_radius(cov, CFG, _pose(10.0), [20.0, 0.0, 0.0]) > search_radius(
        cov, CFG, _pose(10.0))


def test_a_wide_view_reaches_as_far_as_its_extent() -> None:
    street, views = _street_hint()
    own = KeyframeViews.of(views)
    # Keyframes 0-10 only (x = 0-20 m, their views centred at x = 20-40 m). Driving back west
    # at x = 72 the sensor sees around x = 52: 12 m beyond keyframe 10's view, 14 m beyond 9's.
    hint = GraphHint.of(street.indices[:11], street.stamps_ns[:11], street.poses[:11],
                        street.odom[:11], np.eye(4), _cov(0.0))
    q = _pose(72.0, 0.0, math.pi)
    # Beyond the 5 m floor ...
    assert view_keyframes(hint, 200, 200 * 10**9, q, [20.0, 0.0, 0.0], 4.0, own, CFG) == []
    # ... but within a view 14.5 m across (RMS): it saw much of the same stretch.
    seen = view_keyframes(hint, 200, 200 * 10**9, q, [20.0, 0.0, 0.0], 14.5, own, CFG)
    assert [c.index for c in seen] == [10, 9]
    assert search_radius(_cov(0.0), CFG, floor=14.0) == pytest.approx(14.0)
    assert search_radius(_cov(1.0), CFG, floor=14.0) == pytest.approx(15.0)  # the cap
    assert search_radius(_cov(0.0), CFG, floor=2.0) == pytest.approx(5.0)  # the usual floor


def test_the_sigma_to_a_keyframe_is_what_the_two_do_not_share() -> None:
    asked: list[int] = []

    def relative(index: int) -> npt.NDArray[np.float64] | None:
        asked.append(index)
        return _cov(0.05) if index == 3 else None

    poses = np.array([_pose(float(i)) for i in range(6)])
    plain = GraphHint.of(np.arange(6), np.arange(6) * 10**9, poses, poses, np.eye(4), _cov(0.8))
    hint = GraphHint.of(np.arange(6), np.arange(6) * 10**9, poses, poses, np.eye(4), _cov(0.8),
                        relative)
    step, view = _pose(1.0), np.array([15.0, 0.0, 0.0])
    own = position_sigma(_cov(0.8), CFG, step, view)
    assert plain.sigma_to(3, CFG, step, view) == own
    assert hint.sigma_to(3, CFG, step, view) == position_sigma(_cov(0.05), CFG, step, view)
    assert hint.sigma_to(3, CFG, step, view) < own / 4.0
    assert hint.sigma_to(4, CFG, step, view) == own  # the graph could not say: its own
    assert asked == [3, 3, 4]  # asked each time: the detector keeps what it needs
