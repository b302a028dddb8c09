"""End-to-end latency of solid_node: PointCloud2 published -> loop-candidate message received.

Run: .venv/bin/python test/bench/bench_node_latency.py [--duration 30] [--rates 10,15,20,30]

The node runs in its own process (``python -m solid_ros.ros.node``, HDL-64 preset) with settings
that make every scan a query with one candidate (exclude_recent_frames 0, threshold 2.0), so
each published cloud yields one candidate message. By default registration is off
(``verify:=false``): the descriptor path alone; ``--verify`` measures the time to a verified
loop (every scan is the same place turned, so every candidate is registered); ``--backend``
publishes an Odometry before each cloud (the sensor turning in place) so that the preset's
back end takes every keyframe and its loops after they are published; ``--kiss`` lets the
node register every cloud with KISS-ICP instead (``odometry_source: kiss_icp``).

The Odometry comes from a process of its own, as from an odometry stack beside the LiDAR
driver. Sent by the participant that sends the clouds, over Fast DDS's default transport
(shared memory on one machine: the kernel counted only discovery's ~200 UDP datagrams, none
dropped), a third of the odometry samples were lost (a best-effort reader got 130 of 200)
and a reliable reader got them up to 2.8 s late: the writer repairs a loss on its next
heartbeat (every 3 s), and later samples wait in order. Losses stop with the odometry in a
participant of its own, or with the 32 MB segment of ``config/fastdds_shm.xml``: the 1.5 MB
clouds overrun that participant's 512 KB segment.

The publisher sends KITTI scan 313 (~121k points), rotated and jittered per message, at 10 Hz
for ``--duration`` seconds and prints median / p95 / max latency and the skipped-cloud count
from /diagnostics; then it steps the rate up (``--rates``) to find the highest rate
sustained without skips. Timings are noisy on a shared machine; re-run on an idle one for
published figures.

Before the node, the same publisher runs for ``--duration`` seconds against an echo process
(a bare rclpy subscriber with the node's QoS and allocator tuning that answers each cloud at
once): the transport floor, what any subscriber pays for the cloud to arrive. The node's own
share is its median minus that floor. ``--no-floor`` skips it.
"""

from __future__ import annotations

import argparse
import array
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / 'shared' / 'data'
NS = 1_000_000_000
_ECHO_TOPIC = '/solid_latency_echo'


