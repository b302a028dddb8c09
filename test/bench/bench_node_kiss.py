"""solid_node with ``odometry_source: kiss_icp`` fed real clouds at 10 Hz: does it keep them?

Run: ``nice python test/bench/bench_node_kiss.py [--clouds 150] [--duration 20] [--sim-clouds 200]
[--report doc/reports/bench_node_kiss.md] [--node-root ../main]``.

The node runs in its own process (``python -m solid_ros.ros.node``) with KISS-ICP set as
test/bench/bench_kiss.py's RECIPE (max range 50 m, voxel 0.5 m, no deskew) and the default
``queue_size``. The bench publishes, at 10 Hz with 0.1 s stamps:

1. hku1 (real Livox Avia keyframes, 3.5k-13k points, config/avia.yaml): the first
   ``--clouds`` clouds in order;
2. KITTI scan 313 (~121k points, HDL-64, config/hdl64.yaml), turned by 1 deg more per cloud
   (up to 39 deg, then back) and jittered by 2 cm (a sensor turning slowly in place): the
   same real scan, so that odometry has a motion to follow, for ``--duration`` seconds; then
   the same at the ``--rates`` to find the highest rate at which no cloud is dropped;
3. simulated sensor streams (``--sim-clouds`` clouds each): Avia-like (config/avia.yaml) and
   Mid-360-like (config/mid360.yaml; again with KISS-ICP's voxel at 1 m) clouds as the sensor
   gives them at 10 Hz on a robot at 2.5 m/s, 0.25 m apart. hku1's clouds are keyframes
   0.4 s apart: at 10 Hz KISS-ICP gets four times a real stream's motion per cloud, a
   harder case than a sensor's own stream; these are the sensor's own.

For each it prints the processed fraction (clouds that got a KISS-ICP pose on
``~/kiss/odometry`` over clouds published), the clouds the node dropped (``clouds_skipped``,
of which before registration ``odometry_skipped``), the node's per-cloud odometry cost
(``odometry_ms_p50/p95`` on /diagnostics: registration including the hand-over to KISS-ICP's
process; of it, ``kiss_icp_ms_p50`` in KISS-ICP's process and ``kiss_handover_ms_p50`` the
hand-over there and back) and, after the node has stopped, plain KISS-ICP 1.3's per-cloud
cost on the same clouds in this process (``register_frame``, same settings). The KITTI part
runs again with ``--coarse`` (KISS-ICP voxel 1 m, max range 30 m). Last, the odometry's ATE
on hku1 against the reference poses: the node's over the clouds it posed, and plain
KISS-ICP's over every cloud and over those (a dropped cloud is a gap the odometry must
bridge); and what verification did meanwhile (keyframes stored, dropped before
verification, loops published: the odometry shares the 2 cores with it). ``--node-root``
runs the node of another checkout (e.g. main before the odometry stage; it reports no
odometry_ms).
Timings on a shared 2-core machine are noisy: the load is printed with each part.
"""

from __future__ import annotations

import argparse
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
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'test'))

from bench.report import PrintedReport, bench_meta  # noqa: E402

from solid_ros.formats.poses import read_kitti_poses  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
NS = 1_000_000_000
RECIPE = (0.5, 50.0)  # KISS-ICP's voxel and max range, metres (bench_kiss.py's RECIPE)


def kiss_args(voxel: float, max_range: float) -> list[str]:
    """The node's KISS-ICP parameters."""
    return ['-p', 'odometry_source:=kiss_icp', '-p', f'kiss_max_range:={max_range!r}', '-p',
            f'kiss_voxel_size:={voxel!r}', '-p', 'kiss_deskew:=false']


def _load() -> str:
    return f'load {os.getloadavg()[0]:.1f}'


def _ms(values: list[float]) -> str:
    v = np.asarray(values, dtype=np.float64)
    return f'median {np.median(v):6.1f} ms, p95 {np.percentile(v, 95):6.1f} ms'


