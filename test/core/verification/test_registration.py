"""Free-space conflict counts coherent patches, not scattered points."""

from __future__ import annotations

import numpy as np

from solid_ros.core.verification.registration import free_space_conflict, range_image


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
    scattered[7::97] *= 0.7  # along their rays: the sensor saw the wall through them
    plain = free_space_conflict(scattered, ranges, 1.0)
    assert plain > 0.0
    assert free_space_conflict(scattered, ranges, 1.0, cell=1.0, together=3) == 0.0
    # A misplaced surface: a patch of neighbouring points in front of the wall.
    patch = cloud.copy()
    near = (np.abs(cloud[:, 1]) < 0.5) & (np.abs(cloud[:, 2]) < 0.3)
    patch[near] *= 0.7
    coherent = free_space_conflict(patch, ranges, 1.0, cell=1.0, together=3)
    assert coherent == free_space_conflict(patch, ranges, 1.0) == near.mean()
