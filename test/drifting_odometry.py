"""A drifting odometry for the back end's tests and benches, made from reference poses.

The simulator's poses are perfect; a back end needs odometry that drifts as a LiDAR odometry
does. Each reference step ``P[k-1]^-1 P[k]`` is replayed with its translation scaled by ``1 +
scale``, a heading bias of ``yaw_bias_deg_per_m`` per metre driven, a slight pitch bias (the
odometry climbs or sinks) and a heading random walk of ``yaw_walk_deg`` per square-root metre,
then the steps are chained from ``start`` (the first reference pose unless given).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Drift:
    """How the odometry drifts (defaults: about 5 % of the distance driven over 100-800 m).

    Attributes:
        scale: translation scale error (0.02 = every step 2 % too long).
        yaw_bias_deg_per_m: heading error added per metre driven, degrees.
        pitch_bias_deg_per_m: pitch error added per metre driven, degrees.
        yaw_walk_deg: heading random walk, degrees per square-root metre.
        seed: seed of the random walk.
    """

    scale: float = 0.01
    yaw_bias_deg_per_m: float = 0.055
    pitch_bias_deg_per_m: float = 0.0005
    yaw_walk_deg: float = 0.02
    seed: int = 0


def _rot(axis: int, angle: float) -> FloatArray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    out = np.eye(3)
    out[i, i] = out[j, j] = c
    out[i, j], out[j, i] = -s, s
    return out


def drifting_odometry(reference: npt.ArrayLike, drift: Drift = Drift(),
                      start: npt.ArrayLike | None = None) -> FloatArray:
    """Odometry poses (N, 4, 4) that follow ``reference`` (N, 4, 4) step by step, drifting.

    Args:
        reference: true sensor poses.
        drift: the drift model.
        start: the odometry's first pose (default: the first reference pose, so the odometry
            frame is the reference frame).
    """
    ref = np.asarray(reference, dtype=np.float64)
    rng = np.random.default_rng(drift.seed)
    out = np.empty_like(ref)
    out[0] = ref[0] if start is None else np.asarray(start, dtype=np.float64)
    for k in range(1, len(ref)):
        step = np.linalg.solve(ref[k - 1], ref[k])
        dist = float(np.linalg.norm(step[:3, 3]))
        yaw = math.radians(drift.yaw_bias_deg_per_m * dist
                           + drift.yaw_walk_deg * math.sqrt(dist) * rng.standard_normal())
        pitch = math.radians(drift.pitch_bias_deg_per_m * dist)
        noisy = step.copy()
        noisy[:3, 3] *= 1.0 + drift.scale
        noisy[:3, :3] = _rot(2, yaw) @ _rot(1, pitch) @ step[:3, :3]
        out[k] = out[k - 1] @ noisy
    return out


def drift_percent(odometry: npt.ArrayLike, reference: npt.ArrayLike,
                  lengths: tuple[float, ...] = (100.0, 200.0, 400.0, 800.0)) -> float:
    """KITTI-style drift: mean translation error over segments of ``lengths`` metres, percent
    of the segment length (segments start every 10th pose; lengths beyond the path skipped)."""
    odo = np.asarray(odometry, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0),
                                                           axis=1))])
    errors = []
    for first in range(0, len(ref), 10):
        for length in lengths:
            last = int(np.searchsorted(dist, dist[first] + length))
            if last >= len(ref):
                continue
            d_ref = np.linalg.solve(ref[first], ref[last])
            d_odo = np.linalg.solve(odo[first], odo[last])
            err = np.linalg.solve(d_odo, d_ref)
            errors.append(float(np.linalg.norm(err[:3, 3])) / length)
    return 100.0 * float(np.mean(errors)) if errors else math.nan


def square(n: int, side: int = 40) -> FloatArray:
    """Reference poses driving ``n`` metres counter-clockwise around a square of ``side``
    metres, one per metre (the back end's tests drive it and drift it)."""
    out = []
    pos, heading = np.zeros(2), 0.0
    for k in range(n):
        T = np.eye(4)
        c, s = math.cos(heading), math.sin(heading)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = pos
        out.append(T)
        pos = pos + np.array([c, s])
        if (k + 1) % side == 0:
            heading += math.pi / 2
    return np.array(out)
