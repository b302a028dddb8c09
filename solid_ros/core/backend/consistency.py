"""Inter-robot loops that agree with each other: pairwise consistency and the largest set (PCM).

A loop between this robot's keyframe ``X`` (its map) and a peer's keyframe ``Y`` (the peer's
map) measures ``Z``, this robot's sensor in the peer's sensor frame. It implies the
alignment ``A = T_own_map<-peer_map = X Z^-1 Y^-1`` (:func:`implied`). Two loops ``i`` and
``j`` agree when the cycle ``C = Z_i (X_i^-1 X_j) Z_j^-1 (Y_i^-1 Y_j)^-1`` is the identity
within its covariance: both loops' and both maps' relative poses, each map's from a drift
model over the path driven between the two keyframes (a peer's graph covariances do not travel;
the model is what the back end assumes of an odometry). This is pairwise consistency
maximisation (PCM, Mangelson et al. 2018): the loops that decide the alignment are a maximum
clique of the graph whose edges join agreeing loops (:func:`max_clique`).

Everything here is numpy in gtsam's tangent order (rotation first, right perturbations), so
the consistency of a few hundred loops is a handful of batched matrix products. Residuals are
``(rotation vector, translation)``, first order at the identity, where the test is decided.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.geometry import invert_rigid

__all__ = ['DriftModel', 'adjoint', 'cycle_sigmas', 'implied', 'max_clique', 'mean_alignment',
           'moved_by', 'residual', 'so3_exp']

FloatArray = npt.NDArray[np.float64]


def _hat(w: FloatArray) -> FloatArray:
    """Skew matrices of (..., 3) vectors."""
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def so3_exp(w: FloatArray) -> FloatArray:
    """Rotation matrices of (..., 3) rotation vectors (Rodrigues)."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = _hat(w)
    small = theta < 1e-9
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe ** 2)
    out: FloatArray = np.eye(3) + a * k + b * (k @ k)
    return out


def _so3_log(R: FloatArray) -> FloatArray:
    """Rotation vectors of (..., 3, 3) rotations (stable near 0 and pi)."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = np.sin(theta)
    scale = np.where(sin > 1e-6, theta / np.where(sin > 1e-6, 2.0 * sin, 1.0), 0.5)
    out: FloatArray = v * scale[..., None]
    near_pi = theta > math.pi - 1e-3
    if np.any(near_pi):  # the antisymmetric part vanishes: the axis from R + I
        Rp = R[near_pi]
        col = np.argmax(np.diagonal(Rp, axis1=-2, axis2=-1), axis=-1)
        rows = np.take_along_axis(Rp + np.eye(3), col[:, None, None], axis=-1)[..., 0]
        axis = rows / np.linalg.norm(rows, axis=-1, keepdims=True)
        out[near_pi] = axis * theta[near_pi][:, None]
    return out


def residual(T: FloatArray) -> FloatArray:
    """``(rotation vector, translation)`` of (..., 4, 4) transforms: gtsam's order, equal to
    its Logmap to first order at the identity."""
    out: FloatArray = np.concatenate([_so3_log(T[..., :3, :3]), T[..., :3, 3]], axis=-1)
    return out


def adjoint(T: FloatArray) -> FloatArray:
    """Adjoint matrices (..., 6, 6) of (..., 4, 4) transforms in gtsam's tangent order:
    ``T Exp(xi) = Exp(Ad_T xi) T``."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros((*T.shape[:-2], 6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = _hat(t) @ R
    return out


def _sandwich(ad: FloatArray, cov: FloatArray) -> FloatArray:
    out: FloatArray = ad @ cov @ np.swapaxes(ad, -1, -2)
    return out


