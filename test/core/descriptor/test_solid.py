"""Descriptor: golden match with the authors' files, FOV clipping, robustness."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from project_paths import CONFIG_DIR

from solid_ros import SolidConfig, cosine_distance, describe
from solid_ros.core.descriptor.solid import fov_mask, preprocess, voxel_downsample
from solid_ros.formats.pointfiles import read_kitti_bin, read_pcd


def _golden(data: Path, frame: int) -> tuple[np.ndarray, np.ndarray]:
    path = data / 'kitti' / 'golden' / f'golden_{frame}.txt'
    values = path.read_text().split()
    n_r, n_a = int(values[0]), int(values[1])
    vec = np.array(values[2:], dtype=np.float64)
    assert vec.size == n_r + n_a
    return vec[:n_r], vec[n_r:]


@pytest.mark.parametrize('frame', [313, 314, 315])
def test_reproduces_authors_golden_descriptors(shared_data: Path, frame: int) -> None:
    points = read_pcd(shared_data / 'kitti' / 'pcd' / f'000{frame}.pcd')
    r_ref, a_ref = _golden(shared_data, frame)
    desc = describe(points, SolidConfig())
    np.testing.assert_allclose(desc.r_solid, r_ref, rtol=1e-6, atol=0)
    np.testing.assert_allclose(desc.a_solid, a_ref, rtol=1e-6, atol=0)


def test_golden_cosine_similarities(shared_data: Path) -> None:
    desc = {f: describe(read_pcd(shared_data / 'kitti' / 'pcd' / f'000{f}.pcd'))
            for f in (313, 314, 315)}
    similarity_314 = 1.0 - cosine_distance(desc[313].r_solid, desc[314].r_solid)
    similarity_315 = 1.0 - cosine_distance(desc[313].r_solid, desc[315].r_solid)
    assert similarity_314 == pytest.approx(0.98338, abs=1e-4)
    assert similarity_315 == pytest.approx(0.96573, abs=1e-4)


def test_descriptor_parts_are_consistent(shared_data: Path) -> None:
    desc = describe(read_pcd(shared_data / 'kitti' / 'pcd' / '000313.pcd'))
    assert desc.rec.shape == (40, 32) and desc.aec.shape == (60, 32)
    np.testing.assert_allclose(desc.ec, desc.aec.sum(axis=0))
    assert desc.iev.min() == 0.0 and desc.iev.max() == 1.0
    np.testing.assert_allclose(desc.r_solid, desc.rec @ desc.iev)
    assert desc.rec.sum() == desc.num_points


@pytest.mark.parametrize('fov', [60, 120, 180])
@pytest.mark.parametrize('frame', ['000000', '000001'])
def test_fov_clip_keeps_the_authors_points(shared_data: Path, fov: int, frame: str) -> None:
    full = read_kitti_bin(shared_data / 'kitti' / 'seq00_frames' / f'{frame}.bin')
    clipped = read_kitti_bin(shared_data / 'kitti' / 'seq00_fov_clipped' / f'fov{fov}' /
                             f'{frame}.bin')
    ours = full[fov_mask(full[:, 0], full[:, 1], fov)]
    assert len(ours) == len(clipped)
    theirs = {tuple(p) for p in clipped[:, :3].tolist()}
    assert all(tuple(p) in theirs for p in ours[:, :3].tolist())
    # The full pipeline clips the same way: describing either input gives one descriptor.
    cfg = SolidConfig(fov_width_deg=fov)
    np.testing.assert_allclose(describe(full, cfg).r_solid, describe(clipped, cfg).r_solid)


def test_narrow_fov_still_tells_revisit_from_other_place(shared_data: Path) -> None:
    cfg = SolidConfig(fov_width_deg=60)
    frames = shared_data / 'kitti' / 'seq00_fov_clipped' / 'fov60'
    d = {f: describe(read_kitti_bin(frames / f'{f}.bin'), cfg).r_solid
         for f in ('000000', '000001', '000060')}
    assert cosine_distance(d['000001'], d['000000']) < cosine_distance(d['000060'], d['000000'])


def test_fov_centre_selects_the_heading() -> None:
    x = np.array([10.0, 0.0, -10.0, 0.0])
    y = np.array([0.0, 10.0, 0.0, -10.0])
    assert fov_mask(x, y, 90.0, 0.0).tolist() == [True, False, False, False]
    assert fov_mask(x, y, 90.0, 90.0).tolist() == [False, True, False, False]
    assert fov_mask(x, y, 90.0, 180.0).tolist() == [False, False, True, False]
    assert fov_mask(x, y, 90.0, -90.0).tolist() == [False, False, False, True]


def _assert_zero(desc: object) -> None:
    for name in ('r_solid', 'a_solid'):
        vec = getattr(desc, name)
        assert np.isfinite(vec).all() and not vec.any()


@pytest.mark.parametrize('points', [
    np.empty((0, 3)), np.empty((0, 4), dtype=np.float32), np.full((100, 3), np.nan),
    np.full((10, 3), np.inf), np.zeros((50, 3)), np.array([[500.0, 0.0, 0.0]]), [],
], ids=['empty', 'empty4', 'all-nan', 'inf', 'zeros', 'beyond-gate', 'list'])
def test_degenerate_input_gives_zero_descriptor(points: np.ndarray) -> None:
    desc = describe(points, SolidConfig())
    _assert_zero(desc)
    assert desc.num_points == 0


def test_single_point_and_mixed_invalid_points() -> None:
    pts = np.array([[10.0, 0.0, -1.0], [np.nan, 1, 1], [np.inf, 0, 0], [0, 0, 0]])
    desc = describe(pts, SolidConfig())
    assert desc.num_points == 1
    assert np.isfinite(desc.r_solid).all() and desc.r_solid.sum() > 0
    assert np.flatnonzero(desc.r_solid).tolist() == [5]  # r = 10 m, bins of 2 m


def test_points_beyond_lmax_do_not_pile_into_last_bin() -> None:
    cfg = SolidConfig(min_range=0.0, max_range=500.0, max_distance=50.0, voxel_size=0.0)
    rng = np.random.default_rng(1)
    near = rng.uniform(-20, 20, (500, 3)) * [1, 1, 0.1]
    far = np.column_stack([rng.uniform(60, 400, 500), np.zeros(500), np.zeros(500)])
    desc_near = describe(near, cfg)
    desc_both = describe(np.vstack([near, far]), cfg)
    np.testing.assert_allclose(desc_both.rec, desc_near.rec)


def test_origin_point_without_range_gate_is_finite() -> None:
    cfg = SolidConfig(min_range=0.0, voxel_size=0.0)
    desc = describe(np.zeros((3, 3)), cfg)
    assert np.isfinite(desc.r_solid).all()


def test_constant_elevation_counts_keep_information() -> None:
    # One point per elevation bin gives a constant EC: weights must not collapse to zero.
    cfg = SolidConfig(min_range=0.0, voxel_size=0.0, num_height=2, fov_up_deg=10,
                      fov_down_deg=-10)
    pts = np.array([[10.0, 0.0, -1.0], [10.0, 0.0, 1.0]])
    assert describe(pts, cfg).r_solid.sum() > 0


@pytest.mark.slow
def test_five_million_points_are_deterministic() -> None:
    rng = np.random.default_rng(7)
    pts = rng.normal(0.0, 25.0, (5_000_000, 3)).astype(np.float32)
    pts[::1000] = np.nan
    a, b = describe(pts), describe(pts)
    assert np.isfinite(a.r_solid).all() and a.r_solid.sum() > 0
    np.testing.assert_array_equal(a.r_solid, b.r_solid)
    np.testing.assert_array_equal(a.a_solid, b.a_solid)


def test_float32_float64_and_extra_columns_agree(shared_data: Path) -> None:
    pts = read_pcd(shared_data / 'kitti' / 'pcd' / '000314.pcd')
    ref = describe(pts)
    with_intensity = np.column_stack([pts, np.ones(len(pts), np.float32)])
    np.testing.assert_allclose(describe(with_intensity).r_solid, ref.r_solid)
    np.testing.assert_allclose(describe(pts.astype(np.float64)).r_solid, ref.r_solid,
                               rtol=1e-6)


def test_bad_shape_raises_package_error() -> None:
    from solid_ros import SolidError
    with pytest.raises(SolidError, match='shape'):
        describe(np.ones((10, 2)))


def _naive_voxel(points: np.ndarray, leaf: float) -> np.ndarray:
    cells: dict[tuple[int, ...], list[np.ndarray]] = {}
    for p in points:
        cells.setdefault(tuple(np.floor(p / leaf).astype(int)), []).append(p)
    return np.array(sorted(np.mean(v, axis=0).tolist() for v in cells.values()))


@pytest.mark.parametrize('spread', [5.0, 1e6])  # 1e6 takes the unpacked fallback path
def test_voxel_grid_matches_naive_centroids(spread: float) -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform(-spread, spread, (2000, 3))
    pts = np.vstack([pts, pts[:500] + 0.01])  # shared cells
    got = np.array(sorted(voxel_downsample(pts, 0.5).tolist()))
    np.testing.assert_allclose(got, _naive_voxel(pts, 0.5), atol=1e-9)


def test_preprocess_gate_is_strict_and_3d() -> None:
    cfg = SolidConfig(min_range=3.0, max_range=10.0, voxel_size=0.0)
    pts = np.array([[3.0, 0, 0], [0, 0, 3.0001], [10.0, 0, 0], [6.0, 0, 8.1]])
    np.testing.assert_array_equal(preprocess(pts, cfg), [[0, 0, 3.0001]])


def test_heading_signature_is_a_solid_or_range_weighted(shared_data: Path) -> None:
    pts = read_pcd(shared_data / 'kitti' / 'pcd' / '000313.pcd')
    plain = describe(pts, SolidConfig())
    np.testing.assert_array_equal(plain.heading, plain.a_solid)
    weighted = describe(pts, SolidConfig(heading_weight='range'))
    np.testing.assert_array_equal(weighted.a_solid, plain.a_solid)  # A-SOLiD stays the paper's
    assert not np.allclose(weighted.heading / np.linalg.norm(weighted.heading),
                           plain.a_solid / np.linalg.norm(plain.a_solid))
    # Same points at twice the range weigh four times as much (r squared).
    cfg = SolidConfig(heading_weight='range', voxel_size=0.0, min_range=0.0)
    near = describe(np.array([[10.0, 0.0, -1.0]]), cfg).heading
    far = describe(np.array([[20.0, 0.0, -2.0]]), cfg).heading
    assert far.sum() == pytest.approx(4 * near.sum())


# --- A straightforward re-implementation, the oracle for bit identity: plain numpy, no bit
# packing and no one-pass tricks of the core; only the summation order is shared (points of a
# cell summed in input order, cells in lexicographic order), as bit identity needs it.

def _reference_voxel(cols: np.ndarray, leaf: float) -> np.ndarray:
    n = cols.shape[1]
    if n == 0:
        return np.zeros((3, 0))
    cells = np.floor(cols * cols.dtype.type(1.0 / leaf)).astype(np.int64)
    _, inverse = np.unique(cells.T, axis=0, return_inverse=True)
    order = np.argsort(inverse.ravel(), kind='stable')
    key = inverse.ravel()[order]
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    sums = np.add.reduceat(np.take(cols, order, axis=1), start, axis=1, dtype=np.float64)
    sums /= np.diff(np.append(start, n))
    return sums


def _reference_fov(x: np.ndarray, y: np.ndarray, width: float, center: float) -> np.ndarray:
    if width >= 360.0:
        return np.ones(np.shape(x), dtype=bool)
    rel = np.arctan2(y, x)
    np.degrees(rel, out=rel)
    if center != 0.0:
        rel -= center - 180.0
        np.mod(rel, 360.0, out=rel)
        rel -= 180.0
    np.abs(rel, out=rel)
    return rel <= 0.5 * width


def _reference_describe(points: np.ndarray, cfg: SolidConfig) -> dict[str, np.ndarray]:
    arr = np.asarray(points)
    if arr.size == 0:
        cols = np.empty((3, 0))
    else:
        if arr.dtype not in (np.float32, np.float64):
            arr = arr.astype(np.float64)
        cols = np.ascontiguousarray(arr[:, :3].T)
    if cols.shape[1] == 0:
        pre = np.zeros((3, 0))
    else:
        x, y, z = cols
        with np.errstate(invalid='ignore', over='ignore'):
            d2 = x * x
            d2 += y * y
            d2 += z * z
        keep = d2 > cfg.min_range ** 2
        keep &= d2 < cfg.max_range ** 2
        if cfg.fov_width_deg < 360.0:
            with np.errstate(invalid='ignore'):
                keep &= _reference_fov(x, y, cfg.fov_width_deg, cfg.fov_center_deg)
        if not keep.all():
            cols = np.stack([np.compress(keep, c) for c in cols])
        pre = (_reference_voxel(cols, cfg.voxel_size) if cfg.voxel_size > 0.0
               else cols.astype(np.float64))
    n_r, n_a, n_e = cfg.num_range, cfg.num_angle, cfg.num_height
    x, y, z = pre
    r = np.hypot(x, y)
    inside = r < cfg.max_distance
    x, y, z, r = x[inside], y[inside], z[inside], r[inside]
    theta = np.degrees(np.arctan2(y, x))
    theta[theta < 0.0] += 360.0
    phi = np.degrees(np.arctan2(z, r))
    ir = np.minimum((r * (n_r / cfg.max_distance)).astype(np.int64), n_r - 1)
    ia = np.minimum((theta * (n_a / 360.0)).astype(np.int64), n_a - 1)
    gap_e = (cfg.fov_up_deg - cfg.fov_down_deg) / n_e
    ie = np.clip(((phi - cfg.fov_down_deg) / gap_e).astype(np.int64), 0, n_e - 1)
    rec = np.bincount(ir * n_e + ie, minlength=n_r * n_e).reshape(n_r, n_e).astype(np.float64)
    aec = np.bincount(ia * n_e + ie, minlength=n_a * n_e).reshape(n_a, n_e).astype(np.float64)
    ec = rec.sum(axis=0)
    lo, hi = float(ec.min()), float(ec.max())
    iev = ((ec - lo) / (hi - lo) if hi > lo else
           np.ones_like(ec) if hi > 0.0 else np.zeros_like(ec))
    heading = aec @ iev
    if cfg.heading_weight == 'range':
        a_range = np.bincount(ia * n_e + ie, weights=r * r, minlength=n_a * n_e)
        heading = a_range.reshape(n_a, n_e) @ iev
    return {'r_solid': rec @ iev, 'a_solid': aec @ iev, 'heading': heading,
            'centroids': pre}


_VIEWS = [(360.0, 0.0), (60.0, 0.0), (70.0, 0.0), (90.0, 90.0), (120.0, -45.0),
          (180.0, 0.0), (180.0, 90.0), (270.0, 180.0)]


def _assert_bit_identical(points: np.ndarray, cfg: SolidConfig) -> None:
    ref = _reference_describe(points, cfg)
    got = describe(points, cfg)
    for name in ('r_solid', 'a_solid', 'heading'):
        np.testing.assert_array_equal(getattr(got, name), ref[name], err_msg=name)
    np.testing.assert_array_equal(preprocess(points, cfg), ref['centroids'].T)


@pytest.mark.parametrize('width,center', _VIEWS)
def test_bit_identical_to_the_oracle_on_kitti(
        shared_data: Path, width: float, center: float) -> None:
    scan = read_pcd(shared_data / 'kitti' / 'pcd' / '000313.pcd')
    for weight in ('count', 'range'):
        cfg = SolidConfig(fov_width_deg=width, fov_center_deg=center, heading_weight=weight)
        _assert_bit_identical(scan, cfg)
        _assert_bit_identical(scan.astype(np.float64), cfg)


@pytest.fixture(scope='module')
def simulated_scans() -> list[np.ndarray]:
    from solid_ros.sim import simulate
    scans = []
    for sensor in ('hdl64', 'avia_like'):
        scans += [s.cloud for s in simulate(seed=4, sensor=sensor, num_scans=2)]
    return scans


@pytest.mark.parametrize('width,center', _VIEWS)
def test_bit_identical_to_the_oracle_on_simulated_scans(
        simulated_scans: list[np.ndarray], width: float, center: float) -> None:
    for cloud in simulated_scans:  # (N, 4) float32 with intensity: a strided x, y, z view
        for cfg in (SolidConfig(fov_width_deg=width, fov_center_deg=center),
                    SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml').replace(
                        fov_width_deg=width, fov_center_deg=center, heading_weight='range')):
            _assert_bit_identical(cloud, cfg)


def _edge_points() -> np.ndarray:
    # Points exactly on FOV edges (multiples of 15 deg), on the axes, and near the origin.
    rng = np.random.default_rng(11)
    ang = np.radians(np.repeat(np.arange(-180.0, 180.0, 15.0), 20))
    r = rng.uniform(0.5, 90.0, ang.size)
    ring = np.column_stack([r * np.cos(ang), r * np.sin(ang), rng.uniform(-3, 1, ang.size)])
    tiny = rng.uniform(-10, 10, (300, 3))
    tiny[::3, 0] *= 1e-12  # coordinates near zero: sums of very different magnitudes
    tiny[1::3, 2] = 1e-30
    return np.vstack([ring, tiny]).astype(np.float32)


@pytest.mark.parametrize('width,center', _VIEWS)
def test_bit_identical_on_bad_and_edge_input(shared_data: Path, width: float,
                                             center: float) -> None:
    scan = read_pcd(shared_data / 'kitti' / 'pcd' / '000314.pcd')
    dirty = scan.copy()
    dirty[::97] = np.nan
    dirty[5::101, 1] = np.inf
    dirty[7::89, 0] = -np.inf
    dirty[9::50, 2] = 1e30
    cases = [dirty, _edge_points(), np.vstack([dirty, _edge_points()]).astype(np.float64),
             np.empty((0, 3), np.float32), np.full((20, 3), np.nan, np.float32)]
    settings = [{}, {'voxel_size': 0.0}, {'min_range': 0.0, 'max_range': 120.0},
                {'voxel_size': 0.001, 'max_range': 1000.0, 'max_distance': 100.0}]
    for points in cases:
        for extra in settings:
            cfg = SolidConfig(fov_width_deg=width, fov_center_deg=center, **extra)
            _assert_bit_identical(points, cfg)
            np.testing.assert_array_equal(
                fov_mask(points[:, 0], points[:, 1], width, center),
                _reference_fov(points[:, 0], points[:, 1], width, center))
