"""Settings from the data and the overlap bar calibrated on the run (no KISS-ICP needed)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import NodeConfig
from solid_ros.core.odometry.guard import HISTORY, OverlapGuard, derive_settings, prepare

FloatArray = npt.NDArray[np.float64]


def _room(seed: int, n: int = 6000) -> FloatArray:
    """Four walls of a 16 x 10 m room with boxes on the floor, sampled at random."""
    rng = np.random.default_rng(seed)
    wall = rng.integers(0, 4, n)
    t = rng.uniform(-1.0, 1.0, n)
    x = np.where(wall == 0, 8.0, np.where(wall == 1, -8.0, 8.0 * t))
    y = np.where(wall == 2, 5.0, np.where(wall == 3, -5.0, 5.0 * t))
    z = rng.uniform(-1.5, 2.5, n)
    boxes = rng.uniform([-6, -3, -1.5], [6, 3, 0.5], (n // 4, 3))
    boxes[:, 0] = np.round(boxes[:, 0] / 3.0) * 3.0  # thin vertical slabs
    return np.r_[np.c_[x, y, z], boxes]


def _turn(deg: float) -> FloatArray:
    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


def test_max_range_and_voxel_come_from_the_first_cloud_with_points() -> None:
    rng = np.random.default_rng(0)
    ranges = rng.uniform(1.0, 70.0, 20000)
    direction = rng.normal(size=(20000, 3))
    cloud = direction / np.linalg.norm(direction, axis=1, keepdims=True) * ranges[:, None]
    empty, nan = np.zeros((0, 3)), np.full((50, 3), np.nan)
    got = derive_settings(NodeConfig(kiss_max_range=0.0, kiss_voxel_size=0.0),
                          [empty, nan, cloud, cloud * 3.0])
    want = float(np.ceil(np.percentile(ranges, 99)))
    assert got.kiss_max_range == want and 69.0 <= want <= 70.0
    assert got.kiss_voxel_size == want / 100.0  # KISS-ICP's own rule
    # A room whose corners are 9.8 m away: a 10 m range, a 0.1 m voxel.
    room = derive_settings(NodeConfig(kiss_max_range=0.0, kiss_voxel_size=0.0), [_room(0)])
    assert room.kiss_max_range == 10.0 and room.kiss_voxel_size == 0.1
    # Set values stay; with nothing to measure, nothing changes.
    fixed = NodeConfig(kiss_max_range=50.0, kiss_voxel_size=0.0)
    assert derive_settings(fixed, [cloud]).kiss_max_range == 50.0
    assert derive_settings(fixed, [cloud]).kiss_voxel_size == 0.5
    unset = NodeConfig(kiss_max_range=0.0, kiss_voxel_size=0.0)
    assert derive_settings(unset, [empty, nan]) == unset


def test_the_bar_is_the_runs_own_typical_overlap() -> None:
    guard = OverlapGuard(0.5, 0.4)
    assert guard.bar == 0.0 and guard.typical is None and not guard.fails(0.0)
    for value in (0.9, 0.92, 0.88, 0.95, 0.9):  # a sensor whose clouds overlap well
        guard.accept(value)
    assert guard.bar == 0.45 and guard.fails(0.4) and not guard.fails(0.5)
    sparse = OverlapGuard(0.5, 0.4)
    for value in (0.6, 0.65, 0.55, 0.7, 0.6):  # a fast car at 1 cloud/s
        sparse.accept(value)
    assert sparse.bar == 0.3 and not sparse.fails(0.4) and sparse.fails(0.25)
    for _ in range(HISTORY):  # the bar follows the run, not its start
        sparse.accept(0.2)
    assert abs(sparse.bar - 0.1) < 1e-12


def test_overlap_of_the_right_pose_a_turned_cloud_and_another_place() -> None:
    guard = OverlapGuard(0.5, 0.4)
    a, b = prepare(_room(1)), prepare(_room(2))  # the same room, other samples
    assert 0.3 < a.structure.mean() < 1.0 and a.constraint > 0.01
    right = guard.overlap(b, a, np.eye(4))
    turned = guard.overlap(b, a, _turn(90.0))
    shifted = np.eye(4)
    shifted[:3, 3] = [30.0, 0.0, 0.0]  # KISS-ICP followed a splice from 30 m away
    elsewhere = guard.overlap(b, a, shifted)
    assert right > 0.9, right
    assert turned < 0.3 and elsewhere == 0.0, (turned, elsewhere)
    for _ in range(5):
        guard.accept(right)
    assert not guard.fails(right) and guard.fails(turned) and guard.fails(elsewhere)
    # Too little structure to tell (a bare floor): never a failure.
    floor = np.c_[np.random.default_rng(3).uniform(-10, 10, (3000, 2)), np.zeros(3000)]
    assert guard.overlap(prepare(floor), a, np.eye(4)) == 1.0
