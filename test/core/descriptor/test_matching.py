"""Cosine distance and heading: conventions, sub-bin accuracy on real rotated scans."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from solid_ros import SolidConfig, cosine_distance, describe, estimate_yaw
from solid_ros.core.descriptor.matching import heading_hypotheses
from solid_ros.formats.pointfiles import read_kitti_bin, read_pcd


def rotate(points: np.ndarray, yaw: float) -> np.ndarray:
    """Return points turned CCW by yaw radians about +z."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = points.copy()
    out[:, 0] = c * points[:, 0] - s * points[:, 1]
    out[:, 1] = s * points[:, 0] + c * points[:, 1]
    return out


def angle_error_deg(a: float, b: float) -> float:
    return abs(math.degrees(math.remainder(a - b, 2 * math.pi)))


def test_cosine_distance_range_and_degenerate_vectors() -> None:
    a = np.array([1.0, 2.0, 3.0])
    assert cosine_distance(a, a) == pytest.approx(0.0, abs=1e-12)
    assert cosine_distance(a, 2 * a) == pytest.approx(0.0, abs=1e-12)
    assert cosine_distance(a, -a) == pytest.approx(2.0)
    assert cosine_distance([1, 0], [0, 1]) == pytest.approx(1.0)
    assert cosine_distance(np.zeros(3), np.zeros(3)) == 0.0
    assert cosine_distance(np.zeros(3), a) == 1.0
    assert not math.isnan(cosine_distance(np.zeros(40), np.zeros(40)))


def test_yaw_whole_bin_shift_and_sign() -> None:
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, 60)
    # The candidate sees the query's bin i at bin i + 5: candidate = Rz(+30 deg) query.
    assert math.degrees(estimate_yaw(a, np.roll(a, 5))) == pytest.approx(30.0, abs=1e-9)
    assert math.degrees(estimate_yaw(a, np.roll(a, -5))) == pytest.approx(-30.0, abs=1e-9)
    assert estimate_yaw(a, a) == pytest.approx(0.0, abs=1e-12)
    assert math.degrees(estimate_yaw(a, np.roll(a, 30))) == pytest.approx(180.0)


def test_yaw_of_zero_signature_is_zero_and_shapes_are_checked() -> None:
    assert estimate_yaw(np.zeros(60), np.ones(60)) == 0.0
    with pytest.raises(ValueError):
        estimate_yaw(np.ones(60), np.ones(40))


def test_yaw_convention_on_a_synthetic_scene() -> None:
    # A lone wall seen at +x by the candidate; the query sensor is turned +40 deg, so it
    # sees the wall at azimuth -40 deg, and p_candidate = Rz(+40 deg) p_query.
    rng = np.random.default_rng(2)
    wall = np.column_stack([np.full(3000, 20.0), rng.uniform(-3, 3, 3000),
                            rng.uniform(-1.5, 0.5, 3000)])
    cfg = SolidConfig(voxel_size=0.0)
    cand = describe(wall, cfg)
    query = describe(rotate(wall, math.radians(-40.0)), cfg)
    assert math.degrees(estimate_yaw(query.a_solid, cand.a_solid)) == pytest.approx(40, abs=1.5)


def _yaw_errors(data: Path, cfg: SolidConfig, yaws_deg: np.ndarray) -> np.ndarray:
    errors = []
    for frame in (313, 314, 315):
        scan = read_pcd(data / 'kitti' / 'pcd' / f'000{frame}.pcd')
        cand = describe(scan, cfg)
        for yaw in np.radians(yaws_deg):
            query = describe(rotate(scan, -yaw), cfg)  # query sensor turned by +yaw
            errors.append(angle_error_deg(estimate_yaw(query.heading, cand.heading), yaw))
    return np.array(errors)


def test_heading_of_rotated_real_scans_is_sub_bin_accurate(shared_data: Path) -> None:
    # 25 yaws over (-180, 180], none a multiple of the 6-degree bin.
    yaws = np.linspace(-177.3, 178.1, 25)
    assert not np.any(np.isclose(np.mod(yaws, 6.0), 0.0))
    errors = _yaw_errors(shared_data, SolidConfig(), yaws)
    assert errors.mean() < 1.0, errors
    assert errors.max() < 3.0, errors