def implied(X: FloatArray, Z: FloatArray, Y: FloatArray,
            cov_z: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Alignments ``A = X Z^-1 Y^-1`` implied by loops and their covariances (right
    perturbation of ``A``: ``Ad(Y Z) cov_z Ad(Y Z)^T``, the loop's rotation error levered
    over the keyframe's distance from the peer's origin)."""
    YZ = Y @ Z
    return X @ invert_rigid(YZ), _sandwich(adjoint(YZ), cov_z)


@dataclass(frozen=True)
class DriftModel:
    """How far apart two keyframes of one map may be from their true relative pose: random
    walks over the path driven between them, with floors (the back end's odometry model).

    Attributes:
        trans: translation sigma after 1 m, metres.
        rot: rotation sigma after 1 m, radians.
        floor_m: least translation sigma, metres.
        floor_rad: least rotation sigma, radians.
    """

    trans: float = 0.05
    rot: float = math.radians(0.1)
    floor_m: float = 0.01
    floor_rad: float = math.radians(0.05)

    def covariance(self, path_m: FloatArray) -> FloatArray:
        """Diagonal covariances (m, 6, 6), gtsam order, for paths of ``path_m`` metres."""
        d = np.abs(np.asarray(path_m, dtype=np.float64))
        var_r = self.rot ** 2 * d + self.floor_rad ** 2
        var_t = self.trans ** 2 * d + self.floor_m ** 2
        out = np.zeros((len(d), 6, 6))
        idx = np.arange(6)
        out[:, idx, idx] = np.stack([var_r] * 3 + [var_t] * 3, axis=-1)
        return out


def cycle_sigmas(X: FloatArray, Z: FloatArray, Y: FloatArray, cov_z: FloatArray,
                 path_x: FloatArray, path_y: FloatArray,
                 drift: DriftModel = DriftModel()) -> FloatArray:
    """Mahalanobis distance of every pair's cycle, (n, n) with 0 on the diagonal.

    Args:
        X: (n, 4, 4) own keyframe poses of the loops, own map.
        Z: (n, 4, 4) the loops' measurements (own sensor in the peer's sensor frame).
        Y: (n, 4, 4) peer keyframe poses, the peer's map.
        cov_z: (n, 6, 6) the loops' covariances (gtsam order).
        path_x: (n,) distance driven to each own keyframe, metres.
        path_y: (n,) distance the peer drove to each peer keyframe, metres.
        drift: the maps' relative uncertainty over a path.
    """
    n = len(X)
    out = np.zeros((n, n))
    if n < 2:
        return out
    i, j = np.triu_indices(n, 1)
    cov_x = drift.covariance(path_x[j] - path_x[i])
    cov_y = drift.covariance(path_y[j] - path_y[i])
    d_x = invert_rigid(X[i]) @ X[j]
    d_y = invert_rigid(Y[i]) @ Y[j]
    tail = d_y @ Z[j]  # the factors right of each perturbed part, as adjoints below
    C = Z[i] @ d_x @ invert_rigid(Z[j]) @ invert_rigid(d_y)
    ad_tail = adjoint(tail)
    cov = (_sandwich(adjoint(tail @ invert_rigid(d_x)), cov_z[i]) + _sandwich(ad_tail, cov_x)
           + _sandwich(ad_tail, cov_z[j]) + _sandwich(adjoint(d_y), cov_y))
    r = residual(C)
    try:
        m = np.einsum('ka,ka->k', r, np.linalg.solve(cov, r[..., None])[..., 0])
    except np.linalg.LinAlgError:  # a singular covariance: that pair cannot agree
        m = np.full(len(i), np.inf)
    out[i, j] = out[j, i] = np.sqrt(np.maximum(m, 0.0))
    return out


def mean_alignment(A: FloatArray, cov: FloatArray,
                   iterations: int = 8) -> tuple[FloatArray, FloatArray]:
    """Weighted mean of alignments (n, 4, 4) under their covariances: Gauss-Newton on
    ``sum |res(A_k^-1 A)|^2``; returns the mean and its covariance (gtsam order)."""
    info = np.linalg.inv(cov)
    H = info.sum(axis=0)
    H_inv = np.linalg.inv(H)
    best = int(np.argmax(np.trace(info, axis1=-2, axis2=-1)))
    T = A[best].copy()
    for _ in range(iterations):
        r = residual(invert_rigid(A) @ T)
        step = -H_inv @ np.einsum('kab,kb->a', info, r)
        move = np.eye(4)
        move[:3, :3] = so3_exp(step[:3])
        move[:3, 3] = step[3:]
        T = T @ move
        if float(np.linalg.norm(step)) < 1e-10:
            break
    return T, H_inv


def moved_by(A: FloatArray, B: FloatArray, points: FloatArray) -> tuple[float, float]:
    """How far alignment ``B`` places ``points`` (m, 3) from where ``A`` does: the largest
    distance (metres) and the rotation between them (degrees)."""
    pa = points @ A[:3, :3].T + A[:3, 3]
    pb = points @ B[:3, :3].T + B[:3, 3]
    dist = float(np.max(np.linalg.norm(pa - pb, axis=1))) if len(points) else 0.0
    angle = float(np.linalg.norm(_so3_log(A[:3, :3].T @ B[:3, :3])))
    return dist, math.degrees(angle)


def max_clique(agree: npt.NDArray[np.bool_], among: Sequence[int] | None = None,
               budget: int = 50_000) -> tuple[list[int], bool]:
    """A largest set of mutually agreeing loops (branch and bound with a pivot).

    Args:
        agree: (n, n) symmetric: loops ``i`` and ``j`` agree.
        among: only these loops (default all).
        budget: most branches searched; beyond it the best set found so far is returned.

    Returns:
        The loops of the set, ascending, and whether the search finished (it is then a
        maximum clique; otherwise a maximal one at least as large as a greedy pick).
    """
    nodes = list(range(len(agree))) if among is None else sorted(among)
    nbr = {v: sum(1 << u for u in nodes if u != v and agree[v, u]) for v in nodes}
    best = _greedy(nodes, nbr)
    calls = 0

    def expand(clique: int, cand: int) -> None:
        nonlocal best, calls
        calls += 1
        if calls > budget:
            return
        if not cand:
            if clique.bit_count() > best.bit_count():
                best = clique
            return
        if clique.bit_count() + cand.bit_count() <= best.bit_count():
            return
        pivot = max(_bits(cand), key=lambda u: (cand & nbr[u]).bit_count())
        for v in _bits(cand & ~nbr[pivot]):
            expand(clique | (1 << v), cand & nbr[v])
            cand &= ~(1 << v)
            if clique.bit_count() + cand.bit_count() <= best.bit_count():
                return

    expand(0, sum(1 << v for v in nodes))
    return _bits(best), calls <= budget


def _bits(mask: int) -> list[int]:
    out = []
    while mask:
        low = mask & -mask
        out.append(low.bit_length() - 1)
        mask ^= low
    return out


def _greedy(nodes: list[int], nbr: dict[int, int]) -> int:
    """A maximal clique grown from the best-connected loop: the search's first bound."""
    if not nodes:
        return 0
    start = max(nodes, key=lambda v: nbr[v].bit_count())
    clique, cand = 1 << start, nbr[start]
    while cand:
        v = max(_bits(cand), key=lambda u: (cand & nbr[u]).bit_count())
        clique |= 1 << v
        cand &= nbr[v]
    return clique
