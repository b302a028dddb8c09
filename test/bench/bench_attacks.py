"""The attacks of issue 22 against solid_node: own loops, false loops and memory under each.

Run: PYTHONPATH=. .venv/bin/python test/bench/bench_attacks.py [--only NAME,...] [--list]

Every scenario starts the node in its own process (``solid_node`` next to the interpreter,
else ``python -m solid_ros.ros.node``; set PYTHONPATH to the tree under test) in a fresh ROS
domain with ``config/avia.yaml`` (reliable QoS and a long queue, so that no cloud is dropped)
and feeds it hku1 (../shared/data/hku1: 314 Livox Avia clouds with odometry), paced by its
/diagnostics. The same process acts as the attacker on the domain (its own DDS participant,
publishing from its own thread). RSS is read after the attack's last message plus
``RENEW_GAP_SEC`` + 3 s (re-subscription and heap trim). For the multi-robot
scenarios the node has ``peers: true`` and a fleet key (``peer_key_file``) the attacker does
not have; ``*_nokey`` variants run the same attack against a node without a key (a trusted
domain), to show what the key is for. Both sides use config/fastdds_shm.xml (clouds over
shared memory), as doc/node.md recommends for the node and its driver.

Printed per scenario: loops published against this robot's own keyframes and how many are
false (pose error against optimized_poses.txt, matched by stamp, beyond 1 m or 3 deg),
loops against other robots (all false for fake robots), the node's RSS after the run (VmRSS,
after 3 s for the heap trim) against the baseline, and what the scenario measures besides
(refusal counters, CPU seconds, /diagnostics size, log lines). Figures depend on the machine's
load (it is shared); run on an idle machine for timings.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path[:0] = [str(HERE.parent), str(HERE.parent / 'ros')]

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from project_paths import CONFIG_DIR, SHARED_DATA  # noqa: E402
from rcl_interfaces.msg import Parameter as ParameterMsg  # noqa: E402
from rcl_interfaces.msg import ParameterType, ParameterValue  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from std_msgs.msg import Float64MultiArray, UInt8MultiArray  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from test_node import read_bag, stamp_of  # noqa: E402

from solid_ros.core.database.archive import read_database  # noqa: E402
from solid_ros.core.database.clouds import KeyframeCloud  # noqa: E402
from solid_ros.core.geometry import quaternion_to_matrix  # noqa: E402
from solid_ros.formats.candidates import decode_candidates  # noqa: E402
from solid_ros.formats.peers import (  # noqa: E402
    CatchUpRequest,
    CloudReply,
    CloudRequest,
    DescriptorMessage,
    decode,
    encode,
    is_sealed,
    seal,
)
from solid_ros.formats.poses import read_kitti_poses  # noqa: E402
from solid_ros.ros.memory import RENEW_GAP_SEC  # noqa: E402
from solid_ros.ros.peers import DESCRIPTOR_TOPIC, REPLY_TOPIC, REQUEST_TOPIC  # noqa: E402
from solid_ros.tools.loops import pose_error  # noqa: E402

SEC = 1_000_000_000
WRONG_KEY = b'the attacker does not have the key'
FAKE = 77


def _matrix(c: dict[str, Any]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(c['qx'], c['qy'], c['qz'], c['qw'])
    T[:3, 3] = c['tx'], c['ty'], c['tz']
    return T


class Rig:
    """solid_node processes in one fresh domain; this process feeds them and attacks."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.domain = random.randint(120, 230)
        self.env = {**os.environ, 'ROS_DOMAIN_ID': str(self.domain)}
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=self.domain)
        self.client = Node('attack_bench', context=self.ctx)
        self.qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.logs: dict[str, Path] = {}
        self.pubs: dict[str, tuple[Any, Any]] = {}
        self.loops: dict[str, list[dict[str, Any]]] = {}
        self.diag: dict[str, dict[str, str]] = {}
        self.diag_bytes: dict[str, int] = {}
        self.lock = threading.Condition()
        self.client.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)
        self.executor = MultiThreadedExecutor(num_threads=3, context=self.ctx)
        self.executor.add_node(self.client)
        self.spinner = threading.Thread(target=self.executor.spin, daemon=True)
        self.spinner.start()
        # The attacker: its own DDS participant, publishing from its own thread.
        self.actx = Context()
        rclpy.init(context=self.actx, domain_id=self.domain)
        self.attacker = Node('attacker', context=self.actx)
        self.aexecutor = MultiThreadedExecutor(num_threads=2, context=self.actx)
        self.aexecutor.add_node(self.attacker)
        self.aspinner = threading.Thread(target=self.aexecutor.spin, daemon=True)
        self.aspinner.start()
        self.jobs: list[Callable[[], None]] = []
        self.jobs_cv = threading.Condition()
        self.closing = False
        self.worker = threading.Thread(target=self._work, daemon=True)
        self.worker.start()
        self.key = tmp / 'fleet.key'
        self.key.write_bytes(os.urandom(32).hex().encode())
        self.key.chmod(0o600)

    def _work(self) -> None:
        while True:
            with self.jobs_cv:
                while not self.jobs and not self.closing:
                    self.jobs_cv.wait()
                if self.closing:
                    return
                job = self.jobs.pop(0)
            job()

    def later(self, job: Callable[[], None]) -> None:
        """Run ``job`` on the attacker's thread (the feed does not wait for it)."""
        with self.jobs_cv:
            self.jobs.append(job)
            self.jobs_cv.notify_all()

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for st in msg.status:
            name = st.name.split(':')[0]
            with self.lock:
                self.diag[name] = {kv.key: kv.value for kv in st.values}
                self.diag_bytes[name] = max(self.diag_bytes.get(name, 0), len(st.message) + sum(
                    len(kv.key) + len(kv.value) for kv in st.values))
                self.lock.notify_all()

    def start(self, robot: str, *params: str, params_file: Path | None = None) -> None:
        """Start a node; ``robot`` is its namespace ('' for none)."""
        exe = Path(sys.executable).parent / 'solid_node'
        cmd = [str(exe)] if exe.is_file() else [sys.executable, '-m', 'solid_ros.ros.node']
        args = ['--ros-args', '--params-file', str(params_file or CONFIG_DIR / 'avia.yaml'),
                '-p', 'qos_reliability:=reliable', '-p', 'qos_depth:=1000',
                '-p', 'queue_size:=1000', '-p', 'diagnostics_period_sec:=0.25',
                '-r', 'odom:=odom_slam']
        if robot:
            args += ['-r', f'__ns:=/{robot}']
        for p in params:
            args += ['-p', p]
        self.logs[robot] = self.tmp / f'node{robot}.log'
        self.procs[robot] = subprocess.Popen([*cmd, *args], env=self.env,
                                             stdout=self.logs[robot].open('w'),
                                             stderr=subprocess.STDOUT)
        ns = f'/{robot}' if robot else ''
        self.pubs[robot] = (
            self.client.create_publisher(PointCloud2, f'{ns}/points', self.qos),
            self.client.create_publisher(Odometry, f'{ns}/odom_slam', self.qos))
        self.loops[robot] = []
        self.client.create_subscription(
            Float64MultiArray, f'{ns}/solid_node/loop_candidates',
            lambda m, r=robot: self.loops[r].extend(decode_candidates(m)), self.qos)
        self.wait(lambda: self.pubs[robot][0].get_subscription_count() > 0
                  and self.pubs[robot][1].get_subscription_count() > 0
                  and self.status(robot).get('clouds_received') is not None,
                  f'node {robot or "solid_node"} up', 60.0)

    def name(self, robot: str) -> str:
        return f'/{robot}/solid_node' if robot else '/solid_node'

    def status(self, robot: str) -> dict[str, str]:
        with self.lock:
            return dict(self.diag.get(self.name(robot), {}))

    def wait(self, pred: Callable[[], bool], what: str, timeout: float = 300.0) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            for r, p in self.procs.items():
                if p.poll() is not None:
                    raise RuntimeError(f'node {r!r} exited {p.returncode}: '
                                       f'{self.logs[r].read_text()[-2000:]}')
            if time.monotonic() > deadline:
                raise RuntimeError(f'timed out waiting for {what}')
            time.sleep(0.05)

    def done(self, robot: str) -> int:
        s = self.status(robot)
        return sum(int(s.get(k, 0)) for k in ('clouds_processed', 'clouds_rejected',
                                               'clouds_skipped', 'clouds_failed'))

    def feed(self, robot: str, messages: list[tuple[str, Any]], window: int = 6,
             each: Callable[[int], None] | None = None) -> None:
        """Publish ('points' | 'odom' | 'sleep', msg) in order, paced by /diagnostics."""
        pub_points, pub_odom = self.pubs[robot]
        base, sent = self.done(robot), 0
        for kind, msg in messages:
            if kind == 'sleep':
                time.sleep(msg)
                continue
            if kind == 'odom':
                pub_odom.publish(msg)
                continue
            self.wait(lambda n=sent: n - (self.done(robot) - base) <= window, 'pace')
            pub_points.publish(msg)
            sent += 1
            if each is not None:
                each(sent)
        self.wait(lambda: self.done(robot) - base >= sent
                  and self.status(robot).get('verify_queue_length') == '0'
                  and self.status(robot).get('queue_length') == '0', 'all processed')
        time.sleep(1.0)  # the last loop messages

    def rss_mb(self, robot: str) -> float:
        for line in Path(f'/proc/{self.procs[robot].pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024
        return math.nan

    def cpu_sec(self, robot: str) -> float:
        fields = Path(f'/proc/{self.procs[robot].pid}/stat').read_text().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')

    def warnings(self, robot: str) -> int:
        return sum('[WARN]' in ln for ln in self.logs[robot].read_text().splitlines())

    def log_bytes(self, robot: str) -> int:
        return self.logs[robot].stat().st_size

    def call(self, robot: str, srv: str) -> Any:
        ns = f'/{robot}' if robot else ''
        cli = self.client.create_client(Trigger, f'{ns}/solid_node/{srv}')
        assert cli.wait_for_service(timeout_sec=20.0)
        fut = cli.call_async(Trigger.Request())
        self.wait(fut.done, srv, 60.0)
        return fut.result()

    def set_params(self, robot: str, values: dict[str, float]) -> list[bool]:
        ns = f'/{robot}' if robot else ''
        cli = self.client.create_client(SetParameters, f'{ns}/solid_node/set_parameters')
        assert cli.wait_for_service(timeout_sec=20.0)
        out = []
        for name, value in values.items():
            pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(value))
            if isinstance(value, int):
                pv = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
            fut = cli.call_async(SetParameters.Request(
                parameters=[ParameterMsg(name=name, value=pv)]))
            self.wait(fut.done, 'set_parameters', 30.0)
            out.append(bool(fut.result().results[0].successful))
        return out

    def publisher(self, topic: str) -> Any:
        # Keep-all: every message the attacker sends reaches the node (flow control).
        qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
        pub = self.attacker.create_publisher(UInt8MultiArray, topic, qos)
        self.wait(lambda: pub.get_subscription_count() > 0, f'{topic} matched', 30.0)
        return pub

    def listen(self, topic: str, handle: Callable[[Any], None]) -> None:
        self.attacker.create_subscription(UInt8MultiArray, topic, handle, self.qos)

    def close(self) -> None:
        with self.jobs_cv:
            self.closing = True
            self.jobs_cv.notify_all()
        self.worker.join(timeout=30.0)
        self.aexecutor.shutdown()
        self.aspinner.join(timeout=10.0)
        self.attacker.destroy_node()
        rclpy.try_shutdown(context=self.actx)
        for p in self.procs.values():
            p.send_signal(signal.SIGINT)
        for p in self.procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        self.executor.shutdown()
        self.spinner.join(timeout=10.0)
        self.client.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def _send(pub: Any, raw: bytes) -> None:
    msg = UInt8MultiArray()
    msg.data = raw
    pub.publish(msg)


