"""solid_node with the back end on, over real rclpy pub/sub: a drifting drive's revisit moves
map -> odom on /tf, the corrected path, odometry and map come out, and the save services write
only where they may."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')
pytest.importorskip('gtsam', reason='gtsam is not installed')
pytest.importorskip('small_gicp', reason='small-gicp is not installed')
pytest.importorskip('tf2_msgs', reason='tf2_msgs is not installed (./run.sh builds it)')

import test_node  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy_msgs import make_cloud, make_odometry  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from solid_ros.core.geometry import vector_to_matrix  # noqa: E402
from solid_ros.formats.pointcloud2 import cloud_to_xyz  # noqa: E402
from solid_ros.formats.pointfiles import read_pcd  # noqa: E402
from solid_ros.formats.poses import read_kitti_poses, read_tum_poses  # noqa: E402
from solid_ros.sim.drive import Drive, DriveConfig  # noqa: E402

# The node harness and fixtures of test_node (a module-scoped ROS domain, hku1 messages).
AVIA, Harness, key, revisits = (test_node.AVIA, test_node.Harness, test_node.key,
                                test_node._revisits)
domain_id, harness, hku1 = test_node.domain_id, test_node.harness, test_node.hku1

SEC = 1_000_000_000
DRIVE = [5, 40, 80, 120, 273]  # scan 273 revisits scan 5
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _odom(stamp_ns: int, T: np.ndarray) -> Odometry:
    return make_odometry(T, stamp_ns)


def _pose(msg: Any) -> np.ndarray:
    p, o = msg.position, msg.orientation
    return vector_to_matrix([p.x, p.y, p.z, o.x, o.y, o.z, o.w])


def _listen(h: Harness, kind: type, topic: str, qos: Any = 10) -> list[Any]:
    got: list[Any] = []
    h.client.create_subscription(kind, topic, got.append, qos)
    return got


@pytest.fixture()
def backend_node(harness: Callable[..., Harness], tmp_path: Path) -> Harness:
    overrides = [Parameter('backend', value=True), Parameter('exclude_recent_frames', value=2),
                 Parameter('distance_threshold', value=0.2),
                 Parameter('num_candidates', value=3),
                 Parameter('backend_segment_jump_m', value=1000.0),  # scans 70-300 m apart
                 Parameter('map_period_sec', value=0.2), Parameter('path_period_sec', value=0.1),
                 Parameter('output_directory', value=str(tmp_path / 'out')),
                 Parameter('lio_sam_loop_topic', value='/lio_loop/loop_closure_detection')]
    return harness(overrides, params_file=None)


def test_a_revisit_corrects_the_pose_path_map_and_tf(backend_node: Harness,
                                                     tmp_path: Path) -> None:
    h = backend_node
    tf = _listen(h, TFMessage, '/tf', 100)
    corrected = _listen(h, Odometry, '/solid_node/odometry', 100)
    paths = _listen(h, PathMsg, '/solid_node/path', LATCHED)
    maps = _listen(h, PointCloud2, '/solid_node/map', LATCHED)
    lio = _listen(h, Float64MultiArray, '/lio_loop/loop_closure_detection', 10)
    drive = Drive(DriveConfig(seed=0, sensor='hdl64'))  # its odometry drifts
    messages = []
    # Stamps from 1 s: a cloud stamped 0 is untrusted and takes the newest odometry, which
    # under load had not arrived yet (keyframe 0 then stayed out of the graph with its loop).
    for k, i in enumerate(DRIVE, start=1):
        messages.append(('odom', _odom(k * SEC, drive.odometry(i))))
        messages.append(('points', make_cloud(drive.scan(i).points, k * SEC)))
    h.replay(messages)
    assert [(int(c['query_index']), int(c['match_index'])) for c in h.candidates] == [(4, 0)]
    h.wait_for(lambda: bool(lio), 'the LIO-SAM loop message')
    assert list(lio[-1].data) == [5.0, 1.0]
    # map -> odom moved by the loop: the drift at the revisit, taken out.
    # By frame names, not the newest /tf message: another node on the domain may send /tf too.
    def links() -> list[Any]:
        return [t for m in list(tf) for t in m.transforms
                if (t.header.frame_id, t.child_frame_id) == ('map', 'odom')]

    h.wait_for(lambda: any(abs(t.transform.translation.x) + abs(t.transform.translation.y) > 0.5
                           for t in links()[-1:]), 'a moved map -> odom transform')
    # The latched path holds the five keyframes; the revisit lies near its reference.
    h.wait_for(lambda: bool(paths) and len(paths[-1].poses) == 5, 'the corrected path')
    last = _pose(paths[-1].poses[-1].pose)
    drift = np.linalg.norm(drive.odometry(273)[:3, 3] - drive.pose(273)[:3, 3])
    error = np.linalg.norm(last[:3, 3] - drive.pose(273)[:3, 3])
    assert drift > 2.0 and error < 0.5 * drift
    # A new odometry message comes out in the map frame, corrected.
    h.pub_odom.publish(_odom(6 * SEC, drive.odometry(273)))
    h.wait_for(lambda: bool(corrected) and corrected[-1].header.stamp.sec == 6, 'odometry')
    out = corrected[-1]
    assert out.header.frame_id == 'map' and out.child_frame_id == 'lidar'
    assert np.linalg.norm(_pose(out.pose.pose)[:3, 3] - last[:3, 3]) < 1e-3
    assert out.pose.covariance[0] > 0.0
    h.wait_for(lambda: bool(maps) and maps[-1].width > 1000, 'the map')
    assert maps[-1].header.frame_id == 'map' and np.isfinite(cloud_to_xyz(maps[-1])).all()
    # The map and path leave by a participant of their own: megabytes from the node's own
    # overran its shared-memory segment and took /tf and odometry samples with them.
    # Names, not counts: the graph may still list a node of an earlier test in this domain.
    for topic, node_name, not_from in [('/solid_node/map', 'solid_node_bulk', 'solid_node'),
                                       ('/solid_node/path', 'solid_node_bulk', 'solid_node'),
                                       ('/tf', 'solid_node', 'solid_node_bulk'),
                                       ('/solid_node/odometry', 'solid_node',
                                        'solid_node_bulk')]:
        names = {i.node_name for i in h.client.get_publishers_info_by_topic(topic)}
        assert node_name in names and not_from not in names, (topic, names)
    h.wait_for(lambda: h.status().get('backend_loops') == '1', 'the loop on /diagnostics')


def test_save_services_write_their_files_and_replace_only_their_own(backend_node: Harness,
                                                                     tmp_path: Path) -> None:
    h = backend_node
    drive = Drive(DriveConfig(seed=0, sensor='hdl64'))
    # Stamps from 1 s: a cloud stamped 0 is one whose stamp cannot be trusted.
    h.replay([m for k, i in enumerate(DRIVE[:3], start=1) for m in (
        ('odom', _odom(k * SEC, drive.odometry(i))),
        ('points', make_cloud(drive.scan(i).points, k * SEC)))])
    out = tmp_path / 'out'
    res = h.call('/solid_node/save_trajectory')
    assert res.success, res.message
    stamps, poses = read_tum_poses(out / 'trajectory.tum')
    assert stamps.tolist() == [SEC, 2 * SEC, 3 * SEC]
    assert len(read_kitti_poses(out / 'trajectory.kitti')) == 3
    np.testing.assert_allclose(poses[1][:3, 3], drive.odometry(40)[:3, 3], atol=1e-3)
    res = h.call('/solid_node/save_map')
    assert res.success, res.message
    assert len(read_pcd(out / 'map.pcd')) > 1000
    # Saving again replaces its own files; a file that is not a map is never replaced.
    assert h.call('/solid_node/save_map').success
    (out / 'map.pcd').write_text('my notes, not a point cloud\n')
    res = h.call('/solid_node/save_map')
    assert not res.success and 'not replaced' in res.message
    assert (out / 'map.pcd').read_text() == 'my notes, not a point cloud\n'
    (out / 'trajectory.tum').unlink()
    (out / 'trajectory.tum').symlink_to(tmp_path / 'elsewhere.txt')
    res = h.call('/solid_node/save_trajectory')
    assert not res.success and 'not a regular file' in res.message
    assert not (tmp_path / 'elsewhere.txt').exists()


def test_kiss_icp_odometry_gates_keyframes_and_closes_the_revisit(
        harness: Callable[..., Harness], hku1: list[tuple[str, Any]]) -> None:
    pytest.importorskip('kiss_icp', reason='kiss-icp is not installed')
    h = harness([Parameter('odometry_source', value='kiss_icp')], params_file=AVIA)
    odometry = _listen(h, Odometry, '/solid_node/kiss/odometry', 1000)
    tf = _listen(h, TFMessage, '/tf', 1000)
    clouds = [(kind, m) for kind, m in hku1 if kind == 'points']  # the clouds alone
    h.replay(clouds)
    processed = h.node.stats.processed
    assert processed == len(clouds) and h.node.stats.without_odom == 0
    h.wait_for(lambda: len(odometry) == processed, 'an odometry message per cloud')
    assert odometry[0].header.frame_id == 'odom' and odometry[0].child_frame_id
    # The sensor walked a 63.5 m loop: KISS-ICP's odometry went with it.
    xy = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for m in odometry])
    assert 50.0 < np.linalg.norm(np.diff(xy, axis=0), axis=1).sum() < 80.0
    assert any(t.header.frame_id == 'odom' for msg in tf for t in msg.transforms)
    h.wait_for(lambda: 'database_size' in h.status()
               and h.status()['clouds_processed'] == str(processed), 'diagnostics')
    status = h.status()
    assert int(status['database_size']) < processed  # keyframes gated by the odometry
    assert status['kiss_resets'] == '0'
    got = [key(c) for c in h.candidates]
    assert revisits(got, hku1), got  # the end-of-run revisit, verified
    assert all(c['verified'] == 1 for c in h.candidates)
    # With KISS-ICP (a scan-only odometry) 'auto' registers each keyframe to the previous one.
    assert h.node.solid_config.backend_step_registration == 'on'
    h.wait_for(lambda: int(h.status().get('backend_steps', 0)) > 0, 'registered steps')


def _transforms(tf: list[Any], parent: str, child: str) -> list[Any]:
    return [t for m in list(tf) for t in m.transforms
            if (t.header.frame_id, t.child_frame_id) == (parent, child)]


def _warnings(err: list[str], capfd: pytest.CaptureFixture[str], text: str) -> list[str]:
    err.append(capfd.readouterr().err)
    return [line for line in ''.join(err).splitlines() if text in line]


def test_an_odometry_in_the_map_frame_gets_no_map_to_map_transform(
        harness: Callable[..., Harness], capfd: pytest.CaptureFixture[str]) -> None:
    # Several SLAM outputs and recorded bags name their odometry frame 'map', as the
    # default map_frame is: map -> map would break every TF lookup of 'map'.
    h = harness([Parameter('tf_rate_hz', value=50.0)], params_file=AVIA)
    assert h.node.solid_config.backend
    tf = _listen(h, TFMessage, '/tf', 100)
    drive = Drive(DriveConfig(seed=0, sensor='hdl64'))
    err: list[str] = []
    said = 'map_frame and odom_frame'
    sent = [0]

    def warned() -> bool:
        # Odometry keeps coming until the node has it: on a loaded machine the first messages
        # can go out before the subscription is matched.
        sent[0] += 1
        h.pub_odom.publish(make_odometry(drive.odometry(sent[0]), sent[0] * SEC, frame='map'))
        return bool(_warnings(err, capfd, said))
    h.wait_for(warned, 'the frame warning', 20.0)
    time.sleep(1.0)  # 50 more broadcast periods: still one line
    lines = _warnings(err, capfd, said)
    assert len(lines) == 1 and '[WARN]' in lines[0], lines
    assert "both 'map'" in lines[0] and 'map_frame: solid_map' in lines[0]
    assert not _transforms(tf, 'map', 'map')
    # /tf was heard all along: an odometry in its own frame gets map -> odom at once.
    h.pub_odom.publish(make_odometry(drive.odometry(4), 4 * SEC, frame='odom'))
    h.wait_for(lambda: bool(_transforms(tf, 'map', 'odom')), 'map -> odom', 20.0)
    assert not _transforms(tf, 'map', 'map')
    assert len(_warnings(err, capfd, said)) == 1


def test_kiss_icp_clouds_in_the_odom_frame_get_no_odom_to_odom_transform(
        harness: Callable[..., Harness], capfd: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip('kiss_icp', reason='kiss-icp is not installed')
    # KISS-ICP's transform is odom_frame ('odom') -> the clouds' frame (sensor_frame empty).
    h = harness([Parameter('odometry_source', value='kiss_icp')], params_file=None)
    odometry = _listen(h, Odometry, '/solid_node/kiss/odometry', 100)
    tf = _listen(h, TFMessage, '/tf', 100)
    drive = Drive(DriveConfig(seed=0, sensor='hdl64'))
    h.replay([('points', make_cloud(drive.scan(i).points, (i + 1) * SEC, frame='odom'))
              for i in range(3)])
    h.wait_for(lambda: len(odometry) == 3, 'an odometry message per cloud', 20.0)
    err: list[str] = []
    said = 'odom_frame and sensor_frame'
    h.wait_for(lambda: bool(_warnings(err, capfd, said)), 'the frame warning', 20.0)
    lines = _warnings(err, capfd, said)
    assert len(lines) == 1 and '[WARN]' in lines[0] and "both 'odom'" in lines[0], lines
    assert not _transforms(tf, 'odom', 'odom')
    h.replay([('points', make_cloud(drive.scan(3).points, 4 * SEC, frame='lidar'))])
    h.wait_for(lambda: bool(_transforms(tf, 'odom', 'lidar')), 'odom -> lidar', 20.0)
    assert not _transforms(tf, 'odom', 'odom')
    assert len(_warnings(err, capfd, said)) == 1
