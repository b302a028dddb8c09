"""The run's calibration: what it samples and what it learns."""

from __future__ import annotations

import math

import numpy as np
import pytest

from solid_ros.core.geometry import rot_z
from solid_ros.core.verification.calibration import (
    CLOSE_DEG,
    CLOSE_M,
    MAX_DRIFT,
    MIN_SAMPLES,
    SAMPLE_EVERY,
    WINDOW,
    Calibration,
    closes,
)


def test_every_keyframe_is_sampled_until_enough_then_every_nth() -> None:
    cal = Calibration()
    assert all(cal.wants(i) for i in range(1, 7))
    for _ in range(MIN_SAMPLES):
        cal.add(True, 0.01, True, 0.02, 2.0)
    assert cal.wants(SAMPLE_EVERY * 3) and not cal.wants(SAMPLE_EVERY * 3 + 1)


def test_nothing_is_learned_before_enough_right_pairs() -> None:
    cal = Calibration()
    for _ in range(MIN_SAMPLES - 1):
        cal.add(True, 0.05, True, 0.1, 2.0)
    assert math.isnan(cal.learned.conflict_q75) and math.isnan(cal.learned.drift_per_m)
    cal.add(True, 0.05, True, 0.1, 2.0)
    assert cal.learned.conflict_q75 == pytest.approx(0.05)
    assert cal.learned.drift_per_m == pytest.approx(0.05)


def test_wrong_pairs_teach_nothing_about_conflict_and_slides_nothing_about_drift() -> None:
    cal = Calibration()
    for k in range(MIN_SAMPLES):
        cal.add(True, 0.01 * (k % 2), True, 0.02, 1.0)
        cal.add(False, 0.5, False, 5.0, 1.0)  # not right, not verified
        cal.add(False, math.nan, True, MAX_DRIFT * 4.0, 4.0)  # verified, but slid along
    learned = cal.learned
    assert learned.tried == 3 * MIN_SAMPLES and learned.right == MIN_SAMPLES
    assert learned.conflict_q75 == pytest.approx(0.01)
    assert learned.drift_per_m == pytest.approx(0.02) and learned.drift_pairs == MIN_SAMPLES


def test_the_window_keeps_the_newest_samples_and_a_reset_forgets() -> None:
    cal = Calibration()
    for _ in range(WINDOW):
        cal.add(True, 0.2, False, math.nan, 1.0)
    for _ in range(WINDOW):
        cal.add(True, 0.01, False, math.nan, 1.0)
    assert cal.learned.conflict_q75 == pytest.approx(0.01) and cal.learned.right == WINDOW
    cal.clear()
    assert cal.learned.tried == 0 and math.isnan(cal.learned.conflict_q75)


def _pose(x: float, y: float, yaw_deg: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_z(math.radians(yaw_deg))
    T[:2, 3] = [x, y]
    return T


def test_a_triangle_closes_only_within_the_tolerance() -> None:
    T_ak, T_ba = _pose(1.0, 0.2, 4.0), _pose(1.5, -0.3, 7.0)
    T_bk = T_ba @ T_ak
    assert closes(T_ak, T_ba, T_bk)
    # k->b slid along or turned beyond the tolerance: no longer closed.
    assert not closes(T_ak, T_ba, T_bk @ _pose(1.5 * CLOSE_M, 0.0, 0.0))
    assert not closes(T_ak, T_ba, T_bk @ _pose(0.0, 0.0, 1.5 * CLOSE_DEG))
    assert closes(T_ak, T_ba, T_bk @ _pose(0.5 * CLOSE_M, 0.0, 0.5 * CLOSE_DEG))


def test_pairs_a_triangle_showed_right_teach_the_conflict_not_that_the_odometry_agrees() -> None:
    cal = Calibration()
    for _ in range(MIN_SAMPLES):
        cal.add(True, 0.08, False, 1.0, 2.0, agreed=False)  # right far from the odometry
    learned = cal.learned
    assert learned.right == MIN_SAMPLES and learned.conflict_q75 == pytest.approx(0.08)
    assert learned.agreed == 0 and not learned.odometry_agrees
    assert math.isnan(learned.agreed_conflict_q75)
    for _ in range(MIN_SAMPLES):
        cal.add(True, 0.02, False, 0.1, 2.0)  # right where the odometry put it
    learned = cal.learned
    assert learned.agreed == MIN_SAMPLES and learned.odometry_agrees
    assert learned.agreed_conflict_q75 == pytest.approx(0.02)


def test_sampling_stays_dense_until_the_odometry_agreed_but_triangles_thin_out() -> None:
    cal = Calibration()
    for _ in range(MIN_SAMPLES):
        cal.add(True, 0.08, False, 1.0, 2.0, agreed=False)  # a triangle showed them right
    # A registered step's bar still waits for pairs the odometry agreed with: keep sampling
    # every keyframe, but check by a triangle only every n-th.
    odd = SAMPLE_EVERY * 3 + 1
    assert cal.wants(odd) and not cal.wants_triangle(odd)
    assert cal.wants_triangle(SAMPLE_EVERY * 3)
    for _ in range(MIN_SAMPLES):
        cal.add(True, 0.02, False, 0.1, 2.0)
    assert not cal.wants(odd) and cal.wants(SAMPLE_EVERY * 3)
