"""The demo command line's simulator options reach the drive it caches and replays."""

from __future__ import annotations

import pytest

from solid_ros.core.config import SolidConfig
from solid_ros.sim import DEMO_DEFAULTS, DEMO_SENSORS, DriveConfig, vlp16_like
from solid_ros.tools import demo


def _demo_drive(argv: list[str]) -> DriveConfig:
    args = demo._parser().parse_args(argv)
    return DriveConfig(**{**DEMO_DEFAULTS, **demo.drive_options(args)})


def test_demo_command_line_passes_the_options() -> None:
    assert _demo_drive([]).fingerprint() == DriveConfig(**DEMO_DEFAULTS).fingerprint()
    config = _demo_drive(['--sensor', 'ouster_like', '--route', 'no_revisit', '--scene',
                          'lookalike', '--facade-detail', '--tilt-pitch-deg', '5',
                          '--tilt-roll-deg', '-1.5', '--seed', '3'])
    assert config.model == DEMO_SENSORS['ouster_like'].replace(mount_pitch_deg=5.0,
                                                               mount_roll_deg=-1.5)
    assert (config.route, config.scene, config.facade_detail, config.seed) == (
        'no_revisit', 'lookalike', True, 3)
    assert _demo_drive(['--sensor', 'vlp16_like']).model == vlp16_like()
    for bad in (['--route', 'spiral'], ['--scene', 'copies'], ['--sensor', 'velodyne'],
                ['--tilt-pitch-deg', 'up']):
        with pytest.raises(SystemExit) as exc:
            demo._parser().parse_args(bad)
        assert exc.value.code == 2


def test_demo_detector_settings_follow_the_sensor() -> None:
    def overrides(argv: list[str]) -> dict[str, object]:
        return demo.config_overrides(demo._parser().parse_args(argv))

    assert overrides([]) == {} and overrides(['--fov', '90']) == {'fov_width_deg': 90.0}
    assert overrides(['--sensor', 'vlp16_like', '--fov', '120']) == {'fov_width_deg': 120.0}
    # Every simulated sensor replays with the shipped preset of its class, whose vertical
    # FOV is the sensor's.
    assert set(demo.SENSOR_PARAMS) == set(DEMO_SENSORS)
    for sensor, name in demo.SENSOR_PARAMS.items():
        cfg = SolidConfig.from_yaml(demo.shipped_config(name))
        model = DEMO_SENSORS[sensor]
        assert (cfg.fov_up_deg, cfg.fov_down_deg) == (model.fov_up_deg, model.fov_down_deg)
