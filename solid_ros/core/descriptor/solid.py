"""SOLiD descriptor: preprocessing, REC/AEC counts, IEV weighting, R-SOLiD and A-SOLiD.

Conventions (see doc/conventions.md): azimuth theta = atan2(y, x) in [0, 360) degrees CCW from +x,
horizontal range r = hypot(x, y), elevation phi = atan2(z, r). Bin indices truncate and clamp
to the last bin; elevations outside the sensor FOV clamp to the first or last elevation bin;
points with r >= max_distance are dropped rather than piled into the last range bin.

Speed without process-wide settings: the range gate and FOV clip build one mask (the FOV by
two half-plane tests, not an arctan2 per point), voxel keys are computed once for every point
with bounds taken from the range gate, one sort of (key, index) groups the cells, and the
scan-sized scratch arrays live in a per-thread workspace reused from scan to scan. The
centroids are summed in the same order as before, so the output is bit-identical to the
straightforward pipeline (test/core/descriptor/test_solid.py keeps it as the oracle).
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import SolidError
from solid_ros.core.results import Descriptor

__all__ = ['describe', 'fov_mask', 'preprocess', 'voxel_downsample']

FloatArray = npt.NDArray[np.float64]


class _Workspace(threading.local):
    """Per-thread scratch arrays reused from scan to scan.

    Every scan-sized temporary that numpy allocates afresh is served by the C library with
    new pages that must be faulted in again; with glibc's default settings that cost as much
    as the arithmetic itself. Reusing these buffers gives the speed without any process-wide
    allocator setting. Buffers above ``_MAX_CACHED_BYTES`` are not kept (huge clouds
    allocate as before), which bounds what a thread holds to a few tens of megabytes.
    """

    def __init__(self) -> None:
        self.buffers: dict[str, npt.NDArray[Any]] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: npt.DTypeLike) -> npt.NDArray[Any]:
        """Return an uninitialised array of this shape and dtype, reused when possible."""
        dt = np.dtype(dtype)
        size = math.prod(shape)
        buf = self.buffers.get(name)
        if buf is None or buf.dtype != dt or buf.size < size:
            if size * dt.itemsize > _MAX_CACHED_BYTES:
                return np.empty(shape, dtype=dt)
            buf = np.empty(size + size // 4, dtype=dt)  # headroom for slightly larger scans
            self.buffers[name] = buf
        return buf[:size].reshape(shape)


_MAX_CACHED_BYTES = 4 << 20  # per buffer: clouds up to ~350k points reuse every buffer
_WS = _Workspace()


def _as_points(points: npt.ArrayLike) -> npt.NDArray[np.floating]:
    """Return the input as a 2-D float32/float64 array (N, 3+), without copying if possible."""
    arr = np.asarray(points)
    if arr.size == 0:
        return np.empty((0, 3), dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise SolidError(f'points must have shape (N, 3+), got {arr.shape}')
    if arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float64)
    return arr


def _columns(points: npt.ArrayLike) -> npt.NDArray[np.floating]:
    """Return x, y, z as a contiguous (3, N) array in the input's float type.

    Column-major layout makes every later masked copy, gather and reduction contiguous, which
    is several times faster than working on (N, 3) rows.
    """
    arr = _as_points(points)
    return np.ascontiguousarray(arr[:, :3].T)


def _group_centroids(cols: npt.NDArray[np.floating], packed: npt.NDArray[np.int64],
                     idx_bits: int) -> FloatArray:
    """Centroids of the cells in ``packed`` = (cell key << idx_bits | point index), sorted.

    Sorting the packed values orders the points by cell key, and inside a cell by point
    index; the centroid is the float64 sum in that order divided by the count.
    """
    m = packed.shape[0]
    ws = _WS
    order = ws.get('order', (m,), np.int64)
    np.bitwise_and(packed, (1 << idx_bits) - 1, out=order)
    packed >>= idx_bits
    change = ws.get('change', (m,), np.bool_)
    change[0] = True
    np.not_equal(packed[1:], packed[:-1], out=change[1:])
    start = np.flatnonzero(change)
    gathered = ws.get('gathered', (3, m), cols.dtype)
    np.take(cols, order, axis=1, out=gathered)
    sums: FloatArray = np.add.reduceat(gathered, start, axis=1, dtype=np.float64)
    sums /= np.diff(np.append(start, m))
    return sums


def _voxel_columns(cols: npt.NDArray[np.floating], leaf: float) -> FloatArray:
    """Voxel centroids of all points in ``cols`` (3, N); cell extents taken from the data."""
    n = cols.shape[1]
    if n == 0:
        return np.zeros((3, 0))
    scaled = cols * cols.dtype.type(1.0 / leaf)
    np.floor(scaled, out=scaled)
    cells = scaled.astype(np.int64)
    del scaled
    cells -= cells.min(axis=1, keepdims=True)
    bits = [int(e).bit_length() for e in cells.max(axis=1)]
    idx_bits = max(int(n - 1).bit_length(), 1)
    if sum(bits) + idx_bits <= 62:
        # Pack (cell key, point index) into one int64 so a single value sort groups the
        # cells; several times faster than np.unique(..., return_inverse=True).
        packed = cells[0]
        packed <<= bits[1]
        packed |= cells[1]
        packed <<= bits[2]
        packed |= cells[2]
        packed <<= idx_bits
        packed |= np.arange(n, dtype=np.int64)
        packed.sort()
        return _group_centroids(cols, packed, idx_bits)
    # Cells too far apart to pack: slower but general; the same (cell, index) order.
    _, inverse = np.unique(cells.T, axis=0, return_inverse=True)
    order = np.argsort(inverse.ravel(), kind='stable')
    skey = inverse.ravel()[order]
    change = np.empty(n, dtype=bool)
    change[0] = True
    np.not_equal(skey[1:], skey[:-1], out=change[1:])
    start = np.flatnonzero(change)
    sums: FloatArray = np.add.reduceat(np.take(cols, order, axis=1), start, axis=1,
                                       dtype=np.float64)
    sums /= np.diff(np.append(start, n))
    return sums


def _cell_keys(cols: npt.NDArray[np.floating], leaf: float, reach: float,
               drop: npt.NDArray[np.bool_] | None = None,
               ) -> tuple[npt.NDArray[np.signedinteger[Any]], int] | None:
    """Voxel cell key of every point in ``cols`` (3, N), and the bits the keys use.

    The cell bounds come from ``reach`` (the range gate) instead of the data, so the keys
    are computed once for all points and only the kept ones are then used: no copy of the
    points themselves. Points in ``drop`` get a key above every cell's; keys of other points
    beyond ``reach`` (or NaN) would be garbage. Keys order the cells lexicographically by
    (cx, cy, cz), for any offset, as :func:`_voxel_columns` does. None when the keys (and a
    point index beside them) do not fit in 63 bits.
    """
    n = cols.shape[1]
    ws = _WS
    lo = math.floor(-reach * 1.01 / leaf) - 2  # margin for rounding of the gate and scale
    cell_bits = (2 * (-lo) + 1).bit_length()
    key_bits = 3 * cell_bits + 1  # one more for the key of dropped points
    if key_bits + max(int(n - 1).bit_length(), 1) > 63:
        return None
    offset = -lo * ((1 << (2 * cell_bits)) + (1 << cell_bits) + 1)  # makes every field >= 0
    # 32-bit keys when they fit (half the memory traffic), else 64-bit.
    key_type = np.int32 if key_bits <= 31 else np.int64
    scaled = ws.get('scaled', (3, n), cols.dtype)
    cells = ws.get('cells', (3, n), key_type)
    with np.errstate(invalid='ignore', over='ignore'):
        np.multiply(cols, cols.dtype.type(1.0 / leaf), out=scaled)
        np.floor(scaled, out=scaled)
        np.copyto(cells, scaled, casting='unsafe')  # exact: whole numbers within the bounds
    key, cy, cz = cells
    key <<= 2 * cell_bits
    cy <<= cell_bits
    key += cy
    key += cz
    key += offset
    if drop is not None:
        np.copyto(key, 1 << (key_bits - 1), where=drop)
    return key, key_bits


def _run_centroids(cols: npt.NDArray[np.floating], key: npt.NDArray[np.signedinteger[Any]],
                   key_bits: int, kept: int) -> FloatArray:
    """Centroids of the cells in ``key`` (one per point of ``cols``), in key order.

    Scans come ring by ring, so neighbouring points often share a cell: runs of equal keys
    are sorted instead of points (5x fewer on KITTI), by (key, first index). Laid end to
    end, the sorted runs list each cell's points in increasing index, which is the order in
    which the centroid sums are taken: the same as sorting the points by (key, index). Only
    the first ``kept`` points in that order are used (dropped points have the largest key).
    """
    n = key.shape[0]
    ws = _WS
    change = ws.get('change', (n,), np.bool_)
    change[0] = True
    np.not_equal(key[1:], key[:-1], out=change[1:])
    run_start = np.flatnonzero(change)
    runs = run_start.shape[0]
    run_bits = max(int(runs - 1).bit_length(), 1)
    packed = key[run_start].astype(np.int64)
    packed <<= run_bits
    packed |= np.arange(runs)
    packed.sort()
    run = packed & ((1 << run_bits) - 1)
    packed >>= run_bits  # the sorted run keys
    length = np.diff(np.append(run_start, n))[run]
    start = run_start[run]
    out_start = np.cumsum(length)
    runs_kept = int(np.searchsorted(out_start, kept, side='left')) + 1
    out_start -= length  # where each run begins in the sorted point order
    # order[j] = start[r] + (j - out_start[r]) for the run r holding output position j: a
    # cumulative sum of steps of 1 inside runs and jumps where a run begins.
    order = ws.get('order', (kept,), np.int64)
    order.fill(1)
    order[0] = start[0]
    order[out_start[1:runs_kept]] = (start[1:runs_kept] - start[:runs_kept - 1]
                                     - length[:runs_kept - 1] + 1)
    np.cumsum(order, out=order)
    cell = np.empty(runs_kept, dtype=bool)
    cell[0] = True
    np.not_equal(packed[1:runs_kept], packed[:runs_kept - 1], out=cell[1:])
    cell_start = out_start[:runs_kept][cell]
    gathered = ws.get('gathered', (3, kept), cols.dtype)
    np.take(cols, order, axis=1, out=gathered)
    sums: FloatArray = np.add.reduceat(gathered, cell_start, axis=1, dtype=np.float64)
    sums /= np.diff(np.append(cell_start, kept))
    return sums


def voxel_downsample(xyz: npt.ArrayLike, leaf: float) -> FloatArray:
    """Origin-aligned voxel grid: cell = floor(p / leaf), output the centroid of each cell.

    Args:
        xyz: points, shape (N, 3+).
        leaf: cell edge in metres; 0 or less returns the points unchanged.

    Returns:
        Centroids, shape (M, 3), float64, in cell-key order (deterministic).
    """
    cols = _columns(xyz)
    out: FloatArray = cols.T.astype(np.float64) if leaf <= 0.0 else _voxel_columns(cols, leaf).T
    return out


def _reference_fov_mask(x: npt.NDArray[np.floating], y: npt.NDArray[np.floating],
                        width_deg: float, center_deg: float) -> npt.NDArray[np.bool_]:
    """The defining formula: |azimuth - centre| <= width / 2, in the input's float type."""
    rel = np.arctan2(y, x)
    np.degrees(rel, out=rel)
    if center_deg != 0.0:
        rel -= center_deg - 180.0
        np.mod(rel, 360.0, out=rel)
        rel -= 180.0
    np.abs(rel, out=rel)
    inside: npt.NDArray[np.bool_] = rel <= 0.5 * width_deg
    return inside


