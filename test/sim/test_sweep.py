"""A sweep cast while the sensor moves, and KISS-ICP's deskew of it: with the true motion the
deskewed points land on the static scene at the sweep's end, with the motion reversed they land
farther than the raw points. It fails if the sweep's conventions (time direction, frame of
each sector, reference at the end) or KISS-ICP's (deskew to the sweep's end, times normalised
over the sweep) change, or if the odometry adapter stops passing the times as KISS-ICP's
pipeline does."""

from __future__ import annotations

import subprocess
import sys
from functools import lru_cache

import numpy as np
import numpy.typing as npt
import pytest
from scipy.spatial import cKDTree

from solid_ros.core.config import NodeConfig
from solid_ros.sim import DEMO_SENSORS, Drive, DriveConfig
from solid_ros.sim.lidar import cast_scan
from solid_ros.sim.sweep import moving_sweep, pose_at, ramp

FloatArray = npt.NDArray[np.float64]

needs_kiss = pytest.mark.skipif(
    subprocess.run([sys.executable, '-c', 'import kiss_icp.kiss_icp'],
                   capture_output=True).returncode != 0, reason='kiss-icp is not installed')

GROUND_Z = -1.4  # below this (sensor frame) is the simulator's exact ground plane


@lru_cache(maxsize=1)
def _drive() -> Drive:
    # 1.5 m per 0.1 s sweep (54 km/h): a point's position moves up to 1.5 m during the sweep.
    return Drive(DriveConfig(seed=0, sensor=DEMO_SENSORS['hdl64'], block=50.0, spacing=1.5))


@lru_cache(maxsize=4)
def _sweep(index: int) -> tuple[FloatArray, FloatArray]:
    return moving_sweep(_drive(), index, 16, min_z=GROUND_Z)


def test_a_sweep_has_times_over_one_turn_and_ends_at_the_scan_pose() -> None:
    points, times = _sweep(20)
    assert points.shape[1] == 3 and len(points) == len(times) > 10000
    assert times.min() < 0.05 and times.max() > 0.95  # (straight behind: the open street)
    # Time follows the azimuth counter-clockwise from behind the sensor.
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    np.testing.assert_allclose(times, (azimuth + np.pi) / (2 * np.pi))
    with pytest.raises(ValueError):
        moving_sweep(_drive(), 0)
    with pytest.raises(ValueError):
        moving_sweep(_drive(), 3.0, start=4.0)


def test_places_between_scans_and_a_drive_from_standing() -> None:
    drive = _drive()
    np.testing.assert_allclose(pose_at(drive, 20.0), drive.pose(20), atol=1e-12)
    half = pose_at(drive, 20.5)
    np.testing.assert_allclose(half[:3, 3], (drive.pose(20)[:3, 3] + drive.pose(21)[:3, 3]) / 2)
    # Standing 5 sweeps, then 4 m/s^2 up to 1.5 m per 0.1 s sweep (37.5 sweeps at 0.04 m more
    # each), in scans of 1.5 m.
    ends = ramp(1.5, 60, rest=5, accel=4.0)
    steps = np.diff(np.r_[0.0, ends])
    assert np.all(steps[:5] == 0.0) and np.all(np.diff(steps) >= -1e-12)
    np.testing.assert_allclose(steps[5], 0.4 * 0.1 / 1.5)
    np.testing.assert_allclose(steps[45:], 1.0)


@needs_kiss
def test_kiss_deskew_with_the_true_motion_lands_the_sweep_on_the_static_scene() -> None:
    from solid_ros.core.odometry.kiss import load_kiss_icp

    KissICP, KISSConfig, _ = load_kiss_icp()
    kc = KISSConfig()
    kc.data.max_range, kc.data.deskew = 30.0, True  # near points: the reference is dense
    kc.mapping.voxel_size = 0.3
    preprocessor = KissICP(kc).preprocessor
    drive, i = _drive(), 20
    points, times = _sweep(i)
    t = drive.trajectory
    # The static scene seen from the sweep's end pose, four times denser than a scan.
    dense = drive.model.replace(points_per_ring=4 * drive.model.points_per_ring)
    scene = cast_scan(drive.scene, dense, float(t.xy[i, 0]), float(t.xy[i, 1]),
                      float(t.yaw[i]), None)[:, :3].astype(np.float64)
    tree = cKDTree(scene[scene[:, 2] > GROUND_Z])
    step = np.linalg.inv(drive.pose(i - 1)) @ drive.pose(i)

    def mean_distance(delta: FloatArray) -> float:
        deskewed = np.asarray(preprocessor.preprocess(points, times, delta))
        return float(np.mean(tree.query(deskewed)[0]))

    raw, true, reversed_ = (mean_distance(d) for d in (np.eye(4), step, np.linalg.inv(step)))
    # Measured: raw 0.16 m, true motion 0.06 m, reversed 0.34 m.
    assert true < 0.5 * raw and true < 0.1, (raw, true)
    assert reversed_ > 1.5 * raw, (raw, reversed_)


@needs_kiss
def test_the_adapter_deskews_as_kiss_icp_does() -> None:
    from solid_ros.core.odometry.kiss import KissOdometry, load_kiss_icp

    KissICP, KISSConfig, _ = load_kiss_icp()
    sweeps = [_sweep(i) for i in (1, 2, 3)]
    odo = KissOdometry(NodeConfig(kiss_deskew=True))
    kc = KISSConfig()
    kc.data.deskew = True
    kiss = None
    for k, (points, times) in enumerate(sweeps):
        # A NaN row with its time: the adapter drops both, KISS-ICP never sees them.
        with_nan = np.r_[points, np.full((1, 3), np.nan)]
        sample = odo.pose_for(k + 1, with_nan, np.r_[times, 0.5])
        if kiss is None:
            kc.data.max_range = odo.config.kiss_max_range
            kc.data.min_range = odo.config.kiss_min_range
            kc.mapping.voxel_size = odo.config.kiss_voxel_size
            kiss = KissICP(kc)
        kiss.register_frame(points, times)
        assert sample is not None and sample.reason is None
        np.testing.assert_allclose(sample.pose, kiss.last_pose, rtol=0.0, atol=1e-6)
    assert kiss is not None and np.linalg.norm(kiss.last_delta[:3, 3]) > 1.0  # it deskewed
