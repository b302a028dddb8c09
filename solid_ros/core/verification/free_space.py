"""Free-space conflict: points of one scan in space the other sensor saw through.

A right alignment puts each scan's surfaces where the other sensor saw surfaces or saw
nothing; a wrong one puts some into space the other sensor looked through. The range image of
the viewing sensor (:class:`~solid_ros.core.verification.prepared.RangeImage`) says how far it
saw in each direction.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from solid_ros.core.verification.prepared import (
    N_BINS,
    RangeImage,
    direction_bins,
    load_small_gicp,
)

__all__ = ['COHERENT_POINTS', 'EXPLAINED_VOXELS', 'coherent_conflict', 'conflict_masks',
           'fraction', 'free_space_conflict', 'range_image']

FloatArray = npt.NDArray[np.float64]

# A point this close (fine voxels) to a point of the other cloud lies where the other sensor
# saw a surface: never a free-space conflict (see free_space_conflict).
EXPLAINED_VOXELS = 0.25
# A conflict counts where at least this many conflicting points lie within the correspondence
# distance (two fine voxels) of each other: a misplaced surface puts a patch of points into
# seen-through space, while a thin or porous object one scan hit and the other missed, a mixed
# pixel or the sparse pattern of a solid-state sensor leaves scattered ones. On the hand-held
# Avia in a tight space (quickshack) right poses showed a conflict of 0.05-0.13 point by point
# and 0.01-0.05 in patches, wrong ones 0.08-0.33 and 0.02-0.20; on hku1 right ones 0.00-0.03
# and 0.00-0.01 (5th-95th percentiles), the wrong ones alike in both measures.
COHERENT_POINTS = 3


def range_image(points: FloatArray) -> FloatArray:
    """Nearest range per 1-degree direction bin and its 8 neighbours (inf where the cloud has
    no point), every bin: the neighbourhood absorbs edge pixels and small misalignments."""
    return RangeImage(points)[np.arange(N_BINS)]


def free_space_conflict(points: FloatArray, ranges: FloatArray | RangeImage, margin: float,
                        structure: int | None = None,
                        explained: npt.NDArray[np.bool_] | None = None,
                        cell: float = 0.0, together: int = 1) -> float:
    """Fraction of ``points`` (in the viewing sensor's frame) that lie in front of the surface
    that sensor saw in their direction, by more than ``margin`` plus 5 % of the range: the
    sensor looked through where they claim a surface is. Directions it saw nothing in do not
    count (sky, outside its field of view, beyond its range).

    With ``structure`` (the first ``structure`` rows are structure points), the larger of the
    fraction over all points and over the structure points alone: the ground aligns anywhere
    and dilutes the first, so a misplaced wall, pole or tree shows in the second, while a
    wrong tilt shows on the ground in the first.

    ``explained`` marks points that lie where the viewing sensor itself saw a surface (one of
    its points is near): whatever its range image says in their 1-degree direction, they are
    not in seen-through space, so they never count as a conflict (they still count as seen).
    A keyframe cloud holds voxel centroids, and a near object's centroids sit degrees away
    from the directions its surface covers: in the range image the edges of near objects
    (table tops and shelf boards seen edge-on, box and pillar sides) look seen-through, and a
    right alignment a degree off puts the other scan's points of the same objects there
    (occlusion, not contradiction). The caller's radius, a quarter of a voxel, added no
    wrong loop on eight simulated walks through a cluttered room; larger radii explain away
    the points of wrong alignments in clutter too (a third of a voxel added one wrong loop on
    four walks, half a voxel three on eight).

    With ``together`` above 1 only coherent conflict counts: conflicting points with at least
    ``together - 1`` others within ``cell`` metres (see :func:`coherent_conflict`).
    """
    if not len(points):
        return 0.0
    conflict, known = conflict_masks(points, ranges, margin,
                                      np.zeros(len(points), dtype=bool) if explained is None
                                      else explained)
    if not known.any():
        return 0.0
    if together > 1 and conflict.any():
        conflict = coherent_conflict(points, conflict, cell, together)
    return fraction(conflict, known, structure)


def conflict_masks(points: FloatArray, ranges: FloatArray | RangeImage, margin: float,
                    explained: npt.NDArray[np.bool_]
                    ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """Which points conflict and which lie in a direction the viewing sensor saw (see
    :func:`free_space_conflict`)."""
    b, r = direction_bins(points)
    seen = ranges[b]
    known = np.isfinite(seen)
    conflict = np.zeros(len(r), dtype=bool)
    conflict[known] = r[known] < seen[known] - margin - 0.05 * seen[known]
    return conflict & ~explained, known


def fraction(conflict: npt.NDArray[np.bool_], known: npt.NDArray[np.bool_],
              structure: int | None) -> float:
    """Conflicting over seen points, and over seen structure points where more."""
    out = float(conflict.sum()) / float(known.sum())
    if structure is not None:
        n_known = int(known[:structure].sum())
        if n_known:
            out = max(out, float(conflict[:structure].sum()) / n_known)
    return out


def coherent_conflict(points: FloatArray, conflict: npt.NDArray[np.bool_], reach: float,
              together: int) -> npt.NDArray[np.bool_]:
    """The conflicting points with at least ``together - 1`` other conflicting points within
    ``reach`` metres: a surface misplaced into seen-through space puts a patch (or, a pole or
    a trunk, a column) of points there, while a thin or porous object one scan hit and the
    other missed, a mixed pixel or the sparse pattern of a solid-state sensor leaves scattered
    ones."""
    idx = np.flatnonzero(conflict)
    out = np.zeros_like(conflict)
    if len(idx) < together:
        return out
    # A point has together - 1 others within reach when its together-th nearest conflicting
    # point (itself the first) lies within reach: small_gicp's exact kd-tree, no scipy import.
    pts = np.ascontiguousarray(points[idx])
    _, sq = load_small_gicp().KdTree(pts).batch_knn_search(pts, together)
    out[idx[np.asarray(sq)[:, together - 1] <= reach * reach]] = True
    return out
