"""Loop candidates by shared structure: the earlier keyframes that saw what the query sees.

A narrow field of view sees a place from where it stands, and the keyframe that saw the same
structure may stand anywhere: across a crossing, 40 m back along the street it looked down,
or on another street whose view cut through the query's. Neither the position
(:func:`~solid_ros.core.candidates.position.near_keyframes`) nor the nearest view centre
(:func:`~solid_ros.core.candidates.position.view_keyframes`) finds it: on the simulator's 90-degree
drive the keyframes proposed for the revisits left without a loop were those whose view
centres lay nearest, looking at the far side of the same buildings, while one 50 m off at
82 degrees shared half of the query's structure at the right pose.

So the pose graph places each keyframe's coarse structure (its structure points on
``verify_coarse_voxel_size``, kept by the detector) where it put the keyframe, and the
query's at its predicted pose, and counts the share of the query's coarse voxels (each
widened by one voxel across, for the graph's error) that a keyframe also occupies: the
coarse stage's overlap, predicted from the map before any registration. Only keyframes
whose structure's disc meets the query's are counted, and none driven past within twice the
query's view depth (the odometry holds those; a loop to them tells the graph nothing). Those
sharing at least ``verify_min_overlap`` (the structure the tests will ask two views to share;
the widened voxels make the prediction generous: on the simulator's narrow-view streets 1 of
215 registered below 0.35 verified), best first, at most ``graph_candidates``, are
proposed; the detector asks for them only when its other candidates verified nothing. A
keyframe's voxels are placed again only when the graph moved it.

Plain numpy, no ROS, no gtsam.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.position import GraphCandidate, GraphHint, eligible
from solid_ros.core.config import SolidConfig
from solid_ros.core.descriptor.solid import voxel_downsample

__all__ = ['StructureIndex', 'coarse_structure', 'shared_keyframes']

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_OFFSET = 1 << 20  # voxel indices are shifted by this to pack three into one int64
_AROUND = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
_PATH_VIEWS = 2.0  # a keyframe must lie this many view depths of path back
_DEPTH_PERCENTILE = 90.0  # a view's depth: this percentile of its structure's ranges


def coarse_structure(points: npt.ArrayLike, structure: npt.ArrayLike,
                     voxel: float) -> FloatArray:
    """A keyframe's structure points on a grid of ``voxel`` (its frame, (N, 3))."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    mask = np.asarray(structure, dtype=bool).reshape(-1)
    return voxel_downsample(pts[mask], voxel)


def _moved(before: FloatArray, after: FloatArray, disc: tuple[FloatArray, float]) -> float:
    """How far a pose change moves the far edge of a disc (centre, radius) at most."""
    centre, radius = disc
    turn = float(np.linalg.norm(after[:3, :3] - before[:3, :3]))  # about the angle, small
    shift = (after[:3, :3] - before[:3, :3]) @ centre + after[:3, 3] - before[:3, 3]
    return float(np.linalg.norm(shift)) + turn * radius


def _keys(points: FloatArray, voxel: float, dx: int = 0, dy: int = 0) -> IntArray:
    cells = np.floor(points / voxel).astype(np.int64) + _OFFSET
    out: IntArray = ((cells[:, 0] + dx) << 42) | ((cells[:, 1] + dy) << 21) | cells[:, 2]
    return out


