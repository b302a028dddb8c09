"""Tests of solid_ros.formats.poses: pose/times files, Odometry conversion, stamp association."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from solid_ros.core.geometry import rot_z
from solid_ros.formats.poses import (
    PoseError,
    format_stamp_ns,
    load_reference,
    odometry_to_pose,
    parse_stamp_ns,
    read_kitti_poses,
    read_times,
    read_tum_poses,
    write_kitti_poses,
    write_tum_poses,
)


def test_parse_stamp_is_exact() -> None:
    assert parse_stamp_ns('1577836980.0991046') == 1577836980099104600
    assert parse_stamp_ns('12') == 12_000_000_000
    assert parse_stamp_ns('.5') == 500_000_000
    assert parse_stamp_ns('-1.25') == -1_250_000_000
    assert parse_stamp_ns('1.0000000015') == 1_000_000_002  # rounds the 10th digit
    assert parse_stamp_ns('1e3') == 1_000_000_000_000
    for bad in ('abc', '1.2.3', '', 'nan'):
        with pytest.raises(ValueError):
            parse_stamp_ns(bad)


def test_kitti_round_trip(tmp_path: Path) -> None:
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[1, :3, :3] = rot_z(math.radians(30.0))
    poses[:, :3, 3] = [[0, 0, 0], [1, 2, 3], [-4, 5.5, 6]]
    path = tmp_path / 'poses.txt'
    np.savetxt(path, poses[:, :3, :].reshape(3, 12))
    got = read_kitti_poses(path)
    np.testing.assert_allclose(got, poses, atol=1e-12)


def test_kitti_bad_line_is_named(tmp_path: Path) -> None:
    path = tmp_path / 'poses.txt'
    path.write_text('1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0\n')
    with pytest.raises(PoseError, match=r'poses.txt:2: expected 12 numbers, got 3'):
        read_kitti_poses(path)
    path.write_text('1 0 0 0 0 1 0 0 0 0 1 x\n')
    with pytest.raises(PoseError, match=r':1: not a number'):
        read_kitti_poses(path)


def test_tum_reader_and_quaternion(tmp_path: Path) -> None:
    half = math.radians(90.0) / 2
    path = tmp_path / 'traj.tum'
    path.write_text('# stamp tx ty tz qx qy qz qw\n'
                    f'10.5 1 2 3 0 0 {math.sin(half)} {math.cos(half)}\n'
                    '11.0 0 0 0 0 0 0 2\n')
    stamps, poses = read_tum_poses(path)
    assert stamps.tolist() == [10_500_000_000, 11_000_000_000]
    np.testing.assert_allclose(poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(poses[0, :3, 3], [1, 2, 3])
    np.testing.assert_allclose(poses[1, :3, :3], np.eye(3), atol=1e-12)  # normalised
    path.write_text('10.5 1 2 3 0 0 0 0\n')
    with pytest.raises(PoseError, match=r'traj.tum:1: quaternion has zero length'):
        read_tum_poses(path)


def test_times_and_load_reference(tmp_path: Path) -> None:
    poses = tmp_path / 'p.txt'
    poses.write_text('1 0 0 0 0 1 0 0 0 0 1 0\n' * 3)
    times = tmp_path / 't.txt'
    times.write_text('1.0\n2.0\n3.5\n')
    track = load_reference(poses, times)
    assert len(track) == 3
    assert track.stamps_ns is not None and track.stamps_ns.tolist() == [1e9, 2e9, 3.5e9]
    assert load_reference(poses).stamps_ns is None
    times.write_text('1.0\n2.0\n')
    with pytest.raises(PoseError, match='has 3 poses but .* has 2 stamps'):
        load_reference(poses, times)
    times.write_text('1.0 2.0\n')
    with pytest.raises(PoseError, match='expected one stamp'):
        read_times(times)
    with pytest.raises(PoseError, match='cannot read poses file'):
        load_reference(tmp_path / 'missing.txt')
    odd = tmp_path / 'odd.txt'
    odd.write_text('1 2 3\n')
    with pytest.raises(PoseError, match='3 columns'):
        load_reference(odd)
    empty = tmp_path / 'empty.txt'
    empty.write_text('\n# only a comment\n')
    with pytest.raises(PoseError, match='empty'):
        load_reference(empty)


def test_odometry_to_pose() -> None:
    half = math.radians(-45.0) / 2
    msg = SimpleNamespace(pose=SimpleNamespace(pose=SimpleNamespace(
        position=SimpleNamespace(x=1.0, y=-2.0, z=0.5),
        orientation=SimpleNamespace(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)))))
    pose = odometry_to_pose(msg)
    np.testing.assert_allclose(pose[:3, :3], rot_z(math.radians(-45.0)), atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], [1.0, -2.0, 0.5])
    with pytest.raises(PoseError, match='not an Odometry'):
        odometry_to_pose(SimpleNamespace())


@pytest.mark.parametrize('row, words', [
    ('0 0 0 1 0 0 0 2 0 0 0 3', 'not a rotation matrix'),  # all-zero rotation
    ('-1 0 0 0 0 1 0 0 0 0 1 0', 'not a rotation matrix'),  # reflection
    ('2 0 0 0 0 2 0 0 0 0 2 0', 'not a rotation matrix'),  # scaled
])
def test_kitti_rotation_must_be_a_rotation(tmp_path: Path, row: str, words: str) -> None:
    f = tmp_path / 'p.txt'
    f.write_text('1 0 0 0 0 1 0 0 0 0 1 0\n' + row + '\n')
    with pytest.raises(PoseError, match=f'p.txt:2: the 3x3 part is {words}'):
        read_kitti_poses(f)


@pytest.mark.parametrize('stamps, line, words', [
    ('1.0\n2.0\n2.0\n', 3, 'repeats'), ('1.0\n3.0\n2.0\n', 3, 'is before'),
])
def test_stamps_must_increase(tmp_path: Path, stamps: str, line: int, words: str) -> None:
    f = tmp_path / 't.txt'
    f.write_text(stamps)
    with pytest.raises(PoseError, match=f't.txt:{line}: the stamp .* {words} the previous'):
        read_times(f)
    tum = tmp_path / 'tum.txt'
    tum.write_text(''.join(f'{s} 0 0 0 0 0 0 1\n' for s in stamps.split()))
    with pytest.raises(PoseError, match=f'tum.txt:{line}: pose stamp .* {words}'):
        read_tum_poses(tum)


def test_tum_and_kitti_writers_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    poses = np.tile(np.eye(4), (20, 1, 1))
    for k in range(20):
        poses[k, :3, :3] = rot_z(rng.uniform(-3.0, 3.0))
        poses[k, :3, 3] = rng.uniform(-2000.0, 2000.0, 3)
    stamps = 1_700_000_000_123_456_789 + np.arange(20, dtype=np.int64) * 100_000_001
    tum = write_tum_poses(tmp_path / 'trajectory.tum', stamps, poses)
    got_stamps, got = read_tum_poses(tum)
    np.testing.assert_array_equal(got_stamps, stamps)  # exact to the nanosecond
    np.testing.assert_allclose(got, poses, atol=1e-6)
    kitti = write_kitti_poses(tmp_path / 'trajectory.kitti', poses)
    np.testing.assert_allclose(read_kitti_poses(kitti), poses, atol=1e-6)
    assert load_reference(tum).stamps_ns is not None and load_reference(kitti).stamps_ns is None
    assert format_stamp_ns(-1_250_000_000) == '-1.250000000'
    assert parse_stamp_ns(format_stamp_ns(-5)) == -5
    with pytest.raises(PoseError, match='3 poses but 2 stamps'):
        write_tum_poses(tmp_path / 'x.tum', stamps[:2], poses[:3])
    with pytest.raises(PoseError, match='finite'):
        write_kitti_poses(tmp_path / 'x.kitti', np.full((2, 4, 4), np.nan))
