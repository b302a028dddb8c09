"""solid_node and solid_replay run one per-scan flow: on the same bag and parameter file they
publish the same loops and the same corrected keyframe path.

A simulated narrow-view drive with drifting odometry goes into a bag in tmp_path; the replay
reads it, and a test client publishes its odometry and clouds, as recorded, to an in-process
node over real rclpy pub/sub (no mocks). The back end is on, so both verify each keyframe
with the pose graph after the previous one: some loops are the graph's candidates.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')
pytest.importorskip('gtsam', reason='gtsam is not installed')
pytest.importorskip('small_gicp', reason='small-gicp is not installed')

import test_node  # noqa: E402
import yaml  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from project_paths import CONFIG_DIR  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from solid_ros.core.geometry import vector_to_matrix  # noqa: E402
from solid_ros.formats.candidates import SOURCE_CODES  # noqa: E402
from solid_ros.sim import DEMO_DEFAULTS  # noqa: E402
from solid_ros.sim.bagwriter import write_bag  # noqa: E402
from solid_ros.sim.drive import Drive, DriveConfig  # noqa: E402
from solid_ros.tools.replay import load_config, replay  # noqa: E402

# The node harness and fixtures of test_node (a module-scoped ROS domain).
Harness, domain_id, harness = test_node.Harness, test_node.domain_id, test_node.harness

# Avia-like (70 deg) drive: a street (91-95), elsewhere (130-190), the street again the
# other way (217-221). The descriptor closes some revisits, the graph's view the others.
SCANS = [91, 92, 93, 94, 95, 130, 160, 190, 217, 218, 219, 220, 221]
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _parameter_file(path: Path) -> Path:
    """The shipped Avia preset with the back end on, made for a short drive, and a node that
    never drops a cloud (reliable, deep queues)."""
    doc = yaml.safe_load((CONFIG_DIR / 'avia.yaml').read_text())
    doc['solid_node']['ros__parameters'].update(
        backend=True, exclude_recent_frames=2, backend_segment_jump_m=1000.0,
        qos_reliability='reliable', qos_depth=1000, queue_size=1000, path_period_sec=0.2,
        map_period_sec=0.0)
    path.write_text(yaml.safe_dump(doc))
    return path


def _pose(msg: Any) -> np.ndarray:
    p, o = msg.position, msg.orientation
    return vector_to_matrix([p.x, p.y, p.z, o.x, o.y, o.z, o.w])


def test_the_node_and_the_replay_publish_the_same_loops_and_path(
        harness: Callable[..., Harness], tmp_path: Path) -> None:
    drive = Drive(DriveConfig(seed=0, sensor='avia_like', block=DEMO_DEFAULTS['block'],
                              spacing=DEMO_DEFAULTS['spacing']))
    bag = write_bag(tmp_path / 'bag', (drive.scan(i) for i in SCANS), odom_frame='odom').path
    params = _parameter_file(tmp_path / 'params.yaml')

    cfg, node_cfg = load_config(params)
    assert cfg.backend and cfg.graph_candidates > 0 and cfg.verify
    offline = replay(bag, cfg, node_config=node_cfg, progress='quiet')
    assert offline.skipped == 0 and offline.trajectory.backend

    h = harness([], params_file=params, remap=['odom:=/odom_slam'])
    paths: list[PathMsg] = []
    h.client.create_subscription(PathMsg, '/solid_node/path', paths.append, LATCHED)
    # The bag's own messages, each odometry before its cloud: the node pairs as the replay.
    h.replay(test_node._odom_first(test_node.read_bag(bag, '/points', '/odom')))
    stats = h.node.stats
    assert stats.processed == len(SCANS) and stats.without_odom == 0
    assert stats.skipped == 0 and stats.verify_skipped == 0 and stats.failed == 0

    # The same loops: keyframes, stamps, source, verdict, and the pose and covariance.
    want = offline.candidates
    got = h.candidates
    assert [test_node.key(c) for c in got] == [
        (c.query_index, c.match_index, c.query_stamp_ns, c.match_stamp_ns, c.match_session)
        for c in want]
    assert {c.source for c in want} == {'descriptor', 'graph'}  # the graph hint at work
    for c, w in zip(got, want):
        assert c['source'] == SOURCE_CODES[w.source] and c['verified'] == int(w.verified)
        node_pose = [c[k] for k in ('tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw')]
        np.testing.assert_allclose(node_pose, w.pose, rtol=0.0, atol=1e-9)
        np.testing.assert_allclose([c[f'cov_{i}'] for i in range(36)], w.covariance,
                                   rtol=1e-9, atol=1e-12)

    # The same pose graph: its corrected keyframe path, stamp by stamp.
    traj = offline.trajectory
    h.wait_for(lambda: bool(paths) and len(paths[-1].poses) == len(traj.indices),
               'the corrected path of every keyframe', 30.0)
    path = paths[-1].poses
    assert [test_node.stamp_of(p) for p in path] == traj.stamps_ns.tolist()
    for p, corrected in zip(path, traj.corrected):
        np.testing.assert_allclose(_pose(p.pose), corrected, rtol=0.0, atol=1e-9)
    h.wait_for(lambda: h.status().get('backend_loops') == str(
        offline.report['backend']['loops_in_graph']), 'the graph loops on /diagnostics', 30.0)
