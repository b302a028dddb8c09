"""Tests of the offline fleet replay: one bag per robot, scored on inter-robot loops."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from hku1_data import hku1_scans
from project_paths import CONFIG_DIR

from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import ConfigError
from solid_ros.formats.bags import write_cloud_bag
from solid_ros.formats.poses import read_kitti_poses
from solid_ros.tools.fleet import FLEET_CSV_COLUMNS, replay_fleet
from solid_ros.tools.fleet_scoring import FleetResult, RobotRun, fleet_report
from solid_ros.tools.options import ReplayOptions
from solid_ros.tools.replay import main

pytest.importorskip('small_gicp', reason='small-gicp is not installed')

CFG = SolidConfig.from_yaml(CONFIG_DIR / 'hdl64.yaml').replace(exclude_recent_frames=5)
T0 = 10**18


def _robot_bag(path: Path, first: int, offset_ns: int) -> Path:
    """Ten scans of the demo town from ``first``, 0.2 s apart from ``T0 + offset_ns``."""
    from solid_ros.sim.bagwriter import DEMO_DEFAULTS
    from solid_ros.sim.drive import Drive, DriveConfig

    drive = Drive(DriveConfig(**DEMO_DEFAULTS))
    items = []
    for i in range(10):
        scan = drive.scan(first + i)
        items.append((scan.points.copy(), T0 + offset_ns + i * 200_000_000, scan.pose))
    return write_cloud_bag(path, items, 'mcap')


@pytest.fixture(scope='module')
def robots(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Robot 0 drives scans 0-9 of the demo town; robot 1, interleaved 0.1 s later, drives
    scans 166-175, which revisit 0-9 in the same direction on another lane."""
    tmp = tmp_path_factory.mktemp('fleet')
    return _robot_bag(tmp / 'robot0', 0, 0), _robot_bag(tmp / 'robot1', 166, 100_000_000)


def test_robots_find_each_others_places_with_correct_poses(robots: tuple[Path, Path]) -> None:
    result = replay_fleet(robots, CFG)
    rep = result.report
    inter = rep['inter_robot']
    assert inter['false'] == 0 and inter['correct'] >= 15, inter
    assert inter['recall'] >= 0.8, inter
    # Both directions: robot 0's later scans also find robot 1's interleaved keyframes.
    for rb in rep['robots']:
        assert rb['keyframes'] == 10 and rb['inter_robot']['correct'] >= 5, rb
    # Scored independently here: T maps the query into the other robot's match frame.
    for robot, loops in enumerate(result.published):
        for c in loops:
            assert c.match_session == 1 - robot and c.verified
            ref = np.linalg.solve(result.reference[c.match_session][c.match_index],
                                  result.reference[robot][c.query_index])
            assert np.linalg.norm(ref[:3, 3] - c.matrix()[:3, 3]) < 0.2


def test_evicted_peer_clouds_are_never_published(tmp_path: Path,
                                                 robots: tuple[Path, Path]) -> None:
    # Robot 1 comes after robot 0 has finished; robot 0 keeps only its 2 newest clouds, so
    # robot 1's candidates against older keyframes cannot be verified: dropped, not published.
    late = _robot_bag(tmp_path / 'late', 166, 10 * 10**9)
    full = replay_fleet([robots[0], late], CFG)
    assert full.report['robots'][1]['inter_robot']['correct'] >= 8, full.report
    result = replay_fleet([robots[0], late], CFG.replace(cloud_capacity=2))
    reasons = result.report['robots'][1]['reasons']
    assert reasons.get('peer_evicted', 0) >= 5, reasons
    assert result.report['inter_robot']['false'] == 0
    # Only robot 0's two newest keyframes still have a cloud to verify against.
    assert {c.match_index for c in result.published[1]} <= {8, 9}, result.published[1]


def test_cli_writes_fleet_outputs(tmp_path: Path, robots: tuple[Path, Path],
                                  capsys: pytest.CaptureFixture[str]) -> None:
    params = tmp_path / 'fleet.yaml'
    params.write_text((CONFIG_DIR / 'hdl64.yaml').read_text())
    out = tmp_path / 'out'
    code = main([str(robots[0]), str(robots[1]), '--params', str(params), '--set',
                 'exclude_recent_frames=5', '--out', str(out), '--progress', 'lines'])
    text = capsys.readouterr().out
    assert code == 0, text
    assert 'fleet summary (2 robots' in text and 'inter-robot' in text
    report = json.loads((out / 'report.json').read_text())
    assert report['inter_robot']['false'] == 0 and report['inter_robot']['correct'] >= 15
    assert report['config']['exclude_recent_frames'] == 5
    with (out / 'candidates.csv').open() as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == FLEET_CSV_COLUMNS
    assert len(rows) == report['inter_robot']['published'] + report['own']['published']
    assert all(r['pose_correct'] == '1' and r['inter_robot'] == '1' for r in rows)
    assert {r['robot'] for r in rows} == {'0', '1'}


