"""The replay's keyframe trajectory (solid_ros.tools.trajectory): the back end through
solid_replay, its files, its errors (named apart from test/sim/test_trajectory.py: pytest
imports test modules by basename).

A short simulated drive (hdl64) that passes ten places and comes back to them, with odometry
that is 2.5 m and 4 degrees off on the way back (drift piled up in between): the loops must
bring the corrected keyframes back onto the reference, and the files must hold them.
"""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from project_paths import CONFIG_DIR

from solid_ros.core.config import SolidConfig
from solid_ros.core.geometry import rot_z, vector_to_matrix
from solid_ros.formats.bags import write_cloud_bag
from solid_ros.formats.pointfiles import read_pcd
from solid_ros.formats.poses import read_kitti_poses, read_tum_poses
from solid_ros.tools.replay import main, replay, summary_lines

SCANS = list(range(10)) + list(range(166, 176))  # the demo drive comes back to 0-9 at 166
CFG = SolidConfig.from_yaml(CONFIG_DIR / 'hdl64.yaml').replace(exclude_recent_frames=5)
T0 = 10**18


def _drift() -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rot_z(math.radians(4.0))
    out[:3, 3] = [2.5, -1.0, 0.0]
    return out


@pytest.fixture(scope='module')
def drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, np.ndarray]:
    """(bag with the drifting odometry, TUM reference file, reference poses)."""
    pytest.importorskip('small_gicp', reason='small-gicp is not installed')
    pytest.importorskip('gtsam', reason='gtsam is not installed')
    from solid_ros.sim.bagwriter import DEMO_DEFAULTS
    from solid_ros.sim.drive import Drive, DriveConfig

    sim = Drive(DriveConfig(**DEMO_DEFAULTS))
    root = tmp_path_factory.mktemp('drift')
    items, ref = [], []
    for i, k in enumerate(SCANS):
        scan = sim.scan(k)
        odom = scan.pose if i < 10 else _drift() @ scan.pose
        items.append((scan.points.copy(), T0 + i * 200_000_000, odom))
        ref.append(scan.pose)
    tum = root / 'reference.tum'
    from solid_ros.formats.poses import write_tum_poses

    write_tum_poses(tum, [s for _, s, _ in items], np.array(ref))
    return write_cloud_bag(root / 'bag', items, 'mcap'), tum, np.array(ref)


@pytest.mark.slow
def test_loops_bring_the_drifting_odometry_back(tmp_path: Path,
                                                drive: tuple[Path, Path, np.ndarray]) -> None:
    bag, tum, ref = drive
    stream = io.StringIO()
    out = tmp_path / 'out'
    result = replay(bag, CFG, poses=tum, out_dir=out, plots=True, progress='lines',
                    stream=stream)
    report = json.loads((out / 'report.json').read_text())
    t = report['trajectory']
    assert t['keyframes'] == result.keyframes == len(SCANS)
    assert t['odometry']['ate_m'] > 0.5
    assert t['corrected']['ate_m'] < 0.1 * t['odometry']['ate_m'], t
    assert report['backend']['loops_in_graph'] >= 5 and report['loops']['false'] == 0
    # Events reach the progress stream as lines, and the report counts them.
    logged = stream.getvalue()
    assert 'back end ' in logged and report['events']['counts']
    assert all(line in logged for line in report['events']['lines'])
    # One row per keyframe in both files, the corrected poses of report.json.
    stamps, tum_poses = read_tum_poses(out / 'trajectory.tum')
    kitti = read_kitti_poses(out / 'trajectory.kitti')
    rows = report['keyframes']
    assert len(rows) == len(stamps) == len(kitti) == len(SCANS)
    assert stamps.tolist() == [r['stamp_ns'] for r in rows] == result.trajectory.stamps_ns.tolist()
    corrected = np.array([vector_to_matrix(r['pose']) for r in rows])
    np.testing.assert_allclose(tum_poses, corrected, atol=1e-6)
    np.testing.assert_allclose(kitti, corrected, atol=1e-6)
    np.testing.assert_allclose(np.array([vector_to_matrix(r['odom']) for r in rows])[10:, :3, 3],
                               (_drift() @ ref[10:])[:, :3, 3], atol=1e-6)
    assert [r['index'] for r in rows] == list(range(len(SCANS)))
    text = '\n'.join(summary_lines(result))
    assert 'ATE odometry' in text and 'corrected' in text and 'KISS' not in text
    assert (out / 'trajectory.png').stat().st_size > 10_000


def test_back_end_off_writes_the_odometry_and_a_map(tmp_path: Path,
                                                    drive: tuple[Path, Path, np.ndarray],
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    bag, tum, ref = drive
    out = tmp_path / 'out'
    assert main([str(bag), '--params', str(CONFIG_DIR / 'hdl64.yaml'), '--set',
                 'exclude_recent_frames=5', '--set', 'backend=false', '--poses', str(tum),
                 '--out', str(out), '--map', '--no-plots']) == 0
    text = capsys.readouterr().out
    assert 'back end          off' in text and 'ATE odometry' in text
    report = json.loads((out / 'report.json').read_text())
    assert report['backend'] is None
    t = report['trajectory']
    assert t['corrected']['ate_m'] == pytest.approx(t['odometry']['ate_m'])
    _, poses = read_tum_poses(out / 'trajectory.tum')
    odom = np.array([vector_to_matrix(r['odom']) for r in report['keyframes']])
    np.testing.assert_allclose(poses, odom, atol=1e-6)
    cloud = read_pcd(out / 'map.pcd')
    assert len(cloud) > 1000 and np.isfinite(cloud).all()


def test_map_needs_an_output_directory(drive: tuple[Path, Path, np.ndarray],
                                       capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (['--map'], ['--no-odom', '--odometry', 'bag'], ['--odometry', 'lidar']):
        with pytest.raises(SystemExit) as exc:
            main([str(drive[0]), *argv])
        assert exc.value.code == 2
        assert capsys.readouterr().err.startswith('solid_replay: error: ')
