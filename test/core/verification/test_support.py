"""The support measures: their numpy stand-ins for scipy equal scipy, and what a pose shows."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.verification.prepared import Query, RegistrationSettings, Source
from solid_ros.core.verification.support import Support, _cell_ids, _label

pytest.importorskip('small_gicp', reason='small-gicp is not installed')


@pytest.mark.parametrize('density', [0.05, 0.3, 0.6, 0.9])
def test_label_numbers_8_connected_components_as_scipy_does(density: float) -> None:
    ndimage = pytest.importorskip('scipy.ndimage')
    rng = np.random.default_rng(int(density * 100))
    for shape in ((1, 1), (1, 17), (23, 1), (31, 47)):
        grid = rng.random(shape) < density
        want, count = ndimage.label(grid, structure=np.ones((3, 3)))
        got, n = _label(grid)
        assert n == count
        np.testing.assert_array_equal(got, want)


def test_cell_ids_are_the_rank_among_distinct_rows() -> None:
    rng = np.random.default_rng(3)
    near = rng.integers(-5, 5, (500, 3))
    far = near.copy()
    far[::7, 0] = 2 ** 40  # too far apart to pack into one integer: the fallback
    for cells in (near, far, near[:1]):
        _, want = np.unique(cells, axis=0, return_inverse=True)
        np.testing.assert_array_equal(_cell_ids(cells.astype(np.int64)), want.reshape(-1))
    assert len(_cell_ids(np.zeros((0, 3), dtype=np.int64))) == 0


def _room(rng: np.random.Generator) -> np.ndarray:
    """A floor and four walls of an 8 m x 5 m room around the sensor."""
    n = 3000
    floor = np.c_[rng.uniform(-4, 4, n), rng.uniform(-2.5, 2.5, n), np.full(n, -1.0)]
    u, z = rng.uniform(-1, 1, (2, n)), rng.uniform(-1.0, 1.5, n)
    walls = np.vstack([np.c_[np.full(n, 4.0), 2.5 * u[0], z],
                       np.c_[np.full(n, -4.0), 2.5 * u[1], z],
                       np.c_[4 * u[1], np.full(n, 2.5), z],
                       np.c_[4 * u[0], np.full(n, -2.5), z]])
    return np.vstack([floor, walls])


def test_a_right_pose_is_supported_and_a_wrong_one_conflicts() -> None:
    settings = RegistrationSettings(voxel=0.25)
    query = Query(_room(np.random.default_rng(0)), settings)
    source = Source(query.keyframe_cloud(), settings)
    right = Support(query, source, np.eye(4), settings)
    assert right.overlap == pytest.approx(1.0)
    assert right.rmse < 0.02
    assert right.conflict == 0.0
    assert right.constraint > 0.0
    # The room's copy moved 1.5 m along x: its far wall stands in the space the query saw
    # through, and much of its structure finds no partner.
    moved = np.eye(4)
    moved[0, 3] = -1.5
    wrong = Support(query, source, moved, settings)
    assert wrong.conflict > 0.1
    assert wrong.overlap < right.overlap


def test_supporting_points_give_the_point_to_plane_information() -> None:
    settings = RegistrationSettings(voxel=0.25)
    query = Query(_room(np.random.default_rng(1)), settings)
    cloud = query.keyframe_cloud()
    sup = Support(query, Source(cloud, settings), np.eye(4), settings)
    assert sup.inliers == pytest.approx(len(cloud.points), rel=0.05)
    info = sup.information
    np.testing.assert_allclose(info, info.T)
    assert np.linalg.eigvalsh(info)[0] > 0.0  # floor and four walls pin all six directions
    weighted, total = sup.weighted_information
    assert 0.0 < total <= sup.inliers
    assert np.all(np.linalg.eigvalsh(info - weighted) >= -1e-9 * np.abs(info).max())
