"""Tests of the loop covariance: it grows with the error the residuals show, and the model
floor keeps a perfect fit uncertain (the calibration over whole drives is
test/bench/bench_nees.py)."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest
from hdl64_scans import CFG, keyframe_points, scan, truth

from solid_ros.core.geometry import rpy_matrix
from solid_ros.core.verification.covariance import MODEL_FLOOR, support_covariance
from solid_ros.core.verification.prepared import Source
from solid_ros.core.verification.support import Support
from solid_ros.core.verification.verifier import Verifier
from solid_ros.tools.uncertainty import nees

pytest.importorskip('small_gicp', reason='small-gicp is not installed')

FloatArray = npt.NDArray[np.float64]


def _tilted_support(pitch_deg: float) -> tuple[Support, FloatArray, FloatArray]:
    """Support of scan 273 against scan 5 at the reference pose tilted in pitch, the tilted
    ``T_mq`` and the reference."""
    ref = truth(273, 5)
    v = Verifier(CFG)
    query = v.prepare(keyframe_points(scan(273)[0]))
    match = Source(v.prepare(keyframe_points(scan(5)[0])).keyframe_cloud(), v.settings)
    tilt = np.eye(4)
    tilt[:3, :3] = rpy_matrix(0.0, math.radians(pitch_deg), 0.0)
    T_qm = tilt @ np.linalg.inv(ref)
    return Support(query, match, T_qm, v.settings), np.linalg.inv(T_qm), ref


def test_covariance_grows_with_the_error_the_residuals_show() -> None:
    # A pose tilted by 0.1 deg (16-ring scans' GICP tilts by 0.05 deg): the residuals on the
    # far ground show the tilt, and the covariance, read from them, grows to cover most of
    # it; the point-to-plane model's (sigma^2 W / P inv(A)) stayed put at 3 % of it (NEES 823).
    right, _, _ = _tilted_support(0.0)
    tilted, T, ref = _tilted_support(0.1)
    cov_right, cov_tilted = support_covariance(right), support_covariance(tilted)
    assert cov_right is not None and cov_tilted is not None
    assert cov_tilted[4, 4] > 9.0 * cov_right[4, 4]  # pitch sigma at least three times
    assert nees(T, ref, cov_tilted).full < 100.0
    np.testing.assert_allclose(support_covariance(tilted, 4.0), 4.0 * cov_tilted)


def test_covariance_of_a_perfect_fit_is_the_model_floor() -> None:
    # The same cloud on itself: every residual is 0 (to float32 rounding), and the floor keeps
    # the loop uncertain.
    v = Verifier(CFG)
    query = v.prepare(keyframe_points(scan(273)[0]))
    sup = Support(query, Source(query.keyframe_cloud(), v.settings), np.eye(4), v.settings)
    assert sup.inliers == query.size and np.abs(sup.residual_scores).max() < 1e-6
    cov = support_covariance(sup)
    assert cov is not None
    info, weight = sup.weighted_information
    model = 0.02 ** 2 * max(weight / sup.patches, 1.0) * np.linalg.inv(info)
    order = [3, 4, 5, 0, 1, 2]
    np.testing.assert_allclose(cov, MODEL_FLOOR * model[np.ix_(order, order)], rtol=1e-6)