@pytest.mark.parametrize('weight', ['count', 'range'])
def test_heading_with_90_degree_fov(shared_data: Path, weight: str) -> None:
    yaws = np.linspace(-29.3, 28.9, 13)
    cfg = SolidConfig(fov_width_deg=90.0, heading_weight=weight)
    errors = _yaw_errors(shared_data, cfg, yaws)
    assert errors.mean() < 2.0, errors


def test_hypotheses_start_with_estimate_yaw() -> None:
    rng = np.random.default_rng(4)
    for _ in range(50):
        a = rng.uniform(0, 1, 60)
        b = np.roll(a, int(rng.integers(60))) + rng.normal(0, 0.1, 60)
        hyps = heading_hypotheses(a, b, 5)
        assert 1 <= len(hyps) <= 5
        assert hyps[0][0] == estimate_yaw(a, b)
        for yaw, cost in hyps:
            assert -math.pi < yaw <= math.pi and 0.0 <= cost <= 4.0
        yaws = [h[0] for h in hyps]
        assert len(set(yaws)) == len(yaws)


def test_hypotheses_find_both_headings_of_a_symmetric_scene() -> None:
    # A signature that repeats every 180 degrees (a straight corridor) has two equally good
    # headings: the best is the true one (-ish), the second 180 degrees away.
    rng = np.random.default_rng(5)
    half = rng.uniform(0, 1, 30)
    a = np.concatenate([half, half]) + rng.normal(0, 0.01, 60)
    b = np.roll(a, 7)  # candidate = query turned by +42 degrees
    hyps = heading_hypotheses(a, b, 3)
    degs = sorted(math.degrees(y) for y, _ in hyps[:2])
    assert degs == pytest.approx([-138.0, 42.0], abs=0.05)  # the noise breaks the tie
    assert hyps[1][1] < 0.05 and len(hyps) == 3 and hyps[2][1] > hyps[1][1]


def test_hypotheses_are_sub_bin_refined() -> None:
    # A smooth signature turned by 2.5 bins (15 degrees): linear interpolation between the
    # neighbouring shifts recovers it exactly.
    x = np.arange(60)
    a = 2.0 + np.sin(2 * np.pi * x / 60) + 0.5 * np.cos(6 * np.pi * x / 60)
    b = 0.5 * (np.roll(a, 2) + np.roll(a, 3))
    yaw, cost = heading_hypotheses(a, b, 1)[0]
    assert math.degrees(yaw) == pytest.approx(15.0, abs=1e-9)
    assert cost < 1e-6  # the blend of normalised neighbours is not exactly b


def test_hypotheses_of_degenerate_curves() -> None:
    a = np.ones(60)
    flat = heading_hypotheses(a, a, 3)  # flat cost: one hypothesis
    assert len(flat) == 1 and flat[0] == pytest.approx((0.0, 0.0), abs=1e-12)
    assert heading_hypotheses(np.zeros(60), a, 3) == []
    assert heading_hypotheses(a, a, 0) == []
    with pytest.raises(ValueError):
        heading_hypotheses(np.ones(60), np.ones(40), 2)
    # A plateau through shift 0 counts once, at shift 0 (as argmin picks).
    cost_like = np.zeros(60)
    cost_like[0] = 1.0
    hyps = heading_hypotheses(cost_like, np.roll(cost_like, 59), 4)
    assert math.degrees(hyps[0][0]) == pytest.approx(-6.0)
    assert len(hyps) == 1



def test_yaw_agrees_with_the_direct_squared_difference_search() -> None:
    # The correlation form of the cost must pick the shift and fraction the definition does:
    # the squared difference of the normalised signatures, neighbours blended.
    rng = np.random.default_rng(8)
    idx = (np.arange(60)[None, :] - np.arange(60)[:, None]) % 60
    for _ in range(300):
        a = rng.uniform(0, 1, 60) ** 3
        b = np.roll(a, int(rng.integers(60))) + rng.normal(0, 0.05, 60)
        u = (a / np.linalg.norm(a))[idx]
        v = b / np.linalg.norm(b)
        cost = ((u - v) ** 2).sum(axis=1)
        s = int(np.argmin(cost))
        best, frac = cost[s], 0.0
        for step in (1, -1):
            d = u[(s + step) % 60] - u[s]
            f = min(max(float((v - u[s]) @ d) / float(d @ d), 0.0), 1.0)
            if cost[s] - f * f * float(d @ d) < best:
                best, frac = cost[s] - f * f * float(d @ d), step * f
        want = math.radians(math.remainder((s + frac) * 6.0, 360.0))
        assert angle_error_deg(estimate_yaw(a, b), want) < 1e-9
        assert heading_hypotheses(a, b, 1)[0][1] == pytest.approx(best, abs=1e-12)


