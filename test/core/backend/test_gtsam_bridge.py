"""The one crossing into gtsam: poses and ROS-order covariances, both ways, and its meaning."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from solid_ros.core.errors import BackendError
from solid_ros.core.geometry import rpy_matrix

gtsam = pytest.importorskip('gtsam', reason='gtsam is not installed')

from solid_ros.core.backend.gtsam_bridge import from_gtsam, pose3, require_gtsam, robust, to_gtsam  # noqa: E402


def _pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(*rng.uniform(-3.0, 3.0, 3))
    T[:3, 3] = rng.uniform(-50.0, 50.0, 3)
    return T


def _spd(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=(6, 6)) * np.repeat([0.1, 0.01], 3)
    return a @ a.T + np.diag(np.repeat([1e-4, 1e-6], 3))


def test_round_trip_keeps_pose_and_ros_covariance() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        T, cov = _pose(rng), _spd(rng)
        back_T, back_cov = from_gtsam(*to_gtsam(T, cov))
        np.testing.assert_allclose(back_T, T, atol=1e-9)
        np.testing.assert_allclose(back_cov, cov, rtol=1e-7, atol=1e-14)


def test_ros_covariance_means_a_right_perturbation_in_the_query_frame() -> None:
    # A loop T with a covariance that is loose only in the query sensor's x (ROS index 0)
    # and only in yaw (ROS index 5): moving the query along its own x, or turning it about
    # its own z, must cost the factor little; anything else a lot.
    rng = np.random.default_rng(4)
    T = _pose(rng)
    cov = np.diag([1.0, 1e-6, 1e-6, 1e-6, 1e-6, 1.0])
    measured, noise = to_gtsam(T, cov)
    factor = gtsam.PriorFactorPose3(1, measured, noise)

    def cost(delta_ros: np.ndarray) -> float:
        moved = gtsam.Pose3(T).compose(gtsam.Pose3.Expmap(np.r_[delta_ros[3:], delta_ros[:3]]))
        values = gtsam.Values()
        values.insert(1, moved)
        return 2.0 * factor.error(values)  # the squared Mahalanobis distance

    step = 1e-3
    for i in range(6):
        delta = np.zeros(6)
        delta[i] = step
        expected = step ** 2 / cov[i, i]
        assert cost(delta) == pytest.approx(expected, rel=1e-3), i


def test_pose3_accepts_a_slightly_non_orthonormal_rotation() -> None:
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(0.1, 0.2, 0.3) * (1.0 + 1e-7)
    R = pose3(T).rotation().matrix()
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_robust_kernels() -> None:
    _, noise = to_gtsam(np.eye(4), np.eye(6))
    assert robust(noise, 'none', 1.0) is noise
    for kernel in ('huber', 'cauchy'):
        model = robust(noise, kernel, 1.345)
        assert isinstance(model, gtsam.noiseModel.Robust), kernel


def test_missing_gtsam_names_the_install_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, 'gtsam', None)  # makes `import gtsam` raise ImportError
    with pytest.raises(BackendError, match='pip install gtsam'):
        require_gtsam()
