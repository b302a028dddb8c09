"""Clouds prepared for registration: the range image read at bins, structure first."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.verification.prepared import (
    N_BINS,
    Query,
    RangeImage,
    RegistrationSettings,
    direction_bins,
)


def test_a_bin_reads_the_nearest_range_of_its_3_by_3_neighbourhood() -> None:
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(3000, 3)) * [20.0, 20.0, 3.0]
    pts[:50, 1] = -1e-9  # azimuth near 180 deg: its neighbours wrap to the first bins
    pts[50:60] = [[0.0, 0.0, 5.0]] * 10  # straight up: the last elevation row
    b, r = direction_bins(pts)
    n_el = 180
    nearest = np.full(N_BINS, np.inf)
    np.minimum.at(nearest, b, r)
    grid = nearest.reshape(-1, n_el)
    want = np.full(N_BINS, np.inf)
    for flat in range(N_BINS):
        ia, ie = divmod(flat, n_el)
        rows = [(ia + d) % grid.shape[0] for d in (-1, 0, 1)]
        cols = [min(max(ie + d, 0), n_el - 1) for d in (-1, 0, 1)]
        want[flat] = grid[np.ix_(rows, cols)].min()
    np.testing.assert_array_equal(RangeImage(pts)[np.arange(N_BINS)], want)


def test_direction_bins_follow_azimuth_and_elevation() -> None:
    b, r = direction_bins(np.array([[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]]))
    np.testing.assert_allclose(r, 10.0)
    az, el = np.divmod(b, 180)
    assert list(az) == [180, 270, 180]  # azimuth from -180 deg, CCW
    assert list(el) == [90, 90, 179]


def test_a_query_keeps_structure_first_and_refuses_too_few_points() -> None:
    pytest.importorskip('small_gicp', reason='small-gicp is not installed')
    rng = np.random.default_rng(2)
    n = 2000
    ground = np.c_[rng.uniform(-10, 10, (n, 2)), np.full(n, -1.5)]
    wall = np.c_[np.full(n, 6.0), rng.uniform(-5, 5, n), rng.uniform(-1.5, 2.0, n)]
    q = Query(np.vstack([ground, wall]), RegistrationSettings(voxel=0.25))
    cloud = q.keyframe_cloud()
    struct, rest = cloud.points[:cloud.n_struct], cloud.points[cloud.n_struct:]
    assert cloud.n_struct == pytest.approx(n, rel=0.05)
    # Normals where ground meets wall mix both: a few points on either side of the edge.
    assert np.mean(np.abs(struct[:, 0] - 6.0) < 0.3) > 0.97
    assert np.mean(np.abs(rest[:, 2] + 1.5) < 0.1) > 0.97
    assert not Query(wall[:5], RegistrationSettings()).usable


def test_the_closed_form_eigenvalues_agree_with_lapack() -> None:
    """Plane thickness reads the two least eigenvalues of each neighbourhood's scatter in
    closed form: as numpy's eigvalsh on random, planar, linear and isotropic scatters, to
    1e-12 of the trace where the two are apart."""
    from solid_ros.core.verification.prepared import _two_least_eigenvalues

    rng = np.random.default_rng(3)
    d = rng.normal(size=(500, 10, 3)) * rng.uniform(0.0, 2.0, size=(500, 1, 3))
    d[:100, :, 2] = 0.0  # planar: the least is 0
    d[100:200, :, 1:] = 0.0  # a line: two are 0
    cov = np.matmul(d.transpose(0, 2, 1), d)
    cov[200:210] = np.eye(3) * 4.0  # isotropic: all equal
    low, mid = _two_least_eigenvalues(cov)
    ev = np.linalg.eigvalsh(cov)
    scale = np.trace(cov, axis1=1, axis2=2)[:, None]
    assert np.allclose(np.stack([low, mid], axis=1) / scale, ev[:, :2] / scale, atol=1e-7)
    apart = ev[:, 1] - ev[:, 0] > 1e-3 * scale[:, 0]
    assert apart.sum() > 300 and np.allclose(low[apart] / scale[apart, 0],
                                             ev[apart, 0] / scale[apart, 0], atol=1e-12)
    assert np.allclose(low[200:210], 4.0) and np.allclose(mid[200:210], 4.0)
