"""Three solid_node processes in one ROS domain, and the client that feeds them: the drive and
the harness of ``test_fleet_align_processes`` (issue: multi-robot; one run of the processes
checks the loops and the alignment, since each run takes a minute of CI).

Each robot drives its own stretches of the simulated town (64-beam, 360 degrees), at its own
times: robots 0 and 1 map different streets; robot 2 joins late and drives streets of both,
one of them in the opposite direction; then robot 2 leaves and robots 0 and 1 drive streets
the others mapped. The client can also send garbage on the shared descriptor topic.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from polling import wait_until
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy_msgs import make_cloud
from ros_domains import pick_domain
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray, UInt8MultiArray
from test_peer_link import _scan

from solid_ros.formats.candidates import decode_candidates

# Scans of the simulated drive each robot covers, phase by phase (see the module docstring).
PHASES: list[dict[int, list[int]]] = [
    {0: [*range(0, 101), *range(317, 364)], 1: list(range(135, 241))},
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
        self.domain = pick_domain()
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

    settle_sec = 1.5  # after a phase: the last loop messages

    def before_cloud(self, robot: int, pose: Any, stamp: int) -> None:
        """Called before each cloud goes out (nothing here; e.g. its odometry)."""

    def drive(self, phase: dict[int, list[int]], rate_hz: float = 10.0) -> None:
        """Publish the robots' scans interleaved, then wait until each node is through."""
        queues = {r: list(s) for r, s in phase.items()}
        while any(queues.values()):
            for r, q in queues.items():
                if q:
                    i = q.pop(0)
                    pts, pose, stamp = _scan(i)
                    self.before_cloud(r, pose, stamp)
                    self.pubs[r].publish(make_cloud(pts, stamp))
                    self.sent[r].append(i)
            self.spin(1.0 / rate_hz)
        for r in phase:
            self.wait_for(lambda r=r: self.stats(r).get('clouds_processed') == str(
                len(self.sent[r])) and self.stats(r).get('verify_queue_length') == '0'
                and self.stats(r).get('queue_length') == '0', f'robot {r} done')
        self.spin(self.settle_sec)

    def close(self) -> None:
        for r in list(self.procs):
            self.stop(r)
        self.executor.shutdown()
        self.client.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
