"""solid_node with real rclpy and Fast DDS: bag replay, bad clouds, runtime parameters, reload.

The node runs in this process on an executor thread; a separate test node publishes clouds and
odometry and subscribes to the outputs over DDS (no mocks). Every test gets its own rclpy
context and the module a random ROS_DOMAIN_ID, so parallel test runs do not hear each other.
"""

from __future__ import annotations

import array
import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from polling import wait_until  # noqa: E402
from project_paths import CONFIG_DIR  # noqa: E402
from rcl_interfaces.msg import Parameter as ParameterMsg  # noqa: E402
from rcl_interfaces.msg import ParameterType, ParameterValue  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy_msgs import make_cloud  # noqa: E402
from ros_domains import pick_domain  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from spinning import Spinner  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402
from solid_ros.formats.candidates import decode_candidates  # noqa: E402
from solid_ros.formats.pointcloud2 import cloud_to_xyz  # noqa: E402
from solid_ros.ros import health as health_module  # noqa: E402
from solid_ros.ros import node as node_module  # noqa: E402
from solid_ros.ros.node import SolidNode  # noqa: E402

AVIA = CONFIG_DIR / 'avia.yaml'
TIMEOUT = 120.0
# Replays must not lose clouds: reliable QoS and queues longer than the bag.
NO_DROP = [Parameter('qos_reliability', value='reliable'), Parameter('qos_depth', value=1000),
           Parameter('queue_size', value=1000)]


@pytest.fixture(scope='module', autouse=True)
def domain_id() -> Iterator[None]:
    old = os.environ.get('ROS_DOMAIN_ID')
    os.environ['ROS_DOMAIN_ID'] = str(pick_domain())
    yield
    if old is None:
        os.environ.pop('ROS_DOMAIN_ID', None)
    else:
        os.environ['ROS_DOMAIN_ID'] = old


# -- message helpers ---------------------------------------------------------------------------


def from_rosbags_cloud(m: Any) -> PointCloud2:
    """Copy a rosbags PointCloud2 into an rclpy message (all fields, data as is)."""
    msg = PointCloud2()
    msg.header.frame_id = m.header.frame_id
    msg.header.stamp.sec, msg.header.stamp.nanosec = m.header.stamp.sec, m.header.stamp.nanosec
    msg.height, msg.width = m.height, m.width
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                  for f in m.fields]
    msg.is_bigendian, msg.is_dense = bool(m.is_bigendian), bool(m.is_dense)
    msg.point_step, msg.row_step = m.point_step, m.row_step
    msg.data = array.array('B', np.asarray(m.data, dtype=np.uint8).tobytes())
    return msg


def from_rosbags_odom(m: Any) -> Odometry:
    msg = Odometry()
    msg.header.frame_id = m.header.frame_id
    msg.header.stamp.sec, msg.header.stamp.nanosec = m.header.stamp.sec, m.header.stamp.nanosec
    msg.child_frame_id = m.child_frame_id
    p, q = m.pose.pose.position, m.pose.pose.orientation
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = p.x, p.y, p.z
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = q.x, q.y, q.z, q.w
    return msg


def read_bag(path: Path, points_topic: str = '/points',
             odom_topic: str | None = '/odom_slam') -> list[tuple[str, Any]]:
    """Messages of a bag in log order as ('points' | 'odom', rclpy message)."""
    from rosbags.highlevel import AnyReader

    out: list[tuple[str, Any]] = []
    with AnyReader([path]) as reader:
        topics = {points_topic} | ({odom_topic} if odom_topic else set())
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, _, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            if conn.topic == points_topic:
                out.append(('points', from_rosbags_cloud(m)))
            else:
                out.append(('odom', from_rosbags_odom(m)))
    return out


def make_odom(stamp_ns: int, x: float, y: float = 0.0, frame: str = 'odom') -> Odometry:
    msg = Odometry()
    msg.header.frame_id = frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(x), float(y)
    msg.pose.pose.orientation.w = 1.0
    return msg


