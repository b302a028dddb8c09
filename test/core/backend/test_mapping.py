"""The map: levelled keyframe clouds placed at corrected poses, thinned, bounded."""

from __future__ import annotations

import math

import numpy as np
import pytest

from solid_ros.core.backend.mapping import build_map, keyframe_clouds, mount_rotation
from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import SolidError
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.geometry import rot_z, rpy_matrix


def _wall(n: int = 400) -> np.ndarray:
    """A wall 10 m ahead in the world: x = 10, y and z spread."""
    rng = np.random.default_rng(0)
    return np.column_stack([np.full(n, 10.0), rng.uniform(-5, 5, n), rng.uniform(0, 3, n)])


def test_clouds_land_where_the_poses_and_the_mounting_put_them() -> None:
    cfg = SolidConfig(mount_roll_deg=4.0, mount_pitch_deg=-8.0)
    mount = mount_rotation(cfg)
    np.testing.assert_allclose(mount, rpy_matrix(math.radians(4.0), math.radians(-8.0), 0.0))
    world = _wall()
    clouds = []
    for k in range(3):  # three sensors looking at the same wall from different poses
        X = np.eye(4)
        X[:3, :3] = rot_z(0.2 * k) @ mount  # a tilted sensor
        X[:3, 3] = [k, -k, 1.0]
        sensor = (world - X[:3, 3]) @ X[:3, :3]  # p_sensor = X^-1 p_world
        clouds.append((X, sensor @ mount.T))  # stored levelled: p_level = R p_sensor
    got = build_map(clouds, mount, voxel_size=0.01, max_points=10**6)
    assert got.keyframes == 3 and got.voxel_size == 0.01
    np.testing.assert_allclose(got.points[:, 0], 10.0, atol=1e-4)  # all on the wall
    assert len(got.points) <= len(world) + 5  # the three views fall on the same cells


def test_the_map_is_bounded_in_points() -> None:
    rng = np.random.default_rng(1)
    clouds = [(np.eye(4), rng.uniform(-50, 50, (20_000, 3))) for _ in range(5)]
    got = build_map(clouds, np.eye(3), voxel_size=0.1, max_points=5000)
    assert 0 < len(got.points) <= 5000 and got.voxel_size > 0.1
    assert got.points.dtype == np.float32
    with pytest.raises(SolidError, match='max_points'):
        build_map(clouds, np.eye(3), voxel_size=0.0, max_points=10)


def test_keyframe_clouds_of_a_detector() -> None:
    pytest.importorskip('small_gicp', reason='small-gicp is not installed')
    det = LoopDetector(SolidConfig())
    rng = np.random.default_rng(2)
    for k in range(3):
        det.process(rng.uniform(-40.0, 40.0, (5000, 3)), k * 10**9)
    poses = {0: np.eye(4), 2: np.eye(4), 7: np.eye(4)}  # 7: no such keyframe
    got = keyframe_clouds(det, poses)
    assert len(got) == 2
    own = det.own_cloud(2)
    assert own is not None
    np.testing.assert_array_equal(got[1][1], own.points)
