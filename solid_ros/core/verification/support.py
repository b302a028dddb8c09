"""How well two registered clouds support an alignment: overlap, fit, constraint, conflict.

The measures the judge reads (:mod:`.judge`) of one pose between a prepared query and source
(:mod:`.prepared`); the costly ones are computed on first access.
"""

from __future__ import annotations

import math
from functools import cached_property

import numpy as np
import numpy.typing as npt

from solid_ros.core.verification.free_space import (
    COHERENT_POINTS,
    EXPLAINED_VOXELS,
    coherent_conflict,
    conflict_masks,
    fraction,
)
from solid_ros.core.verification.prepared import Query, RegistrationSettings, Source

__all__ = ['PLANE_THICKNESS_SCALE', 'Support']

FloatArray = npt.NDArray[np.float64]

_LEVER_M = 10.0  # the heading's lever in the horizontal constraint, metres
_MIN_LEVER_M = 0.5  # Support.constraint_near: the lever never shorter than this
# Plane thickness (smallest / middle eigenvalue of a point's neighbourhood) at which a
# supporting point's information counts half (see Support.weighted_information); calibrated
# with test/bench/bench_nees.py (README, Loop verification, covariance).
PLANE_THICKNESS_SCALE = 0.05


class Support:
    """How well the two clouds support an alignment.

    A candidate point supports the alignment when, mapped into the query frame, its nearest
    query point lies within ``2 * voxel`` and it lies within ``inlier_distance`` of that
    point's tangent plane. The measures the acceptance tests read last (``conflict``,
    ``spread``, ``patches``) are computed on first access, so a candidate rejected earlier
    does not pay for them.

    Attributes:
        fitness: fraction of all candidate points that support it (ground included).
        overlap_match: fraction of the candidate's structure points that support it.
        overlap_query: fraction of the query's structure points with a candidate point within
            ``2 * voxel`` (the candidate explains the query's structure).
        rmse: RMS point-to-plane distance of the supporting points, metres.
        constraint: smallest eigenvalue of the information that supporting structure points
            give on (x, y, 10 m x yaw), divided by the query's structure points: how well the
            horizontal position and heading are pinned down (0 in a corridor or on a plane).
        constraint_near: (computed on first use) the same with the heading's lever at the
            supporting structure's RMS horizontal range when under 10 m.
        information: 6x6 point-to-plane information sum J J^T over all supporting points,
            J = (t x n, n) for a left perturbation of ``T_qm`` (rotation first).
        inliers: number of supporting points.
        weighted_information: (computed on first use) the information with each supporting
            point weighted by how well its query plane is defined, and the sum of the weights.
        residual_scores: (computed on first use) the weighted residual scores summed per
            coarse voxel, squared and summed: what the residuals say about the pose's error
            (the loop covariance,
            :func:`solid_ros.core.verification.covariance.support_covariance`).
    """

    def __init__(self, query: Query, source: Source, T_qm: FloatArray,
                 settings: RegistrationSettings) -> None:
        T = np.asarray(T_qm, dtype=np.float64)
        self._query, self._source, self._T, self._settings = query, source, T, settings
        moved = source.points @ T[:3, :3].T + T[:3, 3]
        idx, sq = query.tree.batch_nearest_neighbor_search(moved)
        idx = np.asarray(idx, dtype=np.intp)
        near = np.asarray(sq) < settings.neighbour_distance ** 2
        normals = query.normals[idx]
        signed = np.einsum('ij,ij->i', moved - query.points[idx], normals)
        plane = np.abs(signed)
        inlier = near & (plane < settings.inlier_distance)
        struct_m = np.arange(len(moved)) < source.n_struct
        n_inl = int(inlier.sum())
        self.inliers = n_inl
        self.fitness = n_inl / max(len(moved), 1)
        self.rmse = float(math.sqrt(float(np.mean(plane[inlier] ** 2)))) if n_inl else math.inf
        m_in, n_in = moved[inlier], normals[inlier]
        jac = np.empty((n_inl, 6))
        jac[:, 3:] = n_in
        # The cross product moved x normal, written out: np.cross costs more than the rest.
        for k, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
            jac[:, k] = m_in[:, a] * n_in[:, b] - m_in[:, b] * n_in[:, a]
        self.information: FloatArray = jac.T @ jac
        s_rows = inlier[inlier] & struct_m[inlier]
        # Horizontal block (x, y, yaw); yaw scaled by a 10 m lever to compare with metres.
        self._hz = jac[s_rows][:, [3, 4, 2]] * np.array([1.0, 1.0, 1.0 / _LEVER_M])
        self.constraint = _least_constraint(self._hz, query.n_struct)
        self._moved, self._inlier, self._s_rows = moved, inlier, s_rows
        self._near_sq = np.asarray(sq)  # squared distance of each moved point to the query
        self._jac, self._nn, self._residuals = jac, idx[inlier], signed[inlier]
        self.overlap_match = int((inlier & struct_m).sum()) / max(int(struct_m.sum()), 1)
        # Query structure explained by the candidate: query points mapped into the match frame
        # (structure first; the rest's nearest neighbours only when the conflict needs them).
        _, tree = source.fine()
        self._back = (query.points[query.structure_first] - T[:3, 3]) @ T[:3, :3]
        n_struct = query.n_struct
        self._back_sq = np.zeros(0)
        if n_struct:
            _, sq2 = tree.batch_nearest_neighbor_search(self._back[:n_struct])
            self._back_sq = np.asarray(sq2)
            self.overlap_query = float(np.mean(self._back_sq < settings.neighbour_distance ** 2))
        else:
            self.overlap_query = 0.0

    @property
    def overlap(self) -> float:
        """The smaller of the two structure overlaps."""
        return min(self.overlap_match, self.overlap_query)

    @cached_property
    def conflict(self) -> float:
        """Free-space conflict, the largest of both directions, each over all points and over
        the structure points alone: the fraction of one cloud's points (where the other sensor
        saw a surface in their direction) lying in front of that surface, in space the other
        sensor saw through. The ground, which aligns anywhere, would dilute a misplaced wall or
        tree in the fraction over all points. A point within a quarter of a fine voxel of a
        point of the other cloud lies where the other sensor saw a surface and is never a
        conflict, and only coherent conflict counts: conflicting points with at least
        ``COHERENT_POINTS - 1`` others within the correspondence distance (see
        :func:`~solid_ros.core.verification.free_space.free_space_conflict`)."""
        return self._conflicts[0]

    @cached_property
    def conflict_points(self) -> float:
        """:attr:`conflict` point by point, scattered conflicting points counted too."""
        return self._conflicts[1]

    @cached_property
    def _conflicts(self) -> tuple[float, float]:
        """(coherent, point by point) free-space conflict, the larger direction of each."""
        query, source = self._query, self._source
        margin = self._settings.neighbour_distance
        near = (EXPLAINED_VOXELS * self._settings.voxel) ** 2
        back = self._back
        sq = self._back_sq
        if len(sq) < len(back):
            _, tree = source.fine()
            _, rest = tree.batch_nearest_neighbor_search(back[len(sq):])
            sq = np.concatenate([sq, np.asarray(rest)])
        a = conflict_masks(self._moved, query.ranges, margin, self._near_sq < near)
        b = conflict_masks(back, source.ranges, margin, sq < near)
        patchy = max(fraction(coherent_conflict(self._moved, a[0], margin, COHERENT_POINTS),
                              a[1], source.n_struct) if a[0].any() else 0.0,
                     fraction(coherent_conflict(back, b[0], margin, COHERENT_POINTS),
                              b[1], query.n_struct) if b[0].any() else 0.0)
        points = max(fraction(a[0], a[1], source.n_struct) if a[1].any() else 0.0,
                     fraction(b[0], b[1], query.n_struct) if b[1].any() else 0.0)
        return patchy, points

    @cached_property
    def constraint_near(self) -> float:
        """:attr:`constraint` with the heading's lever at the supporting structure's RMS
        horizontal range where that is under 10 m (a room; at least 0.5 m): a heading error
        moves structure at 2-4 m by a third of what the 10 m lever assumes."""
        points = self._moved[self._inlier][self._s_rows]
        if not len(points):
            return 0.0
        rms = math.sqrt(float(np.mean(np.sum(points[:, :2] ** 2, axis=1))))
        lever = min(max(rms, _MIN_LEVER_M), _LEVER_M)
        hz = self._hz * np.array([1.0, 1.0, _LEVER_M / lever])
        return _least_constraint(hz, self._query.n_struct)

    @cached_property
    def spread(self) -> float:
        """The horizontal constraint left without the object that contributes most, per query
        structure point."""
        points = self._moved[self._inlier][self._s_rows]
        worst = _without_strongest_object(points, self._hz, self._settings.coarse_voxel)
        return max(worst / max(self._query.n_struct, 1), 0.0)

    @cached_property
    def weights(self) -> FloatArray:
        """Weight of each supporting point, ``w = 1 / (1 + t / PLANE_THICKNESS_SCALE)`` with
        ``t`` its query point's plane thickness. A point's plane distance is only as good as
        the plane: where the neighbourhood is no clean plane (rough or curved surfaces,
        corners, one ring of a sparse sensor) the normal is uncertain and the residual misses
        that error."""
        w: FloatArray = 1.0 / (1.0 + self._query.thickness(self._nn) / PLANE_THICKNESS_SCALE)
        return w

    @cached_property
    def weighted_information(self) -> tuple[FloatArray, float]:
        """Point-to-plane information sum w J J^T over the supporting points (``w``:
        :attr:`weights`) and the sum of the weights."""
        w = self.weights
        info: FloatArray = (self._jac * w[:, None]).T @ self._jac
        return info, float(w.sum())

    @cached_property
    def residual_scores(self) -> FloatArray:
        """Sum over occupied coarse voxels of ``g g^T``, ``g = sum w r J`` over the voxel's
        supporting points (``r`` their signed plane distance): the middle of the
        cluster-robust ("sandwich") covariance. Residuals on one surface patch are summed
        before squaring, so a patch whose residuals share one error (a tilted normal, a pose
        error they all see) weighs as one measurement of it, and residuals that cancel on a
        patch count as noise that averages out."""
        out: FloatArray = np.zeros((6, 6))
        if not self.inliers:
            return out
        ids = self._patch_ids
        wr = self.weights * self._residuals
        g = np.stack([np.bincount(ids, wr * self._jac[:, k], minlength=self.patches)
                      for k in range(6)], axis=1)
        out = g.T @ g
        return out

    @cached_property
    def _patch_ids(self) -> npt.NDArray[np.intp]:
        """Coarse voxel (numbered 0 ..) of each supporting point."""
        cells = np.floor(self._moved[self._inlier] / self._settings.coarse_voxel)
        return _cell_ids(cells.astype(np.int64))

    @cached_property
    def patches(self) -> int:
        """Coarse voxels holding supporting points: independent surface patches (the errors of
        points on one patch are correlated)."""
        if not self.inliers:
            return 0
        return int(self._patch_ids.max()) + 1


