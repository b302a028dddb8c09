"""BulkParticipant over real rclpy pub/sub: its topics take the owner's names, latched samples
reach late subscribers without an executor, and a large message sent from it no longer takes
the owner's small ones with it (Fast DDS's 512 KB shared-memory segment)."""

from __future__ import annotations

import array
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import (  # noqa: E402
    DurabilityPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from ros_domains import pick_domain  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from spinning import Spinner  # noqa: E402
from std_msgs.msg import Int32  # noqa: E402

from solid_ros.ros.bulk_participant import BulkParticipant  # noqa: E402

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
BEST_EFFORT = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
TIMEOUT = 20.0


def _context() -> Context:
    ctx = Context()
    rclpy.init(context=ctx)
    return ctx


@pytest.fixture()
def contexts() -> Iterator[list[Context]]:
    made: list[Context] = []
    yield made
    for ctx in made:
        ctx.try_shutdown()


def _spin(node: Node) -> Spinner:
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    return Spinner(executor)


def _wait(pred: Any, what: str) -> None:
    deadline = time.monotonic() + TIMEOUT
    while not pred():
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        time.sleep(0.02)


def test_topics_take_the_owner_names_and_a_late_subscriber_gets_the_latched_sample(
        contexts: list[Context]) -> None:
    contexts.append(ctx := _context())
    owner = Node('owner', namespace='/robot1', context=ctx,
                 cli_args=['--ros-args', '-r', '~/path:=/remapped_path'])
    bulk = BulkParticipant(owner)
    pub_map = bulk.create_publisher(Int32, '~/map', LATCHED)
    pub_path = bulk.create_publisher(Int32, '~/path', LATCHED)
    assert (pub_map.topic_name, pub_path.topic_name) == ('/robot1/owner/map', '/remapped_path')
    pub_map.publish(Int32(data=7))
    # Subscribed after the publication, from the owner's participant; nobody spins the bulk.
    got: list[int] = []
    owner.create_subscription(Int32, '/robot1/owner/map', lambda m: got.append(m.data),
                              LATCHED)
    spinner = _spin(owner)
    try:
        _wait(lambda: got == [7], 'the latched sample')
        names = {i.node_name for i in owner.get_publishers_info_by_topic('/robot1/owner/map')}
        assert names == {'owner_bulk'}
    finally:
        spinner.stop()
        bulk.close()
        bulk.close()  # idempotent: BackendIO.stop may come twice
        owner.destroy_node()


# The reader is another process: Fast DDS delivers between participants of one process
# without shared memory, so the overrun does not show there.
_READER = """
import sys, rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Int32
rclpy.init()
node = Node('bulk_test_reader')
got = {}
for phase in ('alone', 'bulk'):
    node.create_subscription(Int32, f'/small_{phase}', lambda m, p=phase: got.setdefault(
        p, set()).add(m.data), QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
    node.create_subscription(PointCloud2, f'/large_{phase}', lambda m: None, QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE))
print('ready', flush=True)
import threading
threading.Thread(target=rclpy.spin, args=(node,), daemon=True).start()
sys.stdin.read()
print(len(got.get('alone', ())), len(got.get('bulk', ())), flush=True)
"""


def _small_before_large(phase: str, sender: Node, large_from: Any, count: int) -> None:
    """Send ``count`` small best-effort messages from ``sender``, each followed at once by a
    1.5 MB cloud from ``large_from``."""
    small = sender.create_publisher(Int32, f'/small_{phase}', BEST_EFFORT)
    large = large_from.create_publisher(PointCloud2, f'/large_{phase}', QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE))
    _wait(lambda: small.get_subscription_count() and large.get_subscription_count(),
          'the reader')
    time.sleep(1.0)  # discovery settles both ways
    cloud = PointCloud2(height=1, width=125_000, point_step=12, row_step=1_500_000)
    cloud.data = array.array('B', bytes(1_500_000))
    for i in range(count):
        small.publish(Int32(data=i))
        large.publish(cloud)
        time.sleep(0.05)
    time.sleep(1.0)


@pytest.mark.skipif(bool(os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')),
                    reason='a Fast DDS profile is set: the default 512 KB segment may not apply')
def test_a_large_message_from_the_bulk_participant_does_not_lose_the_owners_small_ones(
        contexts: list[Context], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv('ROS_DOMAIN_ID', str(pick_domain()))
    reader = subprocess.Popen([sys.executable, '-c', _READER], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    assert reader.stdin is not None and reader.stdout is not None
    contexts.append(ctx := _context())
    owner = Node('owner', context=ctx)
    bulk = BulkParticipant(owner)
    try:
        assert reader.stdout.readline().strip() == 'ready'
        _small_before_large('alone', owner, owner, 30)
        _small_before_large('bulk', owner, bulk, 30)
        reader.stdin.close()
        alone, with_bulk = (int(v) for v in reader.stdout.readline().split())
    finally:
        if reader.poll() is None:
            reader.kill()
        reader.wait(timeout=10.0)
        bulk.close()
        owner.destroy_node()
    # The control: from the owner's own participant the clouds take small samples with them
    # (87 of 100 lost when measured); without a loss there this test would show nothing.
    assert alone < 30, 'the default transport lost nothing: this test shows nothing'
    assert with_bulk == 30, f'{30 - with_bulk} of 30 lost with the clouds in the bulk participant'
