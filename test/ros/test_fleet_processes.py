"""Three solid_node processes in one ROS domain find each other's places (issue: multi-robot).

Each robot drives its own stretches of the simulated town (64-beam, 360 degrees), at its own
times: robots 0 and 1 map different streets; robot 2 joins late and drives streets of both,
one of them in the opposite direction; then robot 2 leaves and robots 0 and 1 drive streets
the others mapped. A fourth process with other descriptor settings and a stream of garbage
on the shared topics run alongside. Every inter-robot loop is checked against the
simulator's relative pose (1 m, 3 degrees); none may be false and each robot must find some.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from polling import wait_until  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy_msgs import make_cloud  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Float64MultiArray, UInt8MultiArray  # noqa: E402
from test_peer_link import _check, _scan  # noqa: E402

from solid_ros.formats.candidates import decode_candidates  # noqa: E402

# Scans of the simulated drive each robot covers, phase by phase (see the module docstring).
PHASES: list[dict[int, list[int]]] = [
    {0: [*range(0, 101), *range(317, 364)], 1: list(range(135, 241)), 3: list(range(0, 5))},
    {2: [*range(268, 316), *range(477, 531), *range(797, 820)]},
    {0: list(range(759, 794)), 1: list(range(268, 301))},
]
PARAMS = """/**:
  ros__parameters:
    peers: true
    use_odom: false
    qos_reliability: 'reliable'
    qos_depth: 1000
    queue_size: 1000
    exclude_recent_frames: 20
    num_candidates: 5
    distance_threshold: 1.0
    verify_voxel_size: 0.75
    verify_coarse_voxel_size: 2.0
    peer_timeout_sec: 2.0
    diagnostics_period_sec: 0.5
"""


class Robots:
    """The node processes and one in-test client that feeds them and listens."""

    def __init__(self, tmp: Path) -> None:
        self.domain = random.randint(50, 200)
        self.env = {**os.environ, 'ROS_DOMAIN_ID': str(self.domain)}
        self.params = tmp / 'fleet.yaml'
        self.params.write_text(PARAMS)
        self.procs: dict[int, subprocess.Popen[bytes]] = {}
        self.logs: dict[int, Path] = {}
        self.tmp = tmp
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=self.domain)
        self.client = Node('fleet_feeder', context=self.ctx)
        self.qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.pubs: dict[int, Any] = {}
        self.loops: dict[int, list[dict[str, Any]]] = {}
        self.diag: dict[str, dict[str, str]] = {}
        self.client.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)
        self.garbage = self.client.create_publisher(UInt8MultiArray, '/solid/descriptors',
                                                    self.qos)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.client)
        self.sent: dict[int, list[int]] = {}

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for st in msg.status:
            self.diag[st.name.split(':')[0]] = {kv.key: kv.value for kv in st.values}

    def start(self, robot: int, *extra: str) -> None:
        self.logs[robot] = self.tmp / f'r{robot}.log'
        cmd = [sys.executable, '-m', 'solid_ros.ros.node', '--ros-args', '-r',
               f'__ns:=/r{robot}', '--params-file', str(self.params), '-p',
               f'session_id:={robot}', *extra]
        self.procs[robot] = subprocess.Popen(cmd, env=self.env, stdout=self.logs[robot].open('w'),
                                             stderr=subprocess.STDOUT)
        self.loops[robot] = []
        self.sent[robot] = []
        self.pubs[robot] = self.client.create_publisher(PointCloud2, f'/r{robot}/points',
                                                        self.qos)
        self.client.create_subscription(
            Float64MultiArray, f'/r{robot}/solid_node/loop_candidates',
            lambda m, r=robot: self.loops[r].extend(decode_candidates(m)), self.qos)
        self.wait_for(lambda: self.pubs[robot].get_subscription_count() > 0,
                      f'robot {robot} up', 60.0)

    def stop(self, robot: int) -> None:
        proc = self.procs.pop(robot)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)

    def spin(self, seconds: float = 0.0) -> None:
        end = time.monotonic() + seconds
        self.executor.spin_once(timeout_sec=0.01)
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.01)

    def wait_for(self, pred: Callable[[], bool], what: str, timeout: float = 240.0) -> None:
        wait_until(pred, what, timeout, step=lambda: self.spin(0.05), check=self._alive)

    def _alive(self) -> None:
        for r, p in self.procs.items():
            assert p.poll() is None, f'robot {r} died:\n{self.logs[r].read_text()[-3000:]}'

    def stats(self, robot: int) -> dict[str, str]:
        return self.diag.get(f'/r{robot}/solid_node', {})

    def drive(self, phase: dict[int, list[int]], rate_hz: float = 10.0) -> None:
        """Publish the robots' scans interleaved, then wait until each node is through."""
        queues = {r: list(s) for r, s in phase.items()}
        while any(queues.values()):
            for r, q in queues.items():
                if q:
                    i = q.pop(0)
                    pts, _, stamp = _scan(i)
                    self.pubs[r].publish(make_cloud(pts, stamp))
                    self.sent[r].append(i)
            self.spin(1.0 / rate_hz)
        for r in phase:
            self.wait_for(lambda r=r: self.stats(r).get('clouds_processed') == str(
                len(self.sent[r])) and self.stats(r).get('verify_queue_length') == '0'
                and self.stats(r).get('queue_length') == '0', f'robot {r} done')
        self.spin(1.5)  # the last loop messages

    def close(self) -> None:
        for r in list(self.procs):
            self.stop(r)
        self.executor.shutdown()
        self.client.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def test_three_robots_publish_correct_inter_robot_loops(tmp_path: Path) -> None:
    for i in {i for ph in PHASES for s in ph.values() for i in s}:
        _scan(i)  # simulate first, so the feed keeps its pace
    fleet = Robots(tmp_path)
    try:
        fleet.start(0)
        fleet.start(1)
        fleet.start(3, '-p', 'num_angle:=90')  # other descriptor settings
        junk = UInt8MultiArray()
        junk.data = b'SLD1\x01not a descriptor'
        fleet.garbage.publish(junk)
        fleet.drive(PHASES[0])
        fleet.start(2)  # late joiner: catches up on what 0 and 1 stored
        fleet.wait_for(lambda: int(fleet.stats(2).get('peer_descriptors_stored', 0))
                       >= len(fleet.sent[0]) + len(fleet.sent[1]), 'catch-up of robot 2')
        fleet.drive(PHASES[1])
        fleet.stop(2)  # robot 2 leaves mid-run
        fleet.drive(PHASES[2])
        fleet.spin(1.0)
        peers_of = {r: {p: fleet.sent[p] for p in (0, 1, 2) if p != r} for r in (0, 1, 2)}
        found = {}
        for r in (0, 1, 2):
            found[r] = _check(fleet.loops[r], fleet.sent[r], peers_of[r])
        assert all(bad == 0 for _, bad in found.values()), found
        assert all(good >= 5 for good, _ in found.values()), found
        print('inter-robot loops (correct, false):', found)
        for r in (0, 1):
            s = fleet.stats(r)
            assert int(s.get('peer_descriptors_refused', 0)) >= 1, s  # robot 3's settings
            assert int(s.get('peer_malformed', 0)) >= 1, s  # the garbage
            assert int(s.get('peer_clouds_received', 0)) >= 1, s
        print('robot 1 peer counters:', {k: v for k, v in fleet.stats(1).items()
                                         if k.startswith('peer_')})
    finally:
        fleet.close()
