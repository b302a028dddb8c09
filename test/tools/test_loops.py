"""Tests of solid_ros.tools.loops: pose errors, precision/recall of loops, the overlap sweep."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from solid_ros.core.geometry import rot_z
from solid_ros.tools.loops import (
    LoopRecord,
    overlap_sweep,
    pose_error,
    revisit_recall,
    revisits,
    score_loops,
)


def _T(x: float, yaw_deg: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_z(math.radians(yaw_deg))
    T[0, 3] = x
    return T


def _rec(q: int, m: int, *, published: bool = True, verified: bool = True, ov: float = 0.6,
         te: float = 0.1, re: float = 0.5, source: str = 'descriptor') -> LoopRecord:
    return LoopRecord(q, m, 0, published, verified, 'verified' if verified else 'overlap', ov,
                      0.05, te, re, 2.0, source)


def test_pose_error_measures_the_difference() -> None:
    te, re = pose_error(_T(2.0, 10.0), _T(2.0, 10.0))
    assert te == pytest.approx(0.0, abs=1e-12) and re == pytest.approx(0.0, abs=1e-6)
    te, re = pose_error(_T(2.5, 14.0), _T(2.0, 10.0))
    assert re == pytest.approx(4.0) and te == pytest.approx(0.5, abs=0.01)
    assert all(math.isnan(v) for v in pose_error(np.full((4, 4), np.nan), _T(0.0, 0.0)))


def test_score_counts_pose_correct_loops_and_queries() -> None:
    positives = np.zeros(10, bool)
    positives[[5, 6, 7, 8]] = True
    records = [_rec(5, 1), _rec(5, 2, te=1.5), _rec(6, 2, re=4.0), _rec(9, 3),
               _rec(7, 1, published=False, verified=False)]
    s = score_loops(records, positives)
    assert (s['published'], s['correct'], s['false']) == (4, 2, 2)
    assert s['precision'] == 0.5
    assert s['recall'] == 0.25  # only query 5 of the four positives has a correct loop
    assert s['trans_err_m']['count'] == 2 and s['reasons'] == {'verified': 4, 'overlap': 1}


def test_sweep_recommends_the_least_overlap_reaching_the_target() -> None:
    positives = np.ones(10, bool)
    records = [_rec(1, 0, ov=0.40, te=3.0), _rec(2, 0, ov=0.55), _rec(3, 0, ov=0.7),
               _rec(4, 0, ov=0.36, verified=False)]
    sweep = overlap_sweep(records, positives, 0.35)
    assert sweep['recommended'] == 0.41
    rows = {r['threshold']: r for r in sweep['rows']}
    assert (rows[0.35]['tp'], rows[0.35]['fp']) == (2, 1)
    assert (rows[0.41]['precision'], rows[0.41]['recall']) == (1.0, 0.2)
    assert overlap_sweep([_rec(1, 0, te=3.0)], positives, 0.35,
                         target_precision=1.0)['recommended'] is None


def test_sweep_at_the_configured_overlap_is_what_was_published() -> None:
    positives = np.zeros(8, bool)
    positives[[2, 3, 4, 5]] = True
    # Query 3 published two places (max_candidates 2): one right, one wrong.
    records = [_rec(2, 0, ov=0.5), _rec(3, 0, ov=0.6), _rec(3, 1, ov=0.45, te=2.0),
               _rec(4, 1, ov=0.5, re=5.0), _rec(6, 0, ov=0.9),
               _rec(5, 0, published=False, verified=False, ov=0.3)]
    score = score_loops(records, positives)
    sweep = overlap_sweep(records, positives, 0.35)
    first = sweep['rows'][0]
    assert first['threshold'] == 0.35
    assert (first['tp'], first['fp']) == (score['correct'], score['false']) == (3, 2)
    assert first['precision'] == score['precision'] and first['recall'] == score['recall']
    # 0.51 drops both false loops (0.45 and 0.5) and query 2's right one.
    assert sweep['recommended'] == 0.51
    rows = {r['threshold']: r for r in sweep['rows']}
    assert (rows[0.51]['tp'], rows[0.51]['fp'], rows[0.51]['recall']) == (2, 0, 0.25)
    # A lower target accepts the configured value.
    assert overlap_sweep(records, positives, 0.35, target_precision=0.6)['recommended'] == 0.35


def test_sweep_ignores_attempts_that_failed_another_test() -> None:
    positives = np.ones(4, bool)
    # A large overlap that failed a later test (e.g. conflict) never counts.
    failed = LoopRecord(1, 0, 0, False, False, 'conflict', 0.95, 0.05, 5.0, 20.0, 9.0)
    sweep = overlap_sweep([failed, _rec(2, 0, ov=0.6)], positives, 0.35)
    assert [(r['threshold'], r['tp'], r['fp']) for r in sweep['rows']] == [(0.35, 1, 0),
                                                                          (0.61, 0, 0)]
    assert sweep['recommended'] == 0.35


def test_pose_error_follows_the_published_convention() -> None:
    # P_match, P_query world poses; T_ref = inv(P_match) @ P_query maps query points into
    # the match frame: a point seen by the query lands where the match saw it.
    p_match, p_query = _T(10.0, 30.0), _T(12.0, 75.0)
    T_ref = np.linalg.solve(p_match, p_query)
    point_q = np.array([3.0, -1.0, 0.5, 1.0])
    world = p_query @ point_q
    assert np.allclose(T_ref @ point_q, np.linalg.solve(p_match, world))
    assert pose_error(T_ref, T_ref) == pytest.approx((0.0, 0.0), abs=1e-6)
    te, re = pose_error(np.linalg.inv(T_ref), T_ref)  # the inverse convention is caught
    assert te > 1.0 and re > 3.0


def test_revisits_need_an_earlier_keyframe_near_after_the_path() -> None:
    # Out 20 m along x and back, then 20 m along y: keyframes every 2 m.
    xs = [(2.0 * i, 0.0) for i in range(11)] + [(20.0 - 2.0 * i, 0.5) for i in range(1, 11)]
    xs += [(0.0, 2.0 * i) for i in range(1, 4)]
    pos = np.array([(x, y, 0.0) for x, y in xs])
    rev = revisits(pos)  # within 5 m after at least 30 m of path
    # Keyframe 17 at (6, 0.5) is 2.1 m from keyframe 2 after 32.1 m; 16 at (8, 0.5) is 6 m from
    # keyframes 0-1, the only ones 30 m of path before it. 23 at (0, 6) is 5.5 m or more from
    # every earlier one.
    assert rev[17] and not rev[:17].any()
    assert rev[17:23].all() and not rev[23]
    assert not revisits(pos, min_path_m=50.0).any()
    assert revisits(pos, min_path_m=10.0)[12]  # (18, 0.5): 4 m of path after keyframe 10
    # Unknown positions are no revisits and do not break the path of the others.
    holes = pos.copy()
    holes[5] = np.nan
    got = revisits(holes)
    assert not got[5] and got[18]
    # Headings: turned back, the return legs see the other way.
    rot = np.array([np.eye(3)] * 11 + [rot_z(math.pi)[:3, :3]] * 10 + [np.eye(3)] * 3)
    turned = revisits(pos, rotations=rot, max_heading_deg=45.0)
    assert not turned[:21].any() and turned[21:23].all() and not turned[23]


def test_revisit_recall_counts_revisiting_keyframes_with_a_correct_loop() -> None:
    rev = np.zeros(10, bool)
    rev[[6, 7, 8, 9]] = True
    records = [_rec(6, 1), _rec(6, 2), _rec(7, 1, te=2.0), _rec(8, 3, published=False),
               _rec(3, 0), _rec(9, 4, source='graph')]
    out = revisit_recall(records, rev)
    assert out == {'revisiting': 4, 'found': 2, 'recall': 0.5}
    assert revisit_recall([], np.zeros(3, bool))['recall'] is None
    s = score_loops(records, rev)
    assert s['by_source'] == {'descriptor': {'published': 4, 'correct': 3},
                              'graph': {'published': 1, 'correct': 1}}


def test_a_pose_nothing_was_registered_on_is_not_measured() -> None:
    # Two views that share nothing keep the graph's guess: right with exact odometry, yet no
    # registration measured it (quickshack: 57 such pairs counted as right poses refused).
    unmoved = LoopRecord(35, 4, 0, False, False, 'coarse_overlap', math.nan, 0.1, 0.0, 0.0,
                         0.3, coarse_overlap=0.0)
    low = replace(unmoved, coarse_overlap=0.2)
    assert unmoved.correct(1.0, 3.0) and not unmoved.measured
    assert low.measured and _rec(1, 0, ov=0.6).measured  # NaN: no coarse stage recorded
