"""Point cloud registration for loop verification, on top of small_gicp.

The registration itself is small_gicp's (GICP for the coarse stage, voxelised GICP for the
fine one); this module prepares clouds for it and measures how well an alignment is supported.

Frames: every cloud here is in its own (levelled) sensor frame. The query is the registration
target, prepared once per scan; each candidate is a source. Registration returns ``T_qm``
(``p_query = T_qm p_match``); callers invert it for the published ``T = T_mq``.

Structure: a point whose surface normal is more than about 45 degrees from vertical
(``|n_z| < STRUCTURE_MAX_NZ``) belongs to a wall, pole, trunk or car side. Only such points
constrain the horizontal position and the heading; the ground aligns anywhere, so the coarse
stage and the acceptance measures look at structure points. Keyframe clouds are stored
structure first (``n_struct`` rows, then the rest), so a candidate's structure is known
without recomputing its normals.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.descriptor.solid import voxel_downsample
from solid_ros.core.errors import SolidError
from solid_ros.core.geometry import rot_z

__all__ = ['PLANE_THICKNESS_SCALE', 'STRUCTURE_MAX_NZ', 'Alignment', 'Query', 'RangeImage',
           'RegistrationSettings', 'Source', 'Support', 'align_coarse', 'align_fine', 'coarsened',
           'for_peers', 'load_small_gicp', 'settled']

FloatArray = npt.NDArray[np.float64]

STRUCTURE_MAX_NZ = 0.7  # |n_z| below this: a non-horizontal surface (about 45 deg or steeper)
_NEIGHBOURS = 10  # points per normal/covariance estimate
_MIN_POINTS = 10  # fewer points than this cannot be registered
_LEVER_M = 10.0  # the heading's lever in the horizontal constraint, metres
_MIN_LEVER_M = 0.5  # Support.constraint_near: the lever never shorter than this
_COARSE_ITERATIONS = 15  # the coarse stage only has to land in the fine stage's basin
_GOOD_COARSE = 0.5  # coarse overlap that ends the search over heading hypotheses
# Coarse convergence: 0.5 deg / 1 cm steps are far inside a coarse voxel (small_gicp's
# defaults, 0.1 deg / 1 mm, kept 80 % of coarse runs going to the iteration cap).
_COARSE_ROTATION_EPS = math.radians(0.5)
_COARSE_TRANSLATION_EPS = 0.01
# A fine run not converged after _FIRST_ITERATIONS is resumed this long; a pose that moves less
# than this (fine voxels, degrees) meanwhile is stationary: converged (see align_fine).
_FIRST_ITERATIONS = 15
_RESUME_ITERATIONS = 5
_STATIONARY_VOXELS = 0.1
_STATIONARY_DEG = 0.5
# A point this close (fine voxels) to a point of the other cloud lies where the other sensor
# saw a surface: never a free-space conflict (see free_space_conflict).
_EXPLAINED_VOXELS = 0.25
# A conflict counts where at least this many conflicting points lie within the correspondence
# distance (two fine voxels) of each other: a misplaced surface puts a patch of points into
# seen-through space, while a thin or porous object one scan hit and the other missed, a mixed
# pixel or the sparse pattern of a solid-state sensor leaves scattered ones. On the hand-held
# Avia in a tight space (quickshack) right poses showed a conflict of 0.05-0.13 point by point
# and 0.01-0.05 in patches, wrong ones 0.08-0.33 and 0.02-0.20; on hku1 right ones 0.00-0.03
# and 0.00-0.01 (5th-95th percentiles), the wrong ones alike in both measures.
_COHERENT_POINTS = 3
# Plane thickness (smallest / middle eigenvalue of a point's neighbourhood) at which a
# supporting point's information counts half (see Support.weighted_information); calibrated
# with test/bench/bench_nees.py (README, Loop verification, covariance).
PLANE_THICKNESS_SCALE = 0.05


def load_small_gicp() -> Any:
    """Import small_gicp on first use, so descriptor-only users need not install it.

    Raises:
        SolidError: small_gicp is not installed (the message says how to install it).
    """
    try:
        import small_gicp as sg
    except ImportError as err:
        raise SolidError('loop verification needs small_gicp: pip install small-gicp '
                         '(or set verify: false for descriptor-only loops)') from err
    return sg


@dataclass(frozen=True)
class RegistrationSettings:
    """Registration and support measurement settings (from ``SolidConfig.verify_*``).

    Attributes:
        voxel: voxel size of keyframe clouds and of the fine stage, metres.
        coarse_voxel: voxel size of the coarse (structure only) stage, metres.
        coarse_distance: largest correspondence distance of the coarse stage, metres.
        coarse_max_points: most coarse points of a candidate (source) in the coarse stage; a
            denser coarse cloud is thinned to an even subsample of this many.
        max_iterations: iteration limit of each registration.
        inlier_distance: a point supports an alignment when its nearest neighbour in the other
            cloud lies within ``2 * voxel`` and within this distance of that neighbour's
            tangent plane, metres.
    """

    voxel: float = 0.5
    coarse_voxel: float = 1.5
    coarse_distance: float = 3.0
    coarse_max_points: int = 250
    max_iterations: int = 30
    inlier_distance: float = 0.15

    @property
    def neighbour_distance(self) -> float:
        """Nearest-neighbour distance limit of a supporting point, metres."""
        return 2.0 * self.voxel


class Query:
    """A scan prepared as registration target: normals, kd-tree, voxel maps, structure.

    Args:
        points: (N, 3) points of the keyframe cloud (already range-gated, FOV-clipped and
            voxel-downsampled at ``settings.voxel``), levelled sensor frame.
        settings: registration settings.
    """

    def __init__(self, points: npt.ArrayLike, settings: RegistrationSettings) -> None:
        sg = load_small_gicp()
        self.settings = settings
        self._grids: dict[RegistrationSettings, Query] = {}
        self._thickness: FloatArray | None = None  # plane thickness, NaN: not computed yet
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        self.size = len(pts)
        self.usable = self.size >= _MIN_POINTS
        self.points: FloatArray = pts
        self.normals: FloatArray = np.zeros_like(pts)
        self.structure: npt.NDArray[np.bool_] = np.zeros(len(pts), dtype=bool)
        # Row order that puts structure points first (stored clouds are kept this way).
        self.structure_first: npt.NDArray[np.intp] = np.arange(len(pts))
        self.ground: FloatArray = np.zeros((0, 3))
        self.ground_tree: Any = None
        if not self.usable:
            return
        cloud = sg.PointCloud(pts)
        tree = sg.KdTree(cloud)
        sg.estimate_normals_covariances(cloud, tree, num_neighbors=_NEIGHBOURS)
        self.cloud, self.tree = cloud, tree
        self.normals = np.ascontiguousarray(cloud.normals()[:, :3])
        self.structure = np.abs(self.normals[:, 2]) < STRUCTURE_MAX_NZ
        self.vmap = sg.GaussianVoxelMap(settings.voxel)
        self.vmap.insert(cloud)
        struct_pts = pts[self.structure]
        self.coarse = sg.voxelgrid_sampling(struct_pts, settings.coarse_voxel)
        self.coarse_tree = sg.KdTree(self.coarse)
        if self.coarse.size() >= _MIN_POINTS:
            sg.estimate_covariances(self.coarse, self.coarse_tree, num_neighbors=_NEIGHBOURS)
        self.structure_first = np.argsort(~self.structure, kind='stable')
        # Horizontal surfaces (mostly ground): what sets the coarse stage's height.
        self.ground = np.ascontiguousarray(pts[~self.structure])
        if len(self.ground) >= _MIN_POINTS:
            self.ground_tree = sg.KdTree(sg.PointCloud(self.ground))

    @property
    def n_struct(self) -> int:
        """Number of structure points."""
        return int(self.structure.sum())

    @cached_property
    def ranges(self) -> RangeImage:
        """Range image of the cloud (computed on first use: most candidates never need it)."""
        return RangeImage(self.points)

    @property
    def plane_thickness(self) -> FloatArray:
        """Per point, the smallest over the middle eigenvalue of its neighbourhood's covariance
        (the points the normal was estimated from): near 0 on a clean plane, near 1 where the
        normal is not defined (a rough or curved surface, a corner, a line of points). small_gicp
        regularises the covariances it keeps, so they are computed afresh here (first use)."""
        return self.thickness(np.arange(self.size))

    def thickness(self, rows: npt.NDArray[np.intp]) -> FloatArray:
        """:attr:`plane_thickness` of the points ``rows``, each computed on first use and
        kept: a loop's covariance reads only its supporting points' (a third to a half of the
        query's), and each row's value does not depend on which others are computed."""
        if not self.usable:
            return np.ones(len(rows))
        if self._thickness is None:
            self._thickness = np.full(self.size, np.nan)
        kept = self._thickness
        need = np.unique(rows[np.isnan(kept[rows])])
        if len(need):
            knn, _ = self.tree.batch_knn_search(self.points[need], _NEIGHBOURS)
            nb = self.points[np.asarray(knn, dtype=np.intp)]
            d = nb - nb.mean(axis=1, keepdims=True)
            ev = np.linalg.eigvalsh(np.einsum('nki,nkj->nij', d, d))
            kept[need] = ev[:, 0] / np.maximum(ev[:, 1], 1e-12)
        out: FloatArray = kept[rows]
        return out

    def keyframe_cloud(self) -> KeyframeCloud:
        """The cloud to store for this scan: float32, structure first, with its grid."""
        return KeyframeCloud(self.points[self.structure_first].astype(np.float32),
                             self.n_struct, self.settings.voxel)

    def on_grid(self, settings: RegistrationSettings) -> Query:
        """This scan prepared with ``settings``: itself when they are its own, else its
        points downsampled on their voxel (a tight-space keyframe registered to an open one;
        kept after the first call)."""
        if settings == self.settings:
            return self
        other = self._grids.get(settings)
        if other is None:
            other = Query(voxel_downsample(self.points, settings.voxel), settings)
            self._grids[settings] = other
        return other


def _least_constraint(hz: FloatArray, n_struct: int) -> float:
    """Smallest eigenvalue of the horizontal information ``hz^T hz`` per query structure
    point (0 at least)."""
    return max(float(np.linalg.eigvalsh(hz.T @ hz)[0]) / max(n_struct, 1), 0.0)


def coarsened(cloud: KeyframeCloud, voxel: float) -> KeyframeCloud:
    """``cloud`` on a grid of ``voxel`` when it was kept on a finer one (a tight-space
    keyframe, see ``verify_tight_range``), structure and the rest downsampled apart so the
    split stays; else ``cloud`` itself (its grid 0: the configuration's)."""
    if not 0.0 < cloud.voxel < voxel * (1.0 - 1e-6):
        return cloud
    struct = voxel_downsample(cloud.points[:cloud.n_struct], voxel)
    rest = voxel_downsample(cloud.points[cloud.n_struct:], voxel)
    return KeyframeCloud(np.concatenate([struct, rest]).astype(np.float32), len(struct), voxel)


PEER_GROUND_SCALE = 2.0  # a cloud sent to a peer keeps its ground on this many voxels


def for_peers(cloud: KeyframeCloud, voxel: float) -> KeyframeCloud:
    """``cloud`` as a peer gets it: its structure as it is, the rest (the ground) on a grid
    of ``PEER_GROUND_SCALE * voxel``, with its grid said (``voxel`` when it was the
    configuration's: the reply's quantisation follows it).

    Structure alone holds the horizontal position and heading but starves the overlap,
    conflict and single-object measures: on the simulated fleet it verified 1 of 55
    inter-robot loops. How far the ground can thin was measured on hku1 cut in two robots
    (Avia, ground-heavy; 36 places found with whole clouds): 4 voxels 28, 3 voxels 29,
    2 voxels 32-35, 1.5 voxels 34; the simulated fleet kept 55 of 55 at 4 voxels. At 2 voxels
    a cloud keeps about a quarter of its ground points."""
    n = int(cloud.n_struct)
    rest = voxel_downsample(cloud.points[n:], PEER_GROUND_SCALE * voxel)
    return KeyframeCloud(np.concatenate([cloud.points[:n], rest]).astype(np.float32), n,
                         cloud.voxel if cloud.voxel > 0.0 else voxel)


class Source:
    """A stored keyframe cloud prepared as registration source (coarse and fine).

    Args:
        cloud: the stored cloud.
        settings: registration settings.
    """

    def __init__(self, cloud: KeyframeCloud, settings: RegistrationSettings) -> None:
        sg = load_small_gicp()
        self.points: FloatArray = np.ascontiguousarray(cloud.points, dtype=np.float64)
        self.n_struct = int(cloud.n_struct)
        self.usable = len(self.points) >= _MIN_POINTS
        self.coarse = sg.voxelgrid_sampling(self.points[:self.n_struct], settings.coarse_voxel)
        n = self.coarse.size()
        if n > settings.coarse_max_points:
            # Coarse GICP costs in proportion to the source points; an even subsample of a
            # dense place still lands in the fine stage's basin.
            keep = np.linspace(0, n - 1, settings.coarse_max_points).round().astype(np.intp)
            self.coarse = sg.PointCloud(np.ascontiguousarray(self.coarse.points()[keep, :3]))
        if self.coarse.size() >= _MIN_POINTS:
            sg.estimate_covariances(self.coarse, num_neighbors=_NEIGHBOURS)
        self._fine: Any = None
        self._tree: Any = None
        self._ranges: RangeImage | None = None

    @property
    def ranges(self) -> RangeImage:
        """Range image of the cloud (computed on first use)."""
        if self._ranges is None:
            self._ranges = RangeImage(self.points)
        return self._ranges

    def fine(self) -> tuple[Any, Any]:
        """The full cloud with covariances and its kd-tree (computed on first use)."""
        if self._fine is None:
            sg = load_small_gicp()
            cloud = sg.PointCloud(self.points)
            tree = sg.KdTree(cloud)
            sg.estimate_covariances(cloud, tree, num_neighbors=_NEIGHBOURS)
            self._fine, self._tree = cloud, tree
        return self._fine, self._tree


_BIN_DEG = 1.0
_N_AZ = int(360 / _BIN_DEG)
_N_EL = int(180 / _BIN_DEG)


def _bins(points: FloatArray) -> tuple[npt.NDArray[np.intp], FloatArray]:
    """Flat range-image bin of each point (1 degree azimuth x elevation) and its range."""
    r = np.sqrt(np.einsum('ij,ij->i', points, points))
    az = np.degrees(np.arctan2(points[:, 1], points[:, 0])) + 180.0
    el = np.degrees(np.arcsin(np.clip(points[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0))) + 90.0
    ia = np.minimum((az / _BIN_DEG).astype(np.intp), _N_AZ - 1)
    ie = np.minimum((el / _BIN_DEG).astype(np.intp), _N_EL - 1)
    return ia * _N_EL + ie, r


class RangeImage:
    """A cloud's range image, read where needed: ``image[bins]`` is :func:`range_image` at
    the flat bins ``bins`` (see :func:`_bins`), each the least of 9 cells of the nearest-range
    grid. The conflict test reads it at the other cloud's points, a few thousand of its
    64,800 bins: the whole neighbourhood image (half a megabyte per cloud, rolled and copied
    six times) cost more than all the reads.

    Args:
        points: (N, 3) points in the sensor's frame.
    """

    def __init__(self, points: FloatArray) -> None:
        self._nearest = np.full(_N_AZ * _N_EL, np.inf)  # nearest range per bin, inf: none
        if len(points):
            b, r = _bins(points)
            np.minimum.at(self._nearest, b, r)

    def __getitem__(self, bins: npt.NDArray[np.intp]) -> FloatArray:
        """The least nearest range of each bin and its 8 neighbours: azimuth wraps around;
        beyond the first and last elevation row there is none (the row itself stands in for
        it, which changes no minimum)."""
        ia, ie = np.divmod(np.asarray(bins, dtype=np.intp), _N_EL)
        out: FloatArray = np.full(len(ia), np.inf)
        for da in (-1, 0, 1):
            row = (ia + da) % _N_AZ * _N_EL
            for de in (-1, 0, 1):
                np.minimum(out, self._nearest[row + np.clip(ie + de, 0, _N_EL - 1)], out=out)
        return out


def range_image(points: FloatArray) -> FloatArray:
    """Nearest range per 1-degree direction bin and its 8 neighbours (inf where the cloud has
    no point), every bin: the neighbourhood absorbs edge pixels and small misalignments."""
    return RangeImage(points)[np.arange(_N_AZ * _N_EL)]


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
    ``together - 1`` others within ``cell`` metres (see :func:`_coherent`).
    """
    if not len(points):
        return 0.0
    conflict, known = _conflict_masks(points, ranges, margin,
                                      np.zeros(len(points), dtype=bool) if explained is None
                                      else explained)
    if not known.any():
        return 0.0
    if together > 1 and conflict.any():
        conflict = _coherent(points, conflict, cell, together)
    return _fraction(conflict, known, structure)


def _conflict_masks(points: FloatArray, ranges: FloatArray | RangeImage, margin: float,
                    explained: npt.NDArray[np.bool_]
                    ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """Which points conflict and which lie in a direction the viewing sensor saw (see
    :func:`free_space_conflict`)."""
    b, r = _bins(points)
    seen = ranges[b]
    known = np.isfinite(seen)
    conflict = np.zeros(len(r), dtype=bool)
    conflict[known] = r[known] < seen[known] - margin - 0.05 * seen[known]
    return conflict & ~explained, known


def _fraction(conflict: npt.NDArray[np.bool_], known: npt.NDArray[np.bool_],
              structure: int | None) -> float:
    """Conflicting over seen points, and over seen structure points where more."""
    out = float(conflict.sum()) / float(known.sum())
    if structure is not None:
        n_known = int(known[:structure].sum())
        if n_known:
            out = max(out, float(conflict[:structure].sum()) / n_known)
    return out


def _coherent(points: FloatArray, conflict: npt.NDArray[np.bool_], reach: float,
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


@dataclass(frozen=True)
class Alignment:
    """Result of one registration.

    Attributes:
        T_qm: 4x4 transform with ``p_query = T_qm p_match``.
        converged: small_gicp's convergence flag.
        iterations: iterations run.
        coarse_overlap: (coarse stage) fraction of the candidate's coarse structure points
            within half a coarse voxel of the query's after alignment; NaN for fine results.
        hypothesis: index of the start that won (coarse stage: the guesses first, then the
            heading hypotheses), else -1.
        start_z: (coarse stage) the winning start's height, kept where the ground does not
            observe it (:func:`settled`).
    """

    T_qm: FloatArray
    converged: bool
    iterations: int
    coarse_overlap: float = math.nan
    hypothesis: int = -1
    start_z: float = 0.0


def align_coarse(query: Query, source: Source, yaws: list[float],
                 settings: RegistrationSettings,
                 guesses: Sequence[FloatArray] = (), settle: bool = True) -> Alignment | None:
    """Register the structure of ``source`` to the query from each start.

    The starts are the ``guesses`` (full poses, e.g. the pose graph's), then the heading
    hypotheses (rotations about z, no translation). They are tried in order; once one reaches
    a coarse overlap of ``_GOOD_COARSE`` the rest are skipped (the first start is usually
    right).

    Args:
        query: the prepared query.
        source: the prepared candidate.
        yaws: heading hypotheses in the detector's convention (``p_match = Rz(yaw) p_query``).
        settings: registration settings.
        guesses: 4x4 ``T_mq`` (``p_match = T_mq p_query``) to start from before the yaws.

    The kept pose's height is then set on the ground (:func:`settled`, unless ``settle`` is
    False: the verifier settles only the alignments that go on to the fine stage, a quarter of
    them on hku1): upright structure does not pin it.

    Returns:
        The start with the largest coarse overlap (``hypothesis`` is its index: guesses
        first); None when either cloud has too little structure to register.
    """
    starts = [np.linalg.inv(np.asarray(g, dtype=np.float64)) for g in guesses]
    for yaw in yaws:
        init = np.eye(4)
        init[:3, :3] = rot_z(-yaw)  # T_qm = inverse of the hypothesis Rz(yaw)
        starts.append(init)
    if query.coarse.size() < _MIN_POINTS or source.coarse.size() < _MIN_POINTS or not starts:
        return None
    sg = load_small_gicp()
    best: Alignment | None = None
    src_pts = source.coarse.points()[:, :3]
    for k, init in enumerate(starts):
        res = sg.align(query.coarse, source.coarse, query.coarse_tree, init,
                       registration_type='GICP',
                       max_correspondence_distance=settings.coarse_distance,
                       max_iterations=min(settings.max_iterations, _COARSE_ITERATIONS),
                       rotation_epsilon=_COARSE_ROTATION_EPS,
                       translation_epsilon=_COARSE_TRANSLATION_EPS)
        T = np.asarray(res.T_target_source, dtype=np.float64)
        _, sq = query.coarse_tree.batch_nearest_neighbor_search(src_pts @ T[:3, :3].T + T[:3, 3])
        overlap = float(np.mean(np.asarray(sq) < (0.5 * settings.coarse_voxel) ** 2))
        if best is None or overlap > best.coarse_overlap:
            best = Alignment(T, bool(res.converged), int(res.iterations), overlap, k,
                             float(init[2, 3]))
        if overlap >= _GOOD_COARSE:
            break
    return settled(query, source, best, settings) if settle and best is not None else best


def settled(query: Query, source: Source, alignment: Alignment,
            settings: RegistrationSettings) -> Alignment:
    """A coarse alignment with its height set on the ground (:func:`_settle_height`)."""
    return replace(alignment, T_qm=_settle_height(query, source, alignment.T_qm, settings,
                                                  alignment.start_z))


def _settle_height(query: Query, source: Source, T_qm: FloatArray,
                   settings: RegistrationSettings, start_z: float) -> FloatArray:
    """``T_qm`` moved vertically by the median height step from the candidate's horizontal
    surfaces (its points that are not structure: mostly ground) to the nearest of the query's
    within the coarse correspondence distance, twice.

    Upright structure leaves the height free, so the few edges it has decide it: where cars
    had moved between the scans, the coarse stage moved the graph's guess (0.15 m off in
    height) by 0.6-1.5 m up or down, beyond the fine stage's reach (two voxels), and the
    ground could not pull it back. The median ignores the odd roof or table top. With fewer
    than ``_MIN_POINTS`` pairs (no ground in one of the views: a facade filling it) nothing
    observes the height, and the start's (``start_z``: the graph's guess, else level) stays.
    """
    ground = source.points[source.n_struct:]
    tree = query.ground_tree
    T = np.array(T_qm, dtype=np.float64)
    for k in range(2):
        near = np.zeros(0, dtype=bool)
        if tree is not None and len(ground) >= _MIN_POINTS:
            moved = ground @ T[:3, :3].T + T[:3, 3]
            idx, sq = tree.batch_nearest_neighbor_search(moved)
            near = np.asarray(sq) < settings.coarse_distance ** 2
        if int(near.sum()) < _MIN_POINTS:
            if k == 0:
                T[2, 3] = start_z
            break
        rows = np.asarray(idx, dtype=np.intp)[near]
        T[2, 3] += float(np.median(query.ground[rows, 2] - moved[near, 2]))
    return T


def align_fine(query: Query, source: Source, T_qm: FloatArray,
               settings: RegistrationSettings) -> Alignment:
    """Refine ``T_qm`` with voxelised GICP against the query's voxel map (all points).

    A run that ends without small_gicp's convergence flag after ``_FIRST_ITERATIONS`` is
    continued for ``_RESUME_ITERATIONS``; when that moves the pose by less than
    ``_STATIONARY_VOXELS`` fine voxels and ``_STATIONARY_DEG`` degrees, the pose is stationary
    and counts as converged. Small near-field clouds end that way: the optimiser keeps refusing
    steps at the optimum (its damping grows, the pose does not move) or alternates between two
    correspondence sets a centimetre apart, so its step-size criterion is never met. A pose
    still moving goes on from there for the rest of ``max_iterations`` and is checked the same
    way at its end. (Checked only at the iteration limit, the stationary runs, a sixth of
    hku1's, ran to it: a third of the fine stage's registration time.)
    """
    sg = load_small_gicp()
    fine, _ = source.fine()

    def run(T: FloatArray, iterations: int) -> tuple[FloatArray, bool, int]:
        res = sg.align(query.vmap, fine, T, max_iterations=iterations,
                       max_correspondence_distance=settings.neighbour_distance)
        return (np.asarray(res.T_target_source, dtype=np.float64), bool(res.converged),
                int(res.iterations))

    first = min(settings.max_iterations, _FIRST_ITERATIONS)
    T, converged, iterations = run(np.asarray(T_qm, dtype=np.float64), first)
    for rest in (settings.max_iterations - first - _RESUME_ITERATIONS, 0):
        if converged:
            break
        moved, _, more = run(T, _RESUME_ITERATIONS)
        iterations += more
        step = np.linalg.solve(T, moved)
        cos = min(max((float(np.trace(step[:3, :3])) - 1.0) / 2.0, -1.0), 1.0)
        converged = (float(np.linalg.norm(step[:3, 3])) <= _STATIONARY_VOXELS * settings.voxel
                     and math.degrees(math.acos(cos)) <= _STATIONARY_DEG)
        if converged or rest <= 0:
            break
        T, converged, more = run(moved, rest)
        iterations += more
    return Alignment(T, converged, iterations)


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
        jac = np.hstack([np.cross(moved[inlier], normals[inlier]), normals[inlier]])
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
        ``_COHERENT_POINTS - 1`` others within the correspondence distance (see
        :func:`free_space_conflict`)."""
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
        near = (_EXPLAINED_VOXELS * self._settings.voxel) ** 2
        back = self._back
        sq = self._back_sq
        if len(sq) < len(back):
            _, tree = source.fine()
            _, rest = tree.batch_nearest_neighbor_search(back[len(sq):])
            sq = np.concatenate([sq, np.asarray(rest)])
        a = _conflict_masks(self._moved, query.ranges, margin, self._near_sq < near)
        b = _conflict_masks(back, source.ranges, margin, sq < near)
        coherent = max(_fraction(_coherent(self._moved, a[0], margin, _COHERENT_POINTS), a[1],
                                 source.n_struct) if a[0].any() else 0.0,
                       _fraction(_coherent(back, b[0], margin, _COHERENT_POINTS), b[1],
                                 query.n_struct) if b[0].any() else 0.0)
        points = max(_fraction(a[0], a[1], source.n_struct) if a[1].any() else 0.0,
                     _fraction(b[0], b[1], query.n_struct) if b[1].any() else 0.0)
        return coherent, points

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
