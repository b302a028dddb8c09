"""Tests of loop verification: true revisits pass with their pose, everything else is refused."""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
from hdl64_scans import CFG
from hdl64_scans import keyframe_points as _cloud
from hdl64_scans import scan as _scan
from hdl64_scans import truth as _truth
from project_paths import CONFIG_DIR

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.descriptor.matching import heading_hypotheses
from solid_ros.core.descriptor.solid import describe
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.geometry import rpy_matrix
from solid_ros.core.reasons import RULE_REASONS as REASONS
from solid_ros.core.results import LoopCandidate
from solid_ros.core.verification.covariance import (
    RESIDUAL_SCALE,
    TIGHT_RESIDUAL,
    support_covariance,
)
from solid_ros.core.verification.judge import KNOWN_PLACE_SHARE as KNOWN_PLACE_OVERLAP
from solid_ros.core.verification.prepared import Source, coarsened
from solid_ros.core.verification.restarts import drift
from solid_ros.core.verification.support import Support
from solid_ros.core.verification.verifier import Verifier, registration_settings
from solid_ros.sim import DEMO_SENSORS, avia_like, cast_scan
from solid_ros.sim.drive import Drive, DriveConfig, pose_matrix
from solid_ros.sim.scene import Room, build_room
from solid_ros.sim.trajectory import handheld_walk
from solid_ros.tools.uncertainty import nees

pytest.importorskip('small_gicp', reason='small-gicp is not installed')


class _At:
    """A place that only says whether the pose graph predicted a pose (no odometry, no
    graph guess to measure against)."""

    graph = False

    def __init__(self, known: Callable[[np.ndarray, float], bool]) -> None:
        self._known = known

    def known(self, T_mq: np.ndarray, coarse_voxel: float) -> bool:
        return self._known(T_mq, coarse_voxel)

    def odometry(self, T_mq: np.ndarray) -> tuple[float, float]:
        return math.nan, math.nan

    heading = odometry

    def position(self, T_mq: np.ndarray, voxel: float) -> tuple[float, float]:
        return math.nan, math.nan

FloatArray = npt.NDArray[np.float64]
SEC = 1_000_000_000


def _verify(q_pts: npt.ArrayLike, m_pts: npt.ArrayLike, yaws: list[float],
            cfg: SolidConfig = CFG) -> object:
    v = Verifier(cfg)
    query = v.prepare(_cloud(q_pts, cfg))
    match = v.prepare(_cloud(m_pts, cfg)).keyframe_cloud()
    return v.fine(query, v.coarse(query, 'm', match, yaws))


def _errors(T: FloatArray, ref: FloatArray) -> tuple[float, float]:
    d = np.linalg.inv(ref) @ T
    angle = math.degrees(math.acos(min(max((np.trace(d[:3, :3]) - 1) / 2, -1.0), 1.0)))
    return float(np.linalg.norm(d[:3, 3])), angle


@pytest.mark.parametrize(('q', 'm'), [(273, 5), (290, 22)])
def test_true_revisit_is_verified_with_its_pose(q: int, m: int) -> None:
    ref = _truth(q, m)
    res = _verify(_scan(q)[0], _scan(m)[0], [math.atan2(ref[1, 0], ref[0, 0]) + 0.05])
    assert res.verified and res.reason == 'verified'  # type: ignore[attr-defined]
    t_err, r_err = _errors(res.T, ref)  # type: ignore[attr-defined]
    assert t_err < 0.1 and r_err < 0.3
    assert res.yaw == pytest.approx(math.atan2(ref[1, 0], ref[0, 0]), abs=0.01)  # type: ignore
    cov = res.covariance  # type: ignore[attr-defined]
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0.0)
    assert 0.5 < res.overlap <= 1.0 and res.rmse < 0.05  # type: ignore[attr-defined]
    # The covariance covers the error: below the chi-square 99.9 % bound for 6 degrees of
    # freedom (the calibration over whole drives is test/bench/bench_nees.py).
    assert nees(res.T, ref, cov).full < 22.46  # type: ignore[attr-defined]


def test_covariance_scale_and_plane_weights() -> None:
    ref = _truth(273, 5)
    yaws = [math.atan2(ref[1, 0], ref[0, 0]) + 0.05]
    one = _verify(_scan(273)[0], _scan(5)[0], yaws)
    four = _verify(_scan(273)[0], _scan(5)[0], yaws, CFG.replace(verify_covariance_scale=4.0))
    np.testing.assert_allclose(four.covariance, 4.0 * one.covariance)  # type: ignore
    # Plane thickness: near 0 on a clean plane, large where no plane is defined.
    rng = np.random.default_rng(5)
    plane = np.c_[rng.uniform(-5, 5, (400, 2)), rng.normal(0.0, 0.005, 400)]
    blob = rng.normal([0.0, 0.0, 3.0], 0.3, (400, 3))
    v = Verifier(CFG)
    assert np.median(v.prepare(plane).plane_thickness) < 0.01
    assert np.median(v.prepare(blob).plane_thickness) > 0.2
    # Weighted information: each point counts at most once.
    query = v.prepare(_cloud(_scan(273)[0]))
    match = Source(v.prepare(_cloud(_scan(5)[0])).keyframe_cloud(), v.settings)
    sup = Support(query, match, np.linalg.inv(ref), v.settings)
    info, weight = sup.weighted_information
    assert 0.0 < weight <= sup.inliers
    assert np.linalg.eigvalsh(sup.information - info).min() > -1e-6 * np.abs(info).max()


