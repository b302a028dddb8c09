"""Mixed pixels: returns that float in free space between two surfaces at a depth edge.

A LiDAR beam's footprint that straddles an edge (a shelf in front of a wall) returns a range
between the two, or a trail of them (Livox sensors are known for it): points where there is
no surface. Another scan of the same place from elsewhere sees straight through that space,
so the free-space conflict test (:mod:`solid_ros.core.verification.free_space`) counts them
against a
right alignment. On the simulator's cluttered room with mixed pixels at half of the edge rays,
almost every conflicting point of a right alignment was one of them, and voxelising makes it
worse: they scatter over many voxels while a surface's points share a few (5-20 % of a
keyframe cloud's voxels).

:func:`drop_mixed_pixels` removes them from a raw scan before its voxel grid: a point whose
range none of its angular neighbours shares, while they saw surfaces both nearer and farther,
is taken for a mixed pixel. A surface's own points always have a neighbour at about their range
(the next ray along it), an edge's foreground and background points too; only the ranges in
between, which no surface explains, go. A scan too sparse to tell (no neighbour nearer or
farther, or fewer than ``_MIN_NEIGHBOURS`` around a point) keeps its points.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

__all__ = ['drop_mixed_pixels', 'mixed_pixels']

FloatArray = npt.NDArray[np.float64]

_BIN_DEG = 1.0  # direction bins; a point's neighbours are those in its own and the 8 around
_N_AZ = int(360 / _BIN_DEG)
_N_EL = int(180 / _BIN_DEG) + 2  # one empty row beyond each pole: no wrap in elevation
_SAME_M = 0.1  # a neighbour within this (or _SAME_SHARE of the range) shares the range
_SAME_SHARE = 0.02
_MIN_NEIGHBOURS = 6
_MIN_SAME = 2
_SPAN = 1024.0  # ranges are below this: bin * _SPAN + range sorts by bin, then range


def mixed_pixels(points: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """Which points of a raw scan (sensor frame, metres) are mixed pixels (see the module
    docstring)."""
    arr = np.asarray(points, dtype=np.float64)
    pts = arr.reshape(-1, arr.shape[-1] if arr.ndim == 2 else 3)[:, :3]
    out = np.zeros(len(pts), dtype=bool)
    r = np.sqrt(np.einsum('ij,ij->i', pts, pts))
    ok = np.flatnonzero(np.isfinite(r) & (r > 0.0) & (r < _SPAN))
    if len(ok) < _MIN_NEIGHBOURS:
        return out
    p, r = pts[ok], r[ok]
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0])) + 180.0
    el = np.degrees(np.arcsin(np.clip(p[:, 2] / r, -1.0, 1.0))) + 90.0
    ia = np.minimum((az / _BIN_DEG).astype(np.intp), _N_AZ - 1)
    ie = np.minimum((el / _BIN_DEG).astype(np.intp), _N_EL - 3) + 1
    cell = ia * _N_EL + ie
    order = np.argsort(cell * _SPAN + r)  # by cell, then range
    cell, r, ia, ie, ok = cell[order], r[order], ia[order], ie[order], ok[order]
    keys = cell * _SPAN + r
    # Each cell's slice of keys, from a histogram: no search for the cells' bounds.
    start = np.zeros(_N_AZ * _N_EL + 1, dtype=np.intp)
    np.cumsum(np.bincount(cell, minlength=_N_AZ * _N_EL), out=start[1:])
    tol = np.maximum(_SAME_M, _SAME_SHARE * r)
    # Only a point with a surface both nearer and farther around it can be one: the nearest
    # and farthest range of each cell and its 8 neighbours rule out the rest at once.
    filled = start[1:] > start[:-1]
    near = np.full(_N_AZ * _N_EL, np.inf)
    far = np.full(_N_AZ * _N_EL, -np.inf)
    near[filled] = r[start[:-1][filled]]
    far[filled] = r[start[1:][filled] - 1]
    near = _filter3(near.reshape(_N_AZ, _N_EL), np.minimum).ravel()
    far = _filter3(far.reshape(_N_AZ, _N_EL), np.maximum).ravel()
    maybe = np.flatnonzero((r - near[cell] > tol) & (far[cell] - r > tol))
    if len(maybe) == 0:
        return out
    r, tol, ia, ie = r[maybe], tol[maybe], ia[maybe], ie[maybe]
    same = np.full(len(maybe), -1, dtype=np.intp)  # the point itself is among its own cell's
    total = np.zeros(len(maybe), dtype=np.intp)
    for da in (-1, 0, 1):
        for de in (-1, 0, 1):
            nb = ((ia + da) % _N_AZ) * _N_EL + ie + de
            base = nb * _SPAN
            same += (np.searchsorted(keys, base + r + tol, side='right')
                     - np.searchsorted(keys, base + r - tol))
            total += start[nb + 1] - start[nb]
    mixed = (same < _MIN_SAME) & (total - 1 >= _MIN_NEIGHBOURS)
    out[ok[maybe[mixed]]] = True
    return out


def _filter3(grid: FloatArray, op: Callable[[FloatArray, FloatArray], FloatArray]
             ) -> FloatArray:
    """The 3 x 3 minimum (``op`` np.minimum) or maximum (np.maximum) of each cell, wrapping
    around in azimuth (axis 0), not beyond the elevation ends: scipy.ndimage's filter with
    modes ('wrap', 'constant') and the identity as the constant, without importing scipy."""
    rows = op(grid, op(np.roll(grid, 1, axis=0), np.roll(grid, -1, axis=0)))
    out: FloatArray = rows.copy()
    out[:, 1:] = op(out[:, 1:], rows[:, :-1])
    out[:, :-1] = op(out[:, :-1], rows[:, 1:])
    return out


def drop_mixed_pixels(points: npt.ArrayLike) -> FloatArray:
    """``points`` without their mixed pixels (rows kept in order, columns unchanged)."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or len(arr) == 0:
        return arr
    out: FloatArray = arr[~mixed_pixels(arr)]
    return out
