"""Loader of the hku1 keyframe bag (../shared/data/hku1) for the database and detector tests."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import numpy.typing as npt

from solid_ros.pointcloud2 import cloud_to_xyz

# Livox Avia: 70.4 x 77.2 deg FOV. On this bag a 0.2 m voxel grid on top of the recorded one
# gave the best Recall@1 / F1 of the settings tried (see the detector report).
HKU1_CONFIG = {'fov_width_deg': 360.0, 'fov_up_deg': 38.6, 'fov_down_deg': -38.6,
               'min_range': 0.5, 'max_range': 60.0, 'max_distance': 60.0, 'voxel_size': 0.2}


@lru_cache(maxsize=2)
def hku1_scans(root: Path) -> tuple[list[npt.NDArray[np.floating]], list[int]]:
    """Return the /points clouds (N, 3) and their stamps in ns, in bag order."""
    from rosbags.highlevel import AnyReader

    clouds: list[npt.NDArray[np.floating]] = []
    stamps: list[int] = []
    with AnyReader([root / 'hku1' / 'bag']) as reader:
        conns = [c for c in reader.connections if c.topic == '/points']
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            clouds.append(np.array(cloud_to_xyz(msg), dtype=np.float32))
            stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
    return clouds, stamps


def hku1_positions(root: Path) -> npt.NDArray[np.float64]:
    """Reference keyframe positions (K, 3) from optimized_poses.txt (KITTI 3x4 rows)."""
    rows = np.loadtxt(root / 'hku1' / 'optimized_poses.txt').reshape(-1, 3, 4)
    return rows[:, :, 3]