def test_wrong_heading_hypothesis_is_recovered_by_the_next() -> None:
    ref = _truth(273, 5)
    yaw = math.atan2(ref[1, 0], ref[0, 0])
    res = _verify(_scan(273)[0], _scan(5)[0], [yaw + math.pi, yaw])
    assert res.verified and res.hypothesis == 1  # type: ignore[attr-defined]


def _perturbed(T: FloatArray, dx: float, dyaw_deg: float) -> FloatArray:
    d = np.eye(4)
    d[:3, :3] = rpy_matrix(0.0, 0.0, math.radians(dyaw_deg))
    d[0, 3] = d[1, 3] = dx
    out: FloatArray = T @ d
    return out


def test_a_pose_graph_guess_seeds_the_coarse_stage() -> None:
    # Heading hypotheses half a turn off do not find the revisit; the pose graph's relative
    # pose, 1.4 m and 8 deg off the truth, does, tried first (hypothesis 0).
    ref = _truth(273, 5)
    wrong = math.atan2(ref[1, 0], ref[0, 0]) + math.pi
    v = Verifier(CFG)
    query = v.prepare(_cloud(_scan(273)[0]))
    match = v.prepare(_cloud(_scan(5)[0])).keyframe_cloud()
    assert not v.fine(query, v.coarse(query, 'm', match, [wrong])).verified
    res = v.fine(query, v.coarse(query, 'm', match, [wrong], [_perturbed(ref, 1.0, 8.0)]))
    assert res.verified and res.hypothesis == 0
    t_err, r_err = _errors(res.T, ref)
    assert t_err < 0.1 and r_err < 0.3
    # A guess alone (no heading hypotheses) is enough.
    res = v.fine(query, v.coarse(query, 'm', match, [], [_perturbed(ref, -1.0, -8.0)]))
    assert res.verified and _errors(res.T, ref)[0] < 0.1


def test_a_dense_candidate_is_thinned_evenly_for_the_coarse_stage_and_still_verified() -> None:
    cfg = CFG.replace(verify_coarse_max_points=80)
    cloud = Verifier(CFG).prepare(_cloud(_scan(5)[0])).keyframe_cloud()
    uncapped = registration_settings(CFG.replace(verify_coarse_max_points=1_000_000))
    full = Source(cloud, uncapped).coarse.points()[:, :2]
    thin = Source(cloud, registration_settings(cfg)).coarse.points()[:, :2]
    assert len(full) > 2 * 80 and len(thin) == 80
    # Spread over the whole place, not one corner of it.
    span_full, span_thin = np.ptp(full, axis=0), np.ptp(thin, axis=0)
    assert np.all(span_thin > 0.8 * span_full)
    ref = _truth(273, 5)
    res = _verify(_scan(273)[0], _scan(5)[0], [math.atan2(ref[1, 0], ref[0, 0]) + 0.05], cfg)
    assert res.verified  # type: ignore[attr-defined]
    t_err, r_err = _errors(res.T, ref)  # type: ignore[attr-defined]
    assert t_err < 0.1 and r_err < 0.3


@pytest.mark.parametrize(('q', 'm'), [(273, 120), (290, 60), (150, 20)])
def test_different_places_are_refused(q: int, m: int) -> None:
    assert np.linalg.norm(_truth(q, m)[:3, 3]) > 30.0
    for yaw in (0.0, math.pi / 2, math.pi, -math.pi / 2):
        res = _verify(_scan(q)[0], _scan(m)[0], [yaw])
        assert not res.verified and res.reason in REASONS  # type: ignore[attr-defined]


def _room(n: int, rng: np.random.Generator, walls: str) -> FloatArray:
    """Ground plus walls: 'corridor' = two long parallel walls, 'plane' = ground only."""
    ground = np.c_[rng.uniform(-30, 30, (n, 2)), np.full(n, -1.7)]
    if walls == 'plane':
        return ground
    x = rng.uniform(-40, 40, n)
    z = rng.uniform(-1.7, 3.0, n)
    side = np.where(rng.random(n) < 0.5, -4.0, 4.0)
    return np.vstack([ground, np.c_[x, side, z]])


@pytest.mark.parametrize('walls', ['corridor', 'plane'])
def test_degenerate_geometry_is_refused(walls: str) -> None:
    rng = np.random.default_rng(3)
    a, b = _room(20000, rng, walls), _room(20000, rng, walls) + [2.5, 0.0, 0.0]
    res = _verify(a, b, [0.0], CFG.replace(fov_up_deg=30.0, fov_down_deg=-30.0))
    assert not res.verified  # type: ignore[attr-defined]
    expected = {'too_sparse', 'constraint', 'single_object', 'unstable'}
    assert res.reason in expected  # type: ignore[attr-defined]