# Points this close to an FOV edge (sine of the angle to it, at least) are decided by the
# defining arctan2 formula; further away both tests agree (float32 arctan2, degree
# conversion and centring err by about 2e-6 rad together).
_EDGE_BAND = 1e-5


def fov_mask(x: npt.NDArray[np.floating], y: npt.NDArray[np.floating], width_deg: float,
             center_deg: float = 0.0) -> npt.NDArray[np.bool_]:
    """Return which points lie in the horizontal FOV (boundary included).

    A point is kept when its azimuth differs from ``center_deg`` by at most ``width_deg / 2``
    degrees, measured CCW from +x; this matches the authors' clipped KITTI frames exactly.
    Computed by half-plane tests (see :func:`_clip_fov`), identical to the arctan2 formula.
    """
    x = np.ascontiguousarray(x)
    y = np.ascontiguousarray(y)
    if width_deg >= 360.0:
        return np.ones(x.shape, dtype=bool)
    if x.dtype != y.dtype or x.dtype not in (np.float32, np.float64) or x.ndim != 1:
        return _reference_fov_mask(x, y, width_deg, center_deg)
    keep = np.ones(x.shape, dtype=bool)
    with np.errstate(invalid='ignore', over='ignore'):
        band = np.abs(x) + np.abs(y)  # at most sqrt(2) * hypot(x, y)
        band *= _EDGE_BAND
    _clip_fov(keep, x, y, width_deg, center_deg, band)
    return keep