def stamp_of(msg: Any) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def offline(messages: list[tuple[str, Any]], config: SolidConfig,
            detector: LoopDetector | None = None) -> list[tuple[int, int, int, int, int]]:
    """What the core finds for the same clouds (poses paired by exact stamp)."""
    from solid_ros.formats.poses import odometry_to_pose

    det = detector or LoopDetector(config)
    poses = {stamp_of(m): odometry_to_pose(m) for kind, m in messages if kind == 'odom'}
    found = []
    for kind, m in messages:
        if kind != 'points':
            continue
        stamp = stamp_of(m)
        for c in det.process(cloud_to_xyz(m), stamp, pose=poses.get(stamp)).loops:
            found.append((c.query_index, c.match_index, c.query_stamp_ns, c.match_stamp_ns,
                          c.match_session))
    return found


def offline_closure(messages: list[tuple[str, Any]], config: SolidConfig,
                    load: Path | None = None
                    ) -> tuple[list[tuple[int, int, int, int, int]], LoopDetector]:
    """What the core's loop closure (detector and, with ``backend``, the pose graph and its
    candidates by position; the database ``load`` if given) finds for the same clouds, each
    with the odometry message of its stamp as the node pairs it; and its detector after them."""
    from solid_ros.core.flow.closure import LoopClosure
    from solid_ros.core.odometry.track import StampedOdometry
    from solid_ros.formats.poses import odometry_to_pose

    closure = (LoopClosure(LoopDetector(config)) if load is None
               else LoopClosure.load(load, config))
    odom = StampedOdometry(0)
    found = []
    for kind, m in messages:
        if kind == 'odom':
            odom.add(stamp_of(m), odometry_to_pose(m), m.pose.covariance)
            continue
        stamp = stamp_of(m)
        step = closure.process(cloud_to_xyz(m), stamp, odom.pose_for(stamp))
        found += [(c.query_index, c.match_index, c.query_stamp_ns, c.match_stamp_ns,
                   c.match_session) for c in step.scan.loops]
    return found, closure.detector


def key(c: dict[str, Any]) -> tuple[int, int, int, int, int]:
    return (int(c['query_index']), int(c['match_index']), int(c['query_stamp_ns']),
            int(c['match_stamp_ns']), int(c['match_session']))


# -- harness ------------------------------------------------------------------------------------


