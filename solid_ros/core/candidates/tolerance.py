"""How well the pose graph knows where the query is, and what a loop it proposed must agree with.

* Radius of the search by position ``r = min(graph_candidate_max_radius_m,
  graph_candidate_radius_m + graph_candidate_sigmas * sigma)`` (:func:`search_radius`),
  ``sigma`` the query's position uncertainty (:func:`position_sigma`): the square root of the
  largest eigenvalue of the newest keyframe's marginal position covariance, plus the odometry
  step from it to the query (the back end's noise model, and the newest pose's heading
  uncertainty times the step's length); the cap when the graph gives no covariance.
* A loop the graph proposed must keep the graph's relative heading within
  :func:`heading_tolerance_deg` (``graph_candidate_sigmas`` of the query's heading
  uncertainty plus 2 degrees): in a symmetric room the registration can also fit the place
  turned by 180 degrees (seen in the simulator), which only the descriptor's own evidence or
  the graph tells apart, and a keyframe proposed by position has only the graph. Nor may it
  move the query's view centre from where the graph put it (:func:`guess_deviation`) by more
  than 1 m (0.5 m between two tight-space keyframes) plus ``graph_candidate_sigmas`` of the
  query's sigma relative to the match: a slide along a room's shelves
  (:func:`solid_ros.core.candidates.hits.graph_stray`, the judge's ``graph_position`` rule).

* Known place (:func:`knows_place`): a loop that puts the query's view centre where the
  graph predicted it, within one coarse voxel counting ``graph_candidate_sigmas`` sigmas of
  the query's position relative to the match keyframe
  (:meth:`~solid_ros.core.candidates.position.GraphHint.sigma_to`: the graph's joint marginal
  of the two, else the newest keyframe's own), rests on the object the graph expected, not
  another like it.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.noise import model_covariance
from solid_ros.core.config import SolidConfig

__all__ = ['HEADING_FLOOR_DEG', 'guess_deviation', 'heading_tolerance_deg', 'knows_place',
           'position_sigma', 'search_radius']

FloatArray = npt.NDArray[np.float64]
# The match keyframe's own heading error in the graph, beyond the query's marginal.
HEADING_FLOOR_DEG = 2.0


def position_sigma(covariance: npt.ArrayLike | None, config: SolidConfig,
                   step: npt.ArrayLike | None = None,
                   view: npt.ArrayLike | None = None) -> float:
    """Standard deviation of the query's predicted position, metres (see the module
    docstring); ``math.inf`` without a usable covariance.

    Args:
        covariance: 6x6 marginal covariance (ROS order) of the newest keyframe's pose.
        config: the back end's odometry model.
        step: 4x4 odometry step from the newest keyframe to the query (None: none).
        view: a point in the query's sensor frame (its view centre): the heading uncertainty
            then acts on its offset from the newest keyframe instead of the sensor's.
    """
    if covariance is None:
        return math.inf
    cov = np.asarray(covariance, dtype=np.float64)
    if cov.shape != (6, 6) or not bool(np.all(np.isfinite(cov))):
        return math.inf
    var = _largest(cov[:3, :3])
    T = np.eye(4) if step is None else np.asarray(step, dtype=np.float64)
    if step is not None:
        var += _largest(model_covariance(T, config)[:3, :3])
    if step is not None or view is not None:
        lever = T[:3, 3] if view is None else T[:3, :3] @ np.asarray(view, np.float64) + T[:3, 3]
        var += float(lever @ lever) * _largest(cov[3:, 3:])
    return math.sqrt(var)


def search_radius(covariance: npt.ArrayLike | None, config: SolidConfig,
                  step: npt.ArrayLike | None = None, view: npt.ArrayLike | None = None,
                  floor: float = 0.0) -> float:
    """The search radius around a query (see the module docstring).

    Args:
        covariance: 6x6 marginal covariance (ROS order) of the newest keyframe's pose.
        config: the ``graph_candidate_*`` settings and the back end's odometry model.
        step: 4x4 odometry step from the newest keyframe to the query (None: none).
        view: the query's view centre (sensor frame, 3-vector): the heading uncertainty then
            acts on its offset from the newest keyframe instead of the sensor's.
        floor: radius when certain, if larger than ``graph_candidate_radius_m``.
    """
    cap = config.graph_candidate_max_radius_m
    sigma = position_sigma(covariance, config, step, view)
    if not math.isfinite(sigma):
        return cap
    return min(cap, max(config.graph_candidate_radius_m, floor)
               + config.graph_candidate_sigmas * sigma)


def heading_tolerance_deg(covariance: npt.ArrayLike | None, config: SolidConfig,
                          step: npt.ArrayLike | None = None) -> float:
    """How far a loop's heading may lie from the graph's relative heading of a keyframe it
    proposed, degrees: ``graph_candidate_sigmas`` standard deviations of the query's heading
    (the newest keyframe's marginal yaw variance plus the odometry model's over ``step``)
    plus ``HEADING_FLOOR_DEG`` for the match's own uncertainty; 180 without a covariance."""
    if covariance is None:
        return 180.0
    cov = np.asarray(covariance, dtype=np.float64)
    if cov.shape != (6, 6) or not bool(np.all(np.isfinite(cov))):
        return 180.0
    var = max(float(cov[5, 5]), 0.0)
    if step is not None:
        var += max(float(model_covariance(np.asarray(step, dtype=np.float64), config)[5, 5]),
                   0.0)
    return min(180.0, HEADING_FLOOR_DEG
               + config.graph_candidate_sigmas * math.degrees(math.sqrt(var)))


