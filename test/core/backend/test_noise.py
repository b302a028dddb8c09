"""Factor noise: block order, the odometry model, odometry and loop covariances."""

from __future__ import annotations

import math

import numpy as np

from solid_ros.core.backend.noise import (
    floored,
    loop_covariance,
    model_covariance,
    odometry_step_noise,
    swap_blocks,
)
from solid_ros.core.config import SolidConfig
from solid_ros.core.geometry import rot_z

CFG = SolidConfig()


def _step(metres: float, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_z(yaw)
    T[0, 3] = metres
    return T


def test_swap_blocks_moves_translation_behind_rotation_and_back() -> None:
    ros = np.arange(36.0).reshape(6, 6)
    tangent = swap_blocks(ros)
    np.testing.assert_array_equal(tangent[:3, :3], ros[3:, 3:])  # rotation block first
    np.testing.assert_array_equal(tangent[3:, :3], ros[:3, 3:])  # translation-rotation
    np.testing.assert_array_equal(swap_blocks(tangent), ros)


def test_model_variance_grows_with_distance_whatever_the_spacing() -> None:
    one = model_covariance(_step(1.0), CFG.replace(backend_odom_floor_m=1e-4,
                                                   backend_odom_floor_deg=1e-4))
    two = model_covariance(_step(2.0), CFG.replace(backend_odom_floor_m=1e-4,
                                                   backend_odom_floor_deg=1e-4))
    np.testing.assert_allclose(np.diag(two), 2.0 * np.diag(one), rtol=1e-3)
    assert math.isclose(math.sqrt(one[0, 0]), CFG.backend_odom_trans_sigma, rel_tol=1e-3)
    turned = model_covariance(_step(0.0, math.pi / 2), CFG)
    assert turned[5, 5] > model_covariance(_step(0.0), CFG)[5, 5]
    standing = model_covariance(_step(0.0), CFG)  # the floors alone
    assert math.isclose(math.sqrt(standing[0, 0]), CFG.backend_odom_floor_m)
    assert math.isclose(math.degrees(math.sqrt(standing[3, 3])), CFG.backend_odom_floor_deg)


def test_odometry_covariance_when_usable_else_the_model() -> None:
    step = _step(1.0)
    model = model_covariance(step, CFG)
    floors = (CFG.backend_odom_floor_m, math.radians(CFG.backend_odom_floor_deg))
    before = np.diag([0.1, 0.1, 0.1, 0.01, 0.01, 0.01])
    grown = before + np.diag([0.02, 0.02, 0.01, 0.001, 0.001, 0.002])
    got = odometry_step_noise(step, before, grown, CFG)
    assert got.source == 'odometry' and not got.bad
    np.testing.assert_allclose(got.covariance, floored(grown - before, *floors))
    # A source publishing a constant covariance per pose: its own value.
    same = odometry_step_noise(step, before, before, CFG)
    np.testing.assert_allclose(same.covariance, floored(before, *floors))
    # Unset (ROS all zeros) or absent: the model, no warning.
    for unset in (None, np.zeros((6, 6))):
        got = odometry_step_noise(step, before, unset, CFG)
        assert got.source == 'model' and not got.bad
        np.testing.assert_allclose(got.covariance, model)
    # NaN, a negative variance, not positive definite, asymmetric: the model and a warning.
    nan = before.copy()
    nan[2, 2] = math.nan
    negative = before.copy()
    negative[0, 0] = -1.0
    singular = np.ones((6, 6))
    skew = before.copy()
    skew[0, 1] = 0.5
    for bad in (nan, negative, singular, skew):
        got = odometry_step_noise(step, before, bad, CFG)
        assert got.source == 'model' and got.bad
        np.testing.assert_allclose(got.covariance, model)


def test_loop_covariance_gets_the_loop_floors() -> None:
    cov = np.diag([1e-6] * 3 + [1e-8] * 3)
    got = loop_covariance(tuple(cov.ravel()), CFG)
    assert got is not None
    assert math.sqrt(got[0, 0]) >= CFG.backend_loop_floor_m
    assert math.degrees(math.sqrt(got[5, 5])) >= CFG.backend_loop_floor_deg
    assert loop_covariance((math.nan,) * 36, CFG) is None


def test_an_unchecked_step_is_known_up_to_its_own_size() -> None:
    from solid_ros.core.backend.noise import unchecked_covariance

    step = np.eye(4)
    step[:3, :3] = rot_z(math.radians(10.0))
    step[:3, 3] = [0.6, 0.8, 0.0]  # 1 m, 10 deg
    cov = np.full((6, 6), 1e-6) + np.diag([1e-4] * 3 + [4.0] * 3)  # rotation already loose
    out = unchecked_covariance(step, cov)
    np.testing.assert_allclose(np.diag(out), [1.0] * 3 + [4.0 + 1e-6] * 3)
    np.testing.assert_allclose(out - np.diag(np.diag(out)), cov - np.diag(np.diag(cov)))
    assert np.all(np.linalg.eigvalsh(out) > 0)
