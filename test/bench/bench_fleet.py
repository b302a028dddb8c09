"""Traffic and latency of the multi-robot exchange on the three-robot drive.

Run: .venv/bin/python test/bench/bench_fleet.py

Runs the scenario of ``test/ros/fleet_processes.py`` (three solid_node processes in one
ROS domain on the simulated town, 64 beams x 512 points per ring, hdl64-like settings with
0.75 m keyframe clouds; robot 2 joins late and leaves) with a listener on the shared topics,
and prints:

- bytes per message on ``/solid/descriptors`` (per keyframe), ``/solid/cloud_requests`` and
  ``/solid/clouds`` (per verification against a peer): the ``UInt8MultiArray`` payload, plus
  16 bytes of CDR framing each (encapsulation, empty layout, data offset, length); DDS/RTPS
  headers (about 60-100 bytes a sample) come on top and are not counted;
- the exchange latency: cloud published to a robot -> that keyframe's descriptor seen on the
  shared topic (includes the robot's describe time), and cloud request -> reply;
- the total payload delivered to the robots (each message times the robots subscribed,
  listener excluded) against sending every keyframe's raw PointCloud2 to every other robot.

Figures depend on the machine's load; run on an idle machine.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parent / 'ros'), str(HERE)]

from fleet_processes import PHASES as DRIVE  # noqa: E402
from fleet_processes import Robots  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from report import PrintedReport, bench_meta  # noqa: E402
from std_msgs.msg import UInt8MultiArray  # noqa: E402
from test_peer_link import _check, _scan  # noqa: E402

from solid_ros.formats.peers import CloudReply, CloudRequest, DescriptorMessage, decode  # noqa: E402
from solid_ros.ros.peers import DESCRIPTOR_TOPIC, REPLY_TOPIC, REQUEST_TOPIC  # noqa: E402

CDR = 16  # encapsulation 4 + empty layout dim sequence 4 + data_offset 4 + data length 4


class Tap:
    """Listens on the shared topics and on the feeder's publishers."""

    def __init__(self, fleet: Robots) -> None:
        self.bytes: dict[str, list[int]] = {DESCRIPTOR_TOPIC: [], REQUEST_TOPIC: [],
                                            REPLY_TOPIC: []}
        self.published: dict[tuple[int, int], float] = {}  # (robot, stamp) -> wall time
        self.raw_cloud: dict[tuple[int, int], int] = {}  # (robot, stamp) -> message bytes
        self.descriptor_ms: list[float] = []
        self.requests: dict[int, float] = {}
        self.reply_ms: list[float] = []
        self.keyframes: set[tuple[int, int]] = set()
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        for topic in self.bytes:
            fleet.client.create_subscription(UInt8MultiArray, topic,
                                             lambda m, t=topic: self._on(t, m), qos)

    def _on(self, topic: str, msg: UInt8MultiArray) -> None:
        now = time.monotonic()
        raw = bytes(msg.data)
        self.bytes[topic].append(len(raw) + CDR)
        try:
            m = decode(raw)
        except Exception:  # the scenario's deliberate garbage
            return
        if isinstance(m, DescriptorMessage):
            key = (m.robot, m.stamp_ns)
            if key in self.published and key not in self.keyframes:
                self.descriptor_ms.append((now - self.published[key]) * 1e3)
            self.keyframes.add(key)
        elif isinstance(m, CloudRequest):
            self.requests[m.request_id] = now
        elif isinstance(m, CloudReply) and m.request_id in self.requests:
            self.reply_ms.append((now - self.requests.pop(m.request_id)) * 1e3)


class TimedPublisher:
    """Wraps a feeder publisher: records when each cloud went out and its size."""

    def __init__(self, pub: Any, robot: int, tap: Tap) -> None:
        self.pub, self.robot, self.tap = pub, robot, tap

    def publish(self, msg: Any) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.tap.raw_cloud[(self.robot, stamp)] = len(msg.data) + 64  # + header, fields
        self.tap.published[(self.robot, stamp)] = time.monotonic()
        self.pub.publish(msg)

    def get_subscription_count(self) -> int:
        return int(self.pub.get_subscription_count())


