"""Does solid_node's ``~/map`` delay or drop its ``/tf`` and ``~/odometry`` for a subscriber
in another process?

Run: .venv/bin/python test/bench/bench_map_transport.py [--duration 30] [--maps off,small,large]
[--profiles default,shm] [--repeat 1] [--map-period 1.0] [--tf-rate 20]

Three processes per case: solid_node (``python -m solid_ros.ros.node`` of this tree, HDL-64
preset, back end on, ``map_period_sec`` = ``--map-period``; keyframe clouds stored at 0.3 m and
the map at 0.2 m so that it passes 512 KB within seconds and reaches 6.5 MB in a minute); a
feeder driving a simulated HDL-64 drive (63k points, 0.75 MB per cloud) at 2 Hz with odometry
at 20 Hz, clouds and odometry from two participants (rclpy contexts) of their own so that the
clouds cannot take the odometry with them; and a listener subscribing to ``/tf`` and
``/solid_node/odometry`` (reliable, as tf2's listener, and best-effort), ``/solid_node/map``
and ``/solid_node/loop_candidates``. Each case runs in a process of its own (Fast DDS reads
its profile file once per process).

Map cases: ``off`` (``map_period_sec`` 0), ``small`` (``map_max_points`` 20,000: 240 KB, under
Fast DDS's 512 KB shared-memory segment), ``large`` (1,000,000, the default). Profiles:
``default`` (Fast DDS's built-in transports) and ``shm`` (``config/fastdds_shm.xml``).

Printed per reader: samples received of those sent (for /tf: every stamp either reader got,
as a reliable reader gets a lost sample again, late; for odometry: every input sent), the
delay (arrival minus the stamp: for /tf the node's clock at broadcast, so transport alone; for
odometry the wall time the input was sent, so feeder -> node -> listener), how many were over
100 ms, the longest gap between arrivals; the map messages and their sizes. ``--tf-rate 200``
makes a /tf sample fall just before a map message more often: the loss needs that. Timings
are noisy on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
NS = 1_000_000_000
CLOUD_HZ, ODOM_HZ = 2.0, 20.0
TF_HZ = float(os.environ.get('BENCH_TF_HZ', '20.0'))
MAPS = {'off': ['map_max_points:=1000000'], 'small': ['map_max_points:=20000'],
        'large': ['map_max_points:=1000000']}


def listen(out: str) -> int:
    """The subscriber process: record arrivals until SIGINT, then write them to ``out``."""
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Float64MultiArray
    from tf2_msgs.msg import TFMessage

    rclpy.init()
    node = Node('map_transport_listener')
    rec: dict[str, list[Any]] = {k: [] for k in ('tf', 'tf_be', 'odom', 'odom_be', 'map',
                                                 'cands')}

    def stamp(msg: Any) -> int:
        return int(msg.header.stamp.sec) * NS + int(msg.header.stamp.nanosec)

    def keep(key: str, get: Any) -> Any:
        return lambda msg: rec[key].append((get(msg), time.time_ns()))

    rel = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    be = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    node.create_subscription(TFMessage, '/tf', keep('tf', lambda m: stamp(m.transforms[0])),
                             rel)
    node.create_subscription(TFMessage, '/tf', keep('tf_be', lambda m: stamp(m.transforms[0])),
                             be)
    node.create_subscription(Odometry, '/solid_node/odometry', keep('odom', stamp), rel)
    node.create_subscription(Odometry, '/solid_node/odometry', keep('odom_be', stamp), be)
    node.create_subscription(PointCloud2, '/solid_node/map', keep('map', lambda m: len(m.data)),
                             QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    node.create_subscription(Float64MultiArray, '/solid_node/loop_candidates',
                             keep('cands', lambda m: len(m.data)), 100)
    print('ready', flush=True)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        Path(out).write_text(json.dumps(rec))
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _cloud(points: np.ndarray, stamp_ns: int) -> Any:
    import array

    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2(height=1, width=len(points), point_step=12, row_step=12 * len(points),
                      is_dense=True)
    msg.header.frame_id = 'velodyne'
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, NS)
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, n in enumerate('xyz')]
    msg.data = array.array('B', np.ascontiguousarray(points, dtype='<f4').tobytes())
    return msg


def _odom(T: np.ndarray, stamp_ns: int) -> Any:
    sys.path.insert(0, str(ROOT / 'test'))
    from rclpy_msgs import make_odometry

    return make_odometry(T, stamp_ns, child='velodyne')


def _publisher(name: str, kind: type, topic: str) -> tuple[Any, Any, Any]:
    """A publisher in a participant (rclpy context) of its own."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    ctx = Context()
    rclpy.init(context=ctx)
    node = Node(name, context=ctx)
    pub = node.create_publisher(kind, topic, QoSProfile(
        depth=100, reliability=ReliabilityPolicy.RELIABLE))
    return ctx, node, pub


