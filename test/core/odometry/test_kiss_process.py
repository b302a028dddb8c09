"""KISS-ICP in a child process: the poses and counters of KissOdometry in this process, the
child ends with close(), and a child that died is an error the caller sees, not a hang."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import SolidError
from solid_ros.core.odometry.kiss import KissOdometry
from solid_ros.sim import DEMO_SENSORS, Drive, DriveConfig

pytest.importorskip('kiss_icp', reason='kiss-icp is not installed')

from solid_ros.core.odometry.kiss_process import KissProcess  # noqa: E402

SEC = 1_000_000_000
CONFIG = NodeConfig(kiss_max_range=50.0, kiss_voxel_size=0.5)


def _clouds(count: int) -> list[np.ndarray]:
    drive = Drive(DriveConfig(seed=0, sensor=DEMO_SENSORS['hdl64'], block=50.0, spacing=1.0))
    out = []
    for i in range(count):
        pts = drive.scan(i).points
        out.append(pts[pts[:, 2] > -1.5])  # no ground rings (see test_kiss.py)
    return out


def test_the_child_gives_the_poses_and_counters_of_kiss_odometry_here() -> None:
    clouds = _clouds(4)
    times = [np.linspace(0.0, 1.0, len(c)) for c in clouds]
    here = KissOdometry(CONFIG)
    child = KissProcess(CONFIG)
    try:
        assert child.pid is not None and child.pid != os.getpid()
        for i, (cloud, t) in enumerate(zip(clouds, times)):
            want = here.pose_for((i + 1) * SEC, cloud, point_times=t)
            got = child.pose_for((i + 1) * SEC, cloud, t)
            assert want is not None and got is not None
            assert got.stamp_ns == want.stamp_ns and got.segment == want.segment
            # TBB's parallel sums may differ in the last bits between two runs.
            np.testing.assert_allclose(got.pose, want.pose, atol=1e-6)
        assert child.pose_for(5 * SEC, None) is None
        assert (child.registered, child.deskewed, child.resets) == (4, 4, 0)
        assert child.config.kiss_voxel_size == here.config.kiss_voxel_size
    finally:
        child.close()
    assert not child._child.is_alive()


def test_a_child_that_died_raises_solid_error() -> None:
    child = KissProcess(CONFIG)
    try:
        assert child.pid is not None
        os.kill(child.pid, signal.SIGKILL)
        child._child.join(10.0)
        with pytest.raises(SolidError, match='KISS-ICP process ended'):
            child.pose_for(SEC, _clouds(1)[0])
    finally:
        child.close()
