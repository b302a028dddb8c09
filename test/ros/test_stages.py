"""Stages and SharedDetector without ROS: clouds in, one Verified per keyframe out, in order."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import OdometryUnavailable
from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.odometry.track import OdomSample
from solid_ros.ros.health import InputHealth
from solid_ros.ros.sensor_watch import SensorWatch
from solid_ros.ros.shared_detector import SharedDetector
from solid_ros.ros.stages import ODOMETRY_QUEUE, Stages, Verified

SEC = 1_000_000_000
# Every scan is a keyframe and, after the first, a loop to an earlier one.
LOOP_EVERY_SCAN = SolidConfig().replace(distance_threshold=0.5, exclude_recent_frames=0,
                                        keyframe_min_sec=0.0, keyframe_min_distance=0.0,
                                        keyframe_min_rotation_deg=0.0)


class Log:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def debug(self, message: str, **kwargs: Any) -> None:
        self.lines.append(('debug', message))

    def info(self, message: str, **kwargs: Any) -> None:
        self.lines.append(('info', message))

    def warning(self, message: str, **kwargs: Any) -> None:
        self.lines.append(('warning', message))

    def error(self, message: str, **kwargs: Any) -> None:
        self.lines.append(('error', message))


def scene(seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-40, -40, -2], [40, 40, 6], size=(6000, 3))
    return pts[np.hypot(pts[:, 0], pts[:, 1]) > 4.0]


def every_other(stamp_ns: int, points: object) -> OdomSample | None:
    """Odometry for even stamps (in seconds), at x = the stamp in seconds."""
    pose = np.eye(4)
    pose[0, 3] = stamp_ns / SEC
    return OdomSample(stamp_ns, pose) if stamp_ns % (2 * SEC) == 0 else None


def run(config: SolidConfig, clouds: list[tuple[np.ndarray, int]], use_odom: bool = True,
        pair: Callable[[int, Any], OdomSample | None] = every_other, commit: bool = False,
        sensor_clouds: int | None = None) -> tuple[list[Verified], InputHealth, Log, list[str]]:
    """The stages over ``clouds``; with ``commit`` each keyframe is committed to the loop
    closure's back end after it is handed on, as the node does."""
    shared = SharedDetector(LoopClosure(LoopDetector(config)))
    health = InputHealth('/points', '/odom' if use_odom else None, 'reliable', 0.05,
                         lambda topic: 0)
    log = Log()
    out: list[Verified] = []
    threads: list[str] = []

    def hand_on(v: Verified) -> None:
        threads.append(threading.current_thread().name)
        out.append(v)
        if commit:
            shared.commit(v.proposal, v.result, v.odom, v.detector)

    sensor = (SensorWatch(config, log, sensor_clouds) if sensor_clouds is not None else None)
    stages = Stages(shared, health, pair, hand_on, log, queue_size=100, verify=config.verify,
                    use_odom=use_odom, sensor=sensor)
    stages.start()
    try:
        for cloud in clouds:
            stages.put(cloud)
        assert stages.wait_idle(120.0)
        assert stages.waiting() == (0, 0)
    finally:
        stages.stop(10.0)
    return out, health, log, threads


def test_descriptor_only_hands_on_every_keyframe_in_order_on_the_describe_thread() -> None:
    pts = scene()
    clouds = [(pts, (i + 1) * SEC) for i in range(4)]
    out, health, log, threads = run(LOOP_EVERY_SCAN.replace(verify=False), clouds)
    assert [v.result.query_index for v in out] == [0, 1, 2, 3]
    assert [v.result.stamp_ns for v in out] == [c[1] for c in clouds]
    # The odometry paired with each cloud travels with its result (even stamps had one).
    assert [None if v.odom is None else v.odom.stamp_ns for v in out] == [None, 2 * SEC, None,
                                                                          4 * SEC]
    assert [len(v.result.loops) for v in out] == [0, 1, 1, 1]
    assert all(v.detector is out[0].detector for v in out)
    assert set(threads) == {'solid_describe'}
    assert (health.stats.processed, health.stats.without_odom) == (4, 2)
    assert log.lines == []


