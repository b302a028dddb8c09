"""The simulated odometry: drifts like a real one by default, the same for the same seed, and
is the reference exactly when asked to be perfect."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.errors import ConfigError
from solid_ros.sim import DEMO_DEFAULTS, Drive, DriveConfig, OdometryDrift, simulate
from solid_ros.sim.odometry import drift_planar

SMALL = {'sensor': 'avia_like', 'block': 40.0, 'spacing': 10.0}


def _end_error_percent(drive: Drive) -> float:
    ref, odom = drive.poses(), drive.odometry_poses()
    path = float(np.sum(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1)))
    return 100.0 * float(np.linalg.norm(odom[-1, :3, 3] - ref[-1, :3, 3])) / path


def test_default_drift_is_one_to_two_percent_of_the_path() -> None:
    # The documented figures: the demo's revisits drive (1.13 km, back at its start).
    errors = [_end_error_percent(Drive(DriveConfig(**{**DEMO_DEFAULTS, 'seed': seed})))
              for seed in range(5)]
    assert all(1.0 <= e <= 2.0 for e in errors), errors
    assert 1.3 <= float(np.mean(errors)) <= 1.7, errors


def test_same_seed_same_odometry_and_another_seed_another() -> None:
    a = Drive(DriveConfig(seed=4, **SMALL)).odometry_poses()
    np.testing.assert_array_equal(a, Drive(DriveConfig(seed=4, **SMALL)).odometry_poses())
    b = Drive(DriveConfig(seed=5, **SMALL))
    assert not np.allclose(b.odometry_poses(), b.poses(), atol=0.05)
    assert not np.allclose(a[-1], Drive(DriveConfig(seed=5, **SMALL)).odometry_poses()[-1])
    drive = Drive(DriveConfig(seed=4, **SMALL))
    np.testing.assert_array_equal(drive.odometry(7), a[7])
    np.testing.assert_array_equal(drive.odometry(0), drive.pose(0))  # starts at the reference


def test_perfect_odometry_is_the_reference() -> None:
    drive = Drive(DriveConfig(perfect_odometry=True, **SMALL))
    np.testing.assert_array_equal(drive.odometry_poses(), drive.poses())
    scan = next(simulate(perfect_odometry=True, num_scans=1, **SMALL))
    np.testing.assert_array_equal(scan.odom, scan.pose)


def test_height_roll_and_pitch_stay_exact_on_a_tilted_sensor() -> None:
    drive = Drive(DriveConfig(mount_roll_deg=3.0, mount_pitch_deg=-4.0, **SMALL))
    ref, odom = drive.poses(), drive.odometry_poses()
    np.testing.assert_allclose(odom[:, 2, :], ref[:, 2, :], atol=1e-12)
    for R in odom[:, :3, :3]:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.max(np.linalg.norm(odom[:, :2, 3] - ref[:, :2, 3], axis=1)) > 0.5


def test_laps_beyond_the_route_keep_drifting() -> None:
    drive = Drive(DriveConfig(**SMALL))
    n = len(drive)
    scans = list(simulate(num_scans=n + 3, **SMALL))
    np.testing.assert_array_equal(np.stack([s.odom for s in scans[:n]]),
                                  drive.odometry_poses())
    np.testing.assert_array_equal(scans[n].pose, scans[0].pose)
    # The odometry goes on from where the lap ended: it does not restart at the reference.
    assert np.linalg.norm(scans[n].odom[:3, 3] - scans[0].odom[:3, 3]) > 0.1
    np.testing.assert_array_equal(drive.odometry_poses(2)[:n], drive.odometry_poses())


def test_drift_model_terms() -> None:
    xy = np.c_[np.arange(0.0, 101.0), np.zeros(101)]
    yaw = np.zeros(101)
    zero = np.zeros((101, 3))
    none = OdometryDrift(0.0, 0.0, 0.0, 0.0)
    got_xy, got_yaw = drift_planar(xy, yaw, none, zero)
    np.testing.assert_allclose(got_xy, xy, atol=1e-12)
    np.testing.assert_allclose(got_yaw, yaw, atol=1e-12)
    got_xy, _ = drift_planar(xy, yaw, OdometryDrift(0.02, 0.0, 0.0, 0.0), zero)
    assert got_xy[-1, 0] == pytest.approx(102.0)
    _, got_yaw = drift_planar(xy, yaw, OdometryDrift(0.0, 0.01, 0.0, 0.0), zero)
    assert np.degrees(got_yaw[-1]) == pytest.approx(1.0)  # 0.01 deg/m over 100 m
    rng = np.random.default_rng(0)
    ends = [drift_planar(xy, yaw, OdometryDrift(0.0, 0.0, 0.0, 0.1),
                         rng.standard_normal((101, 3)))[0][-1] for _ in range(400)]
    # A position random walk of 0.1 m per sqrt(m): 1 m standard deviation after 100 m.
    assert np.std(np.asarray(ends)[:, 1]) == pytest.approx(1.0, rel=0.15)


def test_bad_drift_values_are_refused() -> None:
    with pytest.raises(ConfigError, match='odom_scale_error'):
        DriveConfig(odom_scale_error=0.9)
    with pytest.raises(ConfigError, match='odom_heading_walk_deg'):
        DriveConfig(odom_heading_walk_deg=-1.0)
    with pytest.raises(ConfigError, match='perfect_odometry'):
        DriveConfig(perfect_odometry='yes')  # type: ignore[arg-type]
