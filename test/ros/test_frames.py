"""The frames of solid_node's transforms: settings that make one from a frame to itself are
refused, and frames from messages that would are dropped with one warning."""

from __future__ import annotations

from solid_ros.core.config import NodeConfig
from solid_ros.ros.frames import SelfTransformGuard, frame_conflict, map_odom_advice


def test_settings_that_make_a_self_transform_are_named() -> None:
    assert frame_conflict(NodeConfig()) is None  # odometry frame from the messages
    assert frame_conflict(NodeConfig(odom_frame='odom')) is None
    problem = frame_conflict(NodeConfig(odom_frame='map'))
    assert problem is not None
    assert 'map_frame and odom_frame' in problem and 'map -> map' in problem
    assert 'map_frame: solid_map' in problem
    assert frame_conflict(NodeConfig(map_frame='solid_map', odom_frame='map')) is None
    # KISS-ICP's odometry frame is 'odom' when odom_frame is empty.
    kiss = NodeConfig(odometry_source='kiss_icp', map_frame='odom')
    assert 'odom -> odom' in (frame_conflict(kiss) or '')
    problem = frame_conflict(NodeConfig(odometry_source='kiss_icp', sensor_frame='odom'))
    assert problem is not None and 'odom_frame and sensor_frame' in problem
    assert frame_conflict(NodeConfig(odometry_source='kiss_icp', sensor_frame='lidar')) is None
    # sensor_frame is only KISS-ICP's: with a topic odometry it makes no transform here.
    assert frame_conflict(NodeConfig(odom_frame='odom', sensor_frame='odom')) is None


def test_guard_drops_self_transforms_and_warns_once_per_frame() -> None:
    lines: list[str] = []
    guard = SelfTransformGuard(lines.append, map_odom_advice)
    assert guard.allows('map', 'odom')
    assert [guard.allows('map', 'map') for _ in range(5)] == [False] * 5
    assert not guard.allows('x', 'x')
    assert guard.allows('map', 'odom')
    assert lines == [map_odom_advice('map'), map_odom_advice('x')]