def turned(points: np.ndarray, count: int, seed: int = 0) -> list[np.ndarray]:
    """The scan turned by 1 deg more per cloud and jittered by 2 cm (published there and back,
    :func:`there_and_back`: a jump back to the first would reset the odometry)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        a = np.radians(k)
        rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0],
                        [0.0, 0.0, 1.0]])
        pts = points[:, :3] @ rot.T + rng.normal(scale=0.02, size=(len(points), 3))
        out.append(np.ascontiguousarray(pts, dtype=np.float32))
    return out


def plain_kiss(clouds: list[np.ndarray], voxel: float = RECIPE[0],
               max_range: float = RECIPE[1]) -> tuple[list[float], np.ndarray]:
    """KISS-ICP 1.3 alone as bench_kiss's RECIPE calls it (or with this voxel and range); ms
    per cloud and the poses."""
    from solid_ros.core.odometry.kiss import load_kiss_icp

    KissICP, KISSConfig, _ = load_kiss_icp()
    config = KISSConfig()
    config.data.max_range = max_range
    config.data.deskew = False
    config.mapping.voxel_size = voxel
    kiss = KissICP(config)
    costs, poses = [], []
    for points in clouds:
        pts = np.asarray(points, dtype=np.float64)
        t0 = time.perf_counter()
        kiss.register_frame(pts, np.zeros(len(pts)))
        costs.append((time.perf_counter() - t0) * 1e3)
        poses.append(np.array(kiss.last_pose, dtype=np.float64))
    return costs, np.stack(poses)


def node_poses(probe: Probe) -> tuple[np.ndarray, np.ndarray]:
    """The clouds of the last publish() that got a pose (indices) and those poses."""
    with probe.lock:
        got = [(i, probe.poses[s]) for i, s in enumerate(probe.sent) if s in probe.poses]
    return np.array([i for i, _ in got], dtype=np.intp), np.stack([T for _, T in got])


def ate(poses: np.ndarray, reference: np.ndarray) -> float:
    """ATE RMSE after one SE(3) fit, metres (bench_kiss's)."""
    from bench.bench_kiss import trajectory_errors

    return trajectory_errors(poses, reference)[0]


def there_and_back(i: int, n: int) -> int:
    """Index ``i`` of 0, 1, ..., n-1, n-2, ..., 1, 0, 1, ...: the sensor turns back and forth."""
    k = i % (2 * n - 2)
    return k if k < n else 2 * n - 2 - k


class Probe:
    """This process's ROS side: publishes clouds, counts poses, keeps the node's diagnostics."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        rclpy.init()
        self.node = Node('solid_kiss_bench')
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.node.create_publisher(PointCloud2, '/points', qos)
        self.posed: set[int] = set()
        self.poses: dict[int, np.ndarray] = {}  # the node's odometry pose by cloud stamp
        self.diag: dict[str, str] = {}
        self.lock = threading.Lock()
        self.node.create_subscription(Odometry, '/solid_node/kiss/odometry', self._on_odom,
                                      QoSProfile(depth=100,
                                                 reliability=ReliabilityPolicy.RELIABLE))
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.spinner = threading.Thread(target=self.executor.spin, daemon=True)
        self.spinner.start()
        self.stamp = 1_000 * NS
        self.sent: list[int] = []  # the stamps of the last publish(), in order

    def _on_odom(self, msg: Any) -> None:
        from solid_ros.core.geometry import vector_to_matrix

        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        stamp = msg.header.stamp.sec * NS + msg.header.stamp.nanosec
        with self.lock:
            self.posed.add(stamp)
            self.poses[stamp] = vector_to_matrix([p.x, p.y, p.z, q.x, q.y, q.z, q.w])

    def _on_diag(self, msg: Any) -> None:
        for s in msg.status:
            if s.name.startswith('/solid_node'):
                with self.lock:
                    self.diag.update({kv.key: kv.value for kv in s.values})

    def value(self, key: str) -> str:
        with self.lock:
            return self.diag.get(key, 'n/a')

    def publish(self, clouds: list[np.ndarray], rate: float, seconds: float | None = None
                ) -> tuple[int, int, int, int]:
        """Publish at ``rate`` (all clouds once, or cycling for ``seconds``); wait for the node
        to finish; return (published, posed, skipped, odometry_skipped) of this run."""
        from solid_ros.ros.graph_msgs import cloud_msg

        msgs = [cloud_msg(c, 'lidar', 0) for c in clouds]
        count = len(clouds) if seconds is None else int(rate * seconds)
        skipped0, odo0 = self._int('clouds_skipped'), self._int('odometry_skipped')
        sent: list[int] = []
        start = time.perf_counter()
        for i in range(count):
            while (wait := start + i / rate - time.perf_counter()) > 0:
                time.sleep(wait)
            self.stamp += int(NS / rate)
            msg = msgs[there_and_back(i, len(msgs))]
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(self.stamp, NS)
            sent.append(self.stamp)
            self.pub.publish(msg)
        self._drain(sent)
        self.sent = sent
        with self.lock:
            posed = len(self.posed.intersection(sent))
        return (count, posed, self._int('clouds_skipped') - skipped0,
                self._int('odometry_skipped') - odo0)

    def _int(self, key: str) -> int:
        value = self.value(key)
        return int(value) if value.isdigit() else 0

    def _drain(self, sent: list[int]) -> None:
        """Until no pose came for 3 s and nothing waits in the node's queues (verification's
        too), plus diagnostics."""
        last, seen = time.monotonic(), -1
        while time.monotonic() - last < 3.0 or any(
                self.value(k) not in ('0', 'n/a') for k in ('queue_length',
                                                            'odometry_queue_length',
                                                            'verify_queue_length')):
            with self.lock:
                n = len(self.posed.intersection(sent))
            if n != seen:
                last, seen = time.monotonic(), n
            time.sleep(0.2)
        time.sleep(1.0)  # a diagnostics message after the last cloud

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.spinner.join(timeout=10.0)
        self.node.destroy_node()
        rclpy.try_shutdown()


def start_node(params: Path, node_root: Path, probe: Probe,
               kiss: tuple[float, float] = RECIPE) -> tuple[subprocess.Popen[str], Any]:
    """The node process (KISS-ICP with ``kiss`` = (voxel, max range)); returns it and its log
    file once it subscribes."""
    env = dict(os.environ, PYTHONPATH=str(node_root))
    cmd = [sys.executable, '-m', 'solid_ros.ros.node', '--ros-args', '--params-file',
           str(params), *kiss_args(*kiss), '-p', 'qos_reliability:=reliable',
           '-p', 'diagnostics_period_sec:=0.5']
    log = tempfile.TemporaryFile(mode='w+')  # a pipe nobody reads would block the node
    proc = subprocess.Popen(cmd, env=env, stderr=log, stdout=log, text=True, cwd=node_root)
    deadline = time.monotonic() + 90
    while probe.pub.get_subscription_count() == 0:
        if proc.poll() is not None or time.monotonic() > deadline:
            log.seek(0)
            raise RuntimeError(f'solid_node did not start: {log.read()[-2000:]}')
        time.sleep(0.1)
    return proc, log


def stop_node(proc: subprocess.Popen[str]) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)


def _line(name: str, run: tuple[int, int, int, int], probe: Probe) -> None:
    published, posed, skipped, odo = run
    print(f'  {name}: processed {posed}/{published} = {posed / published:.3f}; dropped '
          f'{skipped} (before registration {odo}); node odometry per cloud median '
          f"{probe.value('odometry_ms_p50')} ms, p95 {probe.value('odometry_ms_p95')} ms "
          f"(in KISS-ICP's process p50 {probe.value('kiss_icp_ms_p50')} ms, hand-over p50 "
          f"{probe.value('kiss_handover_ms_p50')} ms); "
          f"processing p50 {probe.value('processing_ms_p50')} ms ({_load()})")


def bench_hku1(probe: Probe, args: argparse.Namespace
               ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    from hku1_data import hku1_scans

    clouds = [np.asarray(c[:, :3], dtype=np.float32) for c in hku1_scans(DATA)[0][:args.clouds]]
    sizes = [len(c) for c in clouds]
    proc, _ = start_node(ROOT / 'config' / 'avia.yaml', args.node_root, probe)
    try:
        probe.publish(clouds[:5], 10.0)  # warm-up: KISS-ICP's process, imports
        print(f'hku1 (Livox Avia), {len(clouds)} clouds of {min(sizes)}-{max(sizes)} points '
              f'(median {int(np.median(sizes))}), 10 Hz:')
        _line('node', probe.publish(clouds, 10.0), probe)
        print(f"  verification: {probe.value('database_size')} keyframes stored, "
              f"{probe.value('verify_skipped')} dropped before verification, "
              f"{probe.value('loop_candidates')} loops published, verify p50 "
              f"{probe.value('verify_ms_p50')} ms")
        posed, poses = node_poses(probe)
    finally:
        stop_node(proc)
    return clouds, posed, poses


def bench_kitti(probe: Probe, args: argparse.Namespace, clouds: list[np.ndarray],
                kiss: tuple[float, float]) -> None:
    proc, _ = start_node(ROOT / 'config' / 'hdl64.yaml', args.node_root, probe, kiss)
    try:
        probe.publish(clouds[:3], 2.0)  # warm-up
        print(f'KITTI scan 313 turning, {len(clouds[0])} points per cloud, KISS-ICP voxel '
              f'{kiss[0]:g} m, max range {kiss[1]:g} m:')
        full = probe.publish(clouds, 10.0, args.duration)
        _line(f'10 Hz for {args.duration:.0f} s', full, probe)
        best = 0.0
        for rate in [float(r) for r in args.rates.split(',') if r]:
            run = probe.publish(clouds, rate, args.step_duration)
            _line(f'{rate:4.1f} Hz for {args.step_duration:.0f} s', run, probe)
            if run[1] < run[0]:
                break
            best = rate
        if full[1] >= full[0]:  # the sensor's own rate kept them all: the ladder below it did too
            best = max(best, 10.0)
        print(f'  highest rate tried with every 120k-point cloud kept: {best:g} Hz')
    finally:
        stop_node(proc)


SIM_STREAMS = (('avia_like', 'avia.yaml', RECIPE), ('mid360_like', 'mid360.yaml', RECIPE),
               ('mid360_like', 'mid360.yaml', (1.0, RECIPE[1])))


def sim_stream(sensor: str, count: int) -> tuple[list[np.ndarray], np.ndarray]:
    """A simulated sensor's clouds as it streams them at 10 Hz on a robot at 2.5 m/s (0.25 m
    apart, the simulator's closest spacing), and their reference poses."""
    from solid_ros.sim.drive import Drive, DriveConfig

    drive = Drive(DriveConfig(sensor=sensor, spacing=0.25, speed=2.5))
    scans = [drive.scan(k) for k in range(count)]
    return ([np.ascontiguousarray(s.points[:, :3], dtype=np.float32) for s in scans],
            np.stack([s.pose for s in scans]))