def test_fleet_refusals(tmp_path: Path, robots: tuple[Path, Path],
                        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ConfigError, match='two or more bags'):
        replay_fleet(robots[:1], CFG)
    # The API refuses what belongs to one bag (the command line ignores it, below).
    with pytest.raises(ConfigError, match='poses, load_db: for one bag only; a fleet replay '
                                          'has 2 bags'):
        replay_fleet(robots, CFG, poses='p.txt', load_db='db.npz')
    # --times without --poses, --map without --out: for one bag a bad command line (exit 2),
    # for a fleet ignored like the rest; here the missing bag is then the error.
    assert main([str(robots[0]), str(tmp_path / 'gone'), '--times', 't.txt', '--map']) == 1
    err = capsys.readouterr().err.splitlines()
    assert [line.split(' (')[0] for line in err[:2]] == [
        'solid_replay: ignored for a fleet replay: --times',
        'solid_replay: ignored for a fleet replay: --map'], err
    assert len(err) == 3 and 'gone' in err[2], err
    for alone in (['--times', 't.txt'], ['--map']):
        with pytest.raises(SystemExit) as exc:
            main([str(robots[0]), *alone])
        assert exc.value.code == 2
    capsys.readouterr()
    # A bag without odometry cannot be scored: one line, exit 1.
    bare = write_cloud_bag(tmp_path / 'bare', [(np.zeros((10, 3)) + 5.0, T0, None)], 'mcap')
    assert main([str(robots[0]), str(bare), '-q']) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'no nav_msgs/Odometry topic' in err[0], err


def test_cli_takes_every_option_and_ignores_those_of_one_bag_with_a_line_each(
        tmp_path: Path, robots: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    poses = tmp_path / 'poses.txt'
    poses.write_text('1 0 0 0 0 1 0 0 0 0 1 0\n')
    db, out = tmp_path / 'fleet.npz', tmp_path / 'out'
    # Bags before, between and after the options; --no-odom and --max-heading-deg apply.
    code = main([str(robots[0]), '--no-plots', '--poses', str(poses), '--times', 'times.txt',
                 '--save-db', str(db), '--load-db', str(tmp_path / 'none.npz'), '--map',
                 str(robots[1]), '--no-odom', '--max-heading-deg', '30', '--set',
                 'exclude_recent_frames=5', 'num_candidates=3', '--out', str(out), '-q'])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.out == ''  # -q: no summary; the notes below are about the command line
    assert captured.err.splitlines() == [
        f'solid_replay: ignored for a fleet replay: {flag} ({why})' for flag, why in (
            ('--poses', "a fleet is scored against each bag's odometry"),
            ('--times', 'it goes with --poses'),
            ('--load-db', 'each robot starts a database of its own'),
            ('--save-db', 'each robot has a database of its own; none is saved'),
            ('--map', 'a fleet replay writes no map of clouds'))]
    assert not db.exists()
    report = json.loads((out / 'report.json').read_text())
    assert report['odometry_fed'] == 'none' and report['max_heading_deg'] == 30.0
    assert report['config']['exclude_recent_frames'] == 5
    assert report['config']['num_candidates'] == 3
    # Without odometry every scan is a keyframe, and the robots still find each other.
    assert [rb['keyframes'] for rb in report['robots']] == [10, 10]
    assert report['inter_robot']['false'] == 0 and report['inter_robot']['correct'] >= 10
    # One bag: the same options are its own (the missing poses file is an error there).
    assert main([str(robots[0]), '--poses', str(tmp_path / 'nope.txt'), '-q']) == 1
    assert 'cannot read poses' in capsys.readouterr().err


def test_kiss_icp_odometry_is_fed_to_every_robot(robots: tuple[Path, Path]) -> None:
    pytest.importorskip('kiss_icp', reason='kiss-icp is not installed')
    result = replay_fleet(robots, CFG, odometry='kiss-icp')
    assert result.report['odometry_fed'] == 'kiss-icp'
    assert result.report['config']['backend_step_registration'] == 'on'  # 'auto' resolved
    # KISS-ICP barely moves over the simulator's ringed ground (doc/odometry.md),
    # so its keyframes by distance are fewer than the bag odometry's ten.
    assert all(1 <= rb['keyframes'] < 10 for rb in result.report['robots'])


def test_heading_gate_applies_to_the_fleet_ground_truth() -> None:
    def poses(yaw_deg: float) -> np.ndarray:
        out = np.tile(np.eye(4), (2, 1, 1))
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        out[:, :2, :2] = [[c, -s], [s, c]]
        out[1, 0, 3] = 1.0
        return out

    result = FleetResult([Path('a'), Path('b')], stamps=[[1, 2], [3, 4]],
                         reference=[poses(0.0), poses(40.0)], published=[[], []],
                         errors=[[], []])
    runs = [RobotRun('ok', 0, {})] * 2
    for heading, expected in ((None, 2), (45.0, 2), (30.0, 0)):
        opts = ReplayOptions(max_heading_deg=heading)
        report = fleet_report(result, runs, CFG, opts)
        assert report['robots'][1]['inter_robot']['queries_with_true_loop'] == expected
        assert report['max_heading_deg'] == heading


def test_hku1_split_into_two_robots(shared_data: Path, tmp_path: Path) -> None:
    """hku1's first half is robot 0, its second half robot 1, which returns to robot 0's
    start (keyframes ~274-313 revisit ~19-34): inter-robot loops with correct poses."""
    clouds, stamps = hku1_scans(shared_data)
    poses = read_kitti_poses(shared_data / 'hku1' / 'optimized_poses.txt')
    half = len(clouds) // 2
    bags = [write_cloud_bag(tmp_path / name, [(clouds[i], stamps[i], poses[i]) for i in part],
                            'mcap')
            for name, part in (('first', range(half)), ('second', range(half, len(clouds))))]
    result = replay_fleet(bags, SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml'))
    inter = result.report['inter_robot']
    print('hku1 split, inter-robot:', inter)
    assert inter['precision'] >= 0.98 and inter['recall'] >= 0.5, inter
    assert result.report['robots'][1]['inter_robot']['correct'] >= 10
