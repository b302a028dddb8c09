"""SOLiD descriptor: preprocessing, REC/AEC counts, IEV weighting, R-SOLiD and A-SOLiD.

Conventions (see README): azimuth theta = atan2(y, x) in [0, 360) degrees CCW from +x,
horizontal range r = hypot(x, y), elevation phi = atan2(z, r). Bin indices truncate and clamp
to the last bin; elevations outside the sensor FOV clamp to the first or last elevation bin;
points with r >= max_distance are dropped rather than piled into the last range bin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import SolidError

__all__ = ['Descriptor', 'describe', 'fov_mask', 'preprocess', 'voxel_downsample']

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Descriptor:
    """SOLiD descriptor of one scan.

    Attributes:
        r_solid: R-SOLiD, shape (N_r,): place signature, compared by cosine distance.
        a_solid: A-SOLiD, shape (N_a,): azimuth signature, used for the heading.
        rec: range-elevation counts, shape (N_r, N_e).
        aec: azimuth-elevation counts, shape (N_a, N_e).
        iev: min-max normalised elevation counts (the weights), shape (N_e,).
        num_points: points left after preprocessing.
        heading: signature used for the heading, shape (N_a,): ``a_solid`` itself with
            ``heading_weight='count'``; with ``'range'`` the same sum with each point
            weighted by its squared horizontal range (about the surface it stands for), so
            near objects, whose azimuth shifts most when the sensor moves, count less.
    """

    r_solid: FloatArray
    a_solid: FloatArray
    rec: FloatArray
    aec: FloatArray
    iev: FloatArray
    num_points: int
    heading: FloatArray

    @property
    def ec(self) -> FloatArray:
        """Elevation counts EC[k] = sum_i REC[i, k]."""
        ec: FloatArray = self.rec.sum(axis=0)
        return ec


def _columns(points: npt.ArrayLike) -> npt.NDArray[np.floating]:
    """Return x, y, z as a contiguous (3, N) array in the input's float type.

    Column-major layout makes every later masked copy, gather and reduction contiguous, which
    is several times faster than working on (N, 3) rows.
    """
    arr = np.asarray(points)
    if arr.size == 0:
        return np.empty((3, 0), dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise SolidError(f'points must have shape (N, 3+), got {arr.shape}')
    if arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float64)
    return np.ascontiguousarray(arr[:, :3].T)


def _voxel_columns(cols: npt.NDArray[np.floating], leaf: float) -> FloatArray:
    n = cols.shape[1]
    if n == 0:
        return np.zeros((3, 0))
    # In-place steps throughout: fresh large temporaries cost page faults that dominate here.
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
        order = packed & ((1 << idx_bits) - 1)
        packed >>= idx_bits
        skey = packed
    else:  # cells too far apart to pack: slower but general
        _, inverse = np.unique(cells.T, axis=0, return_inverse=True)
        order = np.argsort(inverse.ravel(), kind='stable')
        skey = inverse.ravel()[order]
    change = np.empty(n, dtype=bool)
    change[0] = True
    np.not_equal(skey[1:], skey[:-1], out=change[1:])
    start = np.flatnonzero(change)
    sums = np.add.reduceat(np.take(cols, order, axis=1), start, axis=1, dtype=np.float64)
    sums /= np.diff(np.append(start, n))
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


def fov_mask(x: npt.NDArray[np.floating], y: npt.NDArray[np.floating], width_deg: float,
             center_deg: float = 0.0) -> npt.NDArray[np.bool_]:
    """Return which points lie in the horizontal FOV (boundary included).

    A point is kept when its azimuth differs from ``center_deg`` by at most ``width_deg / 2``
    degrees, measured CCW from +x; this matches the authors' clipped KITTI frames exactly.
    """
    if width_deg >= 360.0:
        return np.ones(np.shape(x), dtype=bool)
    # In place: each fresh scan-sized temporary costs page faults (see solid_ros.tools.runtime).
    rel = np.arctan2(y, x)
    np.degrees(rel, out=rel)
    if center_deg != 0.0:
        rel -= center_deg - 180.0
        np.mod(rel, 360.0, out=rel)
        rel -= 180.0
    np.abs(rel, out=rel)
    inside: npt.NDArray[np.bool_] = rel <= 0.5 * width_deg
    return inside


def _preprocess_columns(points: npt.ArrayLike, config: SolidConfig) -> FloatArray:
    cols = _columns(points)
    if cols.shape[1] == 0:
        return np.zeros((3, 0))
    x, y, z = cols
    # Range gate on the squared 3-D norm; NaN and inf fail both comparisons and drop out.
    with np.errstate(invalid='ignore', over='ignore'):
        d2 = x * x
        d2 += y * y
        d2 += z * z
    keep = d2 > config.min_range ** 2
    keep &= d2 < config.max_range ** 2
    if config.fov_width_deg < 360.0:
        keep &= fov_mask(x, y, config.fov_width_deg, config.fov_center_deg)
    if not keep.all():
        kept = np.empty((3, int(np.count_nonzero(keep))), dtype=cols.dtype)
        for row, col in zip(kept, cols):
            np.compress(keep, col, out=row)
        cols = kept
    if config.voxel_size > 0.0:
        return _voxel_columns(cols, config.voxel_size)
    return cols.astype(np.float64)


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