def _clip_fov(keep: npt.NDArray[np.bool_], x: npt.NDArray[np.floating],
              y: npt.NDArray[np.floating], width_deg: float, center_deg: float,
              band: float | npt.NDArray[np.floating]) -> None:
    """``keep &= fov_mask(x, y, ...)`` by two half-plane tests instead of arctan2 per point.

    The cross product of an FOV edge direction with a point tells its side of that edge.
    Points whose cross products are within ``band`` of zero (or not finite), among those
    still kept, are decided by :func:`_reference_fov_mask`, so the result is exactly that
    formula's. ``band`` is ``_EDGE_BAND`` times a bound on hypot(x, y): per point, or the
    range gate's reach for all.
    """
    n = x.shape[0]
    ws = _WS
    dt = x.dtype
    half = math.radians(0.5 * width_deg)
    center = math.radians(center_deg)
    c1, s1 = math.cos(center - half), math.sin(center - half)
    c2, s2 = math.cos(center + half), math.sin(center + half)
    left1 = ws.get('fov_left1', (n,), dt)  # cross(edge1, p) >= 0: p is CCW of edge1
    left2 = ws.get('fov_left2', (n,), dt)  # cross(edge2, p) <= 0: p is CW of edge2
    tmp = ws.get('fov_tmp', (n,), dt)
    inside = ws.get('fov_inside', (n,), np.bool_)
    flag = ws.get('fov_flag', (n,), np.bool_)
    with np.errstate(invalid='ignore', over='ignore'):
        np.multiply(y, c1, out=left1)
        np.multiply(x, s1, out=tmp)
        left1 -= tmp
        np.multiply(y, c2, out=left2)
        np.multiply(x, s2, out=tmp)
        left2 -= tmp
        np.greater_equal(left1, 0.0, out=inside)
        np.less_equal(left2, 0.0, out=flag)
        if width_deg <= 180.0:  # a cone: between the edges
            inside &= flag
        else:  # the complement of the cone left out
            inside |= flag
        # Near an edge, or NaN: not clearly on one side.
        np.abs(left1, out=left1)
        np.abs(left2, out=left2)
        np.minimum(left1, left2, out=tmp)
        np.greater(tmp, band, out=flag)
    np.logical_not(flag, out=flag)
    flag &= keep
    keep &= inside
    edge = np.flatnonzero(flag)
    if edge.size:
        keep[edge] = _reference_fov_mask(x[edge], y[edge], width_deg, center_deg)


