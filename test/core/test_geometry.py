"""Tests of solid_ros.core.geometry: quaternions, pose vectors, the yaw convention."""

from __future__ import annotations

import math

import numpy as np
import pytest

from solid_ros.core.errors import PoseError, SolidError
from solid_ros.core.geometry import (
    invert_rigid,
    matrix_to_quaternion,
    matrix_to_vector,
    pose_to_vector,
    quaternion_to_matrix,
    relative_yaw,
    rot_z,
    vector_to_matrix,
    yaw_of,
)


def test_relative_yaw_convention() -> None:
    # Query heading 100 deg, candidate heading 30 deg: a world point seen by the query at
    # azimuth theta is seen by the candidate at theta + 70 deg.
    pq, pc = np.eye(4), np.eye(4)
    pq[:3, :3], pc[:3, :3] = rot_z(math.radians(100.0)), rot_z(math.radians(30.0))
    yaw = relative_yaw(pq, pc)
    assert math.degrees(yaw) == pytest.approx(70.0)
    world = np.array([3.0, 4.0, 0.0])
    p_query = pq[:3, :3].T @ world
    p_cand = pc[:3, :3].T @ world
    np.testing.assert_allclose(rot_z(yaw) @ p_query, p_cand, atol=1e-12)
    assert math.degrees(yaw_of(rot_z(math.radians(-170.0)))) == pytest.approx(-170.0)


def test_matrix_to_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.normal(size=4)
        r = quaternion_to_matrix(*q)
        back = quaternion_to_matrix(*matrix_to_quaternion(r))
        np.testing.assert_allclose(back, r, atol=1e-9)
    assert matrix_to_quaternion(np.eye(3)) == pytest.approx((0.0, 0.0, 0.0, 1.0))


def test_vector_to_matrix_inverts_matrix_to_vector() -> None:
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(0.1, -0.2, 0.3, 0.9)
    T[:3, 3] = [1.0, -2.0, 3.5]
    np.testing.assert_allclose(vector_to_matrix(matrix_to_vector(T)), T, atol=1e-12)
    np.testing.assert_allclose(vector_to_matrix([1, 2, 3, 0, 0, 0, 1])[:3, 3], [1, 2, 3])


def test_pose_formats() -> None:
    v = pose_to_vector([1, 2, 3, 0, 0, 0, 2])
    assert v.tolist() == [1, 2, 3, 0, 0, 0, 1]
    m = np.eye(4)
    m[:3, 3] = [4, 5, 6]
    assert pose_to_vector(m[:3]).tolist() == [4, 5, 6, 0, 0, 0, 1]
    with pytest.raises(SolidError, match='shape'):
        pose_to_vector([1, 2, 3])
    with pytest.raises(SolidError, match='non-finite'):
        pose_to_vector([1, 2, np.nan, 0, 0, 0, 1])


def test_zero_quaternion_is_refused() -> None:
    with pytest.raises(PoseError, match='zero length'):
        quaternion_to_matrix(0, 0, 0, 0)


def test_invert_rigid_inverts_a_batch_of_poses() -> None:
    rng = np.random.default_rng(0)
    T = np.stack([vector_to_matrix(np.r_[rng.normal(size=3) * 10.0, q / np.linalg.norm(q)])
                  for q in rng.normal(size=(5, 4))])
    np.testing.assert_allclose(invert_rigid(T), np.linalg.inv(T), atol=1e-12)
    np.testing.assert_allclose(invert_rigid(T[0]) @ T[0], np.eye(4), atol=1e-12)
