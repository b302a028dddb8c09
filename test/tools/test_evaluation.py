"""Tests of solid_ros.tools.evaluation against brute-force definitions and hand-worked cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from solid_ros.tools.evaluation import (
    evaluate,
    ground_truth,
    pr_curve,
    recommend_threshold,
    roc_auc,
    sweep_table,
    yaw_error_stats,
)


def _rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _brute_truth(pos, radius, stored, stamps, frames, sec):
    n = len(pos)
    out = np.zeros(n, bool)
    for q in range(n):
        stored_before = [j for j in range(q) if stored[j]]
        eligible = stored_before[:max(len(stored_before) - frames, 0)]
        for j in eligible:
            if stamps[q] - stamps[j] < sec * 1e9:
                continue
            if np.linalg.norm(pos[q] - pos[j]) <= radius:
                out[q] = True
    return out


def test_ground_truth_matches_brute_force() -> None:
    rng = np.random.default_rng(3)
    pos = np.cumsum(rng.normal(size=(120, 3)), axis=0) * [1.0, 1.0, 0.1]
    pos[60:] = pos[:60] + rng.normal(scale=2.0, size=(60, 3))  # revisit
    stored = rng.random(120) > 0.2
    stamps = np.arange(120, dtype=np.int64) * 100_000_000
    for frames, sec in ((0, 0.0), (5, 0.0), (20, 3.0)):
        gt = ground_truth(pos, radius=4.0, stored=stored, stamps_ns=stamps,
                          exclude_frames=frames, exclude_sec=sec, block=7)
        expect = _brute_truth(pos, 4.0, stored, stamps, frames, sec)
        assert gt.has_loop.tolist() == expect.tolist()
        assert expect.sum() > 5
        for q in np.flatnonzero(gt.has_loop):
            j = gt.nearest[q]
            assert stored[j] and j < q and np.linalg.norm(pos[q] - pos[j]) <= 4.0


def test_ground_truth_heading_gate_and_nan() -> None:
    pos = np.array([[0, 0, 0], [100, 0, 0], [0.5, 0, 0], [np.nan, 0, 0]], dtype=float)
    rot = np.stack([_rz(0), _rz(0), _rz(170), _rz(0)])
    assert ground_truth(pos, radius=1.0).has_loop.tolist() == [False, False, True, False]
    gated = ground_truth(pos, radius=1.0, rotations=rot, max_heading_deg=90.0)
    assert gated.has_loop.tolist() == [False, False, False, False]
    assert gated.valid.tolist() == [True, True, True, False]


def test_pr_curve_hand_worked() -> None:
    # distances sorted: 0.1 T, 0.2 F, 0.3 T, 0.3 F, 0.5 T; 4 positives.
    d = [0.3, 0.1, 0.5, 0.2, 0.3]
    c = [True, True, True, False, False]
    curve = pr_curve(d, c, num_positive=4)
    assert curve.thresholds.tolist() == [0.1, 0.2, 0.3, 0.5]
    assert curve.tp.tolist() == [1, 1, 2, 3]
    assert curve.fp.tolist() == [0, 1, 2, 2]
    np.testing.assert_allclose(curve.precision, [1.0, 0.5, 0.5, 0.6])
    np.testing.assert_allclose(curve.recall, [0.25, 0.25, 0.5, 0.75])
    f1 = curve.f1
    assert int(np.argmax(f1)) == 3 and f1[3] == pytest.approx(2 * 0.6 * 0.75 / 1.35)


def test_roc_auc_equals_pair_counting() -> None:
    rng = np.random.default_rng(0)
    scores = rng.integers(0, 6, size=40).astype(float)  # many ties
    labels = rng.random(40) > 0.5
    pos, neg = scores[labels], scores[~labels]
    expect = np.mean([(p > n) + 0.5 * (p == n) for p in pos for n in neg])
    assert roc_auc(scores, labels) == pytest.approx(expect)
    assert math.isnan(roc_auc([1.0, 2.0], [True, True]))


def test_recommend_threshold_lies_between_points() -> None:
    curve = pr_curve([0.0123, 0.0456, 0.2], [True, False, True], 2)
    t = recommend_threshold(curve, 0)
    assert 0.0123 < t < 0.0456 and t == 0.02
    t = recommend_threshold(curve, 2)
    assert t > 0.2
    close = pr_curve([0.10001, 0.10002], [True, False], 1)
    t = recommend_threshold(close, 0)
    assert 0.10001 < t < 0.10002


def test_evaluate_end_to_end() -> None:
    # 8 scans on a line, scans 4..7 revisit 0..3; query 6 matched wrongly.
    x = np.array([0, 10, 20, 30, 0.5, 10.5, 20.5, 30.5])
    pos = np.stack([x, np.zeros(8), np.zeros(8)], axis=1)
    rot = np.stack([_rz(0)] * 4 + [_rz(10), _rz(20), _rz(0), _rz(-30)])
    match = np.array([-1, -1, -1, 0, 0, 1, 3, 3])
    dist = np.array([np.nan, np.nan, np.nan, 0.4, 0.05, 0.1, 0.08, 0.2])
    # detector yaw: exact for 4, 2 degrees off for 5, 1 off for 7
    yaw = np.radians([0, 0, 0, 0, 10, 22, 0, -31])
    accepted = dist < 0.15
    ev = evaluate(pos, match, dist, yaw, accepted, radius=1.0, rotations=rot, exclude_frames=2)
    m = ev.metrics()
    assert ev.truth.has_loop.tolist() == [False] * 4 + [True] * 4
    assert m['recall_at_1'] == pytest.approx(3 / 4)
    # sorted: .05 T, .08 F, .1 T, .2 T, .4 F  -> best F1 at .2: P=3/4, R=3/4
    assert m['f1_max'] == pytest.approx(0.75)
    assert m['f1_max_threshold'] == pytest.approx(0.2)
    assert 0.2 < m['recommended_distance_threshold'] < 0.4
    assert m['zero_fp_threshold'] == pytest.approx(0.05)
    assert m['zero_fp_recall'] == pytest.approx(0.25)
    assert m['roc_auc'] == pytest.approx(4 / 6)  # pos .05 .1 .2 vs neg .08 .4
    assert m['accepted'] == {'count': 3, 'true': 2, 'false': 1, 'precision': 2 / 3,
                             'recall': 0.5}
    ye = m['yaw_error_deg']
    assert ye['count'] == 3 and ye['max'] == pytest.approx(2.0)
    assert ye['mean'] == pytest.approx(1.0) and ye['median'] == pytest.approx(1.0)
    rows = sweep_table(ev, rows=3)
    assert any(r['f1'] == pytest.approx(0.75) for r in rows)
    assert all(r['fp'] == 0 for r in rows if r['distance'] <= 0.05)


def test_yaw_error_stats_and_shapes() -> None:
    s = yaw_error_stats([-1.0, 2.0, 3.0])
    assert s['mean'] == pytest.approx(2.0) and s['max'] == 3.0 and s['count'] == 3
    assert yaw_error_stats([])['mean'] is None
    with pytest.raises(ValueError, match='best_distance has shape'):
        evaluate(np.zeros((3, 3)), [0, 0, 0], [0.1], [0, 0, 0], [True] * 3)


@pytest.mark.parametrize('radius, heading', [(float('nan'), None), (-1.0, None),
                                             (float('inf'), None), (5.0, float('nan')),
                                             (5.0, -10.0), (5.0, 0.0), (5.0, 181.0)])
def test_nan_or_negative_gates_are_refused(radius: float, heading: float | None) -> None:
    pos = np.zeros((4, 3))
    with pytest.raises(ValueError, match='radius|max_heading_deg'):
        ground_truth(pos, radius=radius, rotations=np.tile(np.eye(3), (4, 1, 1)),
                     max_heading_deg=heading)