def _gate(cols: npt.NDArray[np.floating], config: SolidConfig) -> npt.NDArray[np.bool_]:
    """Range gate (strict, 3-D) and FOV clip of the points in ``cols`` (3, N)."""
    n = cols.shape[1]
    x, y, z = cols
    ws = _WS
    # Range gate on the squared 3-D norm; NaN and inf fail both comparisons and drop out.
    d2 = ws.get('d2', (n,), cols.dtype)
    sq = ws.get('sq', (n,), cols.dtype)
    with np.errstate(invalid='ignore', over='ignore'):
        np.multiply(x, x, out=d2)
        np.multiply(y, y, out=sq)
        d2 += sq
        np.multiply(z, z, out=sq)
        d2 += sq
    keep = ws.get('keep', (n,), np.bool_)
    below = ws.get('below', (n,), np.bool_)
    np.greater(d2, config.min_range ** 2, out=keep)
    np.less(d2, config.max_range ** 2, out=below)
    keep &= below
    if config.fov_width_deg < 360.0:
        # Every kept point has hypot(x, y) < max_range: one band for all.
        _clip_fov(keep, x, y, config.fov_width_deg, config.fov_center_deg,
                  _EDGE_BAND * config.max_range)
    return keep


def _preprocess_columns(points: npt.ArrayLike, config: SolidConfig) -> FloatArray:
    arr = _as_points(points)
    n = arr.shape[0]
    if n == 0:
        return np.zeros((3, 0))
    ws = _WS
    cols = ws.get('cols', (3, n), arr.dtype)
    np.copyto(cols, arr[:, :3].T)
    keep = _gate(cols, config)
    kept = int(np.count_nonzero(keep))
    if kept == 0:
        return np.zeros((3, 0))
    leaf = config.voxel_size
    if leaf > 0.0 and 2 * kept >= n:
        # Most points pass: key every point in place, dropped ones last.
        drop = ws.get('drop', (n,), np.bool_)
        np.logical_not(keep, out=drop)
        found = _cell_keys(cols, leaf, config.max_range, drop)
        if found is not None:
            return _run_centroids(cols, *found, kept)
    # Few points pass (narrow FOV), or cells too many to pack: copy the kept points first.
    sub = ws.get('sub', (3, kept), cols.dtype)
    np.compress(keep, cols, axis=1, out=sub)
    if leaf <= 0.0:
        return sub.astype(np.float64)
    found = _cell_keys(sub, leaf, config.max_range)
    if found is None:
        return _voxel_columns(sub.copy(), leaf)
    return _run_centroids(sub, *found, kept)