def _least_constraint(hz: FloatArray, n_struct: int) -> float:
    """Smallest eigenvalue of the horizontal information ``hz^T hz`` per query structure
    point (0 at least)."""
    return max(float(np.linalg.eigvalsh(hz.T @ hz)[0]) / max(n_struct, 1), 0.0)


def _cell_ids(cells: npt.NDArray[np.int64]) -> npt.NDArray[np.intp]:
    """Each row's rank among the distinct rows of ``cells`` (N, 3) in lexicographic order:
    ``np.unique(cells, axis=0, return_inverse=True)``'s inverse. The rows packed into one
    integer key keep that order, and a 1-D unique of them is ten times faster (a millisecond
    of every loop's covariance)."""
    if not len(cells):
        return np.zeros(0, dtype=np.intp)
    d = cells - cells.min(axis=0)
    span = d.max(axis=0) + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0 ** 62:  # too far apart to pack
        _, inverse = np.unique(cells, axis=0, return_inverse=True)
    else:
        _, inverse = np.unique((d[:, 0] * span[1] + d[:, 1]) * span[2] + d[:, 2],
                               return_inverse=True)
    ids: npt.NDArray[np.intp] = inverse.reshape(-1).astype(np.intp)
    return ids


def _without_strongest_object(points: FloatArray, rows: FloatArray, cell: float) -> float:
    """Horizontal constraint left when the object that contributes most is taken away.

    Objects are clusters of structure points connected in a top-view grid of ``cell`` metres.
    One generic object (a single building corner, one wall) pins the pose down by itself but
    matches any other like it; a real place is pinned by several.
    """
    if len(points) == 0:
        return 0.0
    ij = np.floor(points[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    grid = np.zeros(tuple(ij.max(axis=0) + 1), dtype=bool)
    grid[ij[:, 0], ij[:, 1]] = True
    labels, count = _label(grid)
    obj = labels[ij[:, 0], ij[:, 1]] - 1
    total = rows.T @ rows
    sizes = np.bincount(obj, minlength=count)
    worst = math.inf
    for k in np.argsort(-sizes)[:3]:
        part = rows[obj == k]
        worst = min(worst, float(np.linalg.eigvalsh(total - part.T @ part)[0]))
    return worst


def _label(grid: npt.NDArray[np.bool_]) -> tuple[npt.NDArray[np.intp], int]:
    """The 8-connected components of a 2-D grid, numbered 1, 2, ... in the raster order of
    their first cell (0: empty), and their count: ``scipy.ndimage.label`` with a 3 x 3
    structure, without importing scipy (half a second of every start-up)."""
    flat = np.flatnonzero(grid.ravel())
    labels = np.zeros(grid.shape, dtype=np.intp)
    if not len(flat):
        return labels, 0
    width = grid.shape[1]
    rows, cols = np.divmod(flat, width)
    key = (rows + 1) * (width + 2) + cols + 1  # on the grid padded by a cell: no wrap
    m = len(key)
    # Each cell's neighbours after it in raster order (right, and the three below).
    nb = (key[None, :] + np.array([1, width + 1, width + 2, width + 3])[:, None]).ravel()
    pos = np.minimum(np.searchsorted(key, nb), m - 1)
    hit = key[pos] == nb
    a, b = np.tile(np.arange(m), 4)[hit], pos[hit]
    # Union by the lower index, then pointer jumping, until every pair shares a root: each
    # cell ends pointing at its component's first cell.
    root = np.arange(m)
    while True:
        ra, rb = root[a], root[b]
        differ = ra != rb
        if not differ.any():
            break
        np.minimum.at(root, np.maximum(ra[differ], rb[differ]),
                      np.minimum(ra[differ], rb[differ]))
        while True:
            up = root[root]
            if np.array_equal(up, root):
                break
            root = up
    firsts, number = np.unique(root, return_inverse=True)
    labels.ravel()[flat] = number.reshape(-1) + 1
    return labels, len(firsts)
