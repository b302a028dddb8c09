"""A fleet in one map: fleet replays with the back end put every robot in robot 0's map frame.

Each robot's odometry is its bag's reference poses drifting (``drifting_odometry``) and, for
every robot but 0, moved by a random rigid transform: the robots' map frames differ and drift
apart, while the bags' Odometry stays the reference in one world frame. False inter-robot loops
(20 m off, tight covariance) are injected alone and as consistent bursts of three; no robot's
trajectory in the fleet frame may move by more than 5 % of its ATE.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from drifting_odometry import Drift, drifting_odometry
from hku1_data import hku1_scans
from project_paths import CONFIG_DIR

from solid_ros.core.config import SolidConfig
from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.geometry import matrix_to_vector, rpy_matrix
from solid_ros.core.odometry.track import OdometrySource, StampedOdometry
from solid_ros.core.results import LoopCandidate
from solid_ros.formats.bags import write_cloud_bag
from solid_ros.formats.poses import read_kitti_poses, read_tum_poses
from solid_ros.tools.fleet import FleetResult, replay_fleet, write_fleet_outputs

pytest.importorskip('small_gicp', reason='small-gicp is not installed')
pytest.importorskip('gtsam', reason='gtsam is not installed')

Wrap = Callable[[OdometrySource | None], OdometrySource | None]
TIGHT = tuple(np.diag([1e-4] * 3 + [math.radians(0.05) ** 2] * 3).ravel())
T0 = 10**18


def _wrap(robot: int, stamps: np.ndarray, truth: np.ndarray, rng: np.random.Generator,
          drift: Drift) -> Wrap:
    """Robot ``robot``'s odometry: ``truth`` drifting, moved by a random rigid transform
    unless it is robot 0."""
    G = np.eye(4)
    if robot:
        G[:3, :3] = rpy_matrix(*rng.uniform(-0.05, 0.05, 2), rng.uniform(-math.pi, math.pi))
        G[:3, 3] = rng.uniform(-100.0, 100.0, 3) * [1.0, 1.0, 0.05]
    odo = G @ drifting_odometry(truth, drift)
    return lambda _: StampedOdometry.from_track(stamps, odo, 50_000_000, f'robot {robot}')


@dataclasses.dataclass
class Fleet:
    bags: list[Path]
    wraps: list[Wrap]
    config: SolidConfig
    clean: FleetResult | None = None

    def run(self, **changes: object) -> FleetResult:
        return replay_fleet(self.bags, self.config, wrap_odometry=self.wraps, **changes)


def make_hku1_fleet(shared_data: Path, tmp: Path) -> Fleet:
    """hku1 cut in two: robot 1 (the second half) returns to robot 0's start (bags in
    ``tmp``; the clean run done)."""
    clouds, stamps = hku1_scans(shared_data)
    poses = read_kitti_poses(shared_data / 'hku1' / 'optimized_poses.txt')
    half = len(clouds) // 2
    rng = np.random.default_rng(5)
    bags, wraps = [], []
    for robot, part in enumerate((range(half), range(half, len(clouds)))):
        bags.append(write_cloud_bag(tmp / f'robot{robot}',
                                    [(clouds[i], stamps[i], poses[i]) for i in part], 'mcap'))
        drift = Drift(scale=0.03, yaw_bias_deg_per_m=0.2, seed=robot) if robot else Drift()
        wraps.append(_wrap(robot, np.array([stamps[i] for i in part]), poses[list(part)], rng,
                           drift))
    fleet = Fleet(bags, wraps, SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml'))
    fleet.clean = fleet.run(out_dir=None)
    return fleet


@pytest.fixture(scope='module')
def hku1_fleet(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Fleet:
    """hku1 cut in two (:func:`make_hku1_fleet`)."""
    return make_hku1_fleet(shared_data, tmp_path_factory.mktemp('hku1_fleet'))


def make_sim_fleet(tmp: Path) -> Fleet:
    """Three robots of the simulated town on one street (30 scans each, 0.2 s apart,
    interleaved): robot 0 from scan 0, robots 1 and 2 from scans 166 and 180 on the other
    lane, each odometry drifting 1 % and 0.055 deg/m (bags in ``tmp``; the clean run done)."""
    from solid_ros.sim.bagwriter import DEMO_DEFAULTS
    from solid_ros.sim.drive import Drive, DriveConfig

    drive = Drive(DriveConfig(**DEMO_DEFAULTS))
    rng = np.random.default_rng(3)
    bags, wraps = [], []
    for robot, first in enumerate((0, 166, 180)):
        scans = [drive.scan(first + i) for i in range(30)]
        stamps = np.array([T0 + robot * 50_000_000 + i * 200_000_000 for i in range(30)])
        bags.append(write_cloud_bag(tmp / f'robot{robot}', [
            (s.points.copy(), int(t), s.pose) for s, t in zip(scans, stamps)], 'mcap'))
        wraps.append(_wrap(robot, stamps, np.array([s.pose for s in scans]), rng,
                           Drift(seed=robot)))
    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'hdl64.yaml').replace(exclude_recent_frames=5)
    fleet = Fleet(bags, wraps, cfg)
    fleet.clean = fleet.run()
    return fleet


@pytest.fixture(scope='module')
def sim_fleet(tmp_path_factory: pytest.TempPathFactory) -> Fleet:
    """Three simulated robots (:func:`make_sim_fleet`)."""
    return make_sim_fleet(tmp_path_factory.mktemp('sim_fleet'))


def _false_loop(result: FleetResult, robot: int, q: int, peer: int, m: int,
                shift_m: tuple[float, float]) -> LoopCandidate:
    """A loop of ``robot``'s keyframe ``q`` to ``peer``'s ``m`` that places ``robot`` shifted
    by ``shift_m`` (x, y metres) in the world: loops with one shift agree with each other."""
    S = np.eye(4)
    S[:2, 3] = shift_m
    ref_q, ref_m = result.reference[robot][q], result.reference[peer][m]
    Z = np.linalg.solve(ref_m, np.linalg.solve(S, ref_q))
    return LoopCandidate(q, m, result.stamps[robot][q], result.stamps[peer][m], peer, 0.1, 0.0,
                         1.0, True, tuple(matrix_to_vector(Z)), covariance=TIGHT,
                         reason='verified')


def _inject(monkeypatch: pytest.MonkeyPatch, fakes: list[tuple[int, LoopCandidate]]) -> None:
    """Every robot's verification publishes the fake loops of its keyframes besides its own."""
    by = {(robot, c.query_index): c for robot, c in fakes}
    original = LoopClosure.verify

    def verify(self: LoopClosure, proposal: object) -> object:
        result = original(self, proposal)  # type: ignore[arg-type]
        fake = by.get((self.config.session_id, result.query_index))
        return result if fake is None else dataclasses.replace(result,
                                                               loops=(*result.loops, fake))

    monkeypatch.setattr(LoopClosure, 'verify', verify)