def _inner(raw: bytes) -> bytes:
    return raw[20:-32] if is_sealed(raw) else raw


# -- the data ----------------------------------------------------------------------------------


class Hku1:
    """hku1 in publishing order (odometry before its cloud) and its reference poses."""

    def __init__(self) -> None:
        msgs = read_bag(SHARED_DATA / 'hku1' / 'bag')
        self.messages = sorted(msgs, key=lambda km: (stamp_of(km[1]), km[0] == 'points'))
        self.stamps = [stamp_of(m) for k, m in self.messages if k == 'points']
        poses = read_kitti_poses(SHARED_DATA / 'hku1' / 'optimized_poses.txt')
        self.pose_of = dict(zip(self.stamps, poses))

    def score(self, loops: list[dict[str, Any]], own: int = 0,
              stamp_map: Callable[[int], int] = lambda s: s) -> tuple[int, int, int]:
        """(own loops, of them false, loops against other sessions)."""
        mine = [c for c in loops if c['match_session'] == own]
        false = 0
        for c in mine:
            q, m = (self.pose_of.get(stamp_map(int(c['query_stamp_ns']))),
                    self.pose_of.get(stamp_map(int(c['match_stamp_ns']))))
            if q is None or m is None:
                false += 1
                continue
            t, r = pose_error(_matrix(c), np.linalg.solve(m, q))
            false += not (c['verified'] == 1 and t <= 1.0 and r <= 3.0)
        return len(mine), false, len(loops) - len(mine)


