"""Soak of solid_node: memory over a stream much longer than its database.

Run: .venv/bin/python test/bench/bench_node_soak.py [--clouds 3000] [--capacity 500]
[--points-per-ring 512] [--no-verify]

The node runs in its own process (``python -m solid_ros.ros.node``, the shipped hdl64.yaml with
``capacity`` overridden, verification on unless ``--no-verify``), as ``solid_node`` does. This
script simulates a drive with :func:`solid_ros.sim.simulate` (HDL-64-like sensor, fewer points
per ring than the preset's 1024 to keep the run short; the route repeats, so places are
revisited and loops found), and publishes each scan as a PointCloud2 (x, y, z, intensity)
right after a nav_msgs/Odometry with the same stamp and the reference pose. Publishing is paced
by the node's /diagnostics (at most ``--window`` clouds ahead of it), so nothing is dropped and
the node runs as fast as it can. Every ``--every`` processed clouds it reads the node process's
VmRSS from /proc/<pid>/status, and at the end prints the curve and whether it is flat once the
database is full: RSS over the last third of the stream after the database filled must not
grow by more than ``--flat-mb`` MB. It is not flat at once: with the node's allocator tuning
(:func:`~solid_ros.runtime.tune_allocator` keeps freed memory up to a 256 MB trim
threshold) the heap's retained free memory steps up with bursts of loop verification and
levels off later; measured 2026-11 on 2 shared cores: 153 MB when the database filled (503
clouds), 172.1 MB from 4250 clouds on, 172.3 MB at 6000 (3000 clouds end before it levels:
152 -> 166.5 MB). The detector alone in one process, same stream, shows the same shape
while glibc's in-use bytes stay at 40-46 MB. The default of 6000 clouds takes about 7.5
minutes there. A benchmark that prints figures, not a test.
"""

from __future__ import annotations

import argparse
import array
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from bench_node_latency import shutdown

ROOT = Path(__file__).resolve().parents[2]
NS = 1_000_000_000


