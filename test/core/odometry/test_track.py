"""Odometry: pairing poses with clouds, path driven between keyframes and loop-versus-odometry
distance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from solid_ros.core.errors import PoseError
from solid_ros.core.geometry import matrix_to_vector, rot_z, vector_to_matrix
from solid_ros.core.odometry.track import (
    OdometryPath,
    StampedOdometry,
    disagreement,
    nearest_stamp,
    usable_covariance,
)


def _pose(x: float, y: float, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_z(yaw)
    T[:2, 3] = (x, y)
    return matrix_to_vector(T)


def _matrix(x: float) -> np.ndarray:
    return vector_to_matrix(_pose(x, 0.0))


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


def test_a_jump_of_the_odometry_is_no_path() -> None:
    """An odometry reset (or relocalisation) jumps: no path runs across it, so the odometry
    check does not compare loops across it (a new segment's frame is another frame)."""
    path = OdometryPath(capacity=10, jump_m=10.0)
    path.add(0, _pose(0.0, 0.0))
    path.add(1, _pose(3.0, 0.0))
    path.add(2, _pose(50.0, 0.0))  # a reset put the sensor 47 m off
    path.add(3, _pose(52.0, 0.0))
    assert path.between(0, 1) == pytest.approx(3.0)
    assert path.between(1, 2) is None and path.between(0, 3) is None
    assert path.between(2, 3) == pytest.approx(2.0)
    # A reset the odometry announces (a new segment where it lost track) with no jump.
    path.add(4, _pose(53.0, 0.0), reset=True)
    assert path.between(3, 4) is None and path.between(2, 3) == pytest.approx(2.0)


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


def test_nearest_stamp_within_tolerance() -> None:
    ref = np.array([300, 100, 200], dtype=np.int64)
    got = nearest_stamp(ref, [99, 151, 260, 1000, 100], tolerance_ns=50)
    assert got.tolist() == [1, 2, 0, -1, 1]
    assert nearest_stamp(np.array([], dtype=np.int64), [5], 10).tolist() == [-1]
    assert nearest_stamp(np.array([0]), [5, 40], 10).tolist() == [0, -1]
    assert nearest_stamp([0, 20], [10], 10).tolist() == [0]  # a tie goes to the earlier pose


def test_stamped_odometry_pairs_like_nearest_stamp_and_refuses_non_finite_poses() -> None:
    src = StampedOdometry(tolerance_ns=50, capacity=3)
    for stamp in (100, 200, 300, 400):
        src.add(stamp, _matrix(stamp / 100.0), np.eye(6) * 0.01)
    assert len(src) == 3 and src.latest_stamp_ns == 400
    assert src.pose_for(100) is None  # fell out of the bounded buffer
    got = src.pose_for(330)
    assert got is not None and got.stamp_ns == 300 and got.pose[0, 3] == pytest.approx(3.0)
    assert got.covariance is not None and src.nearest_gap_ns(1000) == 600
    # A covariance is kept as given, for the back end to judge (and warn about).
    odd = src.add(450, _matrix(4.5), np.full(36, math.nan))
    assert odd.covariance is not None and usable_covariance(odd.covariance) is None
    bad = _matrix(0.0)
    bad[0, 3] = math.nan
    with pytest.raises(PoseError):
        src.add(500, bad)
    assert len(src) == 3 and src.latest_stamp_ns == 450
    track = StampedOdometry.from_track([0, 10], np.stack([_matrix(0.0), _matrix(1.0)]), 5)
    paired = track.pose_for(9)
    assert paired is not None and paired.stamp_ns == 10


@pytest.mark.parametrize('cov, usable', [
    (np.zeros((6, 6)), False),  # unset
    (np.diag([1e-2] * 6), True),
    (np.diag([1e-2] * 5 + [-1.0]), False),  # negative variance
    (np.diag([1e-2] * 5 + [math.nan]), False),
    (np.triu(np.ones((6, 6))) + np.eye(6), False),  # not symmetric
    (np.ones(35), False),
])
def test_usable_covariance(cov: np.ndarray, usable: bool) -> None:
    assert (usable_covariance(cov) is not None) is usable