def _restamp(msg: Any, stamp_ns: int) -> Any:
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), SEC)
    return msg


def _copy(msg: Any) -> Any:
    return copy.deepcopy(msg)


def _huge_cloud(n: int, stamp_ns: int) -> PointCloud2:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-40, 40, size=(n, 3)).astype('<f4')
    msg = PointCloud2(height=1, width=n, point_step=12, row_step=12 * n, is_dense=True)
    msg.fields = [PointField(name=c, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, c in enumerate('xyz')]
    msg.header.frame_id = 'livox'
    _restamp(msg, stamp_ns)
    msg.data = pts.tobytes()
    return msg


# -- scenarios ----------------------------------------------------------------------------------

Result = dict[str, Any]


def run_single(rig: Rig, data: Hku1, params: list[str], attack: Callable[..., Result] | None,
               messages: list[tuple[str, Any]] | None = None,
               stamp_map: Callable[[int], int] | None = lambda s: s) -> Result:
    """One node fed hku1 (or ``messages``), attacked by ``attack``; ``stamp_map`` takes a
    published stamp to the bag's (None: loops cannot be scored, e.g. every stamp 0)."""
    rig.start('', *params)
    out: Result = {}
    each = attack(rig, data, out) if attack is not None else None
    t0, cpu0 = time.monotonic(), rig.cpu_sec('')
    rig.feed('', messages if messages is not None else data.messages, each=each)
    out['wall_s'] = time.monotonic() - t0
    out['cpu_s'] = rig.cpu_sec('') - cpu0
    out['cpu_s_per_min'] = 60.0 * out['cpu_s'] / out['wall_s']
    rig.wait(lambda: not rig.jobs, 'the attack to end', 600.0)
    time.sleep(RENEW_GAP_SEC + 3.0)  # re-subscription and heap trim after huge messages
    own, false, other = data.score(rig.loops[''], 0, stamp_map or (lambda s: s))
    s = rig.status('')
    out.update(own=own, false=false if stamp_map is not None else 'n/a', other=other,
               rss=rig.rss_mb(''),
               keyframes=int(s.get('database_size', 0)), verify_skipped=s.get('verify_skipped'),
               without_odom=s.get('clouds_without_odom'),
               processing_ms_max=s.get('processing_ms_max'),
               refused={k: s[k] for k in ('odom_rejected', 'cloud_stamps_zero',
                                          'cloud_stamps_backward', 'clouds_downsampled')
                        if s.get(k, '0') != '0'},
               verify_p95=s.get('verify_ms_p95'), warn_lines=rig.warnings(''),
               log_kb=rig.log_bytes('') // 1024, diag_bytes=rig.diag_bytes.get('/solid_node'),
               peer={k[5:]: v for k, v in s.items() if k.startswith('peer_')
                     and k[5:] in _PEER_KEYS})
    return out


_PEER_KEYS = ('unauthenticated', 'descriptors_stored', 'oversized', 'rate_limited',
              'robots_full', 'malformed', 'replies_mismatched', 'clouds_timed_out',
              'peers_backed_off', 'clouds_peer_gone', 'catchups_refused', 'robots',
              'robots_dropped', 'clouds_served', 'replayed', 'stale', 'clouds_rerequested')


def peers_params(rig: Rig, key: bool = True) -> list[str]:
    return ['peers:=true', *([f'peer_key_file:={rig.key}'] if key else [])]


def nan_odometry(data: Hku1) -> list[tuple[str, Any]]:
    """Before each cloud an Odometry with NaN pose and the cloud's stamp; the real odometry
    of that stamp 50 ms after the cloud."""
    out: list[tuple[str, Any]] = []
    odom = {stamp_of(m): m for k, m in data.messages if k == 'odom'}
    for kind, m in data.messages:
        if kind != 'points':
            continue
        bad = _copy(odom.get(stamp_of(m), next(iter(odom.values()))))
        _restamp(bad, stamp_of(m))
        bad.pose.pose.position.x = math.nan
        out += [('odom', bad), ('points', m), ('sleep', 0.05)]
        if stamp_of(m) in odom:
            out.append(('odom', odom[stamp_of(m)]))
    return out


def zero_stamps(data: Hku1) -> list[tuple[str, Any]]:
    return [(k, _restamp(_copy(m), 0)) for k, m in data.messages]


def clock_back(data: Hku1, at: int) -> tuple[list[tuple[str, Any]], Callable[[int], int]]:
    """Every stamp from the ``at``-th cloud on 200 s earlier."""
    jump = data.stamps[at]
    out = [(k, _restamp(_copy(m), stamp_of(m) - 200 * SEC) if stamp_of(m) >= jump else m)
           for k, m in data.messages]
    return out, lambda s: s + 200 * SEC if s < data.stamps[0] else s


def attack_params(rig: Rig, data: Hku1, out: Result) -> None:
    weaken = {'verify_min_overlap': 0.0, 'verify_min_coarse_overlap': 0.0,
              'verify_max_rmse': 10.0, 'verify_max_conflict': 1.0,
              'verify_min_constraint': 0.0, 'verify_min_spread': 0.0,
              'verify_single_object_overlap': 0.0, 'verify_max_drift': 100.0,
              'verify_max_drift_deg': 180.0, 'odom_check_drift': 0.0, 'distance_threshold': 2.0,
              'max_candidates': 10, 'num_candidates': 50}
    ok = rig.set_params('', weaken)
    out['accepted'] = f'{sum(ok)}/{len(ok)}'


def attack_huge(rig: Rig, data: Hku1, out: Result) -> Callable[[int], None]:
    pub = rig.pubs[''][0]
    out['rss_before'] = rig.rss_mb('')

    def each(sent: int) -> None:
        if sent in (100, 101, 102):  # three 80 MB clouds of 5M points
            pub.publish(_huge_cloud(5_000_000, data.stamps[sent - 1] + 1000))
        if 100 <= sent <= 110:
            out['rss_peak'] = max(out.get('rss_peak', 0.0), rig.rss_mb(''))
    return each


def attack_reset_save(rig: Rig, data: Hku1, out: Result, db: Path) -> None:
    out['saved'] = rig.call('', 'save_database').message
    out['reset'] = rig.call('', 'reset').message
    out['wiped'] = rig.call('', 'save_database').message
    out['file_scans'] = read_database(db)[0]['count']
    bak = Path(f'{db}.bak')
    out['backup_scans'] = read_database(bak)[0]['count'] if bak.exists() else None


def attack_relay(rig: Rig, data: Hku1, out: Result, fake: int = FAKE,
                 silent: bool = False) -> Callable[[int], None]:
    """A fake robot re-publishes the victim's descriptors; unless ``silent`` it relays the
    victim's own clouds, turned 20 deg and shifted 1.6 m, as its replies (it asks the victim
    for them as another fake robot and in the victim's own name)."""
    desc, req, rep = (rig.publisher(t) for t in (DESCRIPTOR_TOPIC, REQUEST_TOPIC, REPLY_TOPIC))
    waiting: dict[int, CloudRequest] = {}
    c, s = math.cos(math.radians(20)), math.sin(math.radians(20))
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)

    def on_desc(m: UInt8MultiArray) -> None:
        try:
            d = decode(_inner(bytes(m.data)))
        except Exception:
            return
        if isinstance(d, DescriptorMessage) and d.robot == 0:
            for r in ([fake] if not silent else range(81, 86)):
                raw = encode(DescriptorMessage(r, d.index, d.stamp_ns, d.fingerprint, d.r_solid,
                                               d.heading, d.pose))
                _send(desc, raw)
                _send(desc, seal(raw, WRONG_KEY, r, time.time_ns(), DESCRIPTOR_TOPIC))

    def on_req(m: UInt8MultiArray) -> None:
        try:
            q = decode(_inner(bytes(m.data)))
        except Exception:
            return
        if silent or not isinstance(q, CloudRequest) or q.owner != fake:
            return
        rid = random.getrandbits(32)
        waiting[rid] = q
        for requester in (fake + 1, 0):  # as another robot, and in the victim's own name
            _send(req, encode(CloudRequest(requester, 0, q.index, rid, q.stamp_ns)))

    def on_rep(m: UInt8MultiArray) -> None:
        try:
            r = decode(_inner(bytes(m.data)))
        except Exception:
            return
        if not isinstance(r, CloudReply) or r.owner != 0 or r.request_id not in waiting:
            return
        q = waiting.pop(r.request_id)
        if r.cloud is None:
            return
        pts = r.cloud.points @ R.T + np.array([1.6, 0, 0], np.float32)
        raw = encode(CloudReply(fake, 0, q.index, q.request_id, q.stamp_ns,
                                KeyframeCloud(pts.astype(np.float32), r.cloud.n_struct)))
        _send(rep, raw)
        _send(rep, seal(raw, WRONG_KEY, fake, time.time_ns(), REPLY_TOPIC))

    rig.listen(DESCRIPTOR_TOPIC, on_desc)
    rig.listen(REQUEST_TOPIC, on_req)
    rig.listen(REPLY_TOPIC, on_rep)
    return lambda sent: None


