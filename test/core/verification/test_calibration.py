"""The run's calibration: what it samples and what it learns."""

from __future__ import annotations

import math

import pytest

from solid_ros.core.verification.calibration import (
    MAX_DRIFT,
    MIN_SAMPLES,
    SAMPLE_EVERY,
    WINDOW,
    Calibration,
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
