"""Aligned peers' keyframes placed in this robot's map, for candidates by position.

Once a peer is aligned (:class:`~solid_ros.core.backend.alignment.FleetAlignment`:
``T_own_peer`` = ``T_own_map<-peer_map`` with its covariance), its keyframes near the query in
the shared frame become candidates as this robot's own near keyframes are, registered from the
placement first (:func:`~solid_ros.core.candidates.position.peer_keyframes`). What is known
of a peer keyframe ``k``: its odometry pose ``O_k`` as sent with its descriptor, and for some
keyframes ``j`` their pose ``M_j`` in the peer's map (those the peer's loops name, on a live
robot; every keyframe of its graph in the offline fleet replay). ``k`` is placed from the
keyframe ``j`` nearest it by index with both known::

    P_k = T_own_peer @ M_j @ inv(O_j) @ O_k

and its position sigma is the alignment's at ``M_j``'s position (its covariance through the
lever of the peer map's origin) plus the back end's odometry model over the peer's path from
``j`` to ``k`` (a random walk, the heading drift acting over their distance); its heading sigma
likewise. Plain numpy.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.position import PeerPlacement
from solid_ros.core.config import SolidConfig
from solid_ros.core.geometry import invert_rigid

__all__ = ['place_peer', 'placed_peers']

FloatArray = npt.NDArray[np.float64]


def place_peer(peer: int, transform: npt.ArrayLike, covariance: npt.ArrayLike | None,
               map_poses: Mapping[int, FloatArray], odom_poses: Mapping[int, FloatArray],
               config: SolidConfig) -> PeerPlacement:
    """The keyframes of ``odom_poses`` placed in this robot's map (module docstring); none
    without a keyframe whose map and odometry poses are both known, or without a finite 6x6
    ``covariance``.

    Args:
        peer: the peer's robot id.
        transform: 4x4 ``T_own_map<-peer_map``.
        covariance: its 6x6 covariance (ROS order, right perturbation).
        map_poses: the peer's keyframe poses in its map, by index (some keyframes).
        odom_poses: its keyframes' odometry poses as sent, by index.
        config: the back end's odometry model (``backend_odom_*``).
    """
    cov = None if covariance is None else np.asarray(covariance, dtype=np.float64)
    if cov is None or cov.shape != (6, 6) or not bool(np.all(np.isfinite(cov))):
        return PeerPlacement()
    order = np.array(sorted(odom_poses), dtype=np.int64)
    at = np.flatnonzero([i in map_poses for i in order.tolist()])  # anchors' rows
    if not len(at):
        return PeerPlacement()
    odo = np.array([odom_poses[i] for i in order.tolist()], dtype=np.float64).reshape(-1, 4, 4)
    # Each keyframe's nearest anchor by index (the lower one on a tie), as a row of ``at``.
    right = np.clip(np.searchsorted(order[at], order), 0, len(at) - 1)
    left = np.clip(right - 1, 0, len(at) - 1)
    a = np.where(np.abs(order[at[left]] - order) <= np.abs(order[at[right]] - order),
                 left, right)
    M = np.array([map_poses[i] for i in order[at].tolist()], dtype=np.float64)
    rel = invert_rigid(odo[at])[a] @ odo  # inv(O_j) @ O_k
    placed = (np.asarray(transform, dtype=np.float64) @ M)[a] @ rel
    # The peer's odometry path from j to k (its keyframes in index order).
    steps = np.linalg.norm(np.diff(odo[:, :3, 3], axis=0), axis=1)
    path = np.concatenate(([0.0], np.cumsum(steps)))
    var_t, var_r = _drift_variances(np.abs(path - path[at[a]]), config)
    lever = np.linalg.norm(rel[:, :3, 3], axis=1)
    sigma = np.sqrt(_alignment_variances(cov, M[:, :3, 3])[a] + var_t + lever ** 2 * var_r)
    yaw = np.sqrt(max(float(cov[5, 5]), 0.0) + var_r)
    keys = np.stack([np.full(len(order), int(peer)), order], axis=1)
    return PeerPlacement.of(keys, placed, sigma, yaw)


def placed_peers(placements: list[PeerPlacement]) -> PeerPlacement:
    """Several peers' placements as one."""
    kept = [p for p in placements if len(p.keys)]
    if not kept:
        return PeerPlacement()
    return PeerPlacement.of(np.concatenate([p.keys for p in kept]),
                            np.concatenate([p.poses for p in kept]),
                            np.concatenate([p.sigma_m for p in kept]),
                            np.concatenate([p.yaw_sigma_rad for p in kept]))


def _drift_variances(path_m: FloatArray, config: SolidConfig) -> tuple[FloatArray, FloatArray]:
    """Translation (m^2) and rotation (rad^2) variances of the odometry model over paths,
    with its floors."""
    var_t = config.backend_odom_trans_sigma ** 2 * path_m + config.backend_odom_floor_m ** 2
    var_r = (math.radians(config.backend_odom_rot_sigma_deg) ** 2 * path_m
             + math.radians(config.backend_odom_floor_deg) ** 2)
    return var_t, var_r


def _alignment_variances(cov: FloatArray, points: FloatArray) -> FloatArray:
    """Largest position variance of peer-map ``points`` (n, 3) moved by the alignment's
    uncertainty: ``T exp(xi) p`` moves ``p`` by ``dt - [p]x dtheta`` (ROS order)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    J = np.zeros((len(p), 3, 6))
    J[:, [0, 1, 2], [0, 1, 2]] = 1.0
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    J[:, 0, 4], J[:, 0, 5] = z, -y  # -[p]x: rows (0, z, -y), (-z, 0, x), (y, -x, 0)
    J[:, 1, 3], J[:, 1, 5] = -z, x
    J[:, 2, 3], J[:, 2, 4] = y, -x
    c = (J @ cov) @ np.swapaxes(J, 1, 2)
    out: FloatArray = np.maximum(np.linalg.eigvalsh(0.5 * (c + np.swapaxes(c, 1, 2)))[:, -1],
                                 0.0)
    return out