def test_sparse_cloud_and_missing_cloud_are_refused() -> None:
    v = Verifier(CFG)
    query = v.prepare(_cloud(_scan(273)[0]))
    few = KeyframeCloud(np.zeros((4, 3), dtype=np.float32), 4)
    assert v.fine(query, v.coarse(query, 'a', few, [0.0])).reason == 'too_sparse'
    assert v.fine(query, v.coarse(query, 'b', None, [0.0])).reason == 'no_cloud'
    sparse_query = v.prepare(np.zeros((3, 3)))
    cloud = v.prepare(_cloud(_scan(5)[0])).keyframe_cloud()
    assert v.fine(sparse_query, v.coarse(sparse_query, 'c', cloud, [0.0])).reason == 'too_sparse'


def test_registration_that_does_not_converge_is_refused() -> None:
    ref = _truth(273, 5)
    res = _verify(_scan(273)[0], _scan(5)[0], [math.atan2(ref[1, 0], ref[0, 0]) + 0.3],
                  CFG.replace(verify_max_iterations=1))
    assert not res.verified and res.reason in {'not_converged', 'coarse_overlap'}  # type: ignore


def test_keyframe_cloud_is_structure_first() -> None:
    v = Verifier(CFG)
    query = v.prepare(_cloud(_scan(273)[0]))
    cloud = query.keyframe_cloud()
    assert cloud.points.dtype == np.float32 and 0 < cloud.n_struct < len(cloud.points)
    again = v.prepare(cloud.points)
    assert np.mean(again.structure[:cloud.n_struct]) > 0.95
    assert np.mean(again.structure[cloud.n_struct:]) < 0.05


def _drive_detector(cfg: SolidConfig, indices: list[int],
                    transform: FloatArray | None = None,
                    poses: list[FloatArray] | None = None,
                    ) -> tuple[LoopDetector, list[LoopCandidate], tuple[LoopCandidate, ...]]:
    """The detector, every loop it published and the candidates of the last scan."""
    det = LoopDetector(cfg)
    published: list[LoopCandidate] = []
    res = None
    for k, i in enumerate(indices):
        pts = _scan(i)[0].astype(np.float64)
        if transform is not None:
            pts = pts @ transform.T
        res = det.process(pts, k * SEC, None if poses is None else poses[k])
        published += res.loops
    return det, published, () if res is None else res.attempts


def test_detector_publishes_verified_pose_and_split_equals_process() -> None:
    cfg = CFG.replace(exclude_recent_frames=2, distance_threshold=0.2, num_candidates=3)
    indices = [5, 40, 80, 120, 273]
    det, published, _ = _drive_detector(cfg, indices)
    (loop,) = published
    assert (loop.match_index, loop.query_index, loop.verified) == (0, 4, True)
    t_err, r_err = _errors(loop.matrix(), _truth(273, 5))
    assert t_err < 0.1 and r_err < 0.3
    assert all(not math.isnan(v) for v in loop.covariance)
    split = LoopDetector(cfg)
    out = []
    for k, i in enumerate(indices):
        proposal = split.propose(_scan(i)[0], k * SEC)
        assert proposal is not None
        res = split.verify(proposal)
        out += res.loops
        assert res.times.verify > 0.0
    assert out == published
    assert det.reasons['verified'] == 1


LOOP_DRIVE = [5, 40, 80, 120, 273]  # 273 revisits 5


def _odometry(jump_m: float) -> list[FloatArray]:
    """The drive's poses as odometry that jumps ``jump_m`` along x before the revisit."""
    poses = [_scan(i)[1].copy() for i in LOOP_DRIVE]
    poses[-1][0, 3] += jump_m
    return poses


def _revisit_loops(published: list[LoopCandidate]) -> list[int]:
    return [c.match_index for c in published if c.query_index == 4]


@pytest.mark.parametrize('verify', [True, False])
def test_a_loop_the_odometry_contradicts_is_refused(verify: bool) -> None:
    # The drive's keyframes lie 70-250 m apart: no step of theirs is a jump of the odometry.
    cfg = CFG.replace(exclude_recent_frames=2, distance_threshold=0.2, num_candidates=3,
                      verify=verify, backend_segment_jump_m=1000.0)
    # Odometry that agrees: the revisit is published. Without verification the other
    # candidates (places 70-250 m away) are refused by the odometry alone.
    det, published, attempts = _drive_detector(cfg, LOOP_DRIVE, poses=_odometry(0.0))
    assert _revisit_loops(published) == [0]
    others = {c.reason for c in attempts if c.match_index != 0}
    assert others <= ({'coarse_overlap', 'overlap', 'conflict'} if verify else {'odometry'})
    assert det.reasons['odometry'] == 0 or not verify
    # Odometry 400 m off after about 550 m driven: far beyond 10 % drift plus 10 m of slack.
    det, published, attempts = _drive_detector(cfg, LOOP_DRIVE, poses=_odometry(400.0))
    assert _revisit_loops(published) == [] and det.reasons['odometry'] >= 1
    refused = [c for c in attempts if c.match_index == 0]
    assert [c.reason for c in refused] == ['odometry'] and not refused[0].verified
    # The check off, or a drift allowance that covers the jump: published again.
    for relaxed in (cfg.replace(odom_check_drift=0.0), cfg.replace(odom_check_drift=1.0)):
        _, published, _ = _drive_detector(relaxed, LOOP_DRIVE, poses=_odometry(400.0))
        assert _revisit_loops(published) == [0]
    # Without poses there is nothing to check.
    _, published, _ = _drive_detector(cfg, LOOP_DRIVE)
    assert _revisit_loops(published) == [0]


