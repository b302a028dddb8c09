"""solid_node's ~/save_database: a read-only path, never a non-database, stale temporaries.

Real rclpy: the node and a client node in one context, services called over DDS.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')

from rcl_interfaces.msg import Parameter as ParameterMsg  # noqa: E402
from rcl_interfaces.msg import ParameterType, ParameterValue  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from ros_domains import pick_domain  # noqa: E402
from spinning import Spinner  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from solid_ros.core.database.archive import is_database  # noqa: E402
from solid_ros.ros.node import SolidNode  # noqa: E402


@pytest.fixture(scope='module', autouse=True)
def domain_id() -> Iterator[None]:
    old = os.environ.get('ROS_DOMAIN_ID')
    os.environ['ROS_DOMAIN_ID'] = str(pick_domain())
    yield
    if old is None:
        os.environ.pop('ROS_DOMAIN_ID', None)
    else:
        os.environ['ROS_DOMAIN_ID'] = old


def _call(client: Node, srv_type: type, name: str, request: object) -> object:
    cli = client.create_client(srv_type, name)
    assert cli.wait_for_service(timeout_sec=30.0), name
    done = threading.Event()
    fut = cli.call_async(request)
    fut.add_done_callback(lambda _: done.set())
    assert done.wait(30.0), name
    return fut.result()


def test_save_path_read_only_and_never_replaces_other_files(context: Context,
                                                            tmp_path: Path) -> None:
    text = tmp_path / 'notes.npz'
    text.write_text('not a database\n')
    stale = tmp_path / '.notes.npz.a1b2c3d4.tmp'
    stale.write_bytes(bytes(4096))
    node = SolidNode(context=context, parameter_overrides=[
        Parameter('database_save_path', value=str(text))])
    assert not stale.exists()  # removed at start
    client = Node('save_test_client', context=context)
    executor = MultiThreadedExecutor(num_threads=2, context=context)
    executor.add_node(node)
    executor.add_node(client)
    spinner = Spinner(executor)
    try:
        refused = _call(client, Trigger, '/solid_node/save_database', Trigger.Request())
        assert not refused.success and 'not a solid_ros database' in refused.message
        assert text.read_text() == 'not a database\n'
        # A peer cannot point the save somewhere else at runtime.
        other = tmp_path / 'elsewhere.npz'
        value = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=str(other))
        result = _call(client, SetParameters, '/solid_node/set_parameters',
                       SetParameters.Request(parameters=[
                           ParameterMsg(name='database_save_path', value=value)]))
        assert not result.results[0].successful
        assert node.node_config.database_save_path == str(text)
        text.unlink()
        saved = _call(client, Trigger, '/solid_node/save_database', Trigger.Request())
        assert saved.success, saved.message
        assert is_database(text) and not other.exists()
    finally:
        spinner.stop()  # out of the wait set before the nodes go
        node.destroy_node()
        client.destroy_node()