def attack_flood(rig: Rig, data: Hku1, out: Result, total: int = 110_000,
                 ) -> Callable[[int], None]:
    """``total`` valid descriptors (the victim's settings) from 10 robot ids, spread over the
    run."""
    pub = rig.publisher(DESCRIPTOR_TOPIC)
    fp = _fingerprint()
    rng = np.random.default_rng(1)
    per_cloud = total // len(data.stamps) + 1
    count = [0]

    def burst() -> None:
        for _ in range(per_cloud):
            if count[0] >= total:
                return
            i = count[0]
            _send(pub, encode(DescriptorMessage(
                100 + i % 10, i, i, fp, rng.random(40).astype(np.float32),
                rng.random(60).astype(np.float32))))
            count[0] += 1
    return lambda sent: rig.later(burst)


def _fingerprint() -> str:
    from solid_ros.core.config import SolidConfig

    return SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml').fingerprint()


def attack_big_replies(rig: Rig, data: Hku1, out: Result) -> Callable[[int], None]:
    pub = rig.publisher(REPLY_TOPIC)
    # A reply announcing a small cloud padded to 24 MB (clouds go packed: 2 million points
    # would no longer make a big message).
    pts = np.random.default_rng(2).uniform(-50, 50, size=(2_000, 3)).astype(np.float32)
    raw = encode(CloudReply(FAKE, 0, 1, 2, 3, KeyframeCloud(pts, 1000))) + bytes(24_000_000)

    def each(sent: int) -> None:
        if sent % 15 == 0 and sent <= 300:  # 20 of them, 24 MB each
            rig.later(lambda: _send(pub, raw))
    return each