def test_mounting_levels_a_tilted_sensor() -> None:
    # The same drive seen by a sensor pitched 8 deg and rolled -5 deg: with the mounting set,
    # the loop is found and its pose is the level one expressed in the tilted frames.
    mount = rpy_matrix(math.radians(-5.0), math.radians(8.0), 0.0)
    cfg = CFG.replace(exclude_recent_frames=2, distance_threshold=0.2, num_candidates=3,
                      mount_roll_deg=-5.0, mount_pitch_deg=8.0)
    _, published, _ = _drive_detector(cfg, [5, 40, 80, 120, 273], mount.T)
    (loop,) = published
    m4 = np.eye(4)
    m4[:3, :3] = mount
    ref = m4.T @ _truth(273, 5) @ m4
    t_err, r_err = _errors(loop.matrix(), ref)
    assert loop.verified and t_err < 0.1 and r_err < 0.3
    assert loop.yaw == pytest.approx(
        math.atan2(_truth(273, 5)[1, 0], _truth(273, 5)[0, 0]), abs=0.01)


def test_unverifiable_candidates_are_never_published() -> None:
    cfg = CFG.replace(exclude_recent_frames=2, distance_threshold=0.2, num_candidates=3,
                      cloud_capacity=2)  # only the two newest clouds are kept
    det, published, attempts = _drive_detector(cfg, [5, 40, 80, 120, 273])
    assert published == []
    assert any(a.reason == 'no_cloud' for a in attempts)
    assert len(det.clouds) == 2 and det.clouds.dropped == 3
    assert attempts and not any(a.verified for a in attempts)


# Transfer: the shipped presets on the demo's simulated streets (50 m blocks, a scan every 2 m,
# 512 points per ring), small slices of test/bench/bench_generalisation.py.


@lru_cache(maxsize=2)
def _demo_drive(sensor: str, route: str, scene: str) -> Drive:
    return Drive(DriveConfig(seed=0, sensor=DEMO_SENSORS[sensor], block=50.0, spacing=2.0,
                             route=route, scene=scene))


def _pose_errors(drive: Drive, q: int, m: int, T: FloatArray) -> tuple[float, float]:
    return _errors(T, np.linalg.inv(drive.pose(m)) @ drive.pose(q))


@pytest.mark.parametrize(('q', 'm'), [(166, 95), (174, 80), (606, 233)])
def test_lookalike_street_through_a_90_degree_clip_is_refused(q: int, m: int) -> None:
    # Pairs 100-290 m apart on the look-alike no-revisit drive that the 90-degree preset
    # published before the conflict test also looked at structure alone: the ground aligned,
    # so the trees and building ends in seen-through space were too few of all points.
    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'spinning_fov90.yaml')
    drive = _demo_drive('hdl64', 'no_revisit', 'lookalike')
    det = LoopDetector(cfg)
    sq, sm = drive.scan(q).points, drive.scan(m).points
    yaws = [y for y, _ in heading_hypotheses(describe(sq, cfg).heading, describe(sm, cfg).heading,
                                             cfg.verify_hypotheses, cfg.heading_match)]
    v = Verifier(cfg)
    query = v.prepare(det._proposer.keyframe_points(sq))
    match = v.prepare(det._proposer.keyframe_points(sm)).keyframe_cloud()
    assert not v.fine(query, v.coarse(query, 'm', match, yaws)).verified
    # Some of these pairs stop at the shipped coarse screen (0.25) now; at the former 0.2 all
    # reach the fine stage, where the conflict test must refuse them.
    v.reconfigure(cfg.replace(verify_min_coarse_overlap=0.2))
    res = v.fine(query, v.coarse(query, 'm', match, yaws))
    assert not res.verified
    assert _pose_errors(drive, q, m, res.T)[0] > 50.0  # the alignment found is a false one
    assert res.conflict > cfg.verify_max_conflict, res
    # A pose graph that drifted so far that it puts the two places on top of each other
    # (its guess is that false alignment, or one 1 m and 5 deg beside it) seeds the coarse
    # stage there: the tests still refuse it.
    v.reconfigure(cfg)
    for guess in (res.T, _perturbed(res.T, 1.0, 5.0)):
        again = v.fine(query, v.coarse(query, 'm', match, yaws, [guess]))
        assert not again.verified, again


