"""Free-space conflict: seen-through points count, explained and scattered ones do not."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.verification.free_space import free_space_conflict, range_image


def test_free_space_conflict_counts_seen_through_points_unless_explained() -> None:
    # A wall 10 m ahead seen over +-20 deg; three points 5 m ahead in seen-through space and
    # one on the wall.
    az = np.radians(np.linspace(-20.0, 20.0, 81))
    el = np.radians(np.linspace(-10.0, 10.0, 41))
    a, e = np.meshgrid(az, el)
    wall = 10.0 * np.c_[np.cos(e.ravel()) * np.cos(a.ravel()),
                        np.cos(e.ravel()) * np.sin(a.ravel()), np.sin(e.ravel())]
    ranges = range_image(wall)
    pts = np.array([[5.0, 0.0, 0.0], [5.0, 1.0, 0.0], [5.0, -1.0, 0.5], [10.0, 0.0, 0.0]])
    assert free_space_conflict(pts, ranges, 1.0) == pytest.approx(0.75)
    assert free_space_conflict(pts, ranges, 1.0, structure=2) == pytest.approx(1.0)
    explained = np.array([True, False, False, False])
    assert free_space_conflict(pts, ranges, 1.0, explained=explained) == pytest.approx(0.5)
    # Directions the sensor saw nothing in do not count at all.
    assert free_space_conflict(np.array([[0.0, 5.0, 0.0]]), ranges, 1.0) == 0.0


def _wall(x: float, n: int = 40) -> np.ndarray:
    """A wall facing the sensor at ``x`` metres, one point every 0.1 m."""
    y, z = np.meshgrid(np.linspace(-2.0, 2.0, n), np.linspace(-1.0, 1.0, n // 2))
    return np.column_stack([np.full(y.size, x), y.ravel(), z.ravel()])


def test_a_patch_in_seen_through_space_conflicts_scattered_points_do_not() -> None:
    ranges = range_image(_wall(10.0))
    cloud = _wall(10.0)
    # Scattered points 3 m in front of the wall, far from each other (a thin post one scan
    # hit, mixed pixels): point by point they conflict, as patches they do not.
    scattered = cloud.copy()
    scattered[[0, 419, 799]] *= 0.7  # along their rays: the sensor saw the wall through them
    plain = free_space_conflict(scattered, ranges, 1.0)
    assert plain > 0.0
    assert free_space_conflict(scattered, ranges, 1.0, cell=1.0, together=3) == 0.0
    # A misplaced surface: a patch of neighbouring points in front of the wall.
    patch = cloud.copy()
    near = (np.abs(cloud[:, 1]) < 0.5) & (np.abs(cloud[:, 2]) < 0.3)
    patch[near] *= 0.7
    coherent = free_space_conflict(patch, ranges, 1.0, cell=1.0, together=3)
    assert coherent == free_space_conflict(patch, ranges, 1.0) == near.mean()