class Harness:
    """The node under test plus a client node, spun by one executor thread."""

    def __init__(self, ctx: Context, overrides: list[Parameter], params_file: Path | None,
                 remap: list[str] | None = None, matched: bool = True) -> None:
        cli = ['--ros-args']
        if params_file is not None:
            cli += ['--params-file', str(params_file)]
        for r in remap or []:
            cli += ['-r', r]
        self.node = SolidNode(context=ctx, cli_args=cli, parameter_overrides=overrides)
        self.client = Node('solid_test_client', context=ctx)
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_points = self.client.create_publisher(PointCloud2, '/points', qos)
        self.pub_odom = self.client.create_publisher(Odometry, '/odom_slam', qos)
        self.candidates: list[dict[str, Any]] = []
        self.markers: list[MarkerArray] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.late_subscriptions: list[Any] = []
        self.client.create_subscription(
            Float64MultiArray, '/solid_node/loop_candidates',
            lambda m: self.candidates.extend(decode_candidates(m)), qos)
        self.client.create_subscription(MarkerArray, '/solid_node/loop_markers',
                                        self.markers.append, 10)
        self.client.create_subscription(DiagnosticArray, '/diagnostics',
                                        self.diagnostics.append, 10)
        self.executor = MultiThreadedExecutor(num_threads=3, context=ctx)
        self.executor.add_node(self.node)
        self.executor.add_node(self.client)
        self.spinner = Spinner(self.executor)
        if matched:
            self.wait_for(lambda: self.pub_points.get_subscription_count() > 0,
                          'points matched')

    def wait_for(self, pred: Callable[[], bool], what: str, timeout: float = TIMEOUT) -> None:
        wait_until(pred, what, timeout)

    def replay(self, messages: list[tuple[str, Any]], bad: dict[int, PointCloud2] | None = None
               ) -> None:
        """Publish in order; ``bad[i]`` is published before the i-th cloud."""
        sent = self.node.stats.received
        loops0, rows0 = self.node.stats.loops, len(self.candidates)
        n = 0
        for kind, msg in messages:
            if kind == 'odom':
                self.pub_odom.publish(msg)
                continue
            if bad and n in bad:
                self.pub_points.publish(bad[n])
                sent += 1
            self.pub_points.publish(msg)
            sent += 1
            n += 1
            # Pace the publisher so DDS history never overflows on a busy machine.
            self.wait_for(lambda s=sent: self.node.stats.received >= s - 50, 'delivery')
        self.wait_for(lambda: self.node.stats.received >= sent, 'all clouds received')
        assert self.node.wait_idle(TIMEOUT)
        # Every candidate row the node published must arrive (a fixed sleep raced under load).
        self.wait_for(lambda: len(self.candidates) - rows0 >= self.node.stats.loops - loops0,
                      'all candidate messages')

    def call(self, service: str) -> Trigger.Response:
        cli = self.client.create_client(Trigger, service)
        assert cli.wait_for_service(timeout_sec=10.0)
        fut = cli.call_async(Trigger.Request())
        self.wait_for(fut.done, service)
        return fut.result()

    def set_param(self, name: str, value: float) -> Any:
        cli = self.client.create_client(SetParameters, '/solid_node/set_parameters')
        assert cli.wait_for_service(timeout_sec=10.0)
        req = SetParameters.Request(parameters=[ParameterMsg(
            name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE,
                                            double_value=value))])
        fut = cli.call_async(req)
        self.wait_for(fut.done, 'set_parameters')
        return fut.result().results[0]

    def late_markers(self) -> MarkerArray:
        """What a display subscribing now with transient-local QoS receives first."""
        got: list[MarkerArray] = []
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # Kept until close(): destroying it while the executor spins raced its wait set
        # ('cannot use Destroyable', a thread exception seen in the suite).
        self.late_subscriptions.append(self.client.create_subscription(
            MarkerArray, '/solid_node/loop_markers', got.append, qos))
        self.wait_for(lambda: bool(got), 'latched markers', 10.0)
        return got[0]

    def status(self) -> dict[str, str]:
        """The newest /diagnostics status: its values plus 'level' and 'message'."""
        if not self.diagnostics:
            return {}
        st = self.diagnostics[-1].status[0]
        return {kv.key: kv.value for kv in st.values} | {'level': str(int.from_bytes(
            st.level, 'little') if isinstance(st.level, bytes) else st.level),
            'message': st.message}

    def close(self) -> None:
        self.spinner.stop()  # out of the wait set before the nodes go
        self.node.destroy_node()
        self.client.destroy_node()


@pytest.fixture()
def harness(context: Context) -> Iterator[Callable[..., Harness]]:
    made: list[Harness] = []

    def make(overrides: list[Parameter] | None = None, params_file: Path | None = AVIA,
             remap: list[str] | None = None, matched: bool = True) -> Harness:
        h = Harness(context, NO_DROP + (overrides or []), params_file,
                    remap if remap is not None else ['odom:=/odom_slam'], matched)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()


@pytest.fixture(scope='module')
def hku1(request: pytest.FixtureRequest) -> list[tuple[str, Any]]:
    shared = request.getfixturevalue('shared_data')
    return read_bag(shared / 'hku1' / 'bag')


def _revisits(cands: list[tuple[int, int, int, int, int]],
              messages: list[tuple[str, Any]]) -> list[tuple[int, int]]:
    # The sequence returns to its start: recorded scans ~274-313 revisit ~19-34. Keyframe
    # indices depend on the gating, so the scans are recognised by their stamps.
    stamps = [stamp_of(m) for k, m in messages if k == 'points']
    return [(q, m) for q, m, qs, ms, _ in cands
            if qs >= stamps[260] and stamps[5] <= ms <= stamps[50]]


# -- tests ---------------------------------------------------------------------------------------


def _odom_first(messages: list[tuple[str, Any]]) -> list[tuple[str, Any]]:
    # Odometry of a stamp before its cloud, so pairing never depends on machine load.
    return sorted(messages, key=lambda km: (stamp_of(km[1]), km[0] == 'points'))