class StructureIndex:
    """Each keyframe's coarse structure (sensor frame) with the disc it covers, and its voxels
    where the graph last placed it (recomputed only for a keyframe the graph moved).

    Args:
        capacity: keyframes kept (the oldest go first).
    """

    def __init__(self, capacity: int) -> None:
        self._capacity = capacity
        self._points: dict[int, FloatArray] = {}
        self._discs: dict[int, tuple[FloatArray, float]] = {}
        self._placed: dict[int, tuple[FloatArray, IntArray]] = {}

    def __len__(self) -> int:
        return len(self._points)

    def __contains__(self, index: object) -> bool:
        return index in self._points

    def add(self, index: int, structure: npt.ArrayLike) -> None:
        """Keep keyframe ``index``'s coarse structure (sensor frame; empty: nothing kept)."""
        pts = np.asarray(structure, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return
        centre = pts.mean(axis=0)
        self._points[index] = pts
        self._discs[index] = (centre, float(np.max(np.linalg.norm(pts - centre, axis=1))))
        while len(self._points) > self._capacity:
            old = next(iter(self._points))
            del self._points[old], self._discs[old]
            self._placed.pop(old, None)

    def clear(self) -> None:
        """Forget every keyframe."""
        self._points.clear()
        self._discs.clear()
        self._placed.clear()

    def keys_at(self, index: int, pose: FloatArray, voxel: float) -> IntArray:
        """Keyframe ``index``'s coarse voxels with it at ``pose`` (4x4), sorted, unique."""
        cached = self._placed.get(index)
        # The graph nudges every pose a little at each update; a tenth of a voxel at the
        # structure's far edge is no move.
        if cached is not None and _moved(cached[0], pose, self._discs[index]) < 0.1 * voxel:
            return cached[1]
        pts = self._points[index]
        keys = np.unique(_keys(pts @ pose[:3, :3].T + pose[:3, 3], voxel))
        self._placed[index] = (pose.copy(), keys)
        return keys

    def shared(self, hint: GraphHint, query_index: int, stamp_ns: int,
               odom_pose: npt.ArrayLike, structure: npt.ArrayLike, config: SolidConfig,
               exclude: Sequence[int] = ()) -> list[GraphCandidate]:
        """:func:`shared_keyframes` over the kept keyframes."""
        return shared_keyframes(hint, query_index, stamp_ns, odom_pose, structure, self,
                                config, exclude)

    def discs(self, indices: IntArray) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """Centres (N, 3, sensor frames) and radii of ``indices``' structure, and which are
        kept (the rest zero)."""
        centres, radii = np.zeros((len(indices), 3)), np.zeros(len(indices))
        kept = np.zeros(len(indices), dtype=bool)
        for n, j in enumerate(indices.tolist()):
            disc = self._discs.get(j)
            if disc is not None:
                centres[n], radii[n], kept[n] = disc[0], disc[1], True
        return centres, radii, kept


def shared_keyframes(hint: GraphHint, query_index: int, stamp_ns: int,
                     odom_pose: npt.ArrayLike, structure: npt.ArrayLike,
                     index: StructureIndex, config: SolidConfig,
                     exclude: Sequence[int] = ()) -> list[GraphCandidate]:
    """The eligible keyframes that share the most of the query's coarse structure in the
    graph's estimate, best first (see the module docstring).

    Args:
        hint: the graph's estimate.
        query_index: the query keyframe's index.
        stamp_ns: its stamp.
        odom_pose: its 4x4 odometry pose.
        structure: its coarse structure (:func:`coarse_structure`, sensor frame).
        index: the earlier keyframes' (one not kept is not proposed).
        config: ``graph_candidates``, ``verify_coarse_voxel_size``, ``verify_min_overlap``
            and the exclusion window.
        exclude: keyframes already proposed.
    """
    mine = np.asarray(structure, dtype=np.float64).reshape(-1, 3)
    if config.graph_candidates <= 0 or len(hint.indices) == 0 or len(mine) == 0:
        return []
    voxel = config.verify_coarse_voxel_size
    odom = np.asarray(odom_pose, dtype=np.float64)
    predicted = hint.predict(odom)
    here = mine @ predicted[:3, :3].T + predicted[:3, 3]
    ok = eligible(hint, query_index, stamp_ns, odom, config)
    ok &= ~np.isin(hint.indices, np.asarray(exclude, dtype=np.int64))
    # Keyframes driven past within twice the view's depth see what it sees too, and the
    # odometry already holds them: only a place come back to is worth a loop.
    ranges = np.hypot(mine[:, 0], mine[:, 1])
    path = hint.path_m[-1] + float(np.linalg.norm(odom[:3, 3] - hint.odom[-1, :3, 3]))
    ok &= path - hint.path_m >= _PATH_VIEWS * float(np.percentile(ranges, _DEPTH_PERCENTILE))
    # Only keyframes whose structure's disc meets the query's can share any of it.
    centre = here.mean(axis=0)
    radius = float(np.max(np.linalg.norm(here - centre, axis=1)))
    centres, radii, kept = index.discs(hint.indices)
    placed = np.einsum('nij,nj->ni', hint.poses[:, :3, :3], centres) + hint.poses[:, :3, 3]
    ok &= kept & (np.linalg.norm(placed[:, :2] - centre[:2], axis=1)
                  <= radius + radii + 2.0 * voxel)
    picked = np.flatnonzero(ok).tolist()
    if not picked:
        return []
    keys = [index.keys_at(int(hint.indices[k]), hint.poses[k], voxel) for k in picked]
    all_keys = np.concatenate(keys)
    all_labels = np.repeat(np.arange(len(picked)), [len(k) for k in keys])
    order = np.argsort(all_keys, kind='stable')
    all_keys, all_labels = all_keys[order], all_labels[order]
    points, owners = [], []
    for dx, dy in _AROUND:
        probe = _keys(here, voxel, dx, dy)
        lo = np.searchsorted(all_keys, probe, side='left')
        count = np.searchsorted(all_keys, probe, side='right') - lo
        points.append(np.repeat(np.arange(len(here)), count))
        # Every match of each probe: positions lo .. hi-1.
        starts = np.repeat(lo - np.concatenate(([0], np.cumsum(count)[:-1])), count)
        owners.append(all_labels[starts + np.arange(int(count.sum()))])
    pairs = np.unique(np.concatenate(points) * len(picked) + np.concatenate(owners))
    share = np.bincount(pairs % len(picked), minlength=len(picked)) / len(here)
    gap = np.linalg.norm(hint.poses[:, :3, 3] - predicted[:3, 3], axis=1)
    out = []
    for j in np.argsort(-share, kind='stable').tolist()[:config.graph_candidates]:
        if share[j] < config.verify_min_overlap:
            break
        k = picked[j]
        out.append(GraphCandidate(int(hint.indices[k]), int(hint.stamps_ns[k]), float(gap[k]),
                                  np.linalg.solve(hint.poses[k], predicted), float(share[j])))
    return out
