"""The replay's keyframe trajectory: odometry and corrected pose per keyframe, the files it is
written to, and its error against reference poses.

The corrected pose is the pose graph's final ``T_map_sensor`` of the keyframe (the odometry's
child frame: the sensor whose clouds are replayed); without the back end it is the odometry
pose. Errors are taken at the keyframes that have all three poses (odometry, corrected,
reference): ATE RMSE after an SE(3) alignment, RPE over pairs 10 m of reference path apart
(:data:`RPE_METRES`), and the end error as a fraction of the path (drift).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.geometry import matrix_to_vector
from solid_ros.formats.poses import write_kitti_poses, write_tum_poses
from solid_ros.tools.pipeline import ScanLog
from solid_ros.tools.trajectory_metrics import (
    align_se3,
    ate_rmse,
    end_error,
    path_length,
    rpe_by_distance,
)

__all__ = ['RPE_METRES', 'TRAJECTORY_FILES', 'Trajectory', 'aligned_positions',
           'keyframe_rows', 'keyframe_trajectory', 'trajectory_errors', 'write_trajectory']

FloatArray = npt.NDArray[np.float64]
RPE_METRES = 10.0  # RPE pairs keyframes this far apart along the reference path
TRAJECTORY_FILES = ('trajectory.tum', 'trajectory.kitti')


@dataclass(frozen=True)
class Trajectory:
    """Per keyframe of the replay, in the log's order.

    Attributes:
        indices: (K,) keyframe index.
        stamps_ns: (K,) stamp.
        odometry: (K, 4, 4) odometry pose ``T_odom_sensor`` (NaN: the keyframe had none).
        corrected: (K, 4, 4) corrected pose ``T_map_sensor`` (the odometry without the back
            end; NaN: none).
        segments: (K,) graph segment (-1: not in the graph; 0 without the back end).
        backend: whether the back end ran.
    """

    indices: npt.NDArray[np.int64]
    stamps_ns: npt.NDArray[np.int64]
    odometry: FloatArray
    corrected: FloatArray
    segments: npt.NDArray[np.int64]
    backend: bool

    @property
    def posed(self) -> npt.NDArray[np.bool_]:
        """Keyframes with a corrected pose."""
        return np.asarray(np.isfinite(self.corrected).all(axis=(1, 2)), dtype=bool)


def keyframe_trajectory(log: ScanLog, closure: LoopClosure) -> Trajectory:
    """The trajectory of a replay's keyframes after the run (the graph's final poses)."""
    results = log.results
    k = len(results)
    odo = np.full((k, 4, 4), np.nan)
    for i, sample in enumerate(log.keyframe_odom):
        if sample is not None:
            odo[i] = sample.pose
    indices = np.asarray([r.query_index for r in results], dtype=np.int64)
    stamps = np.asarray([r.stamp_ns for r in results], dtype=np.int64)
    graph = closure.graph
    if graph is None:
        return Trajectory(indices, stamps, odo, odo.copy(), np.zeros(k, dtype=np.int64), False)
    kfs = {kf.index: kf for kf in graph.keyframes()}
    cor = np.full((k, 4, 4), np.nan)
    seg = np.full(k, -1, dtype=np.int64)
    for i, index in enumerate(indices):
        kf = kfs.get(int(index))
        if kf is not None:
            cor[i], seg[i] = kf.pose, kf.segment
    return Trajectory(indices, stamps, odo, cor, seg, True)


def write_trajectory(out: Path, traj: Trajectory) -> list[Path]:
    """Write the corrected poses of the posed keyframes as ``trajectory.tum`` and
    ``trajectory.kitti`` in ``out`` (one row per keyframe with a pose).

    Raises:
        SolidError: a file cannot be written.
    """
    have = traj.posed
    return [write_tum_poses(out / TRAJECTORY_FILES[0], traj.stamps_ns[have],
                            traj.corrected[have]),
            write_kitti_poses(out / TRAJECTORY_FILES[1], traj.corrected[have])]


def _vector(pose: FloatArray) -> list[float] | None:
    return [float(v) for v in matrix_to_vector(pose)] if np.isfinite(pose).all() else None


def keyframe_rows(traj: Trajectory) -> list[dict[str, Any]]:
    """The report's ``keyframes``: index, stamp, odometry and corrected pose
    (``x y z qx qy qz qw``, null: none) and graph segment of each keyframe, enough for another
    back end to rebuild the keyframe chain."""
    return [{'index': int(i), 'stamp_ns': int(s), 'odom': _vector(o), 'pose': _vector(c),
             'segment': int(g)}
            for i, s, o, c, g in zip(traj.indices, traj.stamps_ns, traj.odometry,
                                     traj.corrected, traj.segments)]


def _scored(traj: Trajectory, reference: FloatArray) -> npt.NDArray[np.bool_]:
    return np.asarray(traj.posed & np.isfinite(traj.odometry).all(axis=(1, 2))
                      & np.isfinite(reference).all(axis=(1, 2)), dtype=bool)


def _errors(est: FloatArray, ref: FloatArray, path: float) -> dict[str, float]:
    rpe_m, rpe_deg, _ = rpe_by_distance(est, ref, RPE_METRES)
    end = end_error(est, ref)
    return {'ate_m': ate_rmse(est, ref), 'rpe_m': rpe_m, 'rpe_deg': rpe_deg,
            'end_error_m': end, 'drift_pct': 100.0 * end / path if path > 0 else math.nan}


def trajectory_errors(traj: Trajectory, reference: FloatArray | None) -> dict[str, Any] | None:
    """ATE, RPE per :data:`RPE_METRES` of path and end error of the odometry and of the
    corrected poses against ``reference`` (per keyframe, NaN: unknown), at the keyframes that
    have all three; None without a reference or fewer than two such keyframes."""
    if reference is None:
        return None
    ok = _scored(traj, reference)
    if ok.sum() < 2:
        return None
    ref = reference[ok]
    path = float(path_length(ref)[-1])
    odo, cor = _errors(traj.odometry[ok], ref, path), _errors(traj.corrected[ok], ref, path)
    return {'keyframes': int(ok.sum()), 'path_m': path, 'rpe_delta_m': RPE_METRES,
            'odometry': odo, 'corrected': cor,
            'ate_ratio': odo['ate_m'] / cor['ate_m'] if cor['ate_m'] > 0 else math.nan}


def aligned_positions(traj: Trajectory, reference: FloatArray,
                      ) -> dict[str, FloatArray] | None:
    """For the plot: the odometry and corrected positions (K, 3) moved onto the reference by
    their ATE alignment (NaN where not scored); None when fewer than two keyframes score."""
    ok = _scored(traj, reference)
    if ok.sum() < 2:
        return None
    out = {}
    for name, poses in (('odometry', traj.odometry), ('corrected', traj.corrected)):
        A = align_se3(poses[ok], reference[ok])
        pos = np.full((len(poses), 3), np.nan)
        pos[ok] = poses[ok, :3, 3] @ A[:3, :3].T + A[:3, 3]
        out[name] = pos
    return out
