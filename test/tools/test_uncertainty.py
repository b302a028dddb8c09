"""NEES of a loop against its reference pose: the convention of doc/conventions.md (right
perturbation in the query frame, ROS order), chi-square statistics, sign invariance."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from solid_ros.tools.uncertainty import Nees, nees, se3_log, summarise

FloatArray = npt.NDArray[np.float64]


def _hat(w: FloatArray) -> FloatArray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _exp(xi: npt.ArrayLike) -> FloatArray:
    """SE(3) exponential of (rho, w), written out independently of the module under test."""
    v = np.asarray(xi, dtype=np.float64)
    rho, w = v[:3], v[3:]
    theta = float(np.linalg.norm(w))
    K = _hat(w)
    if theta < 1e-9:
        R, V = np.eye(3) + K, np.eye(3) + 0.5 * K
    else:
        a = math.sin(theta) / theta
        b = (1.0 - math.cos(theta)) / theta ** 2
        c = (theta - math.sin(theta)) / theta ** 3
        R = np.eye(3) + a * K + b * K @ K
        V = np.eye(3) + b * K + c * K @ K
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, V @ rho
    return out


@pytest.mark.parametrize('xi', [[0.3, -0.2, 0.1, 0.0, 0.0, 0.0],
                                [0.5, 1.0, -2.0, 0.1, -0.2, 0.3],
                                [0.0, 0.0, 0.0, 0.0, 0.0, 3.1],
                                [1.0, 0.0, 0.0, 1e-10, 0.0, 0.0],
                                [0.2, 0.1, 0.0, 0.0, math.pi - 1e-7, 0.0]])
def test_se3_log_inverts_the_exponential(xi: list[float]) -> None:
    np.testing.assert_allclose(se3_log(_exp(xi)), xi, atol=1e-6)


def test_known_error_gives_its_nees() -> None:
    T = _exp([4.0, -1.0, 0.2, 0.0, 0.0, 0.7])
    cov = np.diag([0.1 ** 2, 0.2 ** 2, 0.05 ** 2, 0.01 ** 2, 0.01 ** 2, 0.02 ** 2])
    # The reference 0.1 m ahead of T along the query sensor's x and turned 0.02 rad about its
    # z: one sigma in x, one in yaw.
    ref = T @ _exp([0.1, 0.0, 0.0, 0.0, 0.0, 0.02])
    out = nees(T, ref, cov)
    assert isinstance(out, Nees)
    assert out.full == pytest.approx(2.0, rel=1e-3)
    assert out.translation == pytest.approx(1.0, rel=1e-3)
    np.testing.assert_allclose(out.error, [0.1, 0.0, 0.0, 0.0, 0.0, 0.02], atol=1e-4)
    # The same error on the left (in the match frame) is another error: x is turned by 0.7 rad.
    left = nees(T, _exp([0.1, 0.0, 0.0, 0.0, 0.0, 0.02]) @ T, cov)
    assert left.full != pytest.approx(out.full, rel=1e-2)
    # Sign invariant, and the 36-value row-major form is accepted.
    assert nees(ref, T, cov.ravel().tolist()).full == pytest.approx(out.full, rel=1e-6)


def test_errors_drawn_from_the_covariance_average_six() -> None:
    rng = np.random.default_rng(7)
    A = rng.normal(size=(6, 6)) * np.array([0.05, 0.05, 0.02, 0.002, 0.002, 0.004])
    cov = A @ A.T + np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6])
    L = np.linalg.cholesky(cov)
    T = _exp([10.0, 2.0, 0.0, 0.0, 0.05, 1.2])
    values = [nees(T, T @ _exp(L @ rng.normal(size=6)), cov) for _ in range(4000)]
    s = summarise(values)
    assert s['count'] == 4000
    assert s['mean'] == pytest.approx(6.0, abs=0.3)
    assert s['median'] == pytest.approx(5.35, abs=0.3)  # chi-square(6) median
    assert s['mean_t'] == pytest.approx(3.0, abs=0.2)
    # A covariance four times too small shows as four times the NEES.
    small = summarise([nees(T, T @ _exp(L @ rng.normal(size=6)), cov / 4.0)
                       for _ in range(2000)])
    assert small['mean'] == pytest.approx(24.0, rel=0.08)


def test_bad_covariances_are_refused() -> None:
    T = np.eye(4)
    with pytest.raises(ValueError, match='non-finite'):
        nees(T, T, np.full(36, math.nan))
    with pytest.raises(ValueError, match='positive definite'):
        nees(T, T, np.zeros((6, 6)))
    assert summarise([])['count'] == 0 and math.isnan(summarise([])['mean'])