def test_hku1_bag_replay_finds_the_revisit(harness: Callable[..., Harness],
                                           hku1: list[tuple[str, Any]]) -> None:
    h = harness()
    h.replay(_odom_first(hku1))
    assert h.node.stats.without_odom == 0
    got = [key(c) for c in h.candidates]
    # The preset's back end runs on the recorded odometry; the node verifies each keyframe
    # with the graph after the previous one, as the core's loop closure does.
    want, twin = offline_closure(_odom_first(hku1), SolidConfig.from_yaml(AVIA))
    assert got == want
    assert any(c['source'] == 1 for c in h.candidates)  # some proposed by the pose graph
    assert _revisits(got, hku1), got
    # Every published loop was verified and carries its pose and covariance.
    assert all(c['verified'] == 1 and 0.0 < c['fitness'] <= 1.0 and c['cov_0'] > 0.0
               for c in h.candidates)
    assert h.node.stats.processed == sum(1 for k, _ in hku1 if k == 'points')
    assert h.node.stats.skipped == 0 and h.node.stats.rejected == 0
    # Odometry was paired, so the loop edges were drawn between keyframe positions.
    h.wait_for(lambda: bool(h.markers)
               and len(h.markers[-1].markers[0].points) == 2 * len(got), 'all loop edges', 10.0)
    assert h.markers[-1].markers[0].header.frame_id == 'map'
    # Latched: a display started after the last loop still gets every edge.
    late = h.late_markers().markers[0]
    assert len(late.points) == 2 * len(got) and late.ns == 'loop_edges'

    def latest() -> dict[str, str]:
        return {kv.key: kv.value for d in h.diagnostics[-1:] for kv in d.status[0].values}

    # Diagnostics are periodic: wait for one issued after the last cloud.
    h.wait_for(lambda: latest().get('clouds_processed') == str(h.node.stats.processed),
               'up-to-date diagnostics')
    values = latest()
    # The preset's keyframe gating stores fewer scans than it processes, as offline.
    assert int(values['database_size']) == twin.num_keyframes < h.node.stats.processed
    assert float(values['processing_ms_p50']) > 0.0
    # Per-stage times and what verification decided.
    assert float(values['describe_ms_p50']) > 0.0 and float(values['verify_ms_p50']) > 0.0
    assert int(values['verify_verified']) == len(got) and int(values['keyframe_clouds']) > 0
    # What the run learned about itself, as the replay's twin learned it.
    learned = twin.calibration.learned
    assert int(values['calibration_tried']) == learned.tried > 0
    assert float(values['verify_max_conflict_in_force']) == pytest.approx(
        twin.bars.max_conflict, abs=1e-4)


def test_bag_written_in_tmp_path(harness: Callable[..., Harness], hku1: list[tuple[str, Any]],
                                 tmp_path: Path) -> None:
    from solid_ros.formats.bags import write_cloud_bag
    from solid_ros.formats.pointcloud2 import FLOAT64, CloudLayout, Field

    def padded_f8(m: PointCloud2) -> tuple[CloudLayout, int]:
        # Rewrite as float64 x y z with padding, to exercise another layout end to end.
        xyz = np.asarray(cloud_to_xyz(m), dtype='<f8')
        rec = np.zeros(len(xyz), dtype=[('x', '<f8'), ('y', '<f8'), ('z', '<f8'),
                                        ('pad', 'u1', 8)])
        rec['x'], rec['y'], rec['z'] = xyz.T
        layout = CloudLayout(fields=tuple(Field(n, 8 * i, FLOAT64) for i, n in enumerate('xyz')),
                             width=len(xyz), point_step=32, row_step=32 * len(xyz),
                             data=rec.view(np.uint8).reshape(-1))
        return layout, stamp_of(m)

    bag = tmp_path / 'replay_bag'
    clouds = [m for k, m in hku1 if k == 'points']
    write_cloud_bag(bag, [padded_f8(m) for m in clouds], 'sqlite3', points_topic='/lidar',
                    odom_topic=None)
    messages = read_bag(bag, points_topic='/lidar', odom_topic=None)
    assert len(messages) == len(clouds)
    h = harness([Parameter('use_odom', value=False)], remap=['points:=/points'])
    h.replay(messages)
    got = [key(c) for c in h.candidates]
    assert got == offline(messages, SolidConfig.from_yaml(AVIA))
    assert _revisits(got, messages)