def test_the_same_loops_as_the_detector_alone() -> None:
    # The node's flow (two stages, verification on its own thread) finds what process() does.
    rng = np.random.default_rng(0)
    base = scene(7)
    clouds = []
    for i in range(6):
        a = rng.uniform(-np.pi, np.pi)
        rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        clouds.append((base @ rot.T + rng.normal(scale=0.02, size=base.shape), (i + 1) * SEC))
    out, _, _, threads = run(LOOP_EVERY_SCAN, clouds, use_odom=False)
    alone = LoopDetector(LOOP_EVERY_SCAN)
    want = [alone.process(pts, stamp).loops for pts, stamp in clouds]
    got = [v.result.loops for v in out]
    assert [[(c.query_index, c.match_index) for c in r] for r in got] == [
        [(c.query_index, c.match_index) for c in r] for r in want]
    assert sum(len(r) for r in got) > 0
    assert set(threads) == {'solid_verify'}


def test_the_verify_thread_verifies_with_the_graph_after_the_previous_keyframe() -> None:
    # A drifting drive whose last scan revisits the first; the descriptor proposes nothing
    # (distance_threshold 0), so its one loop is the graph's candidate, as in the loop
    # closure run scan by scan.
    pytest.importorskip('gtsam', reason='gtsam is not installed')
    pytest.importorskip('small_gicp', reason='small-gicp is not installed')
    from solid_ros.sim.drive import Drive, DriveConfig

    drive = Drive(DriveConfig(seed=0, sensor='hdl64'))
    scans = [5, 40, 80, 120, 273]  # scan 273 revisits scan 5
    cfg = SolidConfig(verify_voxel_size=0.5, verify_coarse_voxel_size=1.5,
                      exclude_recent_frames=2, distance_threshold=0.0, num_candidates=3,
                      backend=True, backend_segment_jump_m=1000.0)
    clouds = [(drive.scan(i).points, (k + 1) * SEC) for k, i in enumerate(scans)]
    odom = {(k + 1) * SEC: OdomSample((k + 1) * SEC, drive.odometry(i))
            for k, i in enumerate(scans)}
    out, _, _, threads = run(cfg, clouds, pair=lambda stamp, _: odom[stamp], commit=True)
    loops = [c for v in out for c in v.result.loops]
    assert [(c.query_index, c.match_index, c.source) for c in loops] == [(4, 0, 'graph')]
    assert set(threads) == {'solid_verify'}
    alone = LoopClosure(LoopDetector(cfg))
    want = [alone.process(pts, stamp, odom[stamp]).scan.loops for pts, stamp in clouds]
    assert [v.result.loops for v in out] == want
    # Without the commits there is no graph, so no hint and no loop.
    out, _, _, _ = run(cfg, clouds, pair=lambda stamp, _: odom[stamp])
    assert [c for v in out for c in v.result.loops] == []


def test_unusable_clouds_are_rejected_and_failures_counted_the_stages_go_on() -> None:
    pts = scene()
    clouds = [(pts, 1 * SEC), (np.full((500, 3), np.nan), 2 * SEC), (pts, 3 * SEC)]
    out, health, log, _ = run(LOOP_EVERY_SCAN.replace(verify=False), clouds)
    assert [v.result.query_index for v in out] == [0, 1]
    assert (health.stats.processed, health.stats.rejected, health.stats.failed) == (2, 1, 0)
    assert [level for level, _ in log.lines] == ['warning']
    assert log.lines[0][1].startswith('rejected PointCloud2 on /points: no usable point')


def test_the_describe_thread_checks_the_first_clouds_once() -> None:
    # Points up to 25 deg above the sensor: the authors' +2 deg top bin takes most of them.
    rng = np.random.default_rng(5)
    pts = scene()
    tall = np.concatenate([pts, pts * [1.0, 1.0, 0.0] + [0.0, 0.0, 1.0] * rng.uniform(
        0.0, 0.45, (len(pts), 1)) * np.hypot(pts[:, :1], pts[:, 1:2])])
    clouds = [(tall, (i + 1) * SEC) for i in range(4)]
    out, _, log, _ = run(LOOP_EVERY_SCAN.replace(verify=False), clouds, sensor_clouds=3)
    assert len(out) == 4
    assert [level for level, _ in log.lines] == ['warning']
    assert 'fov_up_deg' in log.lines[0][1]


class SlowOdometry:
    """An odometry stage's registration that takes ``delay`` seconds per cloud and notes its
    thread, the per-point times it got and when each cloud's registration ended."""

    def __init__(self, delay: float) -> None:
        self.delay = delay
        self.threads: list[str] = []
        self.times: list[Any] = []
        self.done: dict[int, float] = {}

    def __call__(self, stamp_ns: int, points: Any, times: Any) -> OdomSample:
        self.threads.append(threading.current_thread().name)
        self.times.append(times)
        time.sleep(self.delay)
        self.done[stamp_ns] = time.monotonic()
        return OdomSample(stamp_ns, np.eye(4))