def preprocess(points: npt.ArrayLike, config: SolidConfig) -> FloatArray:
    """Drop non-finite points, range-gate, clip the horizontal FOV, voxel-downsample.

    Args:
        points: array of shape (N, 3+) (float32 or float64); only x, y, z are read.
        config: settings.

    Returns:
        The kept points, shape (M, 3), float64.
    """
    out: FloatArray = _preprocess_columns(points, config).T
    return out


def _weights(ec: FloatArray) -> FloatArray:
    lo, hi = float(ec.min()), float(ec.max())
    if hi > lo:
        return (ec - lo) / (hi - lo)
    # Constant EC: min-max normalisation is undefined; keep information if there is any.
    return np.ones_like(ec) if hi > 0.0 else np.zeros_like(ec)


def describe(points: npt.ArrayLike, config: SolidConfig | None = None) -> Descriptor:
    """Build the SOLiD descriptor of one scan.

    Args:
        points: array of shape (N, 3+), float32 or float64, in the sensor frame.
        config: settings; ``SolidConfig()`` (the authors' defaults) when omitted.

    Returns:
        The descriptor. Empty or all-invalid input gives all-zero vectors, never NaN.
    """
    cfg = config if config is not None else SolidConfig()
    n_r, n_a, n_e = cfg.num_range, cfg.num_angle, cfg.num_height
    x, y, z = _preprocess_columns(points, cfg)
    r = np.hypot(x, y)
    inside = r < cfg.max_distance
    if not inside.all():
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
    iev = _weights(rec.sum(axis=0))
    a_solid = aec @ iev
    heading = a_solid
    if cfg.heading_weight == 'range':
        a_range = np.bincount(ia * n_e + ie, weights=r * r, minlength=n_a * n_e)
        heading = a_range.reshape(n_a, n_e) @ iev
    return Descriptor(r_solid=rec @ iev, a_solid=a_solid, rec=rec, aec=aec, iev=iev,
                      num_points=int(len(r)), heading=heading)
