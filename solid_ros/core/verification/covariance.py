"""The covariance of a verified loop, read from the registration's residuals.

The relative pose is ``T = T_mq``; its covariance, for a right perturbation ``T exp(delta)``
with ``delta = (tx, ty, tz, rx, ry, rz)`` in the query frame (ROS order), is
``verify_covariance_scale * RESIDUAL_SCALE * inv(A) G inv(A)`` (:func:`support_covariance`;
``TIGHT_RESIDUAL`` of ``RESIDUAL_SCALE`` for two tight-space keyframes, see
:mod:`solid_ros.core.verification.verifier`):
the cluster-robust ("sandwich") covariance of the point-to-plane problem at the registration's
pose. ``A = sum w J J^T`` is its information, each supporting point weighted by how well its
query plane is defined (``w``, see
:attr:`solid_ros.core.verification.support.Support.weights`), and
``G = sum_c g_c g_c^T`` with ``g_c = sum w r J`` over the supporting points in coarse voxel
``c`` (``r`` the signed plane distance): points on one surface patch share their error, so
their residuals are summed before squaring. It reads the pose's error from the residuals. On
16 rings the fine stage's GICP tilts the pose by a few hundredths of a degree (its own
minimum, not the point-to-plane one); the far ground's residuals grow together with that tilt,
and so does this covariance. The model it replaces, ``sigma^2 (W / P) inv(A)`` (inlier RMS,
inflated by the weighted points per coarse voxel), saw the same residual level on 16 and 64
rings, and its roll and pitch sigmas were 3-5 times too small on ``vlp16_like`` (mean NEES
45.7).
That model is kept as a floor: in no direction is the covariance below ``MODEL_FLOOR`` of it,
so residuals that vanish by chance do not make a loop certain. ``RESIDUAL_SCALE`` is calibrated
with ``test/bench/bench_nees.py`` (README, Loop verification): mean NEES 3.4-9.5 on the
simulator's drives and room walk against their exact reference (seed 0; 3.1-8.1 on seed 1),
11.6 on hku1 against ``odom_poses.txt`` and 6.5 against an independent re-registration. It
does not cover a second minimum (a slide of 0.7-1.3 m along a street seen head-on or along
shelves, which the consistency restarts do not catch), nor errors outside the loop (a reference
or odometry frame that is itself off): ``verify_covariance_scale`` scales it for the latter.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from solid_ros.core.verification.support import Support

__all__ = ['MODEL_FLOOR', 'RESIDUAL_SCALE', 'TIGHT_RESIDUAL', 'support_covariance']

FloatArray = npt.NDArray[np.float64]

_SIGMA_FLOOR = 0.02
# The loop covariance is the cluster-robust one times this (support_covariance): the residuals
# at the solution and their sums per coarse voxel understate the error, because neighbouring
# voxels share errors too and the solution fits part of them away. Calibrated with
# test/bench/bench_nees.py on the simulator's drives (seed 0) and checked on seed 1 and hku1.
RESIDUAL_SCALE = 5.0
# Two tight-space keyframes (verification.TIGHT_GRID) use this fraction of it: the room walk's
# loops on that grid are off by millimetres, and with the full factor their mean NEES was 1.2 (room
# walk seed 0, bench_nees.py) and 1.7-4.6 (seeds 0-7 with drifting odometry and the back end);
# with half of it 2.3 and 3.2-8.8, and 4.3 on seed 1.
TIGHT_RESIDUAL = 0.5
# In no direction is the loop covariance below this fraction of the point-to-plane model's
# (sigma^2 W / P inv(A)): residuals that happen to vanish (a noise-free scan, a patch sum that
# cancels) must not make a loop certain. It acted on 0-5 % of the simulated drives' loops and
# 4 of the room walk's 10.
MODEL_FLOOR = 0.05


def support_covariance(sup: Support, scale: float = 1.0,
                       residual_scale: float = RESIDUAL_SCALE) -> FloatArray | None:
    """Covariance of the relative pose ``T_mq`` that ``sup`` measured, ROS order, right
    perturbation in the query frame (see the module docstring).

    ``residual_scale * inv(A) G inv(A)`` (``RESIDUAL_SCALE``; ``TIGHT_RESIDUAL`` of it for
    two tight-space keyframes) with ``A = sum w J J^T`` (the plane-weighted
    information) and ``G`` the supporting points' residual scores summed per coarse voxel
    (:attr:`~solid_ros.core.verification.support.Support.residual_scores`), times ``scale``;
    in no
    direction smaller than ``MODEL_FLOOR`` times the model covariance ``sigma^2 (W / P)
    inv(A)``.

    Returns:
        None when the information is singular (the same cases as before the residual
        scores: verdicts do not depend on them).
    """
    info, weight = sup.weighted_information
    try:
        cov_rt = np.asarray(np.linalg.inv(info), dtype=np.float64)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov_rt)):
        return None
    sigma2 = max(sup.rmse, _SIGMA_FLOOR) ** 2 * max(weight / max(sup.patches, 1), 1.0)
    model: FloatArray = sigma2 * cov_rt
    robust: FloatArray = residual_scale * cov_rt @ sup.residual_scores @ cov_rt
    order = [3, 4, 5, 0, 1, 2]
    out: FloatArray = scale * _floored(robust, model)[np.ix_(order, order)]
    sym: FloatArray = 0.5 * (out + out.T)
    return sym


def _floored(cov: FloatArray, floor: FloatArray) -> FloatArray:
    """``cov`` raised, in the directions where it is below ``MODEL_FLOOR * floor``, to that
    (eigenvalues of ``cov`` whitened by ``floor``); ``floor`` itself when it cannot be
    whitened with or ``cov`` is not finite."""
    try:
        chol = np.linalg.cholesky(0.5 * (floor + floor.T))
    except np.linalg.LinAlgError:
        return floor
    if not np.all(np.isfinite(cov)):
        return floor
    white = np.linalg.solve(chol, np.linalg.solve(chol, cov).T)
    vals, vecs = np.linalg.eigh(0.5 * (white + white.T))
    lifted = (vecs * np.maximum(vals, MODEL_FLOOR)) @ vecs.T
    out: FloatArray = chol @ lifted @ chol.T
    return out