def _variants(points: np.ndarray, count: int, seed: int = 0) -> tuple[list[bytes], list[float]]:
    """The scan turned by angles ``a`` (and jittered), and the angles: the sensor's heading in
    the scan's frame is ``-a``. Consecutive angles, and the last and the first, lie 7/16 of a
    turn +- 6 deg apart, so that with odometry every cloud is a keyframe (the presets take one
    every 10 deg): random ones left one in 18 within 10 deg of the one before, without a loop
    to wait for."""
    rng = np.random.default_rng(seed)
    out, angles = [], []
    for k in range(count):
        a = (k * 7 / 16 * 2 * np.pi + rng.uniform(-0.05, 0.05)) % (2 * np.pi) - np.pi
        rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0],
                        [0.0, 0.0, 1.0]])
        pts = points @ rot.T + rng.normal(scale=0.02, size=points.shape)
        out.append(np.ascontiguousarray(pts, dtype='<f4').tobytes())
        angles.append(float(a))
    return out, angles


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--duration', type=float, default=30.0, help='seconds at 10 Hz')
    parser.add_argument('--rates', default='15,20,30,40,60,80',
                        help='rates (Hz) tried after 10 Hz to find the sustained maximum')
    parser.add_argument('--step-duration', type=float, default=10.0,
                        help='seconds per stepped rate')
    parser.add_argument('--verify', action='store_true',
                        help='keep registration on: latency to a verified loop (default: '
                             'verify:=false, the descriptor path alone)')
    parser.add_argument('--backend', action='store_true',
                        help="publish an Odometry with each cloud (the sensor's heading, in "
                             "place), so the preset's back end runs: every keyframe goes "
                             'into the pose graph after its loops are published')
    parser.add_argument('--kiss', action='store_true',
                        help='odometry_source kiss_icp: the node registers every cloud with '
                             'KISS-ICP (on its describe thread) and runs the back end on it')
    parser.add_argument('--no-floor', action='store_true',
                        help='skip the transport floor (echo process) run')
    parser.add_argument('--scan', type=Path, default=DATA / 'kitti' / 'pcd' / '000313.pcd',
                        help='the PCD published (default: KITTI scan 313 in the shared data '
                             'beside the project; a git worktree elsewhere passes it)')
    parser.add_argument('--echo', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--odometry', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.echo:
        return echo()
    if args.odometry:
        return odometry()
    pcd = args.scan
    if not pcd.is_file():
        print(f'KITTI scan not found at {pcd}; nothing to measure', file=sys.stderr)
        return 1

    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Float64MultiArray

    from solid_ros.formats.candidates import decode_candidates
    from solid_ros.formats.pointfiles import read_pcd

    points = read_pcd(pcd).astype(np.float64)
    variants, angles = _variants(points, 16)
    domain = str(random.randint(1, 100))
    os.environ['ROS_DOMAIN_ID'] = domain
    node_cmd = [sys.executable, '-m', 'solid_ros.ros.node', '--ros-args', '--params-file',
                str(ROOT / 'config' / 'hdl64.yaml'), '-p', 'exclude_recent_frames:=0',
                '-p', 'distance_threshold:=2.0', '-p', 'qos_reliability:=reliable',
                '-p', f'use_odom:={"true" if args.backend or args.kiss else "false"}',
                *(['-p', 'odometry_source:=kiss_icp'] if args.kiss else []),
                '-p', 'diagnostics_period_sec:=0.5',
                '-p', f'verify:={"true" if args.verify else "false"}']
    proc: subprocess.Popen[str] | None = None

    rclpy.init()
    node = Node('solid_latency_bench')
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(PointCloud2, '/points', qos)
    odom_proc: subprocess.Popen[str] | None = None
    sent: dict[int, float] = {}
    latency: dict[int, float] = {}
    diag: dict[str, str] = {}
    lock = threading.Lock()

    def on_cands(msg: Float64MultiArray) -> None:
        now = time.perf_counter()
        for c in decode_candidates(msg):
            with lock:
                t0 = sent.get(int(c['query_stamp_ns']))
                if t0 is not None:
                    latency[int(c['query_stamp_ns'])] = (now - t0) * 1e3

    def on_diag(msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name.startswith('/solid_node'):
                diag.update({kv.key: kv.value for kv in s.values})

    def on_echo(msg: Float64MultiArray) -> None:
        now = time.perf_counter()
        with lock:
            t0 = sent.get(int(msg.data[0]))
            if t0 is not None:
                latency[int(msg.data[0])] = (now - t0) * 1e3

    node.create_subscription(Float64MultiArray, '/solid_node/loop_candidates', on_cands, 100)
    node.create_subscription(Float64MultiArray, _ECHO_TOPIC, on_echo, 100)
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()

    msg = PointCloud2(height=1, width=len(points), point_step=12, row_step=12 * len(points),
                      is_dense=True)
    msg.header.frame_id = 'velodyne'
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, n in enumerate('xyz')]
    datas = [array.array('B', v) for v in variants]
    stamp = [1_000 * NS]

    def run(rate: float, duration: float) -> tuple[np.ndarray, int, int]:
        with lock:
            sent.clear()
            latency.clear()
        skipped0 = int(diag.get('clouds_skipped', 0))
        n = int(rate * duration)
        start = time.perf_counter()
        for i in range(n):
            target = start + i / rate
            while (wait := target - time.perf_counter()) > 0:
                time.sleep(wait)
            stamp[0] += NS // int(rate)
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp[0], NS)
            msg.data = datas[i % len(datas)]
            if odom_proc is not None:  # the odometry first, so that the node pairs it at once
                assert odom_proc.stdin is not None
                odom_proc.stdin.write(f'{stamp[0]} {-angles[i % len(angles)]!r}\n')
                odom_proc.stdin.flush()
            with lock:
                sent[stamp[0]] = time.perf_counter()
            pub.publish(msg)
        time.sleep(1.5)  # let the last results and a diagnostics message arrive
        with lock:
            lat = np.array(sorted(latency.values()))
            missing = len(sent) - len(latency)
        return lat, int(diag.get('clouds_skipped', 0)) - skipped0, missing

    floor = math.nan
    try:
        if not args.no_floor:
            echo_proc = subprocess.Popen([sys.executable, __file__, '--echo'],
                                         env=dict(os.environ))
            try:
                _wait_for_subscriber(pub, echo_proc)
                run(10.0, 2.0)
                lat, _, missing = run(10.0, args.duration)
                floor = float(np.median(lat))
                print(f'transport floor (echo process, no processing), 10 Hz: median '
                      f'{floor:.1f} ms, p95 {np.percentile(lat, 95):.1f} ms, without answer '
                      f'{missing}')
            finally:
                echo_proc.send_signal(signal.SIGINT)
                echo_proc.wait(timeout=20)
            while pub.get_subscription_count() > 0:  # the echo's subscription must be gone
                time.sleep(0.1)
        # The node's log goes to a file: a pipe nobody reads fills up after ~350 log lines
        # (one per published loop) and then blocks the node.
        log = tempfile.TemporaryFile(mode='w+')
        proc = subprocess.Popen(node_cmd, env=dict(os.environ), stderr=log, text=True)
        if args.backend:
            odom_proc = subprocess.Popen([sys.executable, __file__, '--odometry'],
                                         env=dict(os.environ), stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 60
        while pub.get_subscription_count() == 0:
            if proc.poll() is not None or time.monotonic() > deadline:
                log.seek(0)
                print('solid_node did not start:', log.read(), file=sys.stderr)
                return 1
            time.sleep(0.1)
        if odom_proc is not None:
            assert odom_proc.stdout is not None
            if odom_proc.stdout.readline().strip() != 'ready':  # it gives up after 60 s
                print('the odometry process found no subscriber', file=sys.stderr)
                return 1
        run(10.0, 2.0)  # warm-up (imports, kd-tree, DDS discovery)
        lat, skipped, missing = run(10.0, args.duration)
        print(f'10 Hz, {len(points)} points/cloud, {args.duration:.0f} s: '
              f'{len(lat)} candidate messages; latency median {np.median(lat):.1f} ms, '
              f'p95 {np.percentile(lat, 95):.1f} ms, max {lat.max():.1f} ms; '
              f'skipped {skipped}, without result {missing}')
        if math.isfinite(floor):
            print(f'node share over the transport floor: {np.median(lat) - floor:.1f} ms')
        best = 10.0 if skipped == 0 and missing == 0 else 0.0
        for rate in [float(r) for r in args.rates.split(',') if r]:
            lat, skipped, missing = run(rate, args.step_duration)
            ok = skipped == 0 and missing == 0
            print(f'{rate:5.1f} Hz: median {np.median(lat):.1f} ms, p95 '
                  f'{np.percentile(lat, 95):.1f} ms, skipped {skipped}, without result '
                  f'{missing} -> {"sustained" if ok else "falls behind"}')
            if not ok:
                break
            best = rate
        print('diagnostics:', {k: v for k, v in diag.items()
                               if k.startswith(('clouds', 'backend', 'odom', 'seconds_since'))})
        print(f'highest sustained rate without skips: {best:.0f} Hz '
              f'(processing p50 {diag.get("processing_ms_p50")} ms in the node)')
    finally:
        if odom_proc is not None:
            stop_odometry(odom_proc)
        shutdown(proc, executor, spinner, node)
    return 0


def _wait_for_subscriber(pub: Any, proc: subprocess.Popen[Any]) -> None:
    deadline = time.monotonic() + 60
    while pub.get_subscription_count() == 0:
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError('the echo process did not start')
        time.sleep(0.1)


def echo() -> int:
    """The floor's subscriber: the node's QoS and allocator tuning, no processing."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Float64MultiArray

    from solid_ros.runtime import tune_allocator, tune_thread_switching

    tune_allocator()
    tune_thread_switching()
    rclpy.init()
    node = Node('solid_latency_echo')
    pub = node.create_publisher(Float64MultiArray, _ECHO_TOPIC, 10)

    def on_points(msg: PointCloud2) -> None:
        stamp = msg.header.stamp.sec * NS + msg.header.stamp.nanosec
        pub.publish(Float64MultiArray(data=[float(stamp)]))

    node.create_subscription(PointCloud2, '/points', on_points,
                             QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def odometry() -> int:
    """The odometry stack: one Odometry per line on stdin (stamp in ns, heading in rad; the
    sensor turning in place), published at once; prints ``ready`` once the node subscribes."""
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = Node('solid_latency_odometry')
    pub = node.create_publisher(Odometry, '/odom', QoSProfile(
        depth=100, reliability=ReliabilityPolicy.RELIABLE))
    odom = Odometry()
    odom.header.frame_id, odom.child_frame_id = 'odom', 'velodyne'
    try:
        deadline = time.monotonic() + 60
        while pub.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                return 1
            time.sleep(0.05)
        print('ready', flush=True)
        for line in sys.stdin:
            stamp_ns, heading = line.split()
            odom.header.stamp.sec, odom.header.stamp.nanosec = divmod(int(stamp_ns), NS)
            half = float(heading) / 2.0
            odom.pose.pose.orientation.z, odom.pose.pose.orientation.w = (math.sin(half),
                                                                          math.cos(half))
            pub.publish(odom)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def stop_odometry(proc: subprocess.Popen[str]) -> None:
    """End of input ends the odometry process (killed if it does not)."""
    assert proc.stdin is not None
    try:
        proc.stdin.close()
    except BrokenPipeError:
        pass
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()


def shutdown(proc: subprocess.Popen[Any] | None, executor: Any, spinner: threading.Thread,
             node: Any) -> None:
    """Stop the node process (SIGINT, then kill) and this process's probe node."""
    import rclpy

    if proc is not None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
    executor.shutdown()
    # A spin still inside rcl at interpreter exit aborts the process ("terminate called
    # without an active exception"): let it return first.
    spinner.join(timeout=10.0)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
