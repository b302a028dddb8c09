"""solid_node against a buggy driver or a hostile participant of its ROS domain (issue 22):
non-finite odometry, stamps that do not move, remote parameter changes, ~/reset then
~/save_database, and huge clouds. Real rclpy and Fast DDS, as in test_node.py; the peer
exchange is attacked in test_peer_link.py.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')

from rcl_interfaces.msg import Parameter as ParameterMsg  # noqa: E402
from rcl_interfaces.msg import ParameterType, ParameterValue  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy_msgs import make_cloud  # noqa: E402
from test_node import (  # noqa: E402
    LOOP_EVERY_SCAN,
    Harness,
    _problems,
    _scene,
    domain_id,  # noqa: F401  (its autouse fixture: a random ROS_DOMAIN_ID)
    harness,  # noqa: E402,F401  (the fixture)
    make_odom,
)

from solid_ros.core.database.archive import read_database  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402

SEC = 1_000_000_000


def _set(h: Harness, name: str, value: Any) -> Any:
    kinds = {bool: (ParameterType.PARAMETER_BOOL, 'bool_value'),
             int: (ParameterType.PARAMETER_INTEGER, 'integer_value'),
             float: (ParameterType.PARAMETER_DOUBLE, 'double_value')}
    kind, field = kinds[type(value)]
    pv = ParameterValue(type=kind, **{field: value})
    cli = h.client.create_client(SetParameters, '/solid_node/set_parameters')
    assert cli.wait_for_service(timeout_sec=10.0)
    fut = cli.call_async(SetParameters.Request(parameters=[ParameterMsg(name=name, value=pv)]))
    h.wait_for(fut.done, 'set_parameters')
    return fut.result().results[0]


def _latest_diag(h: Harness, key: str, want: str) -> dict[str, str]:
    h.wait_for(lambda: h.status().get(key) == want, f'/diagnostics {key} = {want}', 20.0)
    return h.status()


def test_non_finite_odometry_is_refused_counted_and_never_paired(
        harness: Callable[..., Harness]) -> None:  # noqa: F811
    """A NaN pose refuses the message; a NaN covariance only the covariance (the pose,
    the same as the real one's here, pairs with the back end's noise model)."""
    h = harness(LOOP_EVERY_SCAN, params_file=None)
    scene = _scene(6)
    n = 6
    for i in range(n):
        stamp = (i + 1) * SEC
        nan_pose = make_odom(stamp, math.nan)
        nan_cov = make_odom(stamp, float(i))
        nan_cov.pose.covariance[7] = math.inf
        h.pub_odom.publish(nan_pose)
        h.pub_odom.publish(nan_cov)
        h.pub_odom.publish(make_odom(stamp + 40_000_000, float(i)))  # the real one, 40 ms on
        h.wait_for(lambda s=stamp: h.node._odom.latest_stamp_ns == s + 40_000_000, 'odometry')
        h.replay([('points', make_cloud(scene, stamp))])
    s = h.node.stats
    assert (s.processed, s.failed, s.without_odom, s.odom_rejected) == (n, 0, 0, 2 * n)
    assert s.loops == n - 1
    st = _latest_diag(h, 'odom_rejected', str(2 * n))
    assert 'odom_rejected' in _problems(h) and st['level'] == '1'
    assert 'odometry covariance is not finite' in st['message']
    kept = list(h.node._odom._odom._samples)
    assert sum(v.covariance is None for v in kept) == n  # the NaN covariances, dropped
    assert all(v.covariance is None or all(map(math.isfinite, v.covariance.ravel()))
               for v in kept)


def test_zero_stamps_are_reported_and_processed_in_arrival_order(
        harness: Callable[..., Harness], capfd: pytest.CaptureFixture[str]) -> None:  # noqa: F811
    # Keyframes by distance (0.5 m); the driver stamps every cloud and odometry 0.
    h = harness(LOOP_EVERY_SCAN + [Parameter('keyframe_min_distance', value=0.5)],
                params_file=None)
    scene = _scene(7)
    n = 8
    for i in range(n):
        h.pub_odom.publish(make_odom(0, float(i)))
        h.wait_for(lambda i=i: len(h.node._odom._odom) == i + 1, 'odometry')
        h.replay([('points', make_cloud(scene, 0))])
    # Each cloud went with the newest odometry (1 m on): every one is a keyframe.
    assert h.node._shared.size == n and h.node.stats.stamps_zero == n
    assert h.node.stats.loops == n - 1
    # The published stamps are the header stamps (0), not the detector's arrival order.
    assert {c['query_stamp_ns'] for c in h.candidates} == {0}
    st = _latest_diag(h, 'cloud_stamps_zero', str(n))
    assert 'cloud_stamps' in _problems(h)
    assert 'processed in arrival order' in st['message']
    logged = [ln for ln in capfd.readouterr().err.splitlines()
              if 'processed in arrival order: stamp 0.000 s is zero' in ln]
    assert len(logged) == 1, logged  # throttled


def test_remote_parameter_changes_may_tighten_but_not_weaken(
        harness: Callable[..., Harness], capfd: pytest.CaptureFixture[str]) -> None:  # noqa: F811
    h = harness(params_file=None)
    cfg = h.node.solid_config
    for name, value in (('distance_threshold', 0.5), ('verify_min_overlap', 0.0),
                        ('verify_max_rmse', 1.0), ('odom_check_drift', 0.0),
                        ('exclude_recent_frames', 0), ('keyframe_min_distance', 100.0),
                        ('num_candidates', 50), ('peer_timeout_sec', 30.0)):
        result = _set(h, name, value)
        assert not result.successful, name
        assert 'would weaken' in result.reason and 'allow_runtime_weakening' in result.reason
    assert h.node.solid_config == cfg
    assert not _set(h, 'allow_runtime_weakening', True).successful  # read-only
    for name, value in (('distance_threshold', 0.02), ('verify_min_overlap', 0.5),
                        ('odom_check_drift', 0.05)):
        assert _set(h, name, value).successful, name
    assert h.node.solid_config.distance_threshold == 0.02
    assert h.node.solid_config.verify_min_overlap == 0.5
    h.wait_for(lambda: 'parameter verify_min_overlap changed at runtime: 0.35 -> 0.5' in
               capfd.readouterr().err, 'the change logged with old and new value', 10.0)


def test_a_reset_then_save_keeps_the_saved_database_as_a_backup(
        harness: Callable[..., Harness], tmp_path: Path) -> None:  # noqa: F811
    db = tmp_path / 'map.npz'
    h = harness(LOOP_EVERY_SCAN + [Parameter('use_odom', value=False),
                                   Parameter('database_save_path', value=str(db))],
                params_file=None)
    scene = _scene(8)
    h.replay([('points', make_cloud(scene, (i + 1) * SEC)) for i in range(5)])
    first = h.call('/solid_node/save_database')
    assert first.success and 'backup' not in first.message
    assert h.call('/solid_node/reset').success
    wiped = h.call('/solid_node/save_database')
    assert wiped.success and f'kept as {db}.bak' in wiped.message, wiped.message
    assert read_database(db)[0]['count'] == 0
    assert read_database(Path(f'{db}.bak'))[0]['count'] == 5


def test_a_huge_cloud_is_thinned_to_max_points_per_cloud(
        harness: Callable[..., Harness]) -> None:  # noqa: F811
    h = harness(LOOP_EVERY_SCAN + [Parameter('use_odom', value=False),
                                   Parameter('max_points_per_cloud', value=2000)],
                params_file=None)
    scene = _scene(9)  # about 5,700 points
    assert len(scene) > 4000
    h.replay([('points', make_cloud(scene, SEC)), ('points', make_cloud(scene[:1500], 2 * SEC))])
    s = h.node.stats
    assert (s.processed, s.downsampled, s.rejected, s.failed) == (2, 1, 0, 0)
    _latest_diag(h, 'clouds_downsampled', '1')
    # Thinned deterministically: every k-th point, as a detector given those alone describes.
    det = h.node._shared.detector
    assert det.database.size == 2 and np.isfinite(det.database.r_solid(0)).all()
    step = -(-len(scene) // 2000)
    alone = LoopDetector(h.node.solid_config)
    alone.process(scene.astype(np.float32)[::step], SEC)
    np.testing.assert_allclose(det.database.r_solid(0), alone.database.r_solid(0), rtol=1e-6)
    whole = LoopDetector(h.node.solid_config)
    whole.process(scene.astype(np.float32), SEC)
    assert not np.allclose(det.database.r_solid(0), whole.database.r_solid(0), rtol=1e-6)
