"""The map: kept keyframe clouds placed at their corrected poses, voxel-downsampled, bounded.

The detector keeps each keyframe's cloud levelled (``p_level = R p_sensor``, ``R`` the mounting
rotation, see doc/conventions.md), so a point goes to the map frame as ``p_map = X R^T
p_level`` with ``X = T_map_sensor`` the back end's corrected pose. Clouds are merged into an
origin-aligned voxel grid chunk by chunk (the memory stays near one chunk plus the map), and
when the map holds more than ``max_points`` the voxel grows by half until it fits: the map
thins out evenly rather than losing whole places.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.descriptor.solid import voxel_downsample
from solid_ros.core.errors import SolidError
from solid_ros.core.geometry import rpy_matrix

__all__ = ['KeptClouds', 'MapCloud', 'build_map', 'keyframe_clouds', 'mount_rotation']

FloatArray = npt.NDArray[np.float64]
_CHUNK_POINTS = 1_000_000  # points merged before each downsampling


@dataclass(frozen=True)
class MapCloud:
    """A map built by :func:`build_map`.

    Attributes:
        points: (M, 3) float32 points in the map frame.
        voxel_size: the voxel the points were finally thinned with, metres.
        keyframes: keyframe clouds that went in.
    """

    points: npt.NDArray[np.float32]
    voxel_size: float
    keyframes: int


def mount_rotation(config: SolidConfig) -> FloatArray:
    """The mounting rotation ``R`` that levelled the stored clouds."""
    return rpy_matrix(math.radians(config.mount_roll_deg), math.radians(config.mount_pitch_deg),
                      math.radians(config.mount_yaw_deg))


class KeptClouds(Protocol):
    """What keeps this session's keyframe clouds (the loop detector)."""

    def own_cloud(self, index: int) -> KeyframeCloud | None:
        """The kept cloud of keyframe ``index`` (None: none or evicted)."""


def keyframe_clouds(detector: KeptClouds, poses: Mapping[int, npt.ArrayLike],
                    ) -> list[tuple[FloatArray, npt.NDArray[np.float32]]]:
    """``(T_map_sensor, levelled points)`` of this session's keyframes that have both a pose in
    ``poses`` (by index, e.g. :meth:`PoseGraph.poses`) and a kept cloud, in index order."""
    out = []
    for index in sorted(poses):
        cloud = detector.own_cloud(index)
        if cloud is not None and len(cloud.points):
            out.append((np.asarray(poses[index], dtype=np.float64), cloud.points))
    return out


def build_map(clouds: Iterable[tuple[npt.ArrayLike, npt.ArrayLike]], mount: npt.ArrayLike,
              voxel_size: float, max_points: int) -> MapCloud:
    """Place levelled keyframe clouds at their poses and thin them into a bounded map.

    Args:
        clouds: ``(T_map_sensor 4x4, (N, 3) levelled points)`` per keyframe.
        mount: the 3x3 mounting rotation that levelled them (:func:`mount_rotation`).
        voxel_size: voxel of the map, metres (> 0).
        max_points: most points of the map (>= 1); the voxel grows until it fits.

    Raises:
        SolidError: ``voxel_size`` or ``max_points`` out of range.
    """
    if not voxel_size > 0.0 or max_points < 1:
        raise SolidError(f'map voxel_size must be > 0 and max_points >= 1, got {voxel_size} '
                         f'and {max_points}')
    unlevel = np.asarray(mount, dtype=np.float64).T
    merged = np.zeros((0, 3))
    chunk: list[FloatArray] = []
    pending = count = 0
    for pose, points in clouds:
        T = np.asarray(pose, dtype=np.float64)
        rot = T[:3, :3] @ unlevel
        chunk.append(np.asarray(points, dtype=np.float64)[:, :3] @ rot.T + T[:3, 3])
        pending += len(chunk[-1])
        count += 1
        if pending >= _CHUNK_POINTS:
            merged = voxel_downsample(np.concatenate([merged, *chunk]), voxel_size)
            chunk, pending = [], 0
    merged = voxel_downsample(np.concatenate([merged, *chunk]), voxel_size)
    voxel = voxel_size
    while len(merged) > max_points:
        voxel *= 1.5
        merged = voxel_downsample(merged, voxel)
    return MapCloud(merged.astype(np.float32), voxel, count)
