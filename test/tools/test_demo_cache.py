"""The demo's cache: one entry per drive, written once, named by the drive and the version."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from solid_ros import __version__
from solid_ros.formats.bags import Bag
from solid_ros.sim import DEMO_DEFAULTS, Drive, DriveConfig, read_kitti_poses, vlp16_like
from solid_ros.tools.demo_cache import cache_root, demo_dir, ensure_demo_bag

# A small, fast drive: 40 m blocks, a scan every 10 m.
SMALL = {'sensor': 'avia_like', 'block': 40.0, 'spacing': 10.0}


def test_entry_name() -> None:
    perfect = DriveConfig(**DEMO_DEFAULTS, perfect_odometry=True)
    assert demo_dir(perfect, '/c').name == f'hdl64-194e4ed936b62d53-{__version__}'
    drifting = DriveConfig(**DEMO_DEFAULTS)
    assert demo_dir(drifting, '/c') == Path('/c') / (
        f'hdl64-{drifting.fingerprint()}-{__version__}')


def test_demo_cache_is_written_once(tmp_path: Path) -> None:
    bag = ensure_demo_bag(cache_dir=tmp_path, **SMALL)
    assert (bag / 'metadata.yaml').is_file()
    entry = bag.parent
    assert entry == demo_dir(DriveConfig(**{'seed': 0, **SMALL}), tmp_path)
    for name in ('poses.txt', 'times.txt', 'labels.txt', 'drive.json'):
        assert (entry / name).is_file()
    stamp = (bag / 'metadata.yaml').stat().st_mtime_ns
    assert ensure_demo_bag(cache_dir=tmp_path, **SMALL) == bag
    assert (bag / 'metadata.yaml').stat().st_mtime_ns == stamp
    assert [p.name for p in tmp_path.iterdir()] == [entry.name]  # no temporary left over
    other = ensure_demo_bag(cache_dir=tmp_path, seed=1, **SMALL)
    assert other != bag
    n = len(np.loadtxt(entry / 'times.txt'))
    assert n == len(Drive(DriveConfig(**SMALL))) == len(read_kitti_poses(entry / 'poses.txt'))


def test_entry_holds_drifting_odometry_and_the_reference(tmp_path: Path) -> None:
    bag = ensure_demo_bag(cache_dir=tmp_path, **SMALL)
    drive = Drive(DriveConfig(**SMALL))
    np.testing.assert_allclose(read_kitti_poses(bag.parent / 'poses.txt'), drive.poses(),
                               atol=1e-8)
    with Bag(bag) as b:
        odom = b.odometry('/odom').poses
    np.testing.assert_allclose(odom, drive.odometry_poses(), atol=1e-6)
    assert np.linalg.norm(odom[-1, :3, 3] - drive.pose(len(drive) - 1)[:3, 3]) > 0.1
    meta = json.loads((bag.parent / 'drive.json').read_text())
    assert meta['drive']['perfect_odometry'] is False
    assert meta['drive']['odom_heading_bias_deg_per_m'] == drive.config.odom_heading_bias_deg_per_m
    perfect = ensure_demo_bag(cache_dir=tmp_path, perfect_odometry=True, **SMALL)
    with Bag(perfect) as b:
        np.testing.assert_allclose(b.odometry('/odom').poses, drive.poses(), atol=1e-6)


def test_cache_root_respects_xdg(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path))
    assert cache_root() == tmp_path / 'solid_ros' / 'demo'
    monkeypatch.delenv('XDG_CACHE_HOME')
    assert cache_root() == Path.home() / '.cache' / 'solid_ros' / 'demo'


def test_demo_bag_records_the_options(tmp_path: Path) -> None:
    options = {'sensor': vlp16_like(points_per_ring=180), 'block': 40.0, 'spacing': 10.0,
               'route': ((0, 0), (2, 0), (2, 1)), 'scene': 'lookalike', 'facade_detail': True,
               'mount_roll_deg': 2.0}
    bag = ensure_demo_bag(cache_dir=tmp_path, **options)
    entry = bag.parent
    assert entry == demo_dir(DriveConfig(**{**DEMO_DEFAULTS, **options}), tmp_path)
    meta = json.loads((entry / 'drive.json').read_text())
    drive = meta['drive']
    assert drive['route'] == [[0, 0], [2, 0], [2, 1]] and meta['route_crossings'] == [
        [0, 0], [2, 0], [2, 1]]
    assert (drive['nx'], drive['ny'], drive['scene'], drive['facade_detail']) == (
        3, 2, 'lookalike', True)
    assert drive['sensor']['name'] == 'vlp16_like' and drive['sensor']['mount_roll_deg'] == 2.0
    labels = (entry / 'labels.txt').read_text().split()[1::3]
    assert meta['labels'] == {'new': meta['num_scans']} and labels == ['new'] * meta[
        'num_scans']
    poses = read_kitti_poses(entry / 'poses.txt')
    reference = Drive(DriveConfig(**{**DEMO_DEFAULTS, **options})).poses()
    np.testing.assert_allclose(poses, reference, atol=1e-8)
    assert poses[0, 2, 1] == pytest.approx(np.sin(np.radians(2.0)))  # the roll is recorded
