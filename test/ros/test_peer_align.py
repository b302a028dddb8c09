"""PeerAlign on two in-process nodes: the alignment exchange over DDS (loops with their
keyframe poses, linked poses back), the peers' frames on /tf, paths on request, /diagnostics,
a false loop that moves nothing, and the bounds.

The loop closure is stood in for by the core's FleetAlignment over fixed maps (the synthetic
two-robot drive of ``fleet_scenes``: robot 1's map a random rigid transform away, drifting),
so what is tested is what the adapter carries and wires.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

pytest.importorskip('nav_msgs', reason='ROS 2 message packages are not installed')

from fleet_scenes import TwoRobots  # noqa: E402
from polling import wait_until  # noqa: E402
from ros_domains import pick_domain  # noqa: E402

from solid_ros.core.backend.alignment import FleetAlignment  # noqa: E402
from solid_ros.core.results import LoopCandidate  # noqa: E402

KEY = b'a fleet key of enough bytes 0123456789'


@pytest.fixture(autouse=True)
def domain_id() -> Iterator[None]:
    old = os.environ.get('ROS_DOMAIN_ID')
    os.environ['ROS_DOMAIN_ID'] = str(pick_domain())
    yield
    if old is None:
        os.environ.pop('ROS_DOMAIN_ID', None)
    else:
        os.environ['ROS_DOMAIN_ID'] = old


class Closure:
    """Stands in for SharedDetector: a robot's FleetAlignment over its fixed map."""

    def __init__(self, robot: int, poses: dict[int, np.ndarray]) -> None:
        self.fleet = FleetAlignment(robot)
        self.poses = poses

    def add_peer_loop(self, loop: LoopCandidate, robot: int) -> bool:
        return self.fleet.add(loop, by=robot)

    def align(self, peers: Any, paths: Any) -> list[Any]:
        return self.fleet.solve(self.poses, peers, paths)

    def alignments(self) -> list[Any]:
        return self.fleet.states()

    def forget_peer(self, robot: int) -> None:
        self.fleet.forget(robot)


def _output(poses: dict[int, np.ndarray]) -> SimpleNamespace:
    order = sorted(poses)
    return SimpleNamespace(snapshot=SimpleNamespace(indices=np.array(order),
                                                    poses=np.array([poses[i] for i in order])))


