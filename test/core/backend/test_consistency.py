"""Pairwise consistency of inter-robot loops and the maximum clique (PCM's pieces)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from solid_ros.core.backend.consistency import (
    DriftModel,
    adjoint,
    cycle_sigmas,
    implied,
    max_clique,
    mean_alignment,
    moved_by,
    residual,
    so3_exp,
)
from solid_ros.core.geometry import rpy_matrix


def _pose(rng: np.random.Generator, spread: float = 30.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(*rng.uniform(-math.pi, math.pi, 3))
    T[:3, 3] = rng.uniform(-spread, spread, 3)
    return T


def test_residual_inverts_exp_and_matches_gtsam_adjoint() -> None:
    gtsam = pytest.importorskip('gtsam')
    rng = np.random.default_rng(0)
    for w in [*rng.normal(0, 1, (20, 3)), np.array([math.pi - 1e-5, 0.0, 0.0]),
              np.array([0.0, 1e-12, 0.0])]:
        T = np.eye(4)
        T[:3, :3] = so3_exp(w)
        back = residual(T)[:3]
        assert np.allclose(so3_exp(back), T[:3, :3], atol=1e-6)
    for _ in range(5):
        T = _pose(rng)
        ref = gtsam.Pose3(gtsam.Rot3(T[:3, :3]), T[:3, 3]).AdjointMap()
        assert np.allclose(adjoint(T), ref, atol=1e-9)


def _loops(rng: np.random.Generator, n: int, A: np.ndarray, noise: float = 0.0
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Own poses X, peer poses Y and measurements Z consistent with alignment A."""
    X = np.array([_pose(rng) for _ in range(n)])
    Y = np.array([_pose(rng) for _ in range(n)])
    Z = np.linalg.solve(Y, np.linalg.solve(A, X))
    if noise:
        for k in range(n):
            e = np.eye(4)
            e[:3, :3] = rpy_matrix(*rng.normal(0.0, noise / 10, 3))
            e[:3, 3] = rng.normal(0.0, noise, 3)
            Z[k] = Z[k] @ e
    return X, Y, Z


def test_loops_of_one_alignment_agree_and_a_false_one_does_not() -> None:
    rng = np.random.default_rng(1)
    A = _pose(rng, 100.0)
    X, Y, Z = _loops(rng, 6, A, noise=0.02)
    bad = np.eye(4)
    bad[0, 3] = 20.0
    X[5] = A @ bad @ Y[5] @ Z[5]  # its own keyframe where a 20 m wrong alignment puts it
    cov = np.tile(np.diag([1e-4] * 3 + [4e-4] * 3), (6, 1, 1))
    sig = cycle_sigmas(X, Z, Y, cov, np.zeros(6), np.zeros(6))
    assert sig.shape == (6, 6) and np.allclose(sig, sig.T) and not np.any(np.diag(sig))
    assert sig[:5, :5].max() < 4.1
    assert sig[5, :5].min() > 50.0
    A_k, cov_a = implied(X, Z, Y, cov)
    assert np.allclose(A_k[0], A, atol=0.2)
    # The implied alignment's covariance levers the loop's rotation over the peer keyframe's
    # distance from the peer's origin.
    assert cov_a[0][3:, 3:].trace() > cov[0][3:, 3:].trace()


def test_drift_between_keyframes_widens_the_cycle() -> None:
    rng = np.random.default_rng(2)
    A = _pose(rng, 50.0)
    X, Y, Z = _loops(rng, 2, A)
    move = np.eye(4)
    move[:3, 3] = [1.0, 0.0, 0.0]  # own map drifted 1 m between the two keyframes
    X[1] = X[1] @ move
    cov = np.tile(np.diag([1e-4] * 3 + [1e-4] * 3), (2, 1, 1))
    near = cycle_sigmas(X, Z, Y, cov, np.array([0.0, 1.0]), np.array([0.0, 1.0]))[0, 1]
    far = cycle_sigmas(X, Z, Y, cov, np.array([0.0, 500.0]), np.array([0.0, 500.0]),
                       DriftModel(trans=0.05))[0, 1]
    assert near > 4.1 and far < 3.0, (near, far)


def test_max_clique_is_exact_on_small_graphs() -> None:
    rng = np.random.default_rng(3)
    for _ in range(30):
        n = int(rng.integers(1, 12))
        agree = np.triu(rng.random((n, n)) < 0.5, 1)
        agree = agree | agree.T
        best, exact = max_clique(agree)
        assert exact
        assert all(agree[a, b] for a, b in itertools.combinations(best, 2))
        size = max((k for k in range(n + 1) for c in itertools.combinations(range(n), k)
                    if all(agree[a, b] for a, b in itertools.combinations(c, 2))), default=0)
        assert len(best) == size
    assert max_clique(np.zeros((0, 0), dtype=bool)) == ([], True)


def test_max_clique_within_a_subset_and_under_a_budget() -> None:
    agree = np.ones((40, 40), dtype=bool)
    np.fill_diagonal(agree, False)
    agree[:20, 20:] = agree[20:, :20] = False
    best, exact = max_clique(agree, among=range(20, 40))
    assert best == list(range(20, 40)) and exact
    rng = np.random.default_rng(4)
    dense = np.triu(rng.random((90, 90)) < 0.7, 1)
    dense = dense | dense.T
    best, exact = max_clique(dense, budget=50)
    assert not exact and len(best) >= 3
    assert all(dense[a, b] for a, b in itertools.combinations(best, 2))


def test_mean_alignment_weighs_by_covariance_and_moved_by_measures_it() -> None:
    A = np.tile(np.eye(4), (2, 1, 1))
    A[1, 0, 3] = 1.0
    cov = np.array([np.eye(6) * 1e-4, np.eye(6) * 1e-2])
    T, cov_t = mean_alignment(A, cov)
    assert T[0, 3] == pytest.approx(1e-4 / (1e-4 + 1e-2), abs=1e-6)
    assert cov_t[0, 0] < 1e-4
    dist, deg = moved_by(np.eye(4), A[1], np.zeros((3, 3)))
    assert dist == pytest.approx(1.0) and deg == pytest.approx(0.0)
