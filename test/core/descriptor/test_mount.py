"""Mount: levelling points, poses and covariances of a tilted sensor, and back."""

from __future__ import annotations

import numpy as np

from solid_ros.core.config import SolidConfig
from solid_ros.core.descriptor.mount import Mount
from solid_ros.core.geometry import matrix_to_vector, rpy_matrix


def _pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(0.1, -0.2, 1.0)
    T[:3, 3] = [3.0, -1.0, 0.5]
    return T


def test_levelling_a_pose_and_back_is_the_identity() -> None:
    """The graph's guess goes into the levelled frames, the loop comes back out of them."""
    mount = Mount(SolidConfig(mount_roll_deg=-5.0, mount_pitch_deg=8.0))
    T = _pose()
    level = mount.level_pose(T)
    assert mount.levelled and not np.allclose(level, T)
    np.testing.assert_allclose(mount.unlevel(level), T, atol=1e-12)


def test_points_poses_and_covariances_agree() -> None:
    """A loop found between levelled clouds maps the sensor clouds onto each other once
    unlevelled, and its covariance turns with it."""
    mount = Mount(SolidConfig(mount_roll_deg=3.0, mount_pitch_deg=-7.0, mount_yaw_deg=20.0))
    rng = np.random.default_rng(0)
    query = rng.normal(size=(20, 3)) * 10.0
    T = _pose()  # sensor frames: p_match = T p_query
    match = query @ T[:3, :3].T + T[:3, 3]
    L = mount.level_pose(T)
    lq, lm = np.asarray(mount.level(query)), np.asarray(mount.level(match))
    np.testing.assert_allclose(lq @ L[:3, :3].T + L[:3, 3], lm, atol=1e-9)
    np.testing.assert_allclose(mount.to_sensor(lq[0]), query[0], atol=1e-12)
    np.testing.assert_allclose(mount.unlevel_pose(L)[:3], T[:3, 3], atol=1e-12)
    cov = np.diag([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    out = mount.unlevel_cov(cov)
    np.testing.assert_allclose(np.linalg.eigvalsh(out), np.sort(np.diag(cov)), atol=1e-12)
    assert not np.allclose(out, cov)


def test_a_level_mount_changes_nothing() -> None:
    mount = Mount(SolidConfig())
    pts = np.ones((4, 3))
    assert not mount.levelled and mount.level(pts) is pts
    T = _pose()
    assert mount.level_pose(T) is T and mount.unlevel(T) is T


def test_upright_turns_the_levelled_frame_to_the_odometrys_up() -> None:
    """A hand-held sensor's tilt from its pose: the keyframe grid is laid out upright."""
    mount = Mount(SolidConfig())
    T = _pose()  # roll 0.1 rad, pitch -0.2 rad
    up = mount.upright(matrix_to_vector(T))
    assert up is not None
    # The odometry's up, seen from the sensor, is +z of the upright frame; heading kept.
    np.testing.assert_allclose(up @ (T[:3, :3].T @ [0.0, 0.0, 1.0]), [0.0, 0.0, 1.0],
                               atol=1e-12)
    np.testing.assert_allclose(up, rpy_matrix(0.1, -0.2, 0.0), atol=1e-12)
    # No pose, a level one, or a tilt under 2 degrees: the sensor's own grid.
    assert mount.upright(None) is None
    assert mount.upright(matrix_to_vector(_rpy_4x4(0.0, 0.0, 2.0))) is None
    assert mount.upright(matrix_to_vector(_rpy_4x4(0.02, 0.02, 2.0))) is None
    assert mount.upright(matrix_to_vector(_rpy_4x4(0.04, 0.0, 2.0))) is not None


def test_upright_counts_the_tilt_beyond_the_mounts() -> None:
    """A tilted mount is levelled already: a pose tilted by just the mount is upright."""
    mount = Mount(SolidConfig(mount_roll_deg=-5.0, mount_pitch_deg=8.0, mount_yaw_deg=30.0))
    assert mount.upright(matrix_to_vector(_rpy_4x4(0.0, 0.0, 1.0) @ _mount_4x4(mount))) is None
    hand = _rpy_4x4(0.15, 0.0, 1.0) @ _mount_4x4(mount)
    up = mount.upright(matrix_to_vector(hand))
    assert up is not None
    np.testing.assert_allclose(up @ mount.R @ (hand[:3, :3].T @ [0.0, 0.0, 1.0]),
                               [0.0, 0.0, 1.0], atol=1e-12)


def _rpy_4x4(roll: float, pitch: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(roll, pitch, yaw)
    return T


def _mount_4x4(mount: Mount) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = mount.R  # world <- sensor of a level vehicle facing +x
    return T