def _stages_with(register: SlowOdometry, queue_size: int
                 ) -> tuple[Stages, InputHealth, Log, dict[int, float]]:
    config = LOOP_EVERY_SCAN.replace(verify=False)
    shared = SharedDetector(LoopClosure(LoopDetector(config)))
    health = InputHealth('/points', None, 'reliable', 0.05, lambda topic: 0)
    log = Log()
    described: dict[int, float] = {}

    def hand_on(v: Verified) -> None:
        described[v.result.stamp_ns] = time.monotonic()

    def pair(stamp_ns: int, points: Any) -> OdomSample | None:
        raise AssertionError('with an odometry stage the describe stage pairs nothing')

    stages = Stages(shared, health, pair, hand_on, log, queue_size=queue_size, verify=False,
                    use_odom=True, register=register)
    return stages, health, log, described


def test_a_slow_odometry_runs_on_its_own_thread_and_never_holds_the_describe_stage() -> None:
    slow = SlowOdometry(0.4)
    stages, health, log, described = _stages_with(slow, queue_size=10)
    stages.start()
    pts = scene()
    times = np.linspace(0.0, 1.0, len(pts))
    try:
        t0 = time.monotonic()
        for i in range(3):
            stages.put((pts, (i + 1) * SEC), times if i == 0 else None)
        assert time.monotonic() - t0 < 0.2  # the caller (subscription callback) never waits
        assert stages.odometry_waiting is not None
        assert stages.wait_idle(60.0)
    finally:
        stages.stop(10.0)
    assert set(slow.threads) == {'solid_odometry'}
    assert slow.times[0] is times and slow.times[1:] == [None, None]
    assert sorted(described) == [SEC, 2 * SEC, 3 * SEC]
    # Cloud 1 was described while cloud 2 was still being registered: the describe stage
    # waits for no registration but its own cloud's.
    assert described[SEC] < slow.done[2 * SEC]
    assert health.stats.processed == 3 and health.stats.without_odom == 0
    assert stages.timings.values()['odometry_ms_p50'] != 'nan'
    assert float(stages.timings.values()['odometry_ms_p50']) >= 400.0
    assert log.lines == []


def test_clouds_the_odometry_stage_drops_are_counted_and_logged() -> None:
    slow = SlowOdometry(0.05)
    stages, health, log, described = _stages_with(slow, queue_size=1)
    stages.start()
    pts = scene()
    sent = ODOMETRY_QUEUE + 8
    try:
        for i in range(sent):
            stages.put((pts, (i + 1) * SEC))
        assert stages.wait_idle(60.0)
    finally:
        stages.stop(10.0)
    # Registration waits for no describe queue_size: ODOMETRY_QUEUE clouds may wait (a gap
    # costs the odometry), the rest were dropped, oldest first.
    s = health.stats
    assert ODOMETRY_QUEUE <= len(described) < sent
    assert s.odometry_skipped == s.skipped == sent - len(described)
    assert s.processed == len(described) and sent * SEC in described
    warned = [m for level, m in log.lines if level == 'warning']
    assert warned and 'odometry falls behind' in warned[0] and 'not stored' in warned[0]


class DownOdometry(SlowOdometry):
    """Registration whose odometry is unavailable for the clouds of ``down`` stamps."""

    def __init__(self, down: set[int]) -> None:
        super().__init__(0.0)
        self.down = down

    def __call__(self, stamp_ns: int, points: Any, times: Any) -> OdomSample:
        if stamp_ns in self.down:
            raise OdometryUnavailable('the KISS-ICP process ended; it restarts in 4.0 s')
        return super().__call__(stamp_ns, points, times)


def test_clouds_the_odometry_cannot_register_for_now_are_skipped_not_failed() -> None:
    stages, health, log, described = _stages_with(DownOdometry({2 * SEC, 3 * SEC}), 10)
    stages.start()
    pts = scene()
    try:
        for i in range(4):
            stages.put((pts, (i + 1) * SEC))
        assert stages.wait_idle(60.0)
    finally:
        stages.stop(10.0)
    s = health.stats
    assert sorted(described) == [SEC, 4 * SEC]  # neither registered nor stored
    assert (s.odometry_skipped, s.skipped, s.failed, s.processed) == (2, 2, 0, 2)
    warned = [m for level, m in log.lines if level == 'warning']
    assert warned and 'odometry unavailable' in warned[0] and 'restarts in' in warned[0]
