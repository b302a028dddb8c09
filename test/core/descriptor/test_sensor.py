"""Measuring a sensor from its first clouds: coverage, vertical FOV, ranges, rings."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sensor_clouds import rosette, spinning

from solid_ros.core.descriptor.sensor import FIRST_CLOUDS, CloudSample, measure
from solid_ros.core.geometry import rpy_matrix


def _sample(make, **kw) -> CloudSample:  # type: ignore[no-untyped-def]
    sample = CloudSample()
    for seed in range(FIRST_CLOUDS):
        sample.add(make(seed, **kw))
    return sample


def test_spinning_sensor_has_a_full_turn_and_its_rings() -> None:
    view = measure(_sample(spinning))
    assert view is not None and view.full_turn and view.horizontal_deg == 360.0
    assert view.rings == 16 and view.ring_spacing_deg == pytest.approx(2.0, abs=0.05)
    assert view.elevation_low_deg == pytest.approx(-15.0, abs=0.1)
    assert view.elevation_high_deg == pytest.approx(15.0, abs=0.1)
    assert 2.0 <= view.range_low_m < 3.0 and 58.0 < view.range_high_m <= 60.0
    assert view.points_per_cloud == 16 * 900 and view.clouds == FIRST_CLOUDS
    assert view.pattern() == '360-degree, 16 rings'


def test_64_rings_and_a_blocked_sector_still_a_full_turn() -> None:
    view = measure(_sample(spinning, rings=64, down=-16.6, up=16.6, per_ring=600,
                           blocked_deg=60.0))
    assert view is not None and view.full_turn
    assert view.horizontal_deg == pytest.approx(300.0, abs=2.0)
    assert view.rings == 64


@pytest.mark.parametrize('centre', [0.0, 90.0, 180.0, -120.0])
def test_sector_without_rings_and_its_centre(centre: float) -> None:
    view = measure(_sample(rosette, centre=centre))
    assert view is not None and not view.full_turn and view.rings == 0
    assert view.horizontal_deg == pytest.approx(70.0, abs=2.0)
    assert abs(math.remainder(view.center_deg - centre, 360.0)) < 1.5
    assert 'no rings' in view.summary() and 'sector' in view.summary()


def test_rotation_levels_the_elevations_but_not_the_rings() -> None:
    sample = _sample(spinning)  # a sensor pitched 20 deg: its rings are its own
    level = measure(sample, rpy_matrix(0.0, np.radians(20.0), 0.0))
    assert level is not None and level.rings == 16
    assert level.elevation_low_deg < -30.0 and level.elevation_high_deg > 30.0


def test_bad_clouds_are_left_out_and_the_sample_completes_once() -> None:
    sample = CloudSample(clouds=2, max_points=1000)
    nan = np.full((10, 3), np.nan)
    for bad in (None, 'points', np.zeros(5), np.zeros((4, 2)), nan, np.zeros((0, 3)),
                np.zeros((8, 3)), np.array([['a', 'b', 'c']]), [[1.0, float('inf'), 2.0]]):
        assert sample.add(bad) is False  # type: ignore[arg-type]
    assert sample.clouds == 0 and measure(sample) is None
    assert sample.add(spinning(0)) is False and not sample.complete
    assert sample.add(spinning(1)) is True and sample.complete
    assert sample.add(spinning(2)) is False and sample.clouds == 2
    assert len(sample.points()) <= 2 * 1000  # every k-th point of each
    assert sample.counts == [16 * 900, 16 * 900]


def test_too_few_points_say_nothing() -> None:
    sample = CloudSample(clouds=1)
    sample.add(spinning(0)[:100])
    assert measure(sample) is None
