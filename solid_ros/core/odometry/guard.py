"""What the KISS-ICP source takes from the data: its settings and the bar of its overlap check.

Settings (:func:`derive_settings`). KISS-ICP's own pipeline takes the voxel from the range
(``voxel_size = max_range / 100``). A setting of 0 here means "from the data": the max range
is the 99th percentile of the first cloud's point ranges (rounded up to a metre: a 70 m
Ouster in a street, 12 m in a room), and the voxel is KISS-ICP's rule on it.

Overlap (:class:`OverlapGuard`). A cloud KISS-ICP registered is checked against the previous
one: the fraction of its structure points (walls, poles, trunks: normals away from vertical)
that lie within two voxels of the previous cloud where KISS-ICP put it. How much consecutive
clouds overlap depends on the sensor, its rate and the motion (a Livox Avia held in a room
about 0.9, an Ouster on a car at 1-2 clouds/s about 0.65, with steps of 20 m that overlap far
less), so the bar is not fixed: a cloud fails when its overlap is below ``kiss_min_overlap``
times the median overlap of the clouds this run accepted (the last :data:`HISTORY`, across
resets: the overlap is the sensor's and the motion's, not the segment's); the first pair of a
run always passes. A cloud from another place, or one turned by 90 degrees, overlaps
0.0-0.25 (``test/bench/bench_odometry.py``; the guard's tests splice them in).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import NodeConfig

__all__ = ['HISTORY', 'Frame', 'OverlapGuard', 'derive_settings', 'prepare']

FloatArray = npt.NDArray[np.float64]

HISTORY = 50  # accepted overlaps the bar is taken from
RANGE_PERCENTILE = 99.0  # of the first cloud's ranges: the derived max range
_NEIGHBOURS = 10  # points per normal estimate
_PLANAR = 3.0  # a point is planar when its 2nd covariance eigenvalue is this times the 1st
_STRUCTURE_MAX_NZ = 0.7  # |n_z| below this: a wall, pole or trunk rather than the ground
_MIN_STRUCTURE = 20  # fewer structure points than this: the overlap test is skipped


def derive_settings(config: NodeConfig, clouds: list[FloatArray]) -> NodeConfig:
    """``config`` with ``kiss_max_range`` and ``kiss_voxel_size`` of 0 taken from the data.

    Args:
        config: the settings (values other than 0 are kept).
        clouds: clouds in the sensor frame ((N, 3+)); the first one with finite points is used.

    Returns:
        The settings with a max range (99th percentile of the cloud's ranges, rounded up to a
        metre, at least ``kiss_min_range`` + 1 m) and a voxel (max range / 100, KISS-ICP's
        rule), or ``config`` unchanged when there is nothing to derive or no finite point.
    """
    if config.kiss_max_range > 0 and config.kiss_voxel_size > 0:
        return config
    max_range = config.kiss_max_range
    if max_range <= 0:
        ranges = next((r for r in (_ranges(c) for c in clouds) if len(r)), None)
        if ranges is None:
            return config
        max_range = max(math.ceil(float(np.percentile(ranges, RANGE_PERCENTILE))),
                        config.kiss_min_range + 1.0)
    voxel = config.kiss_voxel_size if config.kiss_voxel_size > 0 else max_range / 100.0
    return replace(config, kiss_max_range=float(max_range), kiss_voxel_size=float(voxel))


def _ranges(points: FloatArray) -> FloatArray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] < 3:
        return np.zeros(0)
    r: FloatArray = np.linalg.norm(p[:, :3], axis=1)
    return r[np.isfinite(r) & (r > 0)]


@dataclass(frozen=True)
class Frame:
    """What the checks keep of a cloud: its voxelised points, their normals and a kd-tree.

    Attributes:
        points: (M, 3) voxelised points in the cloud's sensor frame.
        structure: which of them are structure (normal away from vertical).
        constraint: smallest eigenvalue of the mean x-y normal outer product of the planar
            points (about 0 in a corridor).
        tree: small_gicp kd-tree of ``points`` (None without points).
    """

    points: FloatArray
    structure: npt.NDArray[np.bool_]
    constraint: float
    tree: Any


def prepare(points: FloatArray) -> Frame:
    """Normals, structure and horizontal constraint of a voxelised cloud ((M, 3) points,
    voxelised as KISS-ICP does for registration)."""
    import small_gicp as sg  # the neighbours in C++: half scipy's cKDTree time per cloud

    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    tree = sg.KdTree(sg.PointCloud(pts)) if len(pts) else None
    k = min(_NEIGHBOURS, len(pts))
    idx = (np.asarray(tree.batch_knn_search(pts, k)[0], dtype=np.intp) if tree is not None
           else np.zeros((0, k), dtype=np.intp))
    nb = pts[idx.reshape(len(pts), k)]
    centred = nb - nb.mean(axis=1, keepdims=True)
    w, v = np.linalg.eigh(np.matmul(centred.transpose(0, 2, 1), centred))
    normals = v[:, :, 0]
    planar = normals[w[:, 1] > _PLANAR * np.maximum(w[:, 0], 1e-12)]
    # Horizontal only: without ground (a tilted or high sensor) z rests on KISS-ICP's
    # motion prediction, but the structure still fixes the position (x, y).
    xy = planar[:, :2]
    info = xy.T @ xy / max(len(pts), 1)
    return Frame(pts, np.abs(normals[:, 2]) < _STRUCTURE_MAX_NZ,
                 float(np.linalg.eigvalsh(info)[0]), tree)


class OverlapGuard:
    """The overlap check with its bar calibrated on the run.

    Args:
        ratio: a cloud fails below this times the run's median overlap (0: never).
        reach: distance to the previous cloud's nearest point that counts as overlap, metres.
    """

    def __init__(self, ratio: float, reach: float) -> None:
        self.ratio = float(ratio)
        self.reach = float(reach)
        self._seen: deque[float] = deque(maxlen=HISTORY)

    @property
    def bar(self) -> float:
        """The overlap below which a cloud fails now (0 before the first accepted pair)."""
        return self.ratio * float(np.median(self._seen)) if self._seen else 0.0

    @property
    def typical(self) -> float | None:
        """The run's median overlap of accepted clouds (None: none yet)."""
        return float(np.median(self._seen)) if self._seen else None

    def overlap(self, cloud: Frame, previous: Frame, step: FloatArray) -> float:
        """Fraction of ``cloud``'s structure within ``reach`` of ``previous`` once mapped by
        ``step`` (``p_prev = step p``); 1.0 when it has too little structure to tell."""
        struct = cloud.points[cloud.structure]
        if len(struct) < _MIN_STRUCTURE or previous.tree is None:
            return 1.0
        moved = np.ascontiguousarray(struct @ step[:3, :3].T + step[:3, 3])
        _, sq = previous.tree.batch_nearest_neighbor_search(moved)
        return float(np.mean(np.asarray(sq) < self.reach ** 2))

    def fails(self, overlap: float) -> bool:
        """Whether ``overlap`` is below the run's bar."""
        return overlap < self.bar

    def accept(self, overlap: float) -> None:
        """Record the overlap of a cloud that was kept."""
        self._seen.append(float(overlap))
