"""Tests of the loop detector: acceptance rules, yaw, keyframe gating, and the hku1 revisit."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from solid_ros.core.config import SolidConfig
from solid_ros.core.detector import LoopCandidate, LoopDetector
from solid_ros.core.errors import ConfigError, SolidError

SEC = 1_000_000_000


def place(seed: int, n: int = 6000) -> npt.NDArray[np.float64]:
    """A random 360-degree scene: walls of boxes at 5-60 m, ground and clutter."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    r = rng.choice(rng.uniform(5, 60, 12), n) + rng.normal(0, 0.5, n)
    z = rng.uniform(-1.7, 3.0, n)
    return np.stack([r * np.cos(az), r * np.sin(az), z], axis=1)


def rotz(points: npt.NDArray[np.float64], deg: float) -> npt.NDArray[np.float64]:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return points @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T


def _cfg(**kw: object) -> SolidConfig:
    base = {'exclude_recent_frames': 2, 'distance_threshold': 0.02, 'search': 'brute',
            'margin_neighbourhood': 1, 'verify': False}
    base.update(kw)
    return SolidConfig().replace(**base)


def _run(det: LoopDetector, clouds: list[npt.NDArray[np.float64]]) -> list[list[LoopCandidate]]:
    return [det.process(c, i * SEC) for i, c in enumerate(clouds)]


def test_revisit_is_found_with_fields_and_yaw() -> None:
    det = LoopDetector(_cfg())
    out = _run(det, [place(i) for i in range(6)] + [rotz(place(1), 30.0)])
    assert all(not c for c in out[:-1])
    (cand,) = out[-1]
    assert (cand.query_index, cand.match_index, cand.match_session) == (6, 1, 0)
    assert (cand.query_stamp_ns, cand.match_stamp_ns) == (6 * SEC, 1 * SEC)
    assert 0.0 <= cand.distance < 0.02
    # p_match = Rz(yaw) p_query and the query is the match turned by +30 deg.
    assert math.degrees(cand.yaw) == pytest.approx(-30.0, abs=2.0)
    assert cand.margin > 0.1
    assert set(cand.to_dict()) == {'query_index', 'match_index', 'query_stamp_ns',
                                   'match_stamp_ns', 'match_session', 'distance', 'yaw',
                                   'margin', 'verified', 'pose', 'fitness', 'rmse',
                                   'covariance', 'reason', 'overlap', 'conflict', 'constraint',
                                   'spread'}
    # Descriptor only: the pose is the yaw guess, nothing verified.
    assert (cand.verified, cand.reason) == (False, 'descriptor')
    assert cand.pose[:3] == (0.0, 0.0, 0.0) and math.isnan(cand.fitness)


def test_recent_scans_are_excluded() -> None:
    clouds = [place(0), place(1), place(0)]
    assert _run(LoopDetector(_cfg(exclude_recent_frames=2)), clouds)[-1] == []
    assert _run(LoopDetector(_cfg(exclude_recent_frames=1)), clouds)[-1][0].match_index == 0
    det = LoopDetector(_cfg(exclude_recent_frames=0, exclude_recent_sec=2.5))
    assert _run(det, clouds)[-1] == []
    det = LoopDetector(_cfg(exclude_recent_frames=0, exclude_recent_sec=1.5))
    assert _run(det, clouds)[-1][0].match_index == 0


def test_threshold_is_strict() -> None:
    clouds = [place(0), place(1), place(2), place(0) * 1.02]
    d = _run(LoopDetector(_cfg(distance_threshold=1.0)), clouds)[-1][0].distance
    assert d > 0.0
    assert _run(LoopDetector(_cfg(distance_threshold=d)), clouds)[-1] == []
    assert _run(LoopDetector(_cfg(distance_threshold=d * 1.01)), clouds)[-1]


def test_margin_test_rejects_ambiguous_places() -> None:
    # Place 0 seen at indices 0 and 3: two distinct stored places equally good.
    clouds = [place(0), place(1), place(2), place(0), place(4), place(5), place(0)]
    loose = _run(LoopDetector(_cfg()), clouds)[-1]
    assert len(loose) == 1 and loose[0].margin == pytest.approx(0.0, abs=1e-6)
    assert _run(LoopDetector(_cfg(min_margin=0.01)), clouds)[-1] == []
    # Two distinct places reported when asked for.
    both = _run(LoopDetector(_cfg(max_candidates=3)), clouds)[-1]
    assert sorted(c.match_index for c in both) == [0, 3]


def test_margin_ignores_the_neighbourhood_of_the_best() -> None:
    clouds = [place(0), place(0) * 1.001, place(2), place(3), place(4), place(0)]
    cand = _run(LoopDetector(_cfg(margin_neighbourhood=1, min_margin=0.05)), clouds)[-1]
    assert len(cand) == 1 and cand[0].margin > 0.05
    far = _run(LoopDetector(_cfg(margin_neighbourhood=0, min_margin=0.05)), clouds)[-1]
    assert far == []


def test_min_loop_gap() -> None:
    clouds = [place(i) for i in range(4)] + [place(0), place(1), place(2), place(3)]
    hits = [bool(c) for c in _run(LoopDetector(_cfg(min_loop_gap=2)), clouds)]
    assert hits == [False] * 4 + [True, False, True, False]
    hits = [bool(c) for c in _run(LoopDetector(_cfg()), clouds)]
    assert hits == [False] * 4 + [True] * 4


def test_keyframe_gating_by_time() -> None:
    det = LoopDetector(_cfg(keyframe_min_sec=1.0))
    cloud = place(0)
    for t in (0.0, 0.4, 0.9, 1.0, 1.5, 2.2):
        det.process(cloud, int(t * SEC))
    assert det.num_keyframes == 3  # 0.0, 1.0, 2.2
    assert [int(s) for s in det.database.export_arrays()['stamps_ns']] == [0, SEC, 2.2 * SEC]