def _step(loop: LoopCandidate, pose: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(scan=SimpleNamespace(loops=(loop,), query_index=loop.query_index),
                           backend=SimpleNamespace(pose=pose))


def test_two_nodes_align_each_other_and_ignore_a_false_loop(context: Any) -> None:
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from spinning import Spinner
    from tf2_msgs.msg import TFMessage

    from solid_ros.ros.peer_align import PeerAlign, peer_frame
    from solid_ros.ros.peer_guard import PeerGuard

    scene = TwoRobots(n=200, lead=10, seed=4)
    maps = {0: scene.own_poses(), 1: scene.peer_poses()}
    nodes = [Node(f'robot{r}', context=context) for r in (0, 1)]
    listener = Node('listener', context=context)
    closures = {r: Closure(r, maps[r]) for r in (0, 1)}
    aligns = {r: PeerAlign(nodes[r], r, closures[r], PeerGuard(r, KEY),  # type: ignore[arg-type]
                           _output(maps[r]), 'map', 20.0) for r in (0, 1)}
    frames: set[tuple[str, str]] = set()
    paths: list[Any] = []
    listener.create_subscription(TFMessage, '/tf', lambda m: frames.update(
        (t.header.frame_id, t.child_frame_id) for t in m.transforms), 100)
    ex = SingleThreadedExecutor(context=context)
    for n in (*nodes, listener):
        ex.add_node(n)
    spinner = Spinner(ex)
    try:
        wait_until(lambda: all(n.count_subscribers('/solid/alignment') >= 2 for n in nodes),
                   'alignment topic matched', 10.0)
        # Robot 0 verifies 8 loops to robot 1 (its closure holds them, PeerAlign sends them).
        for q in range(40, 80, 5):
            loop = scene.loop(q, scene.matching(q))
            closures[0].fleet.add(loop)
            aligns[0].keyframe(_step(loop, maps[0][q]))  # type: ignore[arg-type]
        wait_until(lambda: all(closures[r].fleet.state(1 - r).inliers == 8 for r in (0, 1)),
                   'both robots aligned by all 8 loops', 15.0)
        T01 = closures[0].fleet.state(1).transform
        T10 = closures[1].fleet.state(0).transform
        linked = sorted(scene.matching(q) for q in range(40, 80, 5))
        assert scene.placement_error(T01, linked) < 0.3
        assert scene.placement_error(np.linalg.inv(T10), linked) < 0.3
        # Robot 1 got only the poses its loops name, with their paths: not the whole map.
        assert aligns[1].counts['poses_received'] == 0 and aligns[0].counts['loops_sent'] == 8
        assert aligns[0].counts['poses_received'] == 8
        wait_until(lambda: {('map', peer_frame('map', 1)), ('map', peer_frame('map', 0))}
                   <= frames, 'peer frames on /tf', 5.0)
        values = aligns[0].values()
        assert values['fleet_aligned'] == '1' and 'aligned by 8 of 8' in str(
            values['fleet_robot1'])
        # A false loop, 20 m off and sure of itself, moves neither robot's alignment.
        false = scene.loop(60, scene.matching(60) + 3, offset=20.0)
        closures[0].fleet.add(false)
        aligns[0].keyframe(_step(false, maps[0][60]))  # type: ignore[arg-type]
        wait_until(lambda: closures[1].fleet.state(0).loops == 9, 'false loop received', 5.0)
        time.sleep(2.5)  # two ticks: aligned again with it
        for r, T in ((0, T01), (1, T10)):
            st = closures[r].fleet.state(1 - r)
            assert st.aligned and st.inliers == 8 and np.allclose(st.transform, T, atol=1e-9)
        # Robot 1's whole path, asked for by robot 0, arrives in robot 0's map.
        from nav_msgs.msg import Path
        from std_srvs.srv import Trigger

        listener.create_subscription(Path, '/robot0/peer_paths/robot1', paths.append, 10)
        response = aligns[0]._paths._on_request_service(Trigger.Request(),
                                                        Trigger.Response())
        assert response.success
        wait_until(lambda: bool(paths), 'peer path published', 10.0)
        got = np.array([[p.pose.position.x, p.pose.position.y] for p in paths[-1].poses])
        assert len(got) == scene.n and paths[-1].header.frame_id == 'map'
        want = (T01 @ scene.peer)[:, :2, 3]
        assert np.allclose(got, want, atol=1e-3)
        # Asked again at once, robot 1 does not send its path again.
        aligns[0]._paths._on_request_service(Trigger.Request(), Trigger.Response())
        wait_until(lambda: aligns[1].counts['paths_refused_rate'] == 1, 'rate limit', 5.0)
    finally:
        spinner.stop()
        for n in (*nodes, listener):
            n.destroy_node()


def test_memory_per_peer_is_bounded(context: Any) -> None:
    from rclpy.node import Node

    from solid_ros.formats.fleet_msgs import PosesMessage
    from solid_ros.ros.peer_align import _MAX_LINKED, _MAX_POSES, PeerAlign
    from solid_ros.ros.peer_guard import PeerGuard

    node = Node('robot0', context=context)
    try:
        closure = Closure(0, {})
        align = PeerAlign(node, 0, closure, PeerGuard(0, None),  # type: ignore[arg-type]
                          _output({0: np.eye(4)}), 'map', 0.0)
        pose = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
        for k in range(0, _MAX_POSES + 700, 500):
            align._on_poses(PosesMessage(5, tuple((i, pose, 0.0) for i in range(k, k + 500))))
        assert len(align._poses[5]) == _MAX_POSES
        for i in range(_MAX_LINKED + 10):
            align._link(i, None)
        assert len(align._linked) == _MAX_LINKED
        # A robot's alignment messages share its descriptor budget: a flood is refused.
        from std_msgs.msg import UInt8MultiArray

        from solid_ros.formats.fleet_msgs import encode_align
        flood = UInt8MultiArray()
        flood.data = encode_align(PosesMessage(6, ((0, pose, 0.0),)))
        before = align.counts['poses_received']
        for _ in range(3000):
            align._on_message(flood)
        assert 0 < align.counts['refused_rate_limited'] < 3000
        assert 0 < align.counts['poses_received'] - before < 3000
        # A path announced in more parts than a path may hold is refused before it is kept.
        align._paths.part(PosesMessage(5, ((0, pose, 0.0),), True, 0, 60_000))
        assert align.counts['paths_refused_oversized'] == 1 and not align._paths._parts
    finally:
        node.destroy_node()
