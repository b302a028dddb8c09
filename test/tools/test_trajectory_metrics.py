"""Trajectory metrics: SE(3)-aligned ATE and RPE on known errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from solid_ros.core.geometry import rot_z, rpy_matrix
from solid_ros.tools.trajectory_metrics import (
    align_se3,
    ate_rmse,
    end_error,
    path_length,
    rpe,
    rpe_by_distance,
)


def _track(n: int = 50) -> np.ndarray:
    out = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        out[k, :3, :3] = rot_z(0.1 * k)
        out[k, :3, 3] = [10.0 * math.cos(0.1 * k), 10.0 * math.sin(0.1 * k), 0.05 * k]
    return out


def test_a_rigidly_moved_copy_has_no_error_once_aligned() -> None:
    ref = _track()
    A = np.eye(4)
    A[:3, :3] = rpy_matrix(0.2, -0.1, 2.0)
    A[:3, 3] = [50.0, -20.0, 3.0]
    est = A @ ref
    np.testing.assert_allclose(align_se3(est, ref), np.linalg.inv(A), atol=1e-9)
    assert ate_rmse(est, ref) == pytest.approx(0.0, abs=1e-9)
    assert ate_rmse(est, ref, align=False) > 10.0
    assert rpe(est, ref, 1) == pytest.approx((0.0, 0.0), abs=1e-6)


def test_known_errors() -> None:
    ref = _track()
    est = ref.copy()
    est[::2, 2, 3] += 0.3  # every other pose 0.3 m up; the alignment halves it
    assert ate_rmse(est, ref) == pytest.approx(0.15, rel=1e-3)
    # Every pose but the first turned 2 deg about its z: of the 40 pairs 10 apart only the
    # one from pose 0 sees the turn.
    turned = ref.copy()
    turned[1:, :3, :3] = turned[1:, :3, :3] @ rot_z(math.radians(2.0))
    assert rpe(turned, ref, 10)[1] == pytest.approx(math.sqrt(2.0 ** 2 / 40), rel=1e-6)
    # Every pose 0.1 m further along its own x: each relative motion is off by the turn
    # between the two frames acting on that offset.
    moved = ref.copy()
    moved[:, :3, 3] += 0.1 * ref[:, :3, 0]
    expected = 0.1 * 2.0 * math.sin(0.5)  # |Rz(1.0) e_x - e_x| for 10 steps of 0.1 rad
    assert rpe(moved, ref, 10) == pytest.approx((expected, 0.0), abs=1e-6)
    with pytest.raises(ValueError, match='reference 49'):
        ate_rmse(est, ref[:-1])
    assert math.isnan(ate_rmse(np.zeros((0, 4, 4)), np.zeros((0, 4, 4))))
    assert math.isnan(rpe(ref, ref, 50)[0])


def test_rpe_by_distance_and_end_error_on_a_known_drift() -> None:
    # A straight 1 m-step line; the estimate's steps are 2 % too long.
    ref = np.tile(np.eye(4), (31, 1, 1))
    ref[:, 0, 3] = np.arange(31.0)
    est = ref.copy()
    est[:, 0, 3] *= 1.02
    np.testing.assert_allclose(path_length(ref), np.arange(31.0))
    t, r, n = rpe_by_distance(est, ref, 10.0)
    assert n == 21 and t == pytest.approx(0.2) and r == pytest.approx(0.0, abs=1e-6)
    assert end_error(est, ref) == pytest.approx(0.6)
    assert rpe_by_distance(est, ref, 31.0)[2] == 0 and math.isnan(end_error(est[:1], ref[:1]))
    # Pairs follow the reference path, not the index: with half-metre steps, 20 poses apart.
    half = ref.copy()
    half[:, 0, 3] *= 0.5
    assert rpe_by_distance(half, half, 10.0)[2] == 11
