"""Odometry consistency: path driven between keyframes and loop-versus-odometry distance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from solid_ros.core.geometry import matrix_to_vector, rot_z, vector_to_matrix
from solid_ros.core.odometry import OdometryPath, disagreement


def _pose(x: float, y: float, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_z(yaw)
    T[:2, 3] = (x, y)
    return matrix_to_vector(T)


def test_path_sums_the_straight_lines_between_posed_keyframes() -> None:
    path = OdometryPath(capacity=10)
    path.add(0, _pose(0.0, 0.0))
    path.add(1, _pose(3.0, 4.0))
    path.add(2, None)  # no pose: no path at it, and the gap counts as a straight line
    path.add(3, _pose(3.0, 10.0))
    assert path.between(0, 1) == pytest.approx(5.0)
    assert path.between(0, 3) == pytest.approx(11.0)
    assert path.between(1, 2) is None and path.between(7, 3) is None
    path.clear()
    assert path.between(0, 1) is None


def test_path_forgets_the_oldest_beyond_capacity() -> None:
    path = OdometryPath(capacity=3)
    for i in range(5):
        path.add(i, _pose(float(i), 0.0))
    assert path.between(0, 4) is None and path.between(1, 4) is None
    assert path.between(2, 4) == pytest.approx(2.0)


def test_disagreement_compares_the_loop_with_the_odometry_in_the_match_frame() -> None:
    # Match at (10, 0) facing +y, query at (10, 5) facing -x: odometry T_mq has t = (5, 0).
    pose_m, pose_q = _pose(10.0, 0.0, math.pi / 2), _pose(10.0, 5.0, math.pi)
    T = np.linalg.inv(vector_to_matrix(pose_m)) @ vector_to_matrix(pose_q)
    assert np.allclose(T[:3, 3], [5.0, 0.0, 0.0])
    assert disagreement(T, pose_q, pose_m) == pytest.approx(0.0, abs=1e-9)
    wrong = T.copy()
    wrong[:3, 3] = 0.0  # a loop claiming the two sensors were at the same spot
    assert disagreement(wrong, pose_q, pose_m) == pytest.approx(5.0)