def _moved(clean: FleetResult, other: FleetResult) -> list[tuple[float, float]]:
    """Per robot: the largest move of a keyframe in the fleet frame, and its clean ATE."""
    out = []
    assert len(clean.trajectories) == len(other.trajectories) > 1
    for a, b, row in zip(clean.trajectories, other.trajectories,
                         clean.report['fleet_map']['robots'], strict=True):
        assert b.placed and np.array_equal(a.stamps_ns, b.stamps_ns)
        move = float(np.max(np.linalg.norm(a.poses[:, :3, 3] - b.poses[:, :3, 3], axis=1)))
        out.append((move, row['ate_m']))
    return out


@pytest.mark.slow
def test_hku1_cut_in_two_is_one_map(hku1_fleet: Fleet, tmp_path: Path) -> None:
    result = hku1_fleet.clean
    assert result is not None
    fm = result.report['fleet_map']
    print('hku1 fleet map:', json.dumps(fm))
    assert [rb['placed'] for rb in fm['robots']] == [True, True]
    assert fm['joint_ate_m'] < 0.2, fm
    # The drifting odometry of robot 1 is worse than the map it is placed with.
    assert fm['robots'][1]['ate_m'] < 0.5 * fm['robots'][1]['odometry_ate_m']
    for row in fm['alignments']:
        assert row['aligned'] and row['inliers'] >= 10 and row['jumps'] == 0, row
    assert result.report['inter_robot']['false'] == 0
    assert any('robot 1 aligned' in line for _, _, line in result.alignment_events)
    files = write_fleet_outputs(tmp_path, result)
    names = {f.name for f in files}
    assert {'trajectory_robot0.tum', 'trajectory_robot1.tum', 'fleet_map.png'} <= names
    stamps, poses = read_tum_poses(tmp_path / 'trajectory_robot1.tum')
    assert np.array_equal(stamps, result.trajectories[1].stamps_ns)
    assert np.allclose(poses, result.trajectories[1].poses, atol=1e-6)