def _rss_kb(pid: int, key: str = 'VmRSS') -> int:
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith(key + ':'):
            return int(line.split()[1])
    raise RuntimeError(f'{key} not in /proc/{pid}/status')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--clouds', type=int, default=6000, help='clouds to publish')
    parser.add_argument('--capacity', type=int, default=500, help='database capacity')
    parser.add_argument('--points-per-ring', type=int, default=512,
                        help='rays per ring of the 64-ring simulated sensor (preset: 1024)')
    parser.add_argument('--no-verify', action='store_true',
                        help='descriptor-only node (verify:=false); default: verification on')
    parser.add_argument('--every', type=int, default=100, help='RSS sample period, clouds')
    parser.add_argument('--window', type=int, default=8,
                        help='clouds published ahead of the node at most')
    parser.add_argument('--flat-mb', type=float, default=1.0,
                        help='largest RSS growth over the last third of the stream after the '
                             'database filled that counts as flat, MB')
    parser.add_argument('--marker-max-loops', type=int, default=1000,
                        help='the node parameter (its default: 1000)')
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()

    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2, PointField
    from visualization_msgs.msg import MarkerArray

    from solid_ros.core.geometry import matrix_to_quaternion
    from solid_ros.sim import simulate
    from solid_ros.sim.lidar import hdl64

    verify = not args.no_verify
    os.environ['ROS_DOMAIN_ID'] = str(random.randint(1, 100))
    log_dir = Path(tempfile.mkdtemp(prefix='solid_soak_'))
    node_log = log_dir / 'solid_node.log'
    node_cmd = [sys.executable, '-m', 'solid_ros.ros.node', '--ros-args', '--params-file',
                str(ROOT / 'config' / 'hdl64.yaml'), '-p', f'capacity:={args.capacity}',
                '-p', f'verify:={"true" if verify else "false"}',
                '-p', 'qos_reliability:=reliable', '-p', 'qos_depth:=100',
                '-p', 'queue_size:=50', '-p', 'diagnostics_period_sec:=0.2',
                '-p', f'marker_max_loops:={args.marker_max_loops}',
                '-r', 'points:=/soak/points', '-r', 'odom:=/soak/odom']
    with node_log.open('w') as log:
        proc = subprocess.Popen(node_cmd, env=dict(os.environ), stdout=log,
                                stderr=subprocess.STDOUT)

    rclpy.init()
    node = Node('solid_soak_bench')
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    pub_points = node.create_publisher(PointCloud2, '/soak/points', qos)
    pub_odom = node.create_publisher(Odometry, '/soak/odom', qos)
    diag: dict[str, str] = {}
    level = [0]
    samples: list[tuple[int, int, int, int, float, int, float]] = []
    marker_points = [0]
    next_sample = [1]  # clouds processed at the next RSS sample
    cond = threading.Condition()

    def done() -> int:
        return sum(int(diag.get(k, 0)) for k in ('clouds_processed', 'clouds_rejected',
                                                  'clouds_skipped', 'clouds_failed'))

    def on_diag(msg: DiagnosticArray) -> None:
        for st in msg.status:
            if not st.name.startswith('/solid_node'):
                continue
            with cond:
                diag.update({kv.key: kv.value for kv in st.values})
                level[0] = max(level[0], int.from_bytes(st.level, 'little')
                               if isinstance(st.level, bytes) else int(st.level))
                processed = int(diag['clouds_processed'])
                if processed >= next_sample[0]:
                    next_sample[0] = (processed // args.every + 1) * args.every
                    samples.append((processed, int(diag['database_size']),
                                    int(diag['keyframe_clouds']), int(diag['loop_candidates']),
                                    float(diag['keyframe_clouds_mb']),
                                    _rss_kb(proc.pid), time.monotonic()))
                cond.notify_all()

    def on_markers(msg: MarkerArray) -> None:
        marker_points[0] = sum(len(m.points) for m in msg.markers)

    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 50)
    node.create_subscription(MarkerArray, '/solid_node/loop_markers', on_markers, QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()

    model = hdl64(points_per_ring=args.points_per_ring)
    cloud = PointCloud2(height=1, point_step=16, is_dense=True)
    cloud.header.frame_id = 'velodyne'
    cloud.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                    for i, n in enumerate(('x', 'y', 'z', 'intensity'))]
    odom = Odometry()
    odom.header.frame_id, odom.child_frame_id = 'map', 'velodyne'
    status = 0
    t_start = time.monotonic()
    sim_sec = 0.0
    points_total = 0
    try:
        deadline = time.monotonic() + 60
        while pub_points.get_subscription_count() == 0 or pub_odom.get_subscription_count() == 0:
            if proc.poll() is not None or time.monotonic() > deadline:
                print(f'solid_node did not start; see {node_log}', file=sys.stderr)
                return 1
            time.sleep(0.1)
        print(f'solid_node pid {proc.pid}: hdl64.yaml, capacity {args.capacity}, verification '
              f'{"on" if verify else "off"}; {args.clouds} simulated clouds (64 x '
              f'{args.points_per_ring} rays) with odometry; RSS every {args.every} clouds',
              flush=True)
        t_start = time.monotonic()
        scans: Any = simulate(seed=args.seed, sensor=model, num_scans=args.clouds)
        for sent in range(args.clouds):
            t0 = time.perf_counter()
            scan = next(scans)
            sim_sec += time.perf_counter() - t0
            with cond:
                while (sent - done() > args.window
                       or int(diag.get('verify_queue_length', 0)) > args.window):
                    if proc.poll() is not None:
                        raise RuntimeError(f'solid_node exited ({proc.returncode})')
                    cond.wait(1.0)
            stamp = divmod(int(scan.stamp_ns), NS)
            odom.header.stamp.sec, odom.header.stamp.nanosec = stamp
            p = odom.pose.pose
            p.position.x, p.position.y, p.position.z = (float(v) for v in scan.pose[:3, 3])
            (p.orientation.x, p.orientation.y, p.orientation.z,
             p.orientation.w) = matrix_to_quaternion(scan.pose[:3, :3])
            pub_odom.publish(odom)
            data = np.ascontiguousarray(scan.cloud, dtype='<f4')
            points_total += len(data)
            cloud.header.stamp.sec, cloud.header.stamp.nanosec = stamp
            cloud.width, cloud.row_step = len(data), 16 * len(data)
            cloud.data = array.array('B', data.tobytes())
            pub_points.publish(cloud)
        with cond:
            deadline = time.monotonic() + 120
            while done() < args.clouds or int(diag.get('verify_queue_length', 1)):
                if time.monotonic() > deadline:
                    raise RuntimeError('the node did not finish the stream in 120 s')
                cond.wait(1.0)
        time.sleep(1.0)  # the latched markers and a last diagnostics message
        with cond:
            processed = int(diag['clouds_processed'])
            samples.append((processed, int(diag['database_size']), int(diag['keyframe_clouds']),
                            int(diag['loop_candidates']), float(diag['keyframe_clouds_mb']),
                            _rss_kb(proc.pid), time.monotonic()))
            final = dict(diag)
        hwm = _rss_kb(proc.pid, 'VmHWM')
        wall = time.monotonic() - t_start
        status = _report(args, samples, final, hwm, wall, sim_sec, points_total,
                         marker_points[0], level[0], node_log)
    except RuntimeError as err:
        print(f'soak stopped: {err}; node log {node_log}', file=sys.stderr)
        status = 1
    finally:
        shutdown(proc, executor, spinner, node)
    return status


