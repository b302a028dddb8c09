"""Trajectory error against reference poses: ATE after an SE(3) alignment, and RPE.

Both take two (N, 4, 4) pose arrays of the same instants (``estimate[i]`` and
``reference[i]`` are the same keyframe). ATE: the estimate is moved by the rigid transform
(rotation and translation, no scale; Umeyama / Horn on the positions) that best fits it to the
reference, then the RMS of the position differences. RPE: for every pair ``(i, j)`` of poses
``delta`` apart, the error of the relative motion ``inv(E_i) E_j`` against ``inv(R_i) R_j``,
as RMS translation (metres) and rotation (degrees); :func:`rpe_by_distance` pairs poses a
length of reference path apart instead. :func:`end_error`: the last pose against the
reference's, both relative to their first (drift as a fraction of :func:`path_length`).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = ['align_se3', 'ate_rmse', 'end_error', 'path_length', 'rpe', 'rpe_by_distance']

FloatArray = npt.NDArray[np.float64]


def _poses(poses: npt.ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f'{name}: expected (N, 4, 4) poses, got shape {arr.shape}')
    return arr


def align_se3(estimate: npt.ArrayLike, reference: npt.ArrayLike) -> FloatArray:
    """The 4x4 rigid transform ``A`` minimising ``sum |A p_est - p_ref|^2`` over the positions
    (Umeyama without scale); the identity for fewer than one position."""
    est = _poses(estimate, 'estimate')[:, :3, 3]
    ref = _poses(reference, 'reference')[:, :3, 3]
    if len(est) != len(ref):
        raise ValueError(f'estimate has {len(est)} poses, reference {len(ref)}')
    out = np.eye(4)
    if len(est) == 0:
        return out
    mu_e, mu_r = est.mean(axis=0), ref.mean(axis=0)
    u, _, vt = np.linalg.svd((ref - mu_r).T @ (est - mu_e))
    d = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)) or 1.0)])
    out[:3, :3] = u @ d @ vt
    out[:3, 3] = mu_r - out[:3, :3] @ mu_e
    return out


def ate_rmse(estimate: npt.ArrayLike, reference: npt.ArrayLike, align: bool = True) -> float:
    """Absolute trajectory error: RMS position error in metres, after :func:`align_se3` when
    ``align`` (NaN for no poses)."""
    est = _poses(estimate, 'estimate')
    ref = _poses(reference, 'reference')
    if len(est) == 0:
        return math.nan
    A = align_se3(est, ref) if align else np.eye(4)
    pos = est[:, :3, 3] @ A[:3, :3].T + A[:3, 3]
    return float(np.sqrt(np.mean(np.sum((pos - ref[:, :3, 3]) ** 2, axis=1))))


def rpe(estimate: npt.ArrayLike, reference: npt.ArrayLike,
        delta: int = 1) -> tuple[float, float]:
    """Relative pose error over pose pairs ``delta`` apart: (RMS translation error in metres,
    RMS rotation error in degrees); NaN when there is no such pair."""
    est = _poses(estimate, 'estimate')
    ref = _poses(reference, 'reference')
    if len(est) != len(ref):
        raise ValueError(f'estimate has {len(est)} poses, reference {len(ref)}')
    if delta < 1 or len(est) <= delta:
        return math.nan, math.nan
    i = np.arange(len(est) - delta)
    return _pair_errors(est, ref, i, i + delta)


def _pair_errors(est: FloatArray, ref: FloatArray, i: npt.NDArray[np.intp],
                 j: npt.NDArray[np.intp]) -> tuple[float, float]:
    """RMS translation (m) and rotation (deg) error of the relative motions ``i -> j``."""
    d_est = np.linalg.solve(est[i], est[j])
    d_ref = np.linalg.solve(ref[i], ref[j])
    err = np.linalg.solve(d_est, d_ref)
    trans = np.linalg.norm(err[:, :3, 3], axis=1)
    cos = np.clip((np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot = np.degrees(np.arccos(cos))
    return float(np.sqrt(np.mean(trans ** 2))), float(np.sqrt(np.mean(rot ** 2)))


def path_length(poses: npt.ArrayLike) -> FloatArray:
    """Cumulative distance driven along the positions, metres (0 at the first pose)."""
    pos = _poses(poses, 'poses')[:, :3, 3]
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    out: FloatArray = np.concatenate(([0.0], np.cumsum(steps)))
    return out


def rpe_by_distance(estimate: npt.ArrayLike, reference: npt.ArrayLike,
                    metres: float = 10.0) -> tuple[float, float, int]:
    """Relative pose error over pose pairs ``metres`` of reference path apart: each pose with
    the first later pose at least that far along the reference path.

    Returns:
        RMS translation error (metres), RMS rotation error (degrees), number of pairs (NaN,
        NaN, 0 when the path is shorter).
    """
    est = _poses(estimate, 'estimate')
    ref = _poses(reference, 'reference')
    if len(est) != len(ref):
        raise ValueError(f'estimate has {len(est)} poses, reference {len(ref)}')
    cum = path_length(ref) if len(ref) else np.zeros(0)
    j = np.searchsorted(cum, cum + metres, side='left')
    i = np.flatnonzero(j < len(ref))
    if not i.size:
        return math.nan, math.nan, 0
    return (*_pair_errors(est, ref, i, j[i]), int(i.size))


def end_error(estimate: npt.ArrayLike, reference: npt.ArrayLike) -> float:
    """Error of the last pose relative to the first (metres): the translation of
    ``inv(inv(R_0) R_n) inv(E_0) E_n``; NaN for fewer than two poses."""
    est = _poses(estimate, 'estimate')
    ref = _poses(reference, 'reference')
    if len(est) < 2 or len(est) != len(ref):
        return math.nan
    rel_e = np.linalg.solve(est[0], est[-1])
    rel_r = np.linalg.solve(ref[0], ref[-1])
    return float(np.linalg.norm(np.linalg.solve(rel_r, rel_e)[:3, 3]))
