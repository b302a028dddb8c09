"""Scans of the simulator's default hdl64 drive (seed 0), shared by the verification and
loop-covariance tests: scan 273 revisits scan 5, scan 290 scan 22."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.sim.drive import Drive, DriveConfig

FloatArray = npt.NDArray[np.float64]
CFG = SolidConfig(verify_voxel_size=0.5, verify_coarse_voxel_size=1.5)


@lru_cache(maxsize=1)
def drive() -> Drive:
    return Drive(DriveConfig(seed=0, sensor='hdl64'))


@lru_cache(maxsize=16)
def scan(index: int) -> tuple[npt.NDArray[np.float32], FloatArray]:
    """Points and reference pose of one scan of the drive."""
    s = drive().scan(index)
    return s.points.copy(), s.pose


def truth(q: int, m: int) -> FloatArray:
    """Reference T_mq: pose of the query sensor in the match sensor's frame."""
    out: FloatArray = np.linalg.inv(scan(m)[1]) @ scan(q)[1]
    return out


def keyframe_points(points: npt.ArrayLike, cfg: SolidConfig = CFG) -> FloatArray:
    """A scan's keyframe cloud on the configuration's grid, as the detector keeps it."""
    return LoopDetector(cfg)._proposer.keyframe_points(points)