@pytest.mark.slow
def test_false_loops_on_hku1_move_no_trajectory(hku1_fleet: Fleet,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    clean = hku1_fleet.clean
    assert clean is not None
    fakes = [(1, _false_loop(clean, 1, 30, 0, 5, (20.0, 0.0)))]  # alone
    fakes += [(1, _false_loop(clean, 1, q, 0, m, (0.0, -20.0)))  # a burst that agrees
              for q, m in ((40, 50), (41, 51), (42, 52))]
    _inject(monkeypatch, fakes)
    result = hku1_fleet.run()
    assert result.report['inter_robot']['false'] == 4  # published, and scored as false
    moved = _moved(clean, result)
    print('hku1 with 4 false loops: moved, ATE per robot', moved)
    assert all(move <= 0.05 * ate for move, ate in moved), moved
    alignments = result.report['fleet_map']['alignments']
    assert alignments and all(row['rival'] <= 3 for row in alignments)


@pytest.mark.slow
def test_three_simulated_robots_are_one_map(sim_fleet: Fleet) -> None:
    result = sim_fleet.clean
    assert result is not None
    fm = result.report['fleet_map']
    print('simulated fleet map:', json.dumps(fm))
    assert all(rb['placed'] for rb in fm['robots'])
    assert fm['joint_ate_m'] < 0.4, fm
    assert len(fm['alignments']) == 6 and all(r['aligned'] for r in fm['alignments'])
    # The robots' own maps are random rigid transforms apart: only the alignments make the
    # joint error small (each robot's own-map error is small under its own SE(3) fit).
    assert all(rb['ate_m'] < 0.4 for rb in fm['robots'])
    assert result.report['inter_robot']['false'] == 0


@pytest.mark.slow
def test_a_false_burst_before_any_true_loop_moves_no_simulated_robot(
        sim_fleet: Fleet, monkeypatch: pytest.MonkeyPatch) -> None:
    clean = sim_fleet.clean
    assert clean is not None
    # Robot 2's first keyframes, before it publishes any loop, claim robot 0's start 20 m off
    # (a burst of three that agree); robot 1 later claims one loop to robot 2, 20 m off too.
    fakes = [(2, _false_loop(clean, 2, q, 0, q, (20.0, 0.0))) for q in (0, 1, 2)]
    fakes.append((1, _false_loop(clean, 1, 20, 2, 4, (0.0, 20.0))))
    _inject(monkeypatch, fakes)
    result = sim_fleet.run()
    assert result.report['inter_robot']['false'] == 4
    moved = _moved(clean, result)
    print('simulated fleet with 4 false loops: moved, ATE per robot', moved)
    assert all(move <= 0.05 * ate for move, ate in moved), moved