def test_keyframe_gating_by_pose() -> None:
    det = LoopDetector(_cfg(keyframe_min_distance=1.0, keyframe_min_rotation_deg=20.0))
    cloud = place(0)
    eye = np.eye(4)

    def pose(x: float, yaw_deg: float) -> npt.NDArray[np.float64]:
        p = eye.copy()
        p[:3, :3] = rotz(np.eye(3), yaw_deg).T
        p[0, 3] = x
        return p

    kept = []
    for i, (x, yaw) in enumerate([(0, 0), (0.5, 0), (1.0, 0), (1.2, 10), (1.2, 25), (1.2, 26)]):
        det.process(cloud, i * SEC, pose(x, yaw))
        kept.append(det.last_was_keyframe)
    assert kept == [True, False, True, False, True, False]
    stored = det.database.export_arrays()['poses']
    assert stored.shape == (3, 7) and stored[1, 0] == pytest.approx(1.0)
    # Pose criteria without poses cannot be evaluated: scans are kept, not all dropped.
    det = LoopDetector(_cfg(keyframe_min_distance=1.0))
    for i in range(3):
        det.process(cloud, i * SEC)
    assert det.num_keyframes == 3


def test_empty_and_bad_clouds() -> None:
    det = LoopDetector(_cfg(exclude_recent_frames=0, distance_threshold=2.0))
    assert det.process(np.zeros((0, 3)), 0) == []
    assert det.process(np.full((10, 3), np.nan), SEC) == []
    assert det.process(place(0), 2 * SEC) == []  # empty scans never match
    assert det.process(np.zeros((0, 3)), 3 * SEC) == []
    assert det.num_keyframes == 4
    with pytest.raises(SolidError):
        det.process(np.zeros((5, 2)), 4 * SEC)


def test_reconfigure_only_runtime_settings() -> None:
    det = LoopDetector(_cfg())
    det.reconfigure(det.config.replace(distance_threshold=0.3, min_margin=0.1))
    assert det.config.distance_threshold == 0.3
    with pytest.raises(ConfigError, match='voxel_size'):
        det.reconfigure(det.config.replace(voxel_size=0.2))


def test_kdtree_mode_gives_the_same_candidates() -> None:
    clouds = [place(i % 7) for i in range(20)]
    out = {m: _run(LoopDetector(_cfg(search=m, kdtree_rebuild_every=3)), clouds)
           for m in ('brute', 'kdtree')}
    for brute, tree in zip(out['brute'], out['kdtree']):
        assert [(c.query_index, c.match_index) for c in brute] == [
            (c.query_index, c.match_index) for c in tree]
        for b, t in zip(brute, tree):
            assert (b.distance, b.margin) == pytest.approx((t.distance, t.margin), abs=1e-12)
    assert sum(bool(c) for c in out['brute']) == 13


def test_hku1_revisit_is_found(shared_data: Path) -> None:
    from hku1_data import HKU1_CONFIG, hku1_positions, hku1_scans

    clouds, stamps = hku1_scans(shared_data)
    positions = hku1_positions(shared_data)
    poses = np.loadtxt(shared_data / 'hku1' / 'optimized_poses.txt').reshape(-1, 3, 4)
    assert len(clouds) == len(positions) == 314
    det = LoopDetector(SolidConfig().replace(**HKU1_CONFIG, distance_threshold=0.05,
                                             exclude_recent_frames=50))
    found = []
    for cloud, stamp, pose in zip(clouds, stamps, poses):
        found += det.process(cloud, stamp, pose)
    assert det.num_keyframes == 314
    loop = [c for c in found if 274 <= c.query_index <= 313]
    correct = [c for c in loop
               if np.linalg.norm(positions[c.query_index] - positions[c.match_index]) < 5.0]
    assert correct, f'no correct candidate in the revisit: {loop}'
    assert all(c.match_index < 60 for c in correct)
    assert len(correct) >= 0.9 * len(loop)


def test_heading_match_is_runtime_tunable_and_used_for_the_yaw() -> None:
    from solid_ros.core.descriptor import describe
    from solid_ros.core.matching import estimate_yaw
    cfg = _cfg(fov_width_deg=90.0, exclude_recent_frames=0)
    stored, query = place(1), rotz(place(1), 50.0)
    results = {}
    for mode in ('full', 'overlap'):
        det = LoopDetector(cfg)
        det.process(stored, 0)
        det.reconfigure(cfg.replace(heading_match=mode))  # not read-only
        det.process(query, SEC)
        assert det.last_best is not None and det.last_best.match_index == 0
        results[mode] = det.last_best.yaw
        want = estimate_yaw(describe(query, cfg).heading, describe(stored, cfg).heading, mode)
        assert results[mode] == pytest.approx(want, abs=1e-6)  # stored as float32
    assert results['full'] != pytest.approx(results['overlap'], abs=1e-6)


@pytest.mark.parametrize('stamp', [2**63, -(2**63) - 1, 10**30, float('nan'), float('inf'),
                                   'abc', None])
def test_stamps_outside_int64_are_solid_errors(stamp: object) -> None:
    det = LoopDetector(SolidConfig().replace(exclude_recent_sec=1e9, exclude_recent_frames=0))
    det.process(place(0), 2**63 - 1)
    det.process(place(0), -(2**63))  # both ends of int64 are fine
    with pytest.raises(SolidError, match='stamp'):
        det.process(place(1), stamp)  # type: ignore[arg-type]
    with pytest.raises(SolidError, match='stamp'):
        det.process_descriptor(det.last_descriptor, stamp)  # type: ignore[arg-type]
    assert det.database.size == 2
