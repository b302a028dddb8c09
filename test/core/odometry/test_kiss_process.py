"""KISS-ICP in a child process: the poses and counters of KissOdometry in this process, the
child ends with close(), and a child that died is restarted in a new segment (at most every
restart_sec; the clouds in between are refused with OdometryUnavailable), not a hang."""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from typing import Any

import numpy as np
import pytest

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import OdometryUnavailable
from solid_ros.core.odometry.kiss import KissOdometry
from solid_ros.sim import DEMO_SENSORS, Drive, DriveConfig

pytest.importorskip('kiss_icp', reason='kiss-icp is not installed')

from solid_ros.core.odometry import kiss_process  # noqa: E402
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
            t0 = time.monotonic()
            got = child.pose_for((i + 1) * SEC, cloud, t)
            took_ms = (time.monotonic() - t0) * 1e3
            assert want is not None and got is not None
            # The round trip split with the child's clock: three parts, within it.
            assert child.last_ms is not None and min(child.last_ms) >= 0.0
            assert child.last_ms[1] > 0.0 and sum(child.last_ms) <= took_ms
            assert got.stamp_ns == want.stamp_ns and got.segment == want.segment
            # TBB's parallel sums may differ in the last bits between two runs.
            np.testing.assert_allclose(got.pose, want.pose, atol=1e-6)
        assert child.pose_for(5 * SEC, None) is None
        assert (child.registered, child.deskewed, child.resets) == (4, 4, 0)
        assert child.config.kiss_voxel_size == here.config.kiss_voxel_size
    finally:
        child.close()
    assert not child._child.is_alive()


def test_a_killed_child_is_restarted_in_a_new_segment_at_the_last_pose(
        monkeypatch: pytest.MonkeyPatch) -> None:
    clouds = _clouds(6)
    now = [100.0]
    child = KissProcess(CONFIG, restart_sec=5.0, clock=lambda: now[0])
    try:
        before = [child.pose_for((i + 1) * SEC, clouds[i]) for i in range(3)]
        assert all(s is not None and s.segment == 0 for s in before)
        last = before[-1].pose  # type: ignore[union-attr]
        first_pid = child.pid
        assert first_pid is not None
        os.kill(first_pid, signal.SIGKILL)
        child._child.join(10.0)
        # The next clouds: a fresh child, a new segment from the last pose, counters go on.
        got = [child.pose_for((i + 1) * SEC, clouds[i]) for i in (3, 4)]
        assert child.pid not in (None, first_pid)
        assert got[0] is not None and got[1] is not None
        assert got[0].segment == got[1].segment == 1
        assert got[0].reason is not None and 'restarted' in got[0].reason
        assert 'exit code -9' in got[0].reason and got[1].reason is None
        # As KissOdometry here continues from that pose in that segment.
        here = KissOdometry(child.config, segment=1, pose=last)
        for i, sample in zip((3, 4), got):
            want = here.pose_for((i + 1) * SEC, clouds[i])
            assert want is not None
            np.testing.assert_allclose(sample.pose, want.pose, atol=1e-6)
        np.testing.assert_allclose(got[0].pose, last, atol=1e-9)
        assert not np.allclose(got[1].pose, last, atol=1e-3)  # it moves again
        assert (child.restarts, child.ended, child.resets, child.registered) == (1, 1, 1, 5)
        assert child.reset_counts == {'restart': 1}
        _dies_again_within_restart_sec(child, clouds[5], now, monkeypatch)
    finally:
        child.close()
    assert child.pid is None
    with pytest.raises(OdometryUnavailable, match='closed'):  # and no child starts
        child.pose_for(10 * SEC, clouds[5])
    assert child.pid is None and child.restarts == 2


def _dies_again_within_restart_sec(child: KissProcess, cloud: np.ndarray, now: list[float],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A child that ends with a cloud in it, then again before ``restart_sec``: skipped clouds
    (OdometryUnavailable), no restart until the clock allows it."""
    pid = child.pid
    assert pid is not None
    os.kill(pid, signal.SIGSTOP)  # it takes the cloud and never answers
    sent = threading.Event()
    real = kiss_process._send_once

    def send(conn: Any, item: Any) -> None:
        real(conn, item)
        sent.set()

    monkeypatch.setattr(kiss_process, '_send_once', send)
    refused: list[Exception] = []

    def register() -> None:
        try:
            child.pose_for(7 * SEC, cloud[:2000])  # small: the pipe holds it all
        except OdometryUnavailable as err:
            refused.append(err)

    waiting = threading.Thread(target=register)
    waiting.start()
    assert sent.wait(30.0)
    os.kill(pid, signal.SIGKILL)  # with the cloud in it
    waiting.join(30.0)
    assert len(refused) == 1 and re.search('ended .*exit code -9.*skipped', str(refused[0]))
    now[0] += 4.0
    with pytest.raises(OdometryUnavailable, match=r'restarts in 1\.0 s'):
        child.pose_for(8 * SEC, cloud)
    assert (child.restarts, child.ended, child.pid) == (1, 2, None)
    now[0] += 1.0
    sample = child.pose_for(9 * SEC, cloud)
    assert sample is not None and sample.segment == 2 and child.restarts == 2
    assert child.reset_counts == {'restart': 2}
