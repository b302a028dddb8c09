"""Consistency restarts of the fine stage (solid_ros.core.verification.restarts)."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from project_paths import CONFIG_DIR

from solid_ros.core.config import SolidConfig
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.verification.prepared import Query, Source
from solid_ros.core.verification.restarts import drift
from solid_ros.core.verification.support import Support
from solid_ros.core.verification.verifier import Verifier

FloatArray = npt.NDArray[np.float64]

CFG = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml')


def _ground(rng: np.random.Generator, n: int, half: float) -> FloatArray:
    return np.c_[rng.uniform(-half, half, (n, 2)), np.full(n, -1.5)]


def _wall(rng: np.random.Generator, n: int, a: tuple[float, float],
          b: tuple[float, float]) -> FloatArray:
    u = rng.uniform(0.0, 1.0, (n, 1))
    xy = np.asarray(a) + u * (np.asarray(b) - np.asarray(a))
    return np.c_[xy, rng.uniform(-1.5, 3.0, n)]


def _pair(points: FloatArray) -> tuple[Verifier, Query, Source]:
    """The same scan (3 cm of noise) as query and candidate, downsampled and prepared as the
    detector does."""
    points = points + np.random.default_rng(7).normal(0.0, 0.03, points.shape)
    det, v = LoopDetector(CFG), Verifier(CFG)
    query = v.prepare(det._proposer.keyframe_points(points))
    return v, query, Source(query.keyframe_cloud(), v.settings)


def test_a_pose_pinned_in_every_direction_is_found_again() -> None:
    # Walls facing three ways, two pillars and a far facade: the restarts return to the pose.
    rng = np.random.default_rng(0)
    pts = np.vstack([_ground(rng, 40000, 12.0), _wall(rng, 8000, (8.2, -6), (8.2, 6)),
                     _wall(rng, 8000, (-4, 6.3), (8, 6.3)),
                     _wall(rng, 6000, (-4, -5.9), (3, -5.9)),
                     _wall(rng, 1000, (3, 2), (3.4, 2.4)),
                     _wall(rng, 1000, (-2, -3), (-2.4, -2.6)),
                     _wall(rng, 20000, (30.1, -25), (30.1, 25))])
    v, query, src = _pair(pts)
    T = np.eye(4)
    info = Support(query, src, T, v.settings).information
    drift_m, drift_deg, turn = drift(query, src, T, info)
    assert drift_m < 0.25 * CFG.verify_max_drift and drift_deg < 0.2
    # The turn moves the far points (90th percentile of their range) by one voxel at most.
    far = float(np.percentile(np.linalg.norm(src.points[:, :2], axis=1), 90.0))
    assert turn == min(2.0, math.degrees(v.settings.voxel / far))
    assert 0.5 < turn < 1.5  # the facade's points at 30-39 m


def test_a_pose_along_a_corridor_slides_away() -> None:
    # Two long parallel walls: nothing pins the pose along them, so a restart one voxel
    # along the corridor stays where it was started (the unstable rule refuses it).
    rng = np.random.default_rng(1)
    pts = np.vstack([_ground(rng, 40000, 20.0), _wall(rng, 12000, (-20, 3), (20, 3)),
                     _wall(rng, 12000, (-20, -3), (20, -3))])
    v, query, src = _pair(pts)
    T = np.eye(4)
    info = Support(query, src, T, v.settings).information
    drift_m, _, _ = drift(query, src, T, info)
    assert drift_m > CFG.verify_max_drift