def _published(sensor: str, preset: str, route: str, scene: str, scans: list[int],
               drifting: bool = False) -> list[tuple[int, int, float, float]]:
    """(query scan, match scan, translation error, rotation error) of every published loop:
    the geometric tests alone (the reference poses are fed as odometry, a perfect one: its
    check is off), or with ``drifting`` the simulator's drifting odometry and the preset's
    odometry check."""
    drive = _demo_drive(sensor, route, scene)
    cfg = SolidConfig.from_yaml(CONFIG_DIR / preset)
    det = LoopDetector(cfg if drifting else cfg.replace(odom_check_drift=0.0))
    out = []
    for i in scans:
        scan = drive.scan(i)
        odom = scan.odom if drifting else scan.pose
        for loop in det.process(scan.points, scan.stamp_ns, odom).loops:
            q, m = scans[loop.query_index], scans[loop.match_index]
            out.append((q, m, *_pose_errors(drive, q, m, loop.matrix())))
    return out


@pytest.mark.slow
def test_no_loop_on_lookalike_streets_without_a_revisit_through_a_90_degree_clip() -> None:
    # 120 scans (240 m) of look-alike streets never visited twice; this stretch published two
    # false loops (166-95, 174-80) before the structure conflict. Look-alike streets are what
    # geometry alone cannot always tell apart (167-95 passes every geometric rule; over the
    # whole drive bench_generalisation counts 3-4 such loops without the odometry): with the
    # simulator's drifting odometry, the preset's odometry check refuses them.
    assert _published('hdl64', 'spinning_fov90.yaml', 'no_revisit', 'lookalike',
                      list(range(60, 180)), drifting=True) == []


@pytest.mark.slow
def test_avia_revisit_of_lookalike_streets_publishes_only_correct_loops() -> None:
    # The first street (scans 0-39), other streets (60-99), then scans 148-175 drive the
    # first street again (revisits of scans 0-26, labelled by the simulator).
    scans = [*range(40), *range(60, 100), *range(148, 176)]
    drive = _demo_drive('avia_like', 'revisits', 'lookalike')
    assert all(drive.scan(i).revisit_of in range(27) for i in range(150, 176))
    loops = _published('avia_like', 'avia.yaml', 'revisits', 'lookalike', scans)
    assert all(t < 1.0 and r < 3.0 for _, _, t, r in loops), loops
    assert len({q for q, *_ in loops}) >= 14  # at least half of the 28 revisiting scans


@pytest.mark.parametrize(('q', 'm'), [(324, 163), (309, 148)])
def test_consistency_restarts_stay_within_reach_of_a_narrow_view_that_sees_far(
        q: int, m: int) -> None:
    # Right revisits on the avia_like varied drive whose structure lies mostly 20-35 m out
    # (90th percentile of the range over 28 m): a 2-degree restart moved those points over
    # a metre, beyond the fine stage's reach of two voxels, so it did not come back and the
    # pose was refused as unstable. The turn is now bounded by one voxel at that range.
    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml')
    drive = _demo_drive('avia_like', 'revisits', 'varied')
    det, v = LoopDetector(cfg), Verifier(cfg)
    query = v.prepare(det._proposer.keyframe_points(drive.scan(q).points))
    src = v.prepare(det._proposer.keyframe_points(drive.scan(m).points)).keyframe_cloud()
    ref = np.linalg.inv(drive.pose(m)) @ drive.pose(q)
    coarse = v.coarse(query, 'm', src, [math.atan2(ref[1, 0], ref[0, 0]) + 0.05])
    res = v.fine(query, coarse)
    assert res.verified, res
    t_err, r_err = _pose_errors(drive, q, m, res.T)
    assert t_err < 0.1 and r_err < 0.5
    assert coarse.source is not None
    info = Support(query, coarse.source, np.linalg.inv(res.T), v.settings).information
    turn = drift(query, coarse.source, np.linalg.inv(res.T), info)[2]
    assert 0.5 < turn < 1.5  # one 0.5 m voxel at 20-57 m



# Tight spaces: a handheld Avia-like walk through the simulator's cluttered 7.5 x 6 m room
# (seed 0), the avia.yaml preset. Pairs of the walk's scans, by scan index.


@lru_cache(maxsize=1)
def _furnished_room() -> tuple[Any, Any]:
    room = Room()
    return build_room(room, 0), handheld_walk(room, 0)


@lru_cache(maxsize=16)
def _room_scan(index: int) -> tuple[npt.NDArray[np.float32], FloatArray]:
    scene, walk = _furnished_room()
    x, y, yaw = (float(v) for v in (*walk.xy[index], walk.yaw[index]))
    model = avia_like(min_range=0.5, mount_height=1.4)
    cloud = cast_scan(scene, model, x, y, yaw, np.random.default_rng([0, index, 0x1D4]))
    return cloud[:, :3], pose_matrix(x, y, model.mount_height, yaw)