def bench_sim(probe: Probe, args: argparse.Namespace, sensor: str, preset: str,
              kiss: tuple[float, float]) -> None:
    """A sensor stream at its own rate: each cloud 0.1 s of motion after the last, as a
    10 Hz sensor gives them (hku1's clouds are keyframes 0.4 s apart)."""
    clouds, ref = sim_stream(sensor, args.sim_clouds)
    sizes = [len(c) for c in clouds]
    proc, _ = start_node(ROOT / 'config' / preset, args.node_root, probe, kiss)
    try:
        probe.publish(clouds[:5], 10.0)  # warm-up
        print(f'simulated {sensor} ({preset}) streaming at 10 Hz, 0.25 m per cloud, '
              f'{len(clouds)} clouds of {min(sizes)}-{max(sizes)} points (median '
              f'{int(np.median(sizes))}), KISS-ICP voxel {kiss[0]:g} m, max range {kiss[1]:g} m:')
        _line('node', probe.publish(clouds, 10.0), probe)
        print(f"  verification: {probe.value('database_size')} keyframes stored, "
              f"{probe.value('verify_skipped')} dropped before verification, verify p50 "
              f"{probe.value('verify_ms_p50')} ms")
        posed, poses = node_poses(probe)
    finally:
        stop_node(proc)
    costs, plain = plain_kiss(clouds, *kiss)
    print(f'  plain KISS-ICP alone, same clouds: {_ms(costs)} per cloud ({_load()}); odometry '
          f'ATE the node {ate(poses, ref[posed]):.3f} m, plain {ate(plain, ref):.3f} m')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--clouds', type=int, default=150, help='hku1 clouds published')
    parser.add_argument('--duration', type=float, default=20.0,
                        help='seconds of KITTI clouds at 10 Hz')
    parser.add_argument('--rates', default='0.5,1,2,3,5',
                        help='rates (Hz) stepped up for the KITTI clouds')
    parser.add_argument('--step-duration', type=float, default=15.0,
                        help='seconds per stepped rate')
    parser.add_argument('--node-root', type=Path, default=ROOT,
                        help='checkout whose solid_node runs (default: this one)')
    parser.add_argument('--skip-kitti', action='store_true')
    parser.add_argument('--sim-clouds', type=int, default=200,
                        help='clouds of each simulated 10 Hz stream (0 skips them)')
    parser.add_argument('--coarse', default='1.0,30.0',
                        help="KITTI again with this KISS-ICP 'voxel,max_range' (what the README "
                             "advises for 120k-point clouds); '' skips it")
    parser.add_argument('--report', type=Path, help='write the printed figures (.md or JSON)')
    args = parser.parse_args()
    if not (DATA / 'hku1').is_dir():
        print(f'no shared data at {DATA}; nothing to measure', file=sys.stderr)
        return 1
    os.environ['ROS_DOMAIN_ID'] = str(random.randint(1, 100))
    with PrintedReport(args.report, bench_meta('bench_node_kiss', vars(args))):
        print(f'node from {args.node_root.resolve()} ({_load()})')
        from solid_ros.formats.pointfiles import read_pcd

        kitti = ([] if args.skip_kitti else
                 turned(read_pcd(DATA / 'kitti' / 'pcd' / '000313.pcd'), 40))
        settings = [RECIPE] + ([tuple(float(v) for v in args.coarse.split(','))]
                               if args.coarse else [])
        probe = Probe()
        try:
            hku1, posed, poses = bench_hku1(probe, args)
            for kiss in settings if kitti else []:
                bench_kitti(probe, args, kitti, kiss)  # type: ignore[arg-type]
            for sensor, preset, kiss in SIM_STREAMS if args.sim_clouds > 0 else ():
                bench_sim(probe, args, sensor, preset, kiss)
        finally:
            probe.close()
        print(f'plain KISS-ICP 1.3 in this process, same clouds ({_load()}):')
        costs, plain = plain_kiss(hku1)
        print(f'  hku1: {_ms(costs)} per cloud')
        for voxel, max_range in settings if kitti else []:
            print(f'  KITTI 120k turning, voxel {voxel:g} m, max range {max_range:g} m: '
                  f'{_ms(plain_kiss(kitti, voxel, max_range)[0])} per cloud')
        ref = read_kitti_poses(DATA / 'hku1' / 'optimized_poses.txt')[:len(hku1)]
        print(f'odometry ATE on hku1 against the reference: the node (its {len(posed)} posed '
              f'clouds) {ate(poses, ref[posed]):.3f} m; plain KISS-ICP on every cloud '
              f"{ate(plain, ref):.3f} m, on the node's posed ones "
              f'{ate(plain[posed], ref[posed]):.3f} m')
    return 0


if __name__ == '__main__':
    sys.exit(main())