def knows_place(guess: npt.ArrayLike, T_mq: npt.ArrayLike, centre: npt.ArrayLike,
                sigma_m: float, heading_tol_deg: float, config: SolidConfig,
                coarse_voxel: float | None = None) -> bool:
    """Whether the graph's guess pins a loop to one object (see the module docstring).

    Args:
        guess: the graph's 4x4 ``T_mq`` (levelled frames).
        T_mq: the registered 4x4 ``T_mq`` (same frames).
        centre: the query's view centre in its (levelled) frame, 3-vector.
        sigma_m: the query's position sigma with that centre as the lever
            (:func:`position_sigma`; ``math.inf``: unknown).
        heading_tol_deg: :func:`heading_tolerance_deg`.
        config: ``graph_candidate_sigmas`` and ``verify_coarse_voxel_size``.
        coarse_voxel: the pair's coarse grid instead of ``verify_coarse_voxel_size`` (two
            tight-space keyframes register on a finer one).
    """
    if not math.isfinite(sigma_m):
        return False
    G, T = np.asarray(guess, dtype=np.float64), np.asarray(T_mq, dtype=np.float64)
    deviation = guess_deviation(G, T, centre)
    diff = np.linalg.solve(G, T)
    turn = math.degrees(abs(math.atan2(diff[1, 0], diff[0, 0])))
    reach = config.verify_coarse_voxel_size if coarse_voxel is None else coarse_voxel
    return (deviation + config.graph_candidate_sigmas * sigma_m <= reach
            and turn <= heading_tol_deg)


def guess_deviation(guess: npt.ArrayLike, T_mq: npt.ArrayLike, centre: npt.ArrayLike) -> float:
    """How far the registered ``T_mq`` moves the query's view ``centre`` from where the
    graph's ``guess`` puts it, metres (levelled frames)."""
    G, T = np.asarray(guess, dtype=np.float64), np.asarray(T_mq, dtype=np.float64)
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    return float(np.linalg.norm((T[:3, :3] - G[:3, :3]) @ c + T[:3, 3] - G[:3, 3]))


def _largest(block: FloatArray) -> float:
    """Largest eigenvalue of a symmetric block (0 when negative)."""
    return max(float(np.linalg.eigvalsh(0.5 * (block + block.T))[-1]), 0.0)
