"""Drive options: DriveConfig and simulate pass them through; defaults keep the drive as it
was, and earlier drives keep their cache key."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.errors import ConfigError
from solid_ros.sim import (
    DEMO_DEFAULTS,
    DEMO_SENSORS,
    Drive,
    DriveConfig,
    simulate,
    vlp16_like,
)
from solid_ros.sim.scene import LOOKALIKE_JITTER


def test_drives_of_earlier_versions_keep_their_cache_key() -> None:
    # The keys of the cached demo bags made before the new options existed: those drives had
    # perfect odometry, which leaves the odometry's error model out of the key.
    hdl = DriveConfig(**DEMO_DEFAULTS, perfect_odometry=True)
    assert hdl.fingerprint() == '194e4ed936b62d53'
    avia = DriveConfig(**{**DEMO_DEFAULTS, 'sensor': DEMO_SENSORS['avia_like']},
                       perfect_odometry=True)
    assert avia.fingerprint() == 'f1146a71d351df42'
    # The defaults spelt out are the same drive.
    spelt = DriveConfig(**DEMO_DEFAULTS, route='revisits', nx=4, ny=3, scene='varied',
                        facade_detail=False, mount_roll_deg=0.0, mount_pitch_deg=0.0,
                        perfect_odometry=True, odom_scale_error=0.5)
    assert spelt.fingerprint() == hdl.fingerprint()
    # A drifting odometry writes another /odom: another cache entry, one per error model.
    drifting = DriveConfig(**DEMO_DEFAULTS)
    assert drifting.fingerprint() != hdl.fingerprint()
    assert DriveConfig(**DEMO_DEFAULTS, odom_heading_walk_deg=0.0).fingerprint() != (
        drifting.fingerprint())


def test_default_drive_is_unchanged() -> None:
    # Figures of the first release's default drive (scans are also compared bit for bit
    # against it while developing; tolerances here only absorb other CPUs' last bits).
    d = Drive(DriveConfig())
    assert (len(d.scene.boxes), len(d.scene.cylinders), len(d)) == (297, 317, 892)
    assert d.scene.boxes.sum() == pytest.approx(62493.51584814436, rel=1e-9)
    assert d.scene.cylinders.sum() == pytest.approx(60364.43578324666, rel=1e-9)
    assert d.trajectory.xy.sum() == pytest.approx(110751.17527299814, rel=1e-9)
    scan = next(simulate(seed=0, sensor='hdl64', num_scans=1))
    assert abs(len(scan.cloud) - 62845) <= 3
    np.testing.assert_allclose(scan.cloud.astype(np.float64).mean(axis=0),
                               [-0.33651371, -0.06298375, -1.42857309, 0.24230477], atol=1e-5)


@pytest.mark.parametrize('option', [
    {'route': 'no_revisit'}, {'route': ((0, 0), (2, 0))}, {'nx': 5}, {'scene': 'lookalike'},
    {'facade_detail': True}, {'mount_pitch_deg': 3.0}, {'sensor': 'ouster_like'},
    {'sensor': 'vlp16_like'}, {'perfect_odometry': True}, {'odom_scale_error': 0.02},
    {'odom_heading_bias_deg_per_m': 0.0}, {'odom_position_walk_m': 0.0}, {'people': 2.0},
    {'cars': 1.0}, {'foliage': 1.0}])
def test_every_option_names_another_drive(option: dict[str, object]) -> None:
    assert DriveConfig(**{**DEMO_DEFAULTS, **option}).fingerprint() != DriveConfig(
        **DEMO_DEFAULTS).fingerprint()


def test_grid_follows_the_route() -> None:
    assert DriveConfig().grid_size == (4, 3)
    assert DriveConfig(route='no_revisit').grid_size == (7, 6)
    assert DriveConfig(route=[[0, 0], [0, 1]]).grid_size == (2, 2)
    assert DriveConfig(nx=6, ny=5).grid_size == (6, 5)
    bigger = Drive(DriveConfig(block=40.0, nx=6, ny=5))
    assert (bigger.grid.nx, bigger.grid.ny) == (6, 5)
    assert len(bigger.scene.boxes) > len(Drive(DriveConfig(block=40.0)).scene.boxes)
    with pytest.raises(ConfigError, match='nx'):
        DriveConfig(route='no_revisit', nx=5)
    with pytest.raises(ConfigError, match='ny'):
        DriveConfig(ny=2.5)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match='route'):
        DriveConfig(route='spiral')


def test_options_reach_the_scans() -> None:
    options = {'block': 40.0, 'spacing': 10.0, 'route': [[0, 0], [2, 0], [2, 1]],
               'scene': 'lookalike', 'facade_detail': True, 'mount_pitch_deg': 3.0}
    config = DriveConfig(sensor=vlp16_like(points_per_ring=300), **options)
    assert config.route == ((0, 0), (2, 0), (2, 1)) and hash(config)  # frozen, hashable
    assert config.model.mount_pitch_deg == 3.0 and config.model.name == 'vlp16_like'
    drive = Drive(config)
    assert drive.grid.jitter == LOOKALIKE_JITTER and (drive.grid.nx, drive.grid.ny) == (3, 2)
    scans = list(simulate(seed=0, sensor=vlp16_like(points_per_ring=300), num_scans=2,
                          **options))
    np.testing.assert_array_equal(scans[1].cloud, drive.scan(1).cloud)
    assert scans[0].pose[2, 0] == pytest.approx(-np.sin(np.radians(3.0)))
    assert np.allclose(scans[0].pose[:2, 3], drive.grid.node(0, 0), atol=4.0)
    # A tilt given to the drive overrides the model's; None keeps it.
    tilted = vlp16_like(mount_roll_deg=4.0)
    assert DriveConfig(sensor=tilted).model.mount_roll_deg == 4.0
    assert DriveConfig(sensor=tilted, mount_roll_deg=0.0).model.tilted is False
