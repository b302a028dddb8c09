"""solid_node with ``odometry_source: kiss_icp`` over real rclpy pub/sub: KISS-ICP registers on
the node's odometry thread (in a process of its own), and the clouds' per-point times reach it
for deskew when they carry a time field."""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')
pytest.importorskip('kiss_icp', reason='kiss-icp is not installed')

import test_node  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402

from solid_ros.sim.drive import Drive, DriveConfig  # noqa: E402

Harness = test_node.Harness
domain_id, harness = test_node.domain_id, test_node.harness

SEC = 1_000_000_000
KISS = [Parameter('odometry_source', value='kiss_icp')]


def timed_cloud(points: np.ndarray, stamp_ns: int, field: str | None) -> PointCloud2:
    """x y z float32 and, with ``field``, a uint32 per-point time in ns: the azimuth's share of
    a 0.1 s sweep, as a spinning sensor stamps its points."""
    names = [('x', '<f4'), ('y', '<f4'), ('z', '<f4')]
    if field is not None:
        names.append((field, '<u4'))
    rec = np.zeros(len(points), dtype=names)
    for k, axis in enumerate('xyz'):
        rec[axis] = points[:, k]
    if field is not None:
        azimuth = np.arctan2(points[:, 1], points[:, 0]) + np.pi
        rec[field] = (azimuth / (2 * np.pi) * 1e8).astype(np.uint32)
    msg = PointCloud2()
    msg.header.frame_id = 'lidar'
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, SEC)
    msg.height, msg.width = 1, len(points)
    types = {'<f4': PointField.FLOAT32, '<u4': PointField.UINT32}
    msg.fields = [PointField(name=n, offset=rec.dtype.fields[n][1], datatype=types[t], count=1)
                  for n, t in names]
    msg.point_step = rec.dtype.itemsize
    msg.row_step = msg.point_step * len(points)
    msg.data = rec.tobytes()
    return msg


def _run(harness: Callable[..., Harness], field: str | None,
         extra: list[Parameter] | None = None,
         then: Callable[[Harness, list[Odometry], Drive], None] | None = None
         ) -> dict[str, str]:
    h = harness(KISS + (extra or []), params_file=None)
    odometry: list[Odometry] = []
    h.client.create_subscription(Odometry, '/solid_node/kiss/odometry', odometry.append, 100)
    drive = Drive(DriveConfig(seed=0, sensor='hdl64'))
    h.replay([('points', timed_cloud(drive.scan(i).points, (i + 1) * SEC, field))
              for i in range(4)])
    h.wait_for(lambda: len(odometry) == 4, 'an odometry message per cloud', 30.0)
    # Diagnostics published after the last cloud went through (an older message may come last).
    h.wait_for(lambda: (h.status().get('kiss_registered'), h.status().get('clouds_processed'))
               == ('4', '4'), 'diagnostics', 30.0)
    status = h.status()
    # Registration ran on the node's odometry thread, KISS-ICP itself in another process.
    assert 'solid_odometry' in {t.name for t in threading.enumerate()}
    pid = h.node._kiss._source.pid  # type: ignore[union-attr]
    assert pid is not None and pid != os.getpid()
    assert status['odometry_queue_length'] == '0' and status['odometry_skipped'] == '0'
    assert status['odometry_ms_p50'] != 'nan'
    # The stage's time holds the child's (its clock splits the round trip) and the hand-over.
    assert 0 < float(status['kiss_icp_ms_p50']) <= float(status['odometry_ms_p50'])
    assert 0 < float(status['kiss_handover_ms_p50']) <= float(status['odometry_ms_p50'])
    assert status['clouds_without_odom'] == '0'
    if then is not None:
        then(h, odometry, drive)
    return status


def _kill_kiss_icp(h: Harness, odometry: list[Odometry], drive: Drive) -> None:
    """KISS-ICP's process killed after cloud 4: clouds 5 and 6 get poses from a new one, in a
    new segment that starts at cloud 4's pose, and become keyframes of the back end."""
    source = h.node._kiss._source  # type: ignore[union-attr]
    keyframes, stored = int(h.status()['backend_keyframes']), int(h.status()['database_size'])
    pid = source.pid
    assert pid is not None and h.status()['kiss_restarts'] == '0'
    os.kill(pid, signal.SIGKILL)
    source._child.join(10.0)
    h.replay([('points', timed_cloud(drive.scan(i).points, (i + 1) * SEC, None))
              for i in (4, 5)])
    h.wait_for(lambda: len(odometry) == 6, 'odometry from the restarted process', 30.0)
    assert source.pid not in (None, pid)
    h.wait_for(lambda: (h.status().get('kiss_restarts'), h.status().get('clouds_processed'))
               == ('1', '6'), 'diagnostics after the restart', 30.0)
    status = h.status()
    assert status['kiss_reset_restart'] == '1' and status['odometry_skipped'] == '0'
    assert status['kiss_registered'] == '6' and status['clouds_failed'] == '0'
    assert int(status['backend_keyframes']) > keyframes and int(status['database_size']) > stored
    assert odometry[4].pose.pose == odometry[3].pose.pose  # the new segment's start


@pytest.mark.parametrize('field', ['t', 'offset_time'])
def test_per_point_times_of_the_cloud_reach_kiss_icp(harness: Callable[..., Harness],
                                                     field: str) -> None:
    status = _run(harness, field)
    assert status['kiss_deskewed'] == '4'


def test_a_cloud_without_a_time_field_is_registered_without_deskew_and_a_killed_kiss_icp_restarts(
        harness: Callable[..., Harness]) -> None:
    status = _run(harness, None, [Parameter('backend', value=True)], then=_kill_kiss_icp)
    assert status['kiss_deskewed'] == '0'


def test_kiss_deskew_off_sends_no_times_and_kiss_time_field_names_the_field(
        harness: Callable[..., Harness]) -> None:
    status = _run(harness, 'stamp_ns', [Parameter('kiss_time_field', value='stamp_ns'),
                                        Parameter('kiss_deskew', value=False)])
    assert status['kiss_deskewed'] == '0'


def test_kiss_time_field_names_a_field_the_usual_names_miss(
        harness: Callable[..., Harness]) -> None:
    status = _run(harness, 'stamp_ns', [Parameter('kiss_time_field', value='stamp_ns')])
    assert status['kiss_deskewed'] == '4'


def test_external_odometry_has_no_odometry_thread(harness: Callable[..., Harness]) -> None:
    h = harness([], params_file=None)
    assert h.node._stages.odometry_waiting is None
    h.wait_for(lambda: 'queue_length' in h.status(), 'diagnostics', 30.0)
    assert 'odometry_queue_length' not in h.status()
