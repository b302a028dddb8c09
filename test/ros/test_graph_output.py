"""GraphOutput and the back end's messages: a drifting square corrected by one loop in the
loop closure's pose graph, as the node's publishers would read it."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip('nav_msgs', reason='ROS 2 message packages are not installed')
pytest.importorskip('gtsam', reason='gtsam is not installed')

from drifting_odometry import Drift, drifting_odometry, square  # noqa: E402

from solid_ros.core.candidates.proposal import Proposal  # noqa: E402
from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.core.flow.closure import LoopClosure  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402
from solid_ros.core.geometry import matrix_to_vector, rot_z  # noqa: E402
from solid_ros.core.odometry.track import OdomSample  # noqa: E402
from solid_ros.core.results import LoopCandidate, ScanResult  # noqa: E402
from solid_ros.ros.graph_msgs import (  # noqa: E402
    corrected_odometry,
    covariance_in_parent,
    lio_sam_loop_msg,
    path_msg,
    transform_msg,
)
from solid_ros.ros.graph_output import GraphOutput  # noqa: E402
from solid_ros.ros.shared_detector import SharedDetector  # noqa: E402
from solid_ros.ros.stages import Verified  # noqa: E402

SEC = 10**9


def loop(ref: np.ndarray, q: int, m: int) -> LoopCandidate:
    """A verified loop from keyframe q to m with its true relative pose."""
    cov = tuple(np.diag([1e-4] * 3 + [1e-6] * 3).ravel())
    return LoopCandidate(q, m, q * SEC, m * SEC, 0, 0.1, 0.0, 1.0, True,
                         tuple(matrix_to_vector(np.linalg.solve(ref[m], ref[q]))),
                         covariance=cov, reason='verified')


class Log:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, message: str, **kwargs: object) -> None:
        self.lines.append(('info', message))

    def debug(self, message: str, **kwargs: object) -> None:
        pass

    def warning(self, message: str, **kwargs: object) -> None:
        self.lines.append(('warning', message))

    def error(self, message: str, **kwargs: object) -> None:
        self.lines.append(('error', message))


def _shared() -> SharedDetector:
    return SharedDetector(LoopClosure(LoopDetector(SolidConfig(backend=True))))


def _verified(shared: SharedDetector, k: int, T: np.ndarray | None,
              loops: tuple[LoopCandidate, ...] = ()) -> Verified:
    """Keyframe ``k`` as the current detector verified it (what a graph update reads)."""
    res = ScanResult(k * SEC, True, k, None if T is None else matrix_to_vector(T), loops)
    proposal = Proposal(k, k * SEC, k, np.zeros(4), None)
    return Verified(res, None if T is None else OdomSample(k * SEC, T), proposal,
                    shared.detector)


def test_snapshots_follow_the_graph_and_a_loop_moves_the_correction() -> None:
    ref = square(170)
    odo = drifting_odometry(ref, Drift())
    log = Log()
    shared = _shared()
    out = GraphOutput(shared, log)
    assert out.snapshot.version == 0 and np.array_equal(out.snapshot.correction, np.eye(4))
    assert shared.closure.hint is None  # no keyframe yet
    for k in range(165):
        out.take(_verified(shared, k, odo[k]))
    before = out.snapshot
    assert before.version == 165 and len(before.stamps_ns) == 165
    np.testing.assert_allclose(before.correction, np.eye(4), atol=1e-6)  # no loop: map = odom
    step = out.take(_verified(shared, 165, odo[165], (loop(ref, 165, 5),)))
    assert step is not None and step.backend is not None and step.backend.added
    after = out.snapshot
    assert after.version == 166 and after.loops == 1 and before.loops == 0
    drift = np.linalg.norm(odo[165][:3, 3] - ref[165][:3, 3])
    fixed = np.linalg.norm(after.poses[-1][:3, 3] - ref[165][:3, 3])
    assert drift > 3.0 and fixed < 0.3 * drift
    # The corrected pose is the correction applied to the odometry.
    np.testing.assert_allclose(after.correction @ odo[165], after.poses[-1], atol=1e-6)
    assert after.covariance is not None and after.covariance.shape == (6, 6)
    assert out.values()['backend_loops'] == 1
    # The snapshot is the loop closure's hint for the next keyframe, the graph as it stands
    # (one estimate: the detector verifies with what the node publishes), read-only.
    hint = shared.closure.hint
    assert hint is not None and hint is step.estimate
    assert hint.indices.tolist() == list(range(166))
    kfs = shared.closure.graph.keyframes()  # type: ignore[union-attr]
    np.testing.assert_array_equal(after.poses, np.array([f.pose for f in kfs]))
    np.testing.assert_array_equal(hint.poses, after.poses)
    np.testing.assert_array_equal(hint.correction, after.correction)
    for array in (hint.poses, hint.odom, hint.indices, hint.correction, after.poses,
                  after.stamps_ns):
        with pytest.raises(ValueError):
            array.flat[0] = 1.0
    # Relative covariances come from the live graph, to the hint's newest keyframe.
    assert hint.relative is not None
    rel = hint.relative(164)
    assert rel is not None and rel.shape == (6, 6)
    far = hint.relative(60)
    assert far is not None and np.trace(rel[:3, :3]) < np.trace(far[:3, :3])
    # ~/reset: a new detector and an empty graph, then an empty snapshot.
    stale = _verified(shared, 166, odo[166])
    shared.reset(LoopDetector(SolidConfig(backend=True)))
    out.reset()
    assert out.snapshot.version == 167 and len(out.snapshot.stamps_ns) == 0
    assert shared.closure.hint is None
    # A keyframe verified before the reset changes nothing after it.
    assert out.take(stale) is None and out.snapshot.version == 167
    assert out.take(_verified(shared, 0, odo[0])) is not None
    assert out.snapshot.version == 168 and out.snapshot.indices.tolist() == [0]


def test_a_keyframe_without_pose_is_logged_and_changes_no_snapshot() -> None:
    log = Log()
    shared = _shared()
    out = GraphOutput(shared, log)
    step = out.take(_verified(shared, 0, None))
    assert step is not None and step.backend is not None and not step.backend.added
    assert out.snapshot.version == 0 and shared.closure.hint is None
    assert log.lines and log.lines[0][0] == 'warning' and 'no odometry pose' in log.lines[0][1]


def test_the_snapshot_carries_the_clouds_header_stamps() -> None:
    # The detector's stamps differ from the headers after untrusted ones (StampGuard): the
    # graph keeps the detector's, the published path and trajectory the headers'.
    shared = _shared()
    out = GraphOutput(shared, Log(), header_stamps=lambda stamps: stamps - 7)
    for k in range(3):
        out.take(_verified(shared, k, np.eye(4)))
    assert out.snapshot.stamps_ns.tolist() == [k * SEC - 7 for k in range(3)]
    assert [f.stamp_ns for f in shared.closure.graph.keyframes()  # type: ignore[union-attr]
            ] == [k * SEC for k in range(3)]


def test_messages_carry_the_correction_path_and_covariance() -> None:
    T = np.eye(4)
    T[:3, :3] = rot_z(math.pi / 2)
    T[:3, 3] = [1.0, 2.0, 3.0]
    tf = transform_msg(T, 5 * SEC + 7, 'map', 'odom').transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ('map', 'odom')
    assert (tf.header.stamp.sec, tf.header.stamp.nanosec) == (5, 7)
    assert tf.transform.translation.y == 2.0
    assert tf.transform.rotation.z == pytest.approx(math.sin(math.pi / 4))
    # A variance along the sensor's x is one along the map's y after a quarter turn.
    cov = np.diag([4.0, 1.0, 1.0, 0.1, 0.1, 0.2])
    np.testing.assert_allclose(np.diag(covariance_in_parent(T, cov)),
                               [1.0, 4.0, 1.0, 0.1, 0.1, 0.2], atol=1e-12)
    from nav_msgs.msg import Odometry
    msg = Odometry()
    msg.header.frame_id, msg.child_frame_id = 'odom', 'lidar'
    msg.twist.twist.linear.x = 1.5
    odom_pose = np.eye(4)
    odom_pose[0, 3] = 10.0
    out = corrected_odometry(msg, T, odom_pose, cov, 'map')
    assert (out.header.frame_id, out.child_frame_id) == ('map', 'lidar')
    assert (out.pose.pose.position.x, out.pose.pose.position.y) == pytest.approx((1.0, 12.0))
    assert out.twist.twist.linear.x == 1.5 and out.pose.covariance[0] == pytest.approx(1.0)
    path = path_msg([1, 2], np.stack([np.eye(4), T]), 'map', 3)
    assert len(path.poses) == 2 and path.poses[1].pose.position.z == 3.0
    assert list(lio_sam_loop_msg(12 * SEC, 3 * SEC + SEC // 2).data) == [12.0, 3.5]