def test_overlap_mode_is_the_full_search_when_both_views_go_all_around() -> None:
    rng = np.random.default_rng(9)
    for _ in range(50):
        a = rng.uniform(0.1, 1, 60)
        b = np.roll(a, int(rng.integers(60))) * rng.uniform(0.9, 1.1, 60)
        assert estimate_yaw(a, b, 'overlap') == estimate_yaw(a, b)
        assert heading_hypotheses(a, b, 3, 'overlap') == heading_hypotheses(a, b, 3)


def test_overlap_mode_checks_its_arguments_and_falls_back() -> None:
    with pytest.raises(ValueError, match='mode'):
        estimate_yaw(np.ones(60), np.ones(60), 'partial')
    assert estimate_yaw(np.zeros(60), np.ones(60), 'overlap') == 0.0
    assert heading_hypotheses(np.zeros(60), np.ones(60), 2, 'overlap') == []
    # Views of two bins each never share the 4 bins (24 deg) asked for: the full search.
    a = np.zeros(60)
    a[[0, 1]] = [1.0, 2.0]
    b = np.roll(a, 10)
    assert estimate_yaw(a, b, 'overlap') == estimate_yaw(a, b)


def _narrow_pairs(data: Path, cfg: SolidConfig, yaws_deg: list[float]) -> list[tuple[
        np.ndarray, np.ndarray, float]]:
    # Real KITTI 00 scans turned by yaw and then clipped to the view (what a sensor turned by
    # yaw sees), against the previous scan (about 1 m back) seen with the sensor unturned.
    scans = [read_kitti_bin(data / 'kitti' / 'seq00_frames' / f'00000{i}.bin')[:, :3]
             for i in range(6)]
    out = []
    for prev, cur in zip(scans, scans[1:]):
        cand = describe(prev, cfg).heading
        for yaw in np.radians(yaws_deg):
            out.append((describe(rotate(cur, -yaw), cfg).heading, cand, float(yaw)))
    return out


@pytest.mark.parametrize('width,weight,yaws', [
    (90.0, 'range', [-48.0, -43.0, 41.0, 46.0]), (70.0, 'count', [-38.0, -31.0, 33.0, 37.0])])
def test_overlap_mode_finds_headings_beyond_half_the_view(
        shared_data: Path, width: float, weight: str, yaws: list[float]) -> None:
    # Turned by more than half the view, the two views share only part of it: the full
    # search lines up the views (the paper's failure), the overlap search the scenes.
    cfg = SolidConfig(fov_width_deg=width, heading_weight=weight)
    pairs = _narrow_pairs(shared_data, cfg, yaws)
    full = [angle_error_deg(estimate_yaw(q, c), y) for q, c, y in pairs]
    over = [angle_error_deg(estimate_yaw(q, c, 'overlap'), y) for q, c, y in pairs]
    assert np.mean(over) < 3.0, over
    assert np.mean(full) > 10.0, full
    for q, c, _ in pairs:
        assert heading_hypotheses(q, c, 3, 'overlap')[0][0] == estimate_yaw(q, c, 'overlap')


def test_overlap_mode_keeps_small_headings_sub_bin_accurate(shared_data: Path) -> None:
    cfg = SolidConfig(fov_width_deg=90.0, heading_weight='range')
    pairs = _narrow_pairs(shared_data, cfg, [-17.3, -4.1, 2.9, 13.7, 22.1])
    over = [angle_error_deg(estimate_yaw(q, c, 'overlap'), y) for q, c, y in pairs]
    assert np.mean(over) < 1.0, over
