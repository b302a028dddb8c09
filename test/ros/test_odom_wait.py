"""OdometryWait: the core's pairing plus the describe thread's short wait for late odometry."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from solid_ros.core.errors import PoseError
from solid_ros.core.odometry.track import usable_covariance
from solid_ros.ros.odom_wait import OdometryWait

SEC = 1_000_000_000
# Long enough that a call that does not wait is told apart from one that does on a loaded
# machine; the misses test waits it out three times.
WAIT = 1.0


def pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def timed_pair(odom: OdometryWait, stamp: int, wait: bool) -> tuple[object, float]:
    t0 = time.monotonic()
    sample, _ = odom.pair(stamp, wait=wait)
    return sample, time.monotonic() - t0


def test_pairs_the_nearest_pose_within_the_tolerance() -> None:
    odom = OdometryWait(tolerance_ns=SEC // 20, wait_sec=WAIT)
    assert odom.pair(10 * SEC, wait=False) == (None, None)  # no odometry yet
    odom.add(10 * SEC, pose(1.0), frame_id='odom')
    odom.add(11 * SEC, pose(2.0), frame_id='odom')
    sample, gap = odom.pair(10 * SEC + SEC // 50, wait=False)
    assert sample is not None and sample.pose[0, 3] == 1.0 and gap == SEC // 50
    assert odom.frame_id == 'odom' and odom.latest_stamp_ns == 11 * SEC
    # Beyond the tolerance: no pose, but the gap still tells how far off the odometry is.
    sample, gap = odom.pair(12 * SEC, wait=False)
    assert sample is None and gap == SEC
    odom.tolerance_ns = 2 * SEC  # odom_tolerance_sec is tunable while running
    sample, _ = odom.pair(12 * SEC, wait=False)
    assert sample is not None and sample.pose[0, 3] == 2.0


def test_covariance_is_kept_as_given_for_the_back_end_to_judge() -> None:
    odom = OdometryWait(tolerance_ns=SEC)
    s1 = odom.add(1 * SEC, pose(0.0), np.zeros(36))  # 'unknown' in ROS
    s2 = odom.add(2 * SEC, pose(0.0), np.eye(6).reshape(-1) * 0.01)
    assert s1.covariance is not None and usable_covariance(s1.covariance) is None
    assert s2.covariance is not None and s2.covariance.shape == (6, 6)
    assert usable_covariance(s2.covariance) is not None


def test_refuses_a_non_finite_pose_and_keeps_what_it_had() -> None:
    odom = OdometryWait(tolerance_ns=SEC)
    odom.add(1 * SEC, pose(1.0), frame_id='a')
    with pytest.raises(PoseError):
        odom.add(2 * SEC, pose(np.nan), frame_id='b')
    assert odom.latest_stamp_ns == 1 * SEC and odom.frame_id == 'a'


def test_no_wait_without_a_publisher_or_when_odometry_is_ahead() -> None:
    odom = OdometryWait(tolerance_ns=SEC, wait_sec=WAIT)
    _, took = timed_pair(odom, 5 * SEC, wait=False)
    assert took < WAIT / 2
    odom.add(6 * SEC, pose(0.0))  # already at or past the cloud: nothing to wait for
    sample, took = timed_pair(odom, 5 * SEC, wait=True)
    assert sample is not None and took < WAIT / 2


def test_waits_for_odometry_that_arrives_just_after_its_cloud() -> None:
    odom = OdometryWait(tolerance_ns=SEC // 20, wait_sec=5.0)
    odom.add(1 * SEC, pose(0.0))
    late = threading.Timer(0.05, lambda: odom.add(2 * SEC, pose(7.0)))
    late.start()
    try:
        sample, took = timed_pair(odom, 2 * SEC, wait=True)
    finally:
        late.join()
    # Woken by the message, long before the 5 s wait would end.
    assert sample is not None and sample.pose[0, 3] == 7.0
    assert 0.03 < took < 2.0


def test_a_silent_publisher_stops_the_waiting_after_max_misses_until_odometry_comes() -> None:
    odom = OdometryWait(tolerance_ns=SEC // 20, wait_sec=WAIT, max_misses=3)
    odom.add(1 * SEC, pose(0.0))
    for k in range(3):
        _, took = timed_pair(odom, (2 + k) * SEC, wait=True)
        assert took >= WAIT * 0.95  # waited the whole time, in vain
    _, took = timed_pair(odom, 5 * SEC, wait=True)
    assert took < WAIT / 2  # three misses in a row: no more waiting
    odom.add(5 * SEC, pose(0.0))  # odometry again: waiting resumes
    _, took = timed_pair(odom, 6 * SEC, wait=True)
    assert took >= WAIT * 0.95


def test_close_ends_a_wait_at_once() -> None:
    odom = OdometryWait(tolerance_ns=SEC, wait_sec=30.0)
    done: list[float] = []

    def describe() -> None:
        done.append(timed_pair(odom, 3 * SEC, wait=True)[1])

    thread = threading.Thread(target=describe)
    thread.start()
    time.sleep(0.05)
    odom.close()
    thread.join(timeout=5.0)
    assert done and done[0] < 5.0
    _, took = timed_pair(odom, 4 * SEC, wait=True)
    assert took < 1.0  # and no later wait either