def _verify_room_pair(q: int, m: int, guesses: tuple[FloatArray, ...] = (),
                      cfg: SolidConfig | None = None) -> tuple[Any, float, float]:
    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml') if cfg is None else cfg
    (sq, pq), (sm, pm) = _room_scan(q), _room_scan(m)
    yaws = [y for y, _ in heading_hypotheses(describe(sq, cfg).heading, describe(sm, cfg).heading,
                                             cfg.verify_hypotheses, cfg.heading_match)]
    det, v = LoopDetector(cfg), Verifier(cfg)
    query = v.prepare(det._proposer.keyframe_points(sq))
    match = v.prepare(det._proposer.keyframe_points(sm)).keyframe_cloud()
    res = v.fine(query, v.coarse(query, 'm', match, yaws, guesses))
    return (res, *_errors(res.T, np.linalg.inv(pm) @ pq))


@pytest.mark.parametrize(('axis', 'sigma', 'kept'), [
    # roll: 2 sigmas vs 3 deg (its coupling to pitch and yaw adds about 0.2 deg: 1.4 deg
    # sat at 2.97 deg, on the bar within how far the fine stage stops from the optimum)
    (3, math.radians(1.3), True), (3, math.radians(1.6), False),
    (2, 0.45, True), (2, 0.55, False)])                            # height: 2 sigmas vs 1 m
def test_a_loop_its_own_covariance_does_not_pin_is_refused(
        monkeypatch: pytest.MonkeyPatch, axis: int, sigma: float, kept: bool) -> None:
    # A right loop is within 1 m and 3 deg; one whose covariance puts two sigmas beyond that
    # in some direction is not pinned there: in the simulator's tilted room a hand-held scan
    # facing one wall, the ground out of view, verified 3.7 deg off in roll (its sigma there
    # 2.1 deg) while x, y and the heading were held.
    import solid_ros.core.verification.verifier as verification

    real = verification.support_covariance

    def loose(*args: Any, **kwargs: Any) -> Any:
        cov = real(*args, **kwargs)
        if cov is not None:
            cov = cov.copy()
            cov[axis, axis] = sigma ** 2 * args[1]  # args[1]: verify_covariance_scale
        return cov

    monkeypatch.setattr(verification, 'support_covariance', loose)
    res, _, _ = _verify_room_pair(119, 15)
    assert res.verified is kept and res.reason == ('verified' if kept else 'pinned'), res
    # The calibrated covariance decides: a user's cautious scale changes no verdict.
    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml').replace(verify_covariance_scale=4.0)
    res4, _, _ = _verify_room_pair(119, 15, cfg=cfg)
    assert res4.verified is kept


def test_a_stationary_fine_registration_counts_as_converged() -> None:
    # Scan 119 revisits scan 15 a lap later. small_gicp never flags this run converged (with
    # 170 points its damped steps keep being refused at the optimum, or alternate between two
    # correspondence sets a centimetre apart): before the stationarity check it was refused
    # as not_converged with its pose right.
    res, t_err, r_err = _verify_room_pair(119, 15)
    assert res.verified, res
    assert t_err < 0.3 and r_err < 1.5


@pytest.mark.parametrize(('q', 'm'), [(61, 13), (108, 58)])
def test_near_field_occlusion_is_not_a_conflict(q: int, m: int) -> None:
    # Right alignments a degree or two off whose table tops and shelf boards, seen edge-on,
    # fall in the other scan's range-image directions that passed beside them: counted as
    # seen-through space, the conflict refused them by the single-object bar (half of
    # verify_max_conflict); points next to the other scan's own points are not a conflict.
    res, t_err, r_err = _verify_room_pair(q, m)
    assert res.verified, res
    assert t_err < 0.3 and r_err < 2.0


@pytest.mark.parametrize(('q', 'm'), [(144, 65), (80, 22), (120, 55)])
def test_wrong_room_alignments_are_still_refused(q: int, m: int) -> None:
    # The room turned by 80-95 degrees onto another corner: geometry that contradicts what
    # the query saw, refused (by the conflict rule, or, where the turned walls leave a
    # direction free, the constraint rule before it; all three failed to converge before the
    # stationarity check).
    res, t_err, r_err = _verify_room_pair(q, m)
    assert not res.verified and res.reason in ('conflict', 'constraint'), res
    assert r_err > 45.0
    # Seeded there by a pose graph's guess (the room is where the graph would propose its
    # nearest keyframes), the turned alignment is refused all the same.
    again, _, r_again = _verify_room_pair(q, m, (res.T,))
    assert not again.verified and r_again > 45.0, again