def _ms(values: list[float]) -> str:
    if not values:
        return 'n/a'
    q = statistics.quantiles(values, n=20) if len(values) > 1 else values * 19
    return f'median {statistics.median(values):.1f} ms, p95 {q[18]:.1f} ms (n={len(values)})'


def main() -> int:
    import argparse

    p = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    p.add_argument('--report', type=Path,
                   help='also write what is printed, with date and commit (.md: doc/reports)')
    args = p.parse_args()
    with PrintedReport(args.report, bench_meta('bench_fleet', vars(args))):
        return _run()


# The drive, with a fourth robot of other descriptor settings (refused) in its first phase.
PHASES = [{**DRIVE[0], 3: list(range(0, 5))}, *DRIVE[1:]]


def _run() -> int:
    for i in {i for ph in PHASES for s in ph.values() for i in s}:
        _scan(i)  # simulate first, so the feed keeps its pace
    with tempfile.TemporaryDirectory() as tmp:
        fleet = Robots(Path(tmp))
        tap = Tap(fleet)
        try:
            started = time.monotonic()
            for robot in (0, 1):
                fleet.start(robot)
                fleet.pubs[robot] = TimedPublisher(fleet.pubs[robot], robot, tap)
            fleet.start(3, '-p', 'num_angle:=90')  # other descriptor settings: refused
            fleet.drive(PHASES[0])
            fleet.start(2)
            fleet.pubs[2] = TimedPublisher(fleet.pubs[2], 2, tap)
            fleet.wait_for(lambda: int(fleet.stats(2).get('peer_descriptors_stored', 0))
                           >= len(fleet.sent[0]) + len(fleet.sent[1]), 'catch-up')
            fleet.drive(PHASES[1])
            fleet.stop(2)
            fleet.drive(PHASES[2])
            fleet.spin(1.0)
            wall = time.monotonic() - started
            found = {r: _check(fleet.loops[r], fleet.sent[r],
                               {p: fleet.sent[p] for p in (0, 1, 2) if p != r})
                     for r in (0, 1, 2)}
        finally:
            fleet.close()
    desc, req, rep = (tap.bytes[t] for t in (DESCRIPTOR_TOPIC, REQUEST_TOPIC, REPLY_TOPIC))
    robots = 3
    # Counted for two receivers each: the other two of robots 0-2 (robot 2 runs only in the
    # middle phase, the settings-mismatch node 3 throughout; neither is counted).
    delivered = (sum(desc) + sum(req) + sum(rep)) * (robots - 1)
    kf_raw = [tap.raw_cloud[k] for k in tap.keyframes if k in tap.raw_cloud]
    all_raw = list(tap.raw_cloud.values())  # robots 0-2 (robot 3 is not timed)
    print(f'three-robot drive: {len(all_raw)} clouds fed, {len(tap.keyframes)} keyframes '
          f'shared, {wall:.0f} s; inter-robot loops (correct, false) per robot: {found}')
    print(f'descriptor message: {statistics.median(desc):.0f} bytes per keyframe '
          f'({len(desc)} messages incl. catch-up)')
    if rep:
        print(f'cloud request: {statistics.median(req):.0f} bytes; cloud reply: median '
              f'{statistics.median(rep) / 1e3:.1f} kB, max {max(rep) / 1e3:.1f} kB '
              f'({len(rep)} replies)')
    print(f'latency cloud published -> its descriptor on {DESCRIPTOR_TOPIC}: '
          f'{_ms(tap.descriptor_ms)}')
    print(f'latency cloud request -> reply: {_ms(tap.reply_ms)}')
    print(f'raw PointCloud2 per keyframe: median {statistics.median(kf_raw) / 1e6:.2f} MB')
    print(f'payload delivered to robots: descriptors {sum(desc) * 2 / 1e6:.2f} MB, requests '
          f'{sum(req) * 2 / 1e6:.3f} MB, clouds {sum(rep) * 2 / 1e6:.2f} MB; total '
          f'{delivered / 1e6:.2f} MB')
    raw_kf = sum(kf_raw) * (robots - 1)
    raw_all = sum(all_raw) * (robots - 1)
    print(f'raw clouds to every other robot instead: keyframes {raw_kf / 1e6:.0f} MB '
          f'({raw_kf / delivered:.0f}x), every scan {raw_all / 1e6:.0f} MB '
          f'({raw_all / delivered:.0f}x)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