def _wait(pred: Any, what: str, procs: list[subprocess.Popen[Any]], timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if any(p.poll() is not None for p in procs) or time.monotonic() > deadline:
            raise RuntimeError(f'timed out waiting for {what}')
        time.sleep(0.05)


def _stop(proc: subprocess.Popen[Any]) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def run(map_case: str, map_period: float, duration: float, scans: list[np.ndarray],
        odoms: list[np.ndarray]) -> dict[str, Any]:
    """One run; returns the listener's records and what was sent."""
    import rclpy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    env = dict(os.environ)  # set by main(): this process runs one case
    out = tempfile.NamedTemporaryFile(suffix='.json', delete=False).name
    log = tempfile.TemporaryFile(mode='w+')
    node_cmd = [sys.executable, '-m', 'solid_ros.ros.node', '--ros-args', '--params-file',
                str(ROOT / 'config' / 'hdl64.yaml'), '-p', 'backend:=true',
                '-p', 'qos_reliability:=reliable', '-p', 'verify_voxel_size:=0.3',
                '-p', 'map_voxel_size:=0.2',
                '-p', f'tf_rate_hz:={TF_HZ}', '-p', 'path_period_sec:=1.0',
                '-p', f'map_period_sec:={0.0 if map_case == "off" else map_period}',
                '-p', MAPS[map_case][0]]
    listener = subprocess.Popen([sys.executable, __file__, '--listen', out], env=env,
                                stdout=subprocess.PIPE, text=True, cwd=ROOT)
    node = subprocess.Popen(node_cmd, env=env, stderr=log, stdout=log, text=True, cwd=ROOT)
    contexts = []
    sent_odom: list[int] = []
    try:
        ctx_c, n_c, pub_c = _publisher('map_transport_clouds', PointCloud2, '/points')
        ctx_o, n_o, pub_o = _publisher('map_transport_odom', Odometry, '/odom')
        contexts = [(ctx_c, n_c), (ctx_o, n_o)]
        assert listener.stdout is not None
        _wait(lambda: pub_c.get_subscription_count() > 0
              and pub_o.get_subscription_count() > 0, 'solid_node', [node, listener])
        if listener.stdout.readline().strip() != 'ready':
            raise RuntimeError('the listener did not start')
        time.sleep(2.0)  # discovery of the node's outputs by the listener
        start = time.monotonic()
        per_cloud = int(ODOM_HZ / CLOUD_HZ)
        ticks = int(duration * ODOM_HZ)
        for k in range(ticks):
            while (wait := start + k / ODOM_HZ - time.monotonic()) > 0:
                time.sleep(wait)
            i = min(k // per_cloud, len(scans) - 1)
            now = time.time_ns()
            pub_o.publish(_odom(odoms[i], now))
            sent_odom.append(now)
            if k % per_cloud == 0 and k // per_cloud < len(scans):
                pub_c.publish(_cloud(scans[i], now))
        time.sleep(2.0)
    finally:
        for ctx, n in contexts:
            n.destroy_node()
            rclpy.try_shutdown(context=ctx)
        _stop(listener)
        _stop(node)
    rec = json.loads(Path(out).read_text())
    os.unlink(out)
    log.seek(0)
    rec['node_log'] = log.read()
    rec['sent_odom'] = sent_odom
    rec['duration'] = duration
    return rec


def summary(rec: dict[str, Any]) -> str:
    """One block of figures for a run."""
    lines = []
    got = {k: np.array(rec[k], dtype=np.int64).reshape(-1, 2) for k in
           ('tf', 'tf_be', 'odom', 'odom_be')}
    # What the node sent: every /tf stamp some reader got (a reliable reader gets a lost
    # sample again, late); every odometry this process sent.
    sent = {'tf': np.union1d(got['tf'][:, 0], got['tf_be'][:, 0]),
            'odom': np.array(sorted(rec['sent_odom']), dtype=np.int64)}
    for key, a in got.items():
        base = sent[key.split('_')[0]]
        a = a[np.isin(a[:, 0], base)]
        if not len(a):
            lines.append(f'  {key:7s} received 0/{len(base)}')
            continue
        delay = (a[:, 1] - a[:, 0]) / 1e6
        gaps = np.diff(a[:, 1]) / 1e6 if len(a) > 1 else np.zeros(1)
        lines.append(f'  {key:7s} received {len(a)}/{len(base)}; delay median '
                     f'{np.median(delay):.1f} ms, p99 {np.percentile(delay, 99):.0f} ms, max '
                     f'{delay.max():.0f} ms, over 100 ms: {(delay > 100).sum()}; arrival gap '
                     f'max {gaps.max():.0f} ms')
    sizes = [s for s, _ in rec['map']]
    lines.append(f'  map     {len(sizes)} messages' + (
        f', {min(sizes) / 1e6:.2f}-{max(sizes) / 1e6:.2f} MB' if sizes else ''))
    lines.append(f'  loops   {len(rec["cands"])} candidate messages')
    return '\n'.join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--duration', type=float, default=30.0, help='seconds of driving')
    parser.add_argument('--maps', default='off,small,large', help='map cases: off,small,large')
    parser.add_argument('--profiles', default='default,shm', help='default,shm')
    parser.add_argument('--repeat', type=int, default=1)
    parser.add_argument('--map-period', type=float, default=1.0, help='map_period_sec')
    parser.add_argument('--tf-rate', type=float, default=20.0, help='tf_rate_hz')
    parser.add_argument('--log', action='store_true', help="print the node's log lines")
    parser.add_argument('--listen', help=argparse.SUPPRESS)
    parser.add_argument('--one', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.listen:
        return listen(args.listen)
    if args.one:
        return one(args.one, args.map_period, args.duration, args.log)
    for rep in range(args.repeat):
        for profile in args.profiles.split(','):
            for map_case in args.maps.split(','):
                # A process per case: Fast DDS reads its profile file once per process.
                env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(1, 100)),
                           BENCH_TF_HZ=str(args.tf_rate))
                env.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
                if profile == 'shm':
                    env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(
                        ROOT / 'config' / 'fastdds_shm.xml')
                load = os.getloadavg()[0]
                done = subprocess.run(
                    [sys.executable, __file__, '--one', map_case, '--duration',
                     str(args.duration), '--map-period', str(args.map_period),
                     *(['--log'] if args.log else [])],
                    env=env, cwd=ROOT, capture_output=True, text=True, check=False)
                print(f'run {rep + 1}, transport {profile}, map {map_case} '
                      f'(load {load:.1f} -> {os.getloadavg()[0]:.1f}):', flush=True)
                print(done.stdout.rstrip(), done.stderr[-2000:] if done.returncode else '',
                      flush=True)
    return 0


def one(map_case: str, map_period: float, duration: float, log: bool) -> int:
    """One case, in the transport of this process's environment."""
    from solid_ros.sim.drive import Drive, DriveConfig

    drive = Drive(DriveConfig(seed=0, sensor='hdl64'))
    count = int(duration * CLOUD_HZ) + 1
    scans = [drive.scan(i).points for i in range(count)]
    odoms = [drive.odometry(i) for i in range(count)]
    rec = run(map_case, map_period, duration, scans, odoms)
    print(summary(rec))
    if log:
        print(rec['node_log'])
    return 0


if __name__ == '__main__':
    sys.exit(main())