def test_a_tight_space_registers_on_the_tight_grid() -> None:
    # The room's scans (every 90th percentile of their horizontal ranges under 7 m) are kept
    # on half the voxels; two of them register on half of both (verify_tight_range). A street
    # scan (25 m and more) keeps the configuration's grid, and a pair of one of each
    # registers on it: the tight cloud coarsened, the tight query downsampled once.
    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml')
    det, v = LoopDetector(cfg), Verifier(cfg)
    (sq, pq), (sm, pm) = _room_scan(67), _room_scan(15)  # a lap apart, 0.6 m, 20 deg
    street = _demo_drive('avia_like', 'revisits', 'varied').scan(40).points
    assert v.is_tight(det._proposer.keyframe_points(sq))
    assert v.is_tight(det._proposer.keyframe_points(sm))
    assert not v.is_tight(det._proposer.keyframe_points(street))
    loose = Verifier(cfg.replace(verify_tight_range=0.0))
    assert not loose.is_tight(det._proposer.keyframe_points(sq))
    assert v.tight_settings.voxel == 0.5 * v.settings.voxel
    assert v.tight_settings.coarse_voxel == 0.5 * v.settings.coarse_voxel

    query = v.prepare(det._proposer.keyframe_points(sq, tight=True), tight=True)
    match = v.prepare(det._proposer.keyframe_points(sm, tight=True), tight=True).keyframe_cloud()
    assert match.voxel == v.tight_settings.voxel
    yaws = [y for y, _ in heading_hypotheses(describe(sq, cfg).heading, describe(sm, cfg).heading,
                                             cfg.verify_hypotheses, cfg.heading_match)]
    tight = v.coarse(query, 'm', match, yaws)
    assert tight.query is query and query.settings == v.tight_settings
    res = v.fine(query, tight)
    assert res.verified, res
    t_err, r_err = _errors(res.T, np.linalg.inv(pm) @ pq)
    assert t_err < 0.05 and r_err < 0.5, (t_err, r_err)  # 0.03 m and 0.9 deg on 0.5 m
    # Its covariance reads the residuals with the tight grid's share of the factor.
    sup = Support(query, tight.source, np.linalg.inv(res.T), query.settings)
    np.testing.assert_allclose(
        res.covariance, support_covariance(sup, 1.0, RESIDUAL_SCALE * TIGHT_RESIDUAL))
    assert not np.allclose(res.covariance, support_covariance(sup))

    base_match = v.prepare(det._proposer.keyframe_points(sm)).keyframe_cloud()
    mixed = v.coarse(query, 'b', base_match, yaws)
    assert mixed.query is not None and mixed.query.settings == v.settings
    assert mixed.query is query.on_grid(v.settings)  # downsampled once, then kept
    base_query = v.prepare(det._proposer.keyframe_points(sq))
    other = v.coarse(base_query, 't', match, yaws)
    assert other.query is base_query and other.source is not None
    assert len(other.source.points) == len(coarsened(match, v.settings.voxel).points)


def test_a_known_place_measures_the_heading_at_the_rooms_own_range() -> None:
    # Scan 71 revisits scan 18 a lap later, right to 0.01 m and 0.1 deg; but its structure
    # lies 2-4 m away, and with the 10 m lever the constraint (0.0067) is under the bar.
    # Where the graph predicted the place, the lever is the structure's RMS range.
    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml')
    det, v = LoopDetector(cfg), Verifier(cfg)
    (sq, pq), (sm, pm) = _room_scan(71), _room_scan(18)
    query = v.prepare(det._proposer.keyframe_points(sq, tight=True), tight=True)
    match = v.prepare(det._proposer.keyframe_points(sm, tight=True), tight=True).keyframe_cloud()
    yaws = [y for y, _ in heading_hypotheses(describe(sq, cfg).heading, describe(sm, cfg).heading,
                                             cfg.verify_hypotheses, cfg.heading_match)]
    coarse = v.coarse(query, 'm', match, yaws)
    unknown = v.fine(query, coarse, place=_At(lambda T, c: False))
    assert unknown.reason == 'constraint' and unknown.constraint < cfg.verify_min_constraint
    known = v.fine(query, coarse, place=_At(lambda T, c: True))
    assert known.verified, known
    assert known.evidence.constraint_near >= 3.0 * unknown.constraint  # the one that passed
    t_err, r_err = _errors(known.T, np.linalg.inv(pm) @ pq)
    assert t_err < 0.05 and r_err < 0.5
    sup = Support(query, coarse.source, np.linalg.inv(known.T), query.settings)
    assert sup.constraint == pytest.approx(unknown.constraint, rel=1e-6)
    assert sup.constraint_near == pytest.approx(known.evidence.constraint_near, rel=1e-6)
    # On a street, where the supporting structure lies beyond 10 m, it is the constraint.
    v = Verifier(CFG)
    ref = _truth(273, 5)
    street = v.prepare(_cloud(_scan(273)[0]))
    src = Source(v.prepare(_cloud(_scan(5)[0])).keyframe_cloud(), v.settings)
    far = Support(street, src, np.linalg.inv(ref), v.settings)
    assert far.constraint_near == far.constraint > CFG.verify_min_constraint


def test_a_cloud_is_coarsened_only_from_a_finer_grid_and_keeps_structure_first() -> None:
    rng = np.random.default_rng(0)
    struct, rest = rng.uniform(0, 4, (400, 3)), rng.uniform(0, 4, (300, 3))
    fine = KeyframeCloud(np.vstack([struct, rest]).astype(np.float32), 400, 0.25)
    out = coarsened(fine, 1.0)
    assert out.voxel == 1.0 and 0 < out.n_struct < 400 and len(out.points) - out.n_struct < 300
    # Each part downsampled on its own: one point per occupied 1 m cell of each.
    assert out.n_struct == len(np.unique(np.floor(struct.astype(np.float32)), axis=0))
    for same in (KeyframeCloud(fine.points, 400, 1.0), KeyframeCloud(fine.points, 400, 0.0),
                 KeyframeCloud(fine.points, 400, 2.0)):
        assert coarsened(same, 1.0) is same


