"""The flow of one scan through solid_node: odometry, describe and verify threads.

The threads run the product's loop closure (:class:`~solid_ros.core.flow.closure.LoopClosure`,
through :class:`~solid_ros.ros.shared_detector.SharedDetector`): with a registering odometry
(KISS-ICP) stage 0 (odometry thread) registers each cloud first, so that the describe thread
never waits for it; stage 1 (describe thread) pairs the cloud with odometry (stage 0's pose,
or the odometry topic's) and proposes it (describe, search, store); stage 2 (verify
thread) verifies each keyframe's candidates in keyframe order, with the pose graph's hint, and
hands the result on as one :class:`Verified`, whose receiver publishes its loops and then
commits it to the back end. With ``verify`` off stage 1 hands on itself: what is left
takes well under a millisecond, less than waking the other thread. Each stage is a
:class:`~solid_ros.ros.worker.Worker` with a bounded keep-newest queue; drops and failures are
counted by :class:`~solid_ros.ros.health.InputHealth` and logged, and the stages go on.
The odometry stage's queue is deeper (:data:`ODOMETRY_QUEUE`): a cloud it drops is never
registered nor stored (counted as skipped and as odometry_skipped), and a gap costs the
odometry far more than a late pose. So is a cloud the odometry cannot register for now (its
process ended and restarts later: :class:`~solid_ros.core.errors.OdometryUnavailable`). No ROS
import: the node passes its odometry, its output and its logger in.
"""

from __future__ import annotations

import importlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.proposal import Proposal
from solid_ros.core.errors import CloudError, OdometryUnavailable
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.odometry.track import OdomSample
from solid_ros.core.results import ScanResult
from solid_ros.ros.health import WARN_THROTTLE_SEC, InputHealth
from solid_ros.ros.sensor_watch import SensorWatch
from solid_ros.ros.shared_detector import SharedDetector
from solid_ros.ros.stats import StageTimings
from solid_ros.ros.worker import Worker

__all__ = ['ODOMETRY_QUEUE', 'Cloud', 'Stages', 'Verified']

MIN_PROPOSALS = 20  # keyframes that may wait for verification (at least queue_size)
# Clouds that may wait for registration (at least queue_size): KISS-ICP's bursts (hku1 p95
# 2-3x its median) pass with a late pose instead of a gap, and a gap costs the odometry:
# hku1 with 17 % of its clouds dropped at random tracks at 2.0-3.0 m ATE, not 0.21 m (our
# adapter; plain KISS-ICP with every second cloud 9.1 m). 3 s at 10 Hz; beyond, the node is
# too slow for the rate and drops.
ODOMETRY_QUEUE = 30

Cloud = tuple[npt.NDArray[np.floating[Any]], int]  # (points, stamp_ns) of a decoded cloud
Times = npt.NDArray[np.float64] | None  # per-point times in [0, 1] (deskew), if the cloud has them
# The odometry stage's registration: (stamp_ns, points, times) -> pose.
Register = Callable[[int, npt.NDArray[np.floating[Any]], Times], OdomSample | None]


class Log(Protocol):
    """The logger calls the stages make (an rclpy logger has them)."""

    def debug(self, message: str, **kwargs: Any) -> object: ...
    def info(self, message: str, **kwargs: Any) -> object: ...
    def warning(self, message: str, **kwargs: Any) -> object: ...
    def error(self, message: str, **kwargs: Any) -> object: ...


@dataclass(frozen=True)
class Verified:
    """One keyframe through both stages, as handed on.

    Attributes:
        result: what the detector made of it (loops, attempts, stage times).
        odom: the odometry paired with its cloud, if any.
        proposal: its descriptor stage (the hits, which say where the matches are stored).
        detector: the detector that verified it (``~/reset`` may replace it right after).
    """

    result: ScanResult
    odom: OdomSample | None
    proposal: Proposal
    detector: LoopDetector


@dataclass(frozen=True)
class _Scan:
    points: npt.NDArray[np.floating[Any]]
    stamp_ns: int
    times: Times = None
    odom: OdomSample | None = None
    registered: bool = False  # odom is the odometry stage's (else pair it on stage 1)