def _report(args: argparse.Namespace, samples: list[tuple[int, int, int, int, float, int, float]],
            final: dict[str, str], hwm_kb: int, wall: float, sim_sec: float, points_total: int,
            marker_points: int, worst_level: int, node_log: Path) -> int:
    print(f'\n{"clouds":>7} {"db":>5} {"kf clouds":>9} {"kf MB":>7} {"loops":>6} '
          f'{"RSS MB":>8} {"s":>6}')
    t0 = samples[0][6]
    for processed, db, kfc, loops, kf_mb, rss, t in samples:
        print(f'{processed:7d} {db:5d} {kfc:9d} {kf_mb:7.2f} {loops:6d} {rss / 1024:8.1f} '
              f'{t - t0:6.0f}')
    full = next((s for s in samples if s[1] >= args.capacity), None)
    warn = sum(1 for line in node_log.read_text().splitlines() if '[WARN]' in line)
    print(f'\n{final["clouds_processed"]} processed, {final["clouds_skipped"]} skipped, '
          f'{final["clouds_rejected"]} rejected, {final["clouds_failed"]} failed, '
          f'{final["clouds_without_odom"]} without odometry, {final["loop_candidates"]} loops '
          f'({final.get("verify_verified", "0")} verified), verify_skipped '
          f'{final["verify_skipped"]}; marker points {marker_points} '
          f'(marker_max_loops {args.marker_max_loops}: at most {2 * args.marker_max_loops}); '
          f'{warn} warnings in the node log; '
          f'worst /diagnostics level {worst_level}')
    print(f'{wall:.0f} s wall ({sim_sec:.0f} s simulating in this process), '
          f'{points_total / args.clouds:.0f} points per cloud on '
          f'average; node processing p50 {final["processing_ms_p50"]} ms, p95 '
          f'{final["processing_ms_p95"]} ms; node VmHWM {hwm_kb / 1024:.1f} MB')
    if full is None:
        print(f'the database never filled ({samples[-1][1]} of {args.capacity}): no verdict')
        return 1
    after = [s for s in samples if s[0] >= full[0]]
    rss = np.array([s[5] / 1024 for s in after])
    print(f'database full at {full[0]} clouds: RSS {rss[0]:.1f} MB then, {rss[-1]:.1f} MB at '
          f'the end (+{rss[-1] - rss[0]:.1f} MB), range after full {rss.min():.1f}-'
          f'{rss.max():.1f} MB')
    rises = [after[k][0] for k in range(1, len(after)) if rss[k] - rss[:k].max() > 1.0]
    if rises:
        print(f'last rise above the earlier peak by more than 1 MB: at {rises[-1]} clouds')
    end = after[-1][0]
    tail_start = full[0] + 2 * (end - full[0]) // 3
    tail = [s for s in after if s[0] >= tail_start]
    if len(tail) < 3:
        print('too few samples in the last third after the database filled: no verdict')
        return 1
    growth = (tail[-1][5] - tail[0][5]) / 1024
    flat = growth <= args.flat_mb
    print(f'last third after full ({tail[0][0]}-{tail[-1][0]} clouds, {len(tail)} samples): RSS '
          f'{tail[0][5] / 1024:.1f} -> {tail[-1][5] / 1024:.1f} MB ({growth:+.1f} MB) -> '
          f'{"FLAT" if flat else "NOT FLAT"} (criterion: at most +{args.flat_mb} MB)')
    return 0 if flat else 2

if __name__ == '__main__':
    sys.exit(main())
