"""One line when the configuration contradicts the first clouds, with what to set."""

from __future__ import annotations

import numpy as np
import pytest
from sensor_clouds import cloud, rosette, spinning

from solid_ros.core.config import SolidConfig
from solid_ros.core.descriptor.sensor import FIRST_CLOUDS, CloudSample
from solid_ros.core.descriptor.sensor_check import check_line, findings, suggest_settings

AVIA = SolidConfig(fov_up_deg=38.6, fov_down_deg=-38.6, min_range=0.5, max_range=50.0,
                   max_distance=50.0, heading_match='overlap')
VLP16 = SolidConfig(fov_up_deg=15.0, fov_down_deg=-15.0)


def _sample(make, **kw) -> CloudSample:  # type: ignore[no-untyped-def]
    sample = CloudSample()
    for seed in range(FIRST_CLOUDS):
        sample.add(make(seed, **kw))
    return sample


def _fixed(sample: CloudSample, config: SolidConfig) -> SolidConfig:
    for f in findings(sample, config):
        config = config.replace(**f.settings)
    return config


@pytest.mark.parametrize('make, config', [(spinning, VLP16), (rosette, AVIA)])
def test_fitting_configuration_says_nothing(make, config: SolidConfig) -> None:  # type: ignore[no-untyped-def]
    assert check_line(_sample(make), config) is None


def test_authors_defaults_on_a_vlp16_clamp_the_upper_rings() -> None:
    sample = _sample(spinning)
    (found,) = findings(sample, SolidConfig())
    assert found.topic == 'elevation'
    assert found.settings == {'fov_up_deg': 15.0, 'fov_down_deg': -15.0}
    assert 'into the top elevation bin' in found.message and 'stay empty' in found.message
    line = check_line(sample, SolidConfig())
    assert line is not None and '\n' not in line
    assert line.startswith(f'the first {FIRST_CLOUDS} clouds contradict the parameters: ')
    assert line.endswith('set fov_up_deg: 15.0, fov_down_deg: -15.0')
    assert findings(sample, _fixed(sample, SolidConfig())) == []


def test_points_beyond_max_range_and_within_min_range() -> None:
    far = _sample(spinning, far=200.0)
    (found,) = findings(far, VLP16)
    assert found.topic == 'max_range' and found.settings == {'max_range': 200.0,
                                                               'max_distance': 200.0}
    near = _sample(rosette, near=0.3, far=6.0)
    topics = {f.topic: f for f in findings(near, AVIA.replace(min_range=3.0))}
    assert set(topics) == {'min_range'} and topics['min_range'].settings['min_range'] < 0.5


def test_clip_looking_away_from_the_data() -> None:
    sample = _sample(rosette, centre=0.0)
    config = AVIA.replace(fov_width_deg=60.0, fov_center_deg=180.0)
    (found,) = findings(sample, config)
    assert found.topic == 'fov_clip' and found.settings == {'fov_center_deg': 0.0}
    # A 90-degree clip of a 360-degree sensor is a choice (spinning_fov90.yaml): no line.
    assert check_line(_sample(spinning), VLP16.replace(fov_width_deg=90.0,
                                                       heading_match='overlap')) is None


def test_narrow_view_with_full_heading_match() -> None:
    found = findings(_sample(rosette), AVIA.replace(heading_match='full'))
    assert [f.topic for f in found] == ['heading_match']
    assert found[0].settings == {'heading_match': 'overlap'}


def test_mounting_levels_before_the_elevation_bins() -> None:
    # A VLP-16 pitched 20 deg: levelled, its rings reach -35 .. +35 deg around it.
    sample = _sample(spinning)
    assert findings(sample, VLP16) == []
    (found,) = findings(sample, VLP16.replace(mount_pitch_deg=20.0))
    assert found.topic == 'elevation' and found.settings['fov_up_deg'] > 30.0


def test_too_few_points_say_nothing() -> None:
    sample = CloudSample(clouds=1)
    sample.add(cloud(np.zeros(50), np.zeros(50), np.full(50, 5.0)))
    assert findings(sample, SolidConfig()) == [] and check_line(sample, SolidConfig()) is None
    assert suggest_settings(sample, SolidConfig()) == {}


def test_suggest_changes_only_what_the_clouds_contradict() -> None:
    assert suggest_settings(_sample(spinning), SolidConfig()) == {
        'fov_up_deg': 15.0, 'fov_down_deg': -15.0}
    assert suggest_settings(_sample(spinning), VLP16) == {}
    # A Mid-360's view on a VLP-16's settings: the top clamps; -7 deg is inside -15.
    got = suggest_settings(_sample(rosette, width=360.0, down=-7.0, up=52.0), VLP16)
    assert got == {'fov_up_deg': 52.0}
    far = suggest_settings(_sample(spinning, far=200.0), VLP16)
    assert far == {'max_range': 200.0, 'max_distance': 200.0}


def test_a_sensor_looking_lower_than_the_bins_clamps_into_the_bottom_one() -> None:
    sample = _sample(spinning, down=-45.0, up=2.0, rings=32)
    (found,) = findings(sample, SolidConfig())
    assert 'of the points fall into the bottom elevation bin' in found.message
    assert found.settings == {'fov_up_deg': 2.0, 'fov_down_deg': -45.0}


def test_suggested_values_stay_within_the_settings_ranges() -> None:
    far = suggest_settings(_sample(spinning, far=5000.0), VLP16)
    assert far == {'max_range': 1000.0, 'max_distance': 1000.0}
    VLP16.replace(**far)  # valid