@dataclass(frozen=True)
class _Keyframe:
    proposal: Proposal
    odom: OdomSample | None


class Stages:
    """The odometry (optional), describe and verify threads of the node.

    Args:
        shared: the detector both stages use.
        health: counts drops and failures.
        pair: the odometry for a cloud (its stamp and points; may wait briefly, or register
            the cloud), or None.
        hand_on: takes every verified keyframe, in keyframe order.
        log: where drops and failures are logged.
        queue_size: clouds that may wait for stage 1.
        verify: whether the detector verifies (read-only while running).
        use_odom: whether a cloud without odometry counts as such.
        share: sends each keyframe's descriptor to peer robots, if any.
        sensor: checks the first clouds against the settings, if given.
        register: registers each cloud on an odometry thread of its own before stage 1 (then
            ``pair`` is not called), if given.
    """

    def __init__(self, shared: SharedDetector, health: InputHealth,
                 pair: Callable[[int, npt.NDArray[np.floating[Any]]], OdomSample | None],
                 hand_on: Callable[[Verified], None],
                 log: Log, *, queue_size: int, verify: bool, use_odom: bool,
                 share: Callable[[Proposal], None] | None = None,
                 sensor: SensorWatch | None = None, register: Register | None = None) -> None:
        self.timings = StageTimings()
        self._sensor = sensor
        self._shared, self._health, self._log = shared, health, log
        self._pair, self._hand_on, self._share = pair, hand_on, share
        self._verify, self._use_odom = verify, use_odom
        self._register = register
        self._skip_lock = threading.Lock()
        self._describe_worker: Worker[_Scan] = Worker(
            'solid_describe', self._describe_stage, queue_size, self._describe_failed)
        self._verify_worker: Worker[_Keyframe] = Worker(
            'solid_verify', self._verify_stage, max(MIN_PROPOSALS, queue_size),
            self._verify_failed, prepare=self._import_registration)
        self._odometry_worker: Worker[_Scan] | None = None
        workers: list[Worker[Any]] = [self._describe_worker, self._verify_worker]
        if register is not None:
            self._odometry_worker = Worker('solid_odometry', self._odometry_stage,
                                           max(ODOMETRY_QUEUE, queue_size),
                                           self._describe_failed)
            workers.insert(0, self._odometry_worker)
        self._workers = tuple(workers)

    def start(self) -> None:
        """Start the threads."""
        for worker in self._workers:
            worker.start()

    def put(self, cloud: Cloud, times: Times = None) -> None:
        """Queue a decoded cloud (and its per-point times) for the first stage; when its queue
        is full the oldest waiting cloud is dropped."""
        scan = _Scan(cloud[0], cloud[1], times)
        if self._odometry_worker is None:
            self._to_describe(scan)
        elif self._odometry_worker.put(scan):
            skipped = self._odometry_skipped()
            self._log.warning(
                f'odometry falls behind: {ODOMETRY_QUEUE} clouds wait for registration, '
                f'dropped the oldest ({skipped} skipped so far; the cloud is not stored and '
                'the gap costs the odometry: lower the rate or the points, see the README)',
                throttle_duration_sec=WARN_THROTTLE_SEC)

    def _odometry_skipped(self) -> int:
        """Count a cloud skipped before registration; return the clouds skipped so far."""
        with self._skip_lock:  # the subscription's thread and the odometry thread count
            self._health.stats.odometry_skipped += 1
        return self._health.trouble('skipped')

    def _to_describe(self, scan: _Scan) -> None:
        if self._describe_worker.put(scan):
            skipped = self._health.trouble('skipped')
            self._log.warning(
                f'processing falls behind: dropped the oldest waiting cloud ({skipped} skipped '
                'so far)', throttle_duration_sec=WARN_THROTTLE_SEC)

    def reject(self, reason: str) -> None:
        """Count and log a rejected cloud (its kind of reason throttled)."""
        line = self._health.reject(reason)
        if line is not None:
            self._log.warning(line)

    def waiting(self) -> tuple[int, int]:
        """Clouds waiting for stage 1 and keyframes waiting for stage 2."""
        return len(self._describe_worker), len(self._verify_worker)

    @property
    def odometry_waiting(self) -> int | None:
        """Clouds waiting for the odometry stage (None: there is none)."""
        return None if self._odometry_worker is None else len(self._odometry_worker)

    def clear(self) -> None:
        """Forget what waits in the stages (``~/reset``)."""
        for worker in self._workers:
            worker.clear()

    def wait_idle(self, timeout: float) -> bool:
        """Block until the stages are idle with nothing waiting; return False on timeout."""
        deadline = time.monotonic() + timeout
        while True:
            # A stage hands its item on before it goes idle: once each is idle after the
            # ones behind it were, all are.
            for worker in self._workers:
                if not worker.wait_idle(deadline - time.monotonic()):
                    return False
            if all(worker.idle for worker in self._workers):
                return True

    def stop(self, join_sec: float) -> None:
        """End the threads after the items they handle, waiting up to ``join_sec`` each."""
        for worker in self._workers:
            worker.stop()
        for worker in self._workers:
            worker.join(join_sec)

    # -- on the threads ----------------------------------------------------------------------

    def _odometry_stage(self, scan: _Scan) -> None:
        assert self._register is not None
        t0 = time.perf_counter()
        try:
            odom = self._register(scan.stamp_ns, scan.points, scan.times)
        except OdometryUnavailable as err:
            skipped = self._odometry_skipped()
            self._log.warning(f'odometry unavailable, cloud skipped ({skipped} skipped so far): '
                              f'{err}', throttle_duration_sec=WARN_THROTTLE_SEC)
            return
        self.timings.add('odometry', (time.perf_counter() - t0) * 1e3)
        self._to_describe(_Scan(scan.points, scan.stamp_ns, None, odom, registered=True))

    def _describe_stage(self, scan: _Scan) -> None:
        points, stamp_ns = scan.points, scan.stamp_ns
        if self._sensor is not None:
            self._sensor.add(points)
        t0 = time.perf_counter()
        odom = scan.odom if scan.registered else self._pair(stamp_ns, points)
        proposal = self._shared.propose(points, stamp_ns, odom)
        self.timings.add_total((time.perf_counter() - t0) * 1e3)
        stats = self._health.stats
        stats.processed += 1
        if odom is None and self._use_odom:
            stats.without_odom += 1
        if proposal is None:
            return
        if self._share is not None:
            self._share(proposal)
        self.timings.add('describe', proposal.describe_ms)
        self.timings.add('search', proposal.search_ms)
        keyframe = _Keyframe(proposal, odom)
        if not self._verify:
            self._verify_stage(keyframe)
        elif self._verify_worker.put(keyframe):
            dropped = self._health.trouble('verify_skipped')
            self._log.warning(
                'verification falls behind: dropped the oldest waiting keyframe '
                f'({dropped} so far; its cloud is not stored)',
                throttle_duration_sec=WARN_THROTTLE_SEC)

    def _describe_failed(self, err: Exception) -> None:
        if isinstance(err, CloudError):  # decoded, but nothing the detector can use
            self.reject(str(err))
            return
        self._health.trouble('failed')
        self._log.error(f'processing failed: {type(err).__name__}: {err}',
                        throttle_duration_sec=WARN_THROTTLE_SEC)

    def _import_registration(self) -> None:
        # small_gicp and scipy.ndimage take about 0.8 s to import: here, before the first
        # keyframe, not in its latency (where the queue would drop clouds).
        if not self._verify:
            return
        for module in ('small_gicp', 'scipy.ndimage'):
            try:
                importlib.import_module(module)
            except ImportError as err:
                self._log.error(f'verification needs {module}: {err} (pip install small-gicp)')

    def _verify_stage(self, keyframe: _Keyframe) -> None:
        # With the graph after the previous keyframe: its hand_on committed it on this thread.
        result, detector = self._shared.verify(keyframe.proposal)
        self.timings.add('verify', result.times.verify)
        self._hand_on(Verified(result, keyframe.odom, keyframe.proposal, detector))

    def _verify_failed(self, err: Exception) -> None:
        self._health.trouble('failed')
        self._log.error(f'verification failed: {type(err).__name__}: {err}',
                        throttle_duration_sec=WARN_THROTTLE_SEC)
