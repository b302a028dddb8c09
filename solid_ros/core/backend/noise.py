"""Noise of the pose graph's factors, in numpy: odometry steps, loops, and their conventions.

Conventions. A published loop's covariance (doc/conventions.md) is 6x6 in ROS order ``(x, y,
z, roll, pitch, yaw)`` of a right perturbation ``T exp(delta)`` in the query sensor frame. gtsam's
``Pose3`` uses the same right perturbation (``BetweenFactor`` and ``PriorFactor`` errors are
``Logmap(measured^-1 predicted)``) with the rotation first: ``(rx, ry, rz, x, y, z)``. For the
small angles of a covariance, roll, pitch and yaw are the rotation vector's components, so the
two orders differ only by swapping the 3x3 blocks: :func:`swap_blocks`, the one conversion
(its own inverse). Odometry covariances are read the same way (ROS order, right perturbation in
the sensor frame; ROS leaves their frame open).

Odometry step noise. An odometry step between two keyframes takes its covariance from the
odometry when the source gives a usable one (finite, symmetric, positive definite): the growth
``C_now - C_before`` when that is positive definite (a filter's covariance grows as it drives),
else ``C_now`` itself (a source that publishes each pose's own uncertainty). Otherwise the
model: variances grow with the distance ``d`` driven and the angle ``a`` turned,
``sigma_t^2 = trans^2 d`` and ``sigma_r^2 = rot_m^2 d + rot_rad^2 a`` (random walks: the same
total whatever the keyframe spacing). Floors are added in quadrature to every odometry and loop
covariance, so no factor is tighter than they say (registration covariances are optimistic).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.odometry.track import usable_covariance

__all__ = ['StepNoise', 'floored', 'loop_covariance', 'model_covariance', 'odometry_step_noise',
           'rotation_angle', 'swap_blocks', 'unchecked_covariance']

FloatArray = npt.NDArray[np.float64]
_SWAP = np.array([3, 4, 5, 0, 1, 2])


def swap_blocks(cov: npt.ArrayLike) -> FloatArray:
    """A 6x6 covariance between ROS order (translation first) and gtsam's tangent order
    (rotation first); the same call converts back."""
    c = np.asarray(cov, dtype=np.float64).reshape(6, 6)
    out: FloatArray = c[np.ix_(_SWAP, _SWAP)]
    return out


def rotation_angle(T: npt.ArrayLike) -> float:
    """Angle of the rotation part of a 4x4 transform, radians in [0, pi]."""
    r = np.asarray(T, dtype=np.float64)[:3, :3]
    return math.acos(max(-1.0, min(1.0, (float(np.trace(r)) - 1.0) / 2.0)))


def floored(cov: npt.ArrayLike, floor_m: float, floor_rad: float) -> FloatArray:
    """ROS-order covariance with ``floor_m^2`` and ``floor_rad^2`` added to its diagonal."""
    c = np.array(cov, dtype=np.float64).reshape(6, 6)
    out: FloatArray = 0.5 * (c + c.T)
    out[np.diag_indices(6)] += np.repeat([floor_m ** 2, floor_rad ** 2], 3)
    return out


def model_covariance(step: npt.ArrayLike, config: SolidConfig) -> FloatArray:
    """ROS-order covariance of an odometry step from the per-metre / per-radian model (with
    the floors)."""
    T = np.asarray(step, dtype=np.float64)
    d = float(np.linalg.norm(T[:3, 3]))
    a = rotation_angle(T)
    var_t = config.backend_odom_trans_sigma ** 2 * d
    var_r = (math.radians(config.backend_odom_rot_sigma_deg) ** 2 * d
             + config.backend_odom_rot_per_rad ** 2 * a)
    return floored(np.diag(np.repeat([var_t, var_r], 3)), config.backend_odom_floor_m,
                   math.radians(config.backend_odom_floor_deg))


@dataclass(frozen=True)
class StepNoise:
    """The covariance chosen for one odometry step.

    Attributes:
        covariance: 6x6, ROS order, floors included.
        source: ``'odometry'`` (the source's covariance) or ``'model'``.
        bad: the source gave a covariance that is set but unusable (NaN, negative, not
            positive definite): the model was used instead, a warning is due.
    """

    covariance: FloatArray
    source: str
    bad: bool = False


def _is_set(cov: npt.ArrayLike | None) -> bool:
    """Whether a covariance was given at all (ROS marks 'unknown' with all zeros)."""
    if cov is None:
        return False
    c = np.asarray(cov, dtype=np.float64)
    return bool(c.size and np.any(c != 0.0))


def odometry_step_noise(step: npt.ArrayLike, cov_before: npt.ArrayLike | None,
                        cov_now: npt.ArrayLike | None, config: SolidConfig) -> StepNoise:
    """Covariance of the odometry step to a keyframe (rules in the module docstring).

    Args:
        step: 4x4 odometry motion from the previous keyframe to this one.
        cov_before: the odometry covariance at the previous keyframe, if any.
        cov_now: the odometry covariance at this keyframe, if any.
        config: the model's and the floors' settings.
    """
    now = usable_covariance(cov_now)
    if now is None:
        return StepNoise(model_covariance(step, config), 'model', _is_set(cov_now))
    before = usable_covariance(cov_before)
    chosen = now
    if before is not None:
        grown = usable_covariance(now - before)
        if grown is not None:
            chosen = grown
    return StepNoise(floored(chosen, config.backend_odom_floor_m,
                             math.radians(config.backend_odom_floor_deg)), 'odometry')


def unchecked_covariance(step: npt.ArrayLike, covariance: npt.ArrayLike) -> FloatArray:
    """A scan-only odometry's step that no registration could check: its covariance with
    each translation sigma at least the step's length and each rotation sigma at least the
    angle turned (the step is known up to its own size, no better)."""
    T = np.asarray(step, dtype=np.float64)
    out = np.array(covariance, dtype=np.float64).reshape(6, 6)
    least = np.repeat([float(np.linalg.norm(T[:3, 3])) ** 2, rotation_angle(T) ** 2], 3)
    out[np.diag_indices(6)] = np.maximum(np.diag(out), least)
    return out


def loop_covariance(covariance: npt.ArrayLike, config: SolidConfig) -> FloatArray | None:
    """A published loop's ROS-order covariance with the loop floors, or None when it is not
    usable (unverified loops carry NaN)."""
    cov = usable_covariance(covariance)
    if cov is None:
        return None
    return floored(cov, config.backend_loop_floor_m, math.radians(config.backend_loop_floor_deg))