def _corner(rng: np.random.Generator, n: int = 6000) -> FloatArray:
    """Ground and one building corner (two walls meeting at (12, 4)): a single object."""
    ground = np.c_[rng.uniform(2, 30, (n, 1)), rng.uniform(-12, 12, (n, 1)), np.full(n, -1.7)]
    u, z = rng.uniform(0, 8, n), rng.uniform(-1.7, 4.0, n)
    wall_a = np.c_[np.full(n // 2, 12.0), 4.0 - u[: n // 2], z[: n // 2]]
    wall_b = np.c_[12.0 + u[n // 2:], np.full(n - n // 2, 4.0), z[n // 2:]]
    return np.vstack([ground, wall_a, wall_b])


def test_a_single_object_passes_only_where_the_graph_predicted_it() -> None:
    # One building corner pins the pose down by itself but would match any corner like it:
    # refused as a single object, unless the pose graph predicted that very object.
    cfg = CFG.replace(fov_up_deg=30.0, fov_down_deg=-30.0, verify_single_object_overlap=1.0)
    rng = np.random.default_rng(5)
    pts = _corner(rng)
    v = Verifier(cfg)
    query = v.prepare(_cloud(pts, cfg))
    match = v.prepare(_cloud(pts + [0.4, -0.3, 0.0], cfg)).keyframe_cloud()
    seen: list[FloatArray] = []

    def predicted(T_mq: FloatArray, coarse_voxel: float) -> bool:
        assert coarse_voxel == cfg.verify_coarse_voxel_size  # the pair's grid: not a tight one
        seen.append(T_mq)
        return True

    coarse = v.coarse(query, 'm', match, [0.0])
    assert v.fine(query, coarse).reason == 'single_object'
    assert v.fine(query, coarse, place=_At(lambda T, c: False)).reason == 'single_object'
    res = v.fine(query, coarse, place=_At(predicted))
    assert res.reason != 'single_object' and res.evidence.spread < cfg.verify_min_spread
    # The place is asked about the registered pose T_mq (query -> match): here +0.4, -0.3.
    assert len(seen) == 1 and np.allclose(seen[0][:2, 3], [0.4, -0.3], atol=0.1)
    # The place says which object; whether the pose on it is right is for the other rules:
    # a small panel where the query saw through to the walls is conflict, which the conflict
    # rule weighs (its own bar), not the single-object rule.
    panel = np.c_[rng.uniform(8.0, 8.3, 400), rng.uniform(-0.5, 0.5, 400),
                  rng.uniform(0.0, 1.0, 400)]
    cluttered = np.vstack([pts + [0.4, -0.3, 0.0], panel])
    for bar, passes in ((0.03, True), (0.005, False)):
        c = cfg.replace(verify_max_conflict=bar)
        vc = Verifier(c)
        qc = vc.prepare(_cloud(pts, c))
        got = vc.fine(qc, vc.coarse(qc, 'm', vc.prepare(_cloud(cluttered, c)).keyframe_cloud(),
                                    [0.0]), place=_At(predicted))
        assert got.reason == ('verified' if passes else 'conflict'), (bar, got)


def test_a_known_place_asks_less_overlap_of_the_two_views() -> None:
    # Whether two views show one place is what the overlap bar asks; where the pose graph
    # predicted the place, KNOWN_PLACE_OVERLAP of the bar suffices, and no less.
    base = CFG.replace(fov_up_deg=30.0, fov_down_deg=-30.0, verify_min_spread=0.0)
    rng = np.random.default_rng(5)
    pts = _corner(rng)
    # The match saw the corner's walls only in part (the ground all).
    match_pts = pts + [0.4, -0.3, 0.0]
    wall = match_pts[:, 2] >= -1.5
    match_pts = match_pts[~wall | ((match_pts[:, 0] < 13.0) & (match_pts[:, 1] > -1.0))]
    got = Verifier(base)
    query = got.prepare(_cloud(pts, base))
    overlap = got.fine(query, got.coarse(query, 'm', got.prepare(
        _cloud(match_pts, base)).keyframe_cloud(), [0.0])).overlap
    assert 0.4 < overlap < 0.6
    for share, passes in ((0.85, True), (0.6, False)):
        cfg = base.replace(verify_min_overlap=overlap / share)  # the views share that much
        v = Verifier(cfg)
        q = v.prepare(_cloud(pts, cfg))
        coarse = v.coarse(q, 'm', v.prepare(_cloud(match_pts, cfg)).keyframe_cloud(), [0.0])
        assert v.fine(q, coarse).reason == 'overlap'
        assert v.fine(q, coarse, place=_At(lambda T, c: False)).reason == 'overlap'
        known = v.fine(q, coarse, place=_At(lambda T, c: True)).reason
        assert (known != 'overlap') is passes, (share, known)
    assert KNOWN_PLACE_OVERLAP == pytest.approx(0.7)
