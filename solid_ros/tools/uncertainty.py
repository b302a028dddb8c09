"""Consistency of published loop covariances: the NEES of a loop against a reference pose.

Convention (doc/conventions.md): a loop's covariance is of a right perturbation ``T exp(delta)``
with ``delta = (x, y, z, roll, pitch, yaw)`` in the query sensor frame (ROS order; the rotation
part a rotation vector, which small-angle roll, pitch, yaw equal). The error of a loop ``T``
against the reference ``T_ref`` is therefore ``delta = Log(inv(T) @ T_ref)``, so that ``T_ref =
T exp(delta)``, and its normalised estimation error squared is ``delta^T inv(C) delta``. For a
covariance that matches the error, NEES follows a chi-square law with 6 degrees of freedom:
mean 6 (3 for the translation alone, ``delta_t^T inv(C_tt) delta_t`` with the marginal
translation block ``C_tt``). NEES does not depend on the sign of ``delta``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ['Nees', 'nees', 'se3_log', 'summarise']

FloatArray = npt.NDArray[np.float64]


def _so3_log(R: FloatArray) -> FloatArray:
    """Rotation vector of a rotation matrix."""
    cos = min(max((float(np.trace(R)) - 1.0) / 2.0, -1.0), 1.0)
    angle = math.acos(cos)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-8:
        return 0.5 * axis
    if angle > math.pi - 1e-6:
        # sin -> 0: take the axis from the symmetric part instead.
        b = 0.5 * (R + np.eye(3))
        k = int(np.argmax(np.diag(b)))
        a = b[:, k] / math.sqrt(max(b[k, k], 1e-300))
        out: FloatArray = angle * a
        return out
    w: FloatArray = angle / (2.0 * math.sin(angle)) * axis
    return w


def se3_log(T: npt.ArrayLike) -> FloatArray:
    """``Log`` of a 4x4 rigid transform as ``(rho, w)`` (translation part first, ROS order).

    ``T = exp(xi)`` with ``exp`` the SE(3) exponential: ``w`` is the rotation vector and
    ``rho = inv(V(w)) t``; to first order ``rho`` is the translation of ``T``.
    """
    m = np.asarray(T, dtype=np.float64)
    w = _so3_log(m[:3, :3])
    theta = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-6:
        v_inv = np.eye(3) - 0.5 * K + K @ K / 12.0
    else:
        half = 0.5 * theta
        coef = (1.0 - half * math.cos(half) / math.sin(half)) / theta ** 2
        v_inv = np.eye(3) - 0.5 * K + coef * (K @ K)
    return np.concatenate([v_inv @ m[:3, 3], w])


@dataclass(frozen=True)
class Nees:
    """NEES of one loop.

    Attributes:
        full: 6-DoF NEES (chi-square, 6 degrees of freedom when consistent).
        translation: NEES of the translation alone against the marginal translation block
            (3 degrees of freedom).
        error: the error ``delta = Log(inv(T) @ T_ref)``, ROS order (metres, radians).
    """

    full: float
    translation: float
    error: FloatArray


def nees(T: npt.ArrayLike, T_ref: npt.ArrayLike, covariance: npt.ArrayLike) -> Nees:
    """NEES of the pose ``T`` with ``covariance`` (6x6 or 36 values, ROS order, right
    perturbation) against the reference ``T_ref``.

    Raises:
        ValueError: the covariance is not 36 finite values or not positive definite.
    """
    cov = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
    if not np.all(np.isfinite(cov)):
        raise ValueError('covariance has non-finite values')
    delta = se3_log(np.linalg.solve(np.asarray(T, dtype=np.float64),
                                    np.asarray(T_ref, dtype=np.float64)))
    try:
        full_chol = np.linalg.cholesky(0.5 * (cov + cov.T))
        t_chol = np.linalg.cholesky(0.5 * (cov[:3, :3] + cov[:3, :3].T))
    except np.linalg.LinAlgError as err:
        raise ValueError('covariance is not positive definite') from err
    z = np.linalg.solve(full_chol, delta)
    zt = np.linalg.solve(t_chol, delta[:3])
    return Nees(float(z @ z), float(zt @ zt), delta)


def summarise(values: Sequence[Nees]) -> dict[str, float | int]:
    """Count, mean and median of the 6-DoF and translation NEES of some loops (NaN if none)."""
    full = np.array([v.full for v in values], dtype=np.float64)
    trans = np.array([v.translation for v in values], dtype=np.float64)
    if not len(full):
        nan = math.nan
        return {'count': 0, 'mean': nan, 'median': nan, 'mean_t': nan, 'median_t': nan}
    return {'count': len(full), 'mean': float(full.mean()), 'median': float(np.median(full)),
            'mean_t': float(trans.mean()), 'median_t': float(np.median(trans))}