def _bad_clouds(good: PointCloud2) -> list[PointCloud2]:
    short = make_cloud(np.ones((10, 3)), stamp_of(good))
    short.data = short.data[:-4]
    no_z = make_cloud(np.ones((10, 3)), stamp_of(good))
    no_z.fields = no_z.fields[:2]
    int_x = make_cloud(np.ones((10, 3)), stamp_of(good))
    int_x.fields[0].datatype = PointField.INT32
    zero_step = make_cloud(np.ones((10, 3)), stamp_of(good))
    zero_step.point_step = 0
    empty = make_cloud(np.zeros((0, 3)), stamp_of(good))
    return [short, no_z, int_x, zero_step, empty]


def test_malformed_clouds_leave_results_unchanged(harness: Callable[..., Harness],
                                                  hku1: list[tuple[str, Any]]) -> None:
    clouds = [m for k, m in hku1 if k == 'points']
    bad_list = _bad_clouds(clouds[0])
    bad = {i: bad_list[(i // 20) % len(bad_list)] for i in range(3, len(clouds), 20)}
    h = harness()
    # Odometry first, as in the bag test: each cloud pairs as in the core's loop closure.
    h.replay(_odom_first(hku1), bad=bad)
    got = [key(c) for c in h.candidates]
    assert got == offline_closure(_odom_first(hku1), SolidConfig.from_yaml(AVIA))[0]
    assert h.node.stats.rejected == len(bad)
    assert h.node.stats.processed == len(clouds)
    assert h.node.stats.failed == 0


def _scene(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-40, -40, -2], [40, 40, 6], size=(6000, 3))
    return pts[np.hypot(pts[:, 0], pts[:, 1]) > 4.0]


def test_runtime_threshold_change(harness: Callable[..., Harness]) -> None:
    h = harness([Parameter('distance_threshold', value=0.0),
                 Parameter('exclude_recent_frames', value=0),
                 Parameter('allow_runtime_weakening', value=True)], params_file=None)
    scene = _scene(1)
    h.replay([('points', make_cloud(scene, 10**9)), ('points', make_cloud(scene, 2 * 10**9))])
    assert h.candidates == []  # nothing is below a threshold of 0
    result = h.set_param('distance_threshold', 0.5)
    assert result.successful, result.reason
    assert h.node.solid_config.distance_threshold == 0.5
    h.replay([('points', make_cloud(scene, 3 * 10**9))])
    assert [c['match_index'] for c in h.candidates] == [0]
    assert h.candidates[0]['distance'] < 1e-9
    assert h.candidates[0]['query_stamp_ns'] == 3 * 10**9
    rejected = h.set_param('distance_threshold', 7.5)
    assert not rejected.successful
    assert 'distance_threshold' in rejected.reason and '2.0' in rejected.reason
    read_only = h.set_param('max_range', 50.0)
    assert not read_only.successful and 'max_range' in read_only.reason
    assert h.node.solid_config.distance_threshold == 0.5
    assert h.node.get_parameter('distance_threshold').value == 0.5


def test_save_restart_load_finds_first_session(harness: Callable[..., Harness],
                                               hku1: list[tuple[str, Any]],
                                               tmp_path: Path) -> None:
    db = tmp_path / 'sub' / 'hku1_first.npz'
    stamps = [stamp_of(m) for k, m in hku1 if k == 'points']
    split = stamps[150]
    first = [(k, m) for k, m in hku1 if stamp_of(m) < split]
    second = [(k, m) for k, m in hku1 if stamp_of(m) >= stamps[250]]
    h1 = harness([Parameter('database_save_path', value=str(db))])
    h1.replay(_odom_first(first))
    saved = h1.call('/solid_node/save_database')
    assert saved.success, saved.message
    assert db.is_file()
    h1.close()

    h2 = harness([Parameter('database_load_path', value=str(db)),
                  Parameter('session_id', value=1)])
    assert h2.node.node_config.database_load_path == str(db)
    h2.replay(_odom_first(second))
    got = h2.candidates
    from_first = [c for c in got if c['match_session'] == 0]
    assert from_first, got
    assert all(c['match_stamp_ns'] < split for c in from_first)
    assert any(5 <= c['match_index'] <= 50 for c in from_first)
    cfg = SolidConfig.from_yaml(AVIA).replace(session_id=1)
    # The node runs the core's loop closure on the loaded file: its scans, and with the back
    # end their map poses, so candidates by position in that map too.
    assert [key(c) for c in got] == offline_closure(_odom_first(second), cfg, load=db)[0]
    # Loops against the loaded session are drawn too, at the positions saved with its scans
    # (blue), the others red.
    h2.wait_for(lambda: bool(h2.markers)
                and len(h2.markers[-1].markers[0].points) == 2 * len(got), 'all edges', 10.0)
    edges = h2.markers[-1].markers[0]
    blue = [c.b == 1.0 for c in edges.colors[::2]]
    assert blue == [c['match_session'] == 0 for c in got]
    odom = {stamp_of(m): m.pose.pose.position for k, m in first if k == 'odom'}
    for p, c in zip(edges.points[1::2], got, strict=True):
        if c['match_session'] == 0:  # float32 as stored in the database
            want = odom[int(c['match_stamp_ns'])]
            assert abs(p.x - want.x) + abs(p.y - want.y) + abs(p.z - want.z) < 1e-3

    reset = h2.call('/solid_node/reset')
    assert reset.success
    assert h2.node.wait_idle(10.0)
    # The reset also clears the latched edges.
    assert [m.action for m in h2.late_markers().markers] == [3]  # DELETEALL
    h2.candidates.clear()
    h2.replay(second[:20])
    assert h2.candidates == []  # database cleared: nothing old to match


def test_bad_load_path_refuses_to_start(context: Context, tmp_path: Path) -> None:
    from solid_ros.core.errors import SolidError

    with pytest.raises(SolidError):
        SolidNode(context=context, parameter_overrides=[
            Parameter('database_load_path', value=str(tmp_path / 'missing.npz'))])


def _loops_of_one_scene(n: int) -> list[tuple[str, Any]]:
    """``n`` clouds of one scene, each after odometry at x = i: every cloud after the first
    matches the one before it (no verification, no exclusion window)."""
    scene = _scene(3)
    out: list[tuple[str, Any]] = []
    for i in range(n):
        stamp = (i + 1) * 10**9
        out += [('odom', make_odom(stamp, float(i), 1.0)), ('points', make_cloud(scene, stamp))]
    return out


LOOP_EVERY_SCAN = [Parameter('verify', value=False), Parameter('distance_threshold', value=0.5),
                   Parameter('exclude_recent_frames', value=0)]


def test_markers_keep_only_the_newest_loops(harness: Callable[..., Harness]) -> None:
    h = harness(LOOP_EVERY_SCAN + [Parameter('marker_max_loops', value=3)], params_file=None)
    h.replay(_loops_of_one_scene(9))
    assert h.node.stats.loops == 8 and h.node.stats.without_odom == 0
    h.wait_for(lambda: len(h.markers) == 8, 'one marker message per loop', 10.0)
    edges = h.late_markers().markers[0]
    assert edges.header.frame_id == 'odom'
    # The newest three loops: query at x = 6, 7, 8, each to the first scan (distance ties).
    assert [(p.x, p.y) for p in edges.points] == [(6.0, 1.0), (0.0, 1.0), (7.0, 1.0),
                                                  (0.0, 1.0), (8.0, 1.0), (0.0, 1.0)]
    assert h.node._markers is not None and len(h.node._markers) == 3


def test_markers_off(harness: Callable[..., Harness]) -> None:
    h = harness(LOOP_EVERY_SCAN + [Parameter('marker_max_loops', value=0)], params_file=None)
    h.replay(_loops_of_one_scene(3))
    assert h.node.stats.loops == 2
    assert h.node.count_publishers('/solid_node/loop_markers') == 0
    assert h.markers == [] and h.node._markers is None


# -- health: silent topics, another clock, rejected clouds -----------------------------------


def _problems(h: Harness) -> set[str]:
    return set(h.status().get('problems', 'none').split(', ')) - {'none'}


def test_silent_topics_and_odometry_on_another_clock_warn(
        harness: Callable[..., Harness], capfd: pytest.CaptureFixture[str]) -> None:
    # Remapped to topics nobody publishes (a typo): nothing arrives.
    h = harness(remap=['points:=/lidar_typo', 'odom:=/odom_typo'], matched=False)
    h.wait_for(lambda: {'no_clouds', 'no_odom'} <= _problems(h), 'silence reported', 20.0)
    st = h.status()
    assert st['level'] == '1'  # WARN
    assert 'no PointCloud2 received on /lidar_typo' in st['message']
    assert 'since start' in st['message'] and 'remap points:=' in st['message']
    assert 'no nav_msgs/Odometry received on /odom_typo' in st['message']
    assert st['points_topic'] == '/lidar_typo' and st['seconds_since_last_cloud'] == 'never'
    h.wait_for(lambda: 'no PointCloud2 received on /lidar_typo' in capfd.readouterr().err,
               'the warning naming the resolved topic', 10.0)

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    pub_points = h.client.create_publisher(PointCloud2, '/lidar_typo', qos)
    pub_odom = h.client.create_publisher(Odometry, '/odom_typo', qos)
    h.wait_for(lambda: pub_points.get_subscription_count() > 0, 'points matched')
    h.wait_for(lambda: pub_odom.get_subscription_count() > 0, 'odom matched')
    scene = _scene(4)

    def send(i: int, odom_offset_ns: int) -> None:
        stamp = 10**12 + i * 10**8
        pub_odom.publish(make_odom(stamp + odom_offset_ns, 0.1 * i))
        # The odometry first: on a loaded machine it may otherwise miss the node's wait.
        h.wait_for(lambda: h.node._odom.latest_stamp_ns == stamp + odom_offset_ns,
                   'odometry delivered')
        pub_points.publish(make_cloud(scene, stamp))
        h.wait_for(lambda: h.node.stats.received > i, 'cloud delivered')

    # Clouds arrive, with odometry stamped 1000 s later (another clock).
    for i in range(3):
        send(i, 1000 * 10**9)
    assert h.node.wait_idle(TIMEOUT)
    h.wait_for(lambda: 'odom_clock' in _problems(h) and 'no_clouds' not in _problems(h)
               and 'no_odom' not in _problems(h) and h.status()['clouds_processed'] == '3',
               'the clock offset reported', 20.0)
    st = h.status()
    assert st['level'] == '1'
    # The last cloud's nearest odometry is the first one: 1000 s - 0.2 s away.
    assert 'odometry on /odom_typo is stamped +999.800 s from the clouds on /lidar_typo' in (
        st['message'])
    assert float(st['odom_stamp_offset_sec']) == 999.8
    assert h.node.stats.without_odom == 3
    # Logged when the problem first shows, so with the offset of whichever cloud it saw then
    # (+1000.000 s for the first, +999.9 for a later one); kept across polls.
    err: list[str] = []
    clock_warning = re.compile(r'odometry on /odom_typo is stamped \+(999\.[89]|1000\.0)00 s')
    h.wait_for(lambda: bool(err.append(capfd.readouterr().err)
                            or clock_warning.search(''.join(err))), 'the clock warning', 10.0)

    # Matching stamps: every problem is gone while the clouds keep coming.
    for i in range(3, 6):
        send(i, 0)
    h.wait_for(lambda: h.status().get('level') == '0', 'diagnostics back to OK', 20.0)
    assert h.node.stats.without_odom == 3
    assert float(h.status()['odom_stamp_offset_sec']) == 0.0


def test_rejected_clouds_warn_and_log_every_distinct_reason(
        harness: Callable[..., Harness], capfd: pytest.CaptureFixture[str]) -> None:
    h = harness([Parameter('use_odom', value=False)], params_file=None)

    def short(n: int) -> PointCloud2:
        msg = make_cloud(np.ones((n, 3)), 10**9)
        msg.data = msg.data[:-4]
        return msg

    no_z = make_cloud(np.ones((10, 3)), 10**9)
    no_z.fields = no_z.fields[:2]
    # Two reasons, each several times; short clouds of other sizes are the same reason.
    h.replay([('points', m) for m in (short(10), short(20), no_z, short(30), no_z, no_z)])
    assert h.node.stats.rejected == 6 and h.node.stats.failed == 0
    h.wait_for(lambda: 'rejected' in _problems(h), 'rejections reported', 10.0)
    st = h.status()
    assert st['level'] == '1'
    assert '6 PointCloud2 rejected on /points in the last 5 s' in st['message']
    assert "no field 'z'" in st['last_reject_reason']
    logged = [line for line in capfd.readouterr().err.splitlines()
              if 'rejected PointCloud2 on /points' in line]
    # Each reason once, though they came within the throttle period of one another.
    assert len(logged) == 2, logged
    assert 'data has' in logged[0] and "has no field 'z'" in logged[1]


def test_a_failed_cloud_warns_while_recent_then_clears(
        harness: Callable[..., Harness], monkeypatch: pytest.MonkeyPatch) -> None:
    # One scan fails inside the detector: counted, WARN with the reason, the node goes on;
    # the WARN ends once failures stop (the counter stays).
    monkeypatch.setattr(health_module, 'SILENCE_SEC', 3.0)
    h = harness([Parameter('use_odom', value=False)] + LOOP_EVERY_SCAN, params_file=None)
    det = h.node._shared.detector
    real = det.propose
    calls = [0]

    def propose_failing_once(*args: Any, **kwargs: Any) -> Any:
        calls[0] += 1
        if calls[0] == 2:
            raise RuntimeError('injected failure')
        return real(*args, **kwargs)

    monkeypatch.setattr(det, 'propose', propose_failing_once)
    scene = _scene(3)
    h.replay([('points', make_cloud(scene, (i + 1) * 10**9)) for i in range(3)])
    assert h.node.stats.failed == 1 and h.node.stats.processed == 2
    h.wait_for(lambda: 'failed' in _problems(h), 'the failure on /diagnostics', 10.0)
    st = h.status()
    assert st['level'] == '1' and '1 clouds failed with an error so far' in st['message']
    h.wait_for(lambda: 'failed' not in _problems(h), 'the failure warning to clear', 10.0)
    assert h.status()['clouds_failed'] == '1'


def test_clouds_without_a_usable_point_are_rejected_not_stored(
        harness: Callable[..., Harness], capfd: pytest.CaptureFixture[str]) -> None:
    # They decode, but the detector finds no usable point (CloudError): counted and logged
    # as rejected, no keyframe stored, the node goes on.
    h = harness([Parameter('use_odom', value=False)] + LOOP_EVERY_SCAN, params_file=None)
    scene = _scene(5)
    unusable = [np.full((500, 3), np.nan), np.full((500, 3), np.inf), np.full((500, 3), 1e38),
                np.zeros((500, 3))]
    messages = []
    for i in range(5):
        messages.append(('points', make_cloud(scene, (2 * i + 1) * 10**9)))
        if i < len(unusable):
            messages.append(('points', make_cloud(unusable[i], (2 * i + 2) * 10**9)))
    h.replay(messages)
    s = h.node.stats
    assert (s.received, s.processed, s.rejected, s.failed) == (9, 5, 4, 0)
    assert h.node._shared.size == 5
    # Indices stay contiguous: the good clouds are keyframes 0-4, each loop to keyframe 0.
    assert [(c['query_index'], c['match_index']) for c in h.candidates] == [
        (1, 0), (2, 0), (3, 0), (4, 0)]
    logged = [line for line in capfd.readouterr().err.splitlines()
              if 'rejected PointCloud2 on /points: no usable point' in line]
    assert logged and not any('processing failed' in line for line in logged)
    h.wait_for(lambda: 'rejected' in _problems(h), 'rejections on /diagnostics', 10.0)
    assert h.status()['clouds_rejected'] == '4'


# -- main(): how the process ends ----------------------------------------------------------------


def _spin_failing(shut_down_first: bool) -> Callable[[Any], None]:
    from rclpy._rclpy_pybind11 import RCLError

    def spin(node: Any) -> None:
        if shut_down_first:  # what SIGINT's handler does while spin builds its wait set
            rclpy.shutdown()
        raise RCLError('failed to initialize wait set: the given context is not valid, '
                       'either rcl_init() was not called or rcl_shutdown() was called')
    return spin


def test_main_exits_0_when_sigint_invalidates_the_context_mid_spin(
        monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(rclpy, 'spin', _spin_failing(shut_down_first=True))
    assert node_module.main(['solid_node', '--ros-args', '-p', 'use_odom:=false']) == 0
    assert 'Traceback' not in capfd.readouterr().err
    assert not rclpy.ok()


def test_main_fails_loudly_on_an_rcl_error_while_running(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from rclpy._rclpy_pybind11 import RCLError

    monkeypatch.setattr(rclpy, 'spin', _spin_failing(shut_down_first=False))
    with pytest.raises(RCLError, match='wait set'):
        node_module.main(['solid_node', '--ros-args', '-p', 'use_odom:=false'])
    assert not rclpy.ok()  # shut down all the same