def attack_garbage(rig: Rig, data: Hku1, out: Result) -> Callable[[int], None]:
    pub = rig.publisher(DESCRIPTOR_TOPIC)
    blob = os.urandom(100 * 1024 * 1024)

    def each(sent: int) -> None:
        if sent % 15 == 0 and sent <= 300:  # 20 x 100 MB
            rig.later(lambda: _send(pub, blob))
    return each


def attack_ids(rig: Rig, data: Hku1, out: Result) -> Callable[[int], None]:
    """30,000 robot ids, each with a descriptor of other settings (one warning each, once)."""
    pub = rig.publisher(DESCRIPTOR_TOPIC)
    r, a = np.ones(40, np.float32) / 40 ** 0.5, np.ones(60, np.float32) / 60 ** 0.5
    ids = iter(range(1000, 31_000))

    def burst() -> None:
        for robot in [next(ids, None) for _ in range(100)]:
            if robot is not None:
                _send(pub, encode(DescriptorMessage(robot, 0, 1, 'ffffffffffffffff', r, a)))
    return lambda sent: rig.later(burst)


def attack_storms(rig: Rig, data: Hku1, out: Result) -> Callable[[int], None]:
    """Catch-up requests from ever new ids and cloud requests for every stored keyframe."""
    pub = rig.publisher(REQUEST_TOPIC)
    ids = iter(range(2000, 10**6))

    def burst(sent: int) -> None:
        for _ in range(20):
            _send(pub, encode(CatchUpRequest(next(ids), 100_000)))
        for index in range(max(0, sent - 200), sent):
            _send(pub, encode(CloudRequest(next(ids), 0, index, index, data.stamps[index])))
    return lambda sent: rig.later(lambda: burst(sent))


def split_racer(rig: Rig, data: Hku1, key: bool, mode: str) -> Result:
    """hku1's first half is robot 0, its second half robot 1 (which returns to robot 0's
    start). ``mode`` 'racer': an attacker answers robot 1's cloud requests first, with robot
    0's keyframe turned 20 degrees (it asks robot 0 for it, in robot 1's name); 'storm': it
    floods robot 0 with catch-up and cloud requests while robot 1 runs; 'none': no attack."""
    params = rig.tmp / 'fleet.yaml'
    params.write_text((CONFIG_DIR / 'avia.yaml').read_text().replace('solid_node:', '/**:', 1))
    for r, sid in (('r0', 0), ('r1', 1)):
        rig.start(r, f'session_id:={sid}', *peers_params(rig, key), params_file=params)
    req, rep = rig.publisher(REQUEST_TOPIC), rig.publisher(REPLY_TOPIC)
    c, s = math.cos(math.radians(20)), math.sin(math.radians(20))
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)
    pending: dict[int, CloudRequest] = {}

    def on_req(m: UInt8MultiArray) -> None:
        try:
            q = decode(_inner(bytes(m.data)))
        except Exception:
            return
        if isinstance(q, CloudRequest) and q.requester == 1 and q.owner == 0:
            rid = random.getrandbits(32)
            pending[rid] = q
            _send(req, encode(CloudRequest(1, 0, q.index, rid, q.stamp_ns)))

    def on_rep(m: UInt8MultiArray) -> None:
        try:
            r = decode(_inner(bytes(m.data)))
        except Exception:
            return
        if isinstance(r, CloudReply) and r.request_id in pending and r.cloud is not None:
            q = pending.pop(r.request_id)
            pts = (r.cloud.points @ R.T).astype(np.float32)
            raw = encode(CloudReply(0, 1, q.index, q.request_id, q.stamp_ns,
                                    KeyframeCloud(pts, r.cloud.n_struct)))
            _send(rep, raw)
            _send(rep, seal(raw, WRONG_KEY, 0, time.time_ns(), REPLY_TOPIC))

    storm = mode == 'storm'
    if mode == 'racer':
        rig.listen(REQUEST_TOPIC, on_req)
        rig.listen(REPLY_TOPIC, on_rep)
    half = data.stamps[len(data.stamps) // 2]
    first = [(k, m) for k, m in data.messages if stamp_of(m) < half]
    second = [(k, m) for k, m in data.messages if stamp_of(m) >= half]
    rig.feed('r0', first)
    each = None
    if storm:
        ids = iter(range(2000, 10**6))
        stamps = data.stamps[:len(data.stamps) // 2]

        def burst() -> None:
            for _ in range(20):
                _send(req, encode(CatchUpRequest(next(ids), 100_000)))
            for index in range(0, min(200, len(stamps))):
                _send(req, encode(CloudRequest(next(ids), 0, index, index, stamps[index])))

        def each(sent: int) -> None:
            rig.later(burst)
    cpu0 = rig.cpu_sec('r0')
    t0 = time.monotonic()
    rig.feed('r1', second, each=each)
    cpu_r0 = 60.0 * (rig.cpu_sec('r0') - cpu0) / (time.monotonic() - t0)
    loops = rig.loops['r1']
    inter = [c for c in loops if c['match_session'] == 0]
    _, false, _ = data.score(inter, 0)
    s = rig.status('r1')
    s0 = rig.status('r0')
    return {'inter_robot': len(inter), 'false': false, 'robot0_cpu_s_per_min': cpu_r0,
            'peer': {k[5:]: v for k, v in s.items() if k[5:] in _PEER_KEYS},
            'robot0_peer': {k[5:]: v for k, v in s0.items() if k[5:] in _PEER_KEYS}}


def stored_ids(tmp: Path) -> Result:
    """A saved database holding robot 2**31 - 1 and one holding -1: the node's start."""
    from solid_ros.core.config import SolidConfig
    from solid_ros.core.database.descriptors import DescriptorDatabase
    from solid_ros.core.database.persistence import save_database

    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml')
    db = DescriptorDatabase(cfg.replace(session_id=2**31 - 1))
    rng = np.random.default_rng(0)
    db.add(rng.random(40), rng.random(60), 1)
    top = save_database(db, tmp / 'top.npz')
    meta, arrays = read_database(top)
    arrays['sessions'][:] = -1
    meta['sessions'] = [-1]
    arrays['meta'] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    neg = tmp / 'neg.npz'
    np.savez(neg, **arrays)
    out = {}
    exe = Path(sys.executable).parent / 'solid_node'
    cmd = [str(exe)] if exe.is_file() else [sys.executable, '-m', 'solid_ros.ros.node']
    for name, path in (('top', top), ('negative', neg)):
        proc = subprocess.run(
            [*cmd, '--ros-args', '--params-file', str(CONFIG_DIR / 'avia.yaml'), '-p',
             f'database_load_path:={path}', '-p', f'session_id:={2**31 - 1}'],
            capture_output=True, text=True, timeout=60,
            env={**os.environ, 'ROS_DOMAIN_ID': str(random.randint(120, 230))})
        lines = [ln for ln in proc.stderr.splitlines() + proc.stdout.splitlines()
                 if 'FATAL' in ln or 'error' in ln]
        out[name] = f'exit {proc.returncode}: {lines[-1] if lines else ""}'
    return out


# -- main ----------------------------------------------------------------------------------------


def scenarios(tmp: Path) -> dict[str, Callable[[Rig, Hku1], Result]]:
    db = tmp / 'map.npz'
    back: dict[str, Any] = {}

    def clock(rig: Rig, data: Hku1) -> Result:
        msgs, stamp_map = clock_back(data, 157)
        back['map'] = stamp_map
        return run_single(rig, data, ['exclude_recent_sec:=10.0'], None, msgs, stamp_map)

    def peer(attack: Callable[..., Any], key: bool = True, **kw: Any
             ) -> Callable[[Rig, Hku1], Result]:
        return lambda rig, data: run_single(
            rig, data, peers_params(rig, key), lambda r, d, o: attack(r, d, o, **kw))

    return {
        'baseline': lambda rig, data: run_single(rig, data, [], None),
        'baseline_peers': lambda rig, data: run_single(rig, data, peers_params(rig), None),
        'nan_odometry': lambda rig, data: run_single(rig, data, [], None, nan_odometry(data)),
        'zero_stamps': lambda rig, data: run_single(rig, data, [], None, zero_stamps(data),
                                                    None),
        'clock_back_200s': clock,
        'weaken_params': lambda rig, data: run_single(rig, data, [], attack_params),
        'reset_save': lambda rig, data: _reset_save(rig, data, db),
        'huge_clouds': lambda rig, data: run_single(rig, data, [], attack_huge),
        'relay': peer(attack_relay),
        'relay_nokey': peer(attack_relay, key=False),
        'silent_robots': peer(attack_relay, silent=True),
        'silent_robots_nokey': peer(attack_relay, key=False, silent=True),
        'flood_110k': peer(attack_flood),
        'flood_110k_nokey': peer(attack_flood, key=False),
        'replies_2M_points': peer(attack_big_replies),
        'garbage_100MB': peer(attack_garbage),
        'robot_ids_30k': peer(attack_ids),
        'robot_ids_30k_nokey': peer(attack_ids, key=False),
        'request_storms': peer(attack_storms),
        'request_storms_nokey': peer(attack_storms, key=False),
        'split': lambda rig, data: split_racer(rig, data, True, 'none'),
        'racer_split': lambda rig, data: split_racer(rig, data, True, 'racer'),
        'racer_split_nokey': lambda rig, data: split_racer(rig, data, False, 'racer'),
        'storm_split': lambda rig, data: split_racer(rig, data, True, 'storm'),
        'storm_split_nokey': lambda rig, data: split_racer(rig, data, False, 'storm'),
        'stored_ids': lambda rig, data: stored_ids(rig.tmp),
    }


def _reset_save(rig: Rig, data: Hku1, db: Path) -> Result:
    out = run_single(rig, data, [f'database_save_path:={db}'], None)
    attack_reset_save(rig, data, out, db)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--only', default='', help='comma-separated scenario names')
    parser.add_argument('--list', action='store_true')
    args = parser.parse_args()
    # Clouds over shared memory: with fragmented UDP on a loaded machine odometry was held
    # back for seconds by retransmissions, and the baseline itself varied.
    os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(CONFIG_DIR / 'fastdds_shm.xml')
    tmp_root = Path(tempfile.mkdtemp(prefix='solid_attacks_'))
    table = scenarios(tmp_root)
    if args.list:
        print('\n'.join(table))
        return 0
    names = [n for n in args.only.split(',') if n] or list(table)
    data = Hku1()
    print(f'hku1: {len(data.stamps)} clouds; node logs under {tmp_root}', flush=True)
    base_rss = None
    for name in names:
        tmp = tmp_root / name
        tmp.mkdir()
        rig = Rig(tmp)
        try:
            result = table[name](rig, data)
        except RuntimeError as err:
            result = {'error': str(err)[:500]}
        finally:
            rig.close()
        if name == 'baseline' and 'rss' in result:
            base_rss = result['rss']
        if base_rss is not None and 'rss' in result:
            result['rss_vs_baseline'] = round(result['rss'] - base_rss, 1)
        shown = {k: (round(v, 1) if isinstance(v, float) else v) for k, v in result.items()}
        print(f'{name}: {shown}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
