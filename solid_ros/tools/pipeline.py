"""The replay's scan loop: bag -> odometry source -> loop closure, one record per cloud.

:class:`ReplayPipeline` reads the clouds of one topic, asks its odometry source
(:class:`~solid_ros.core.odometry.track.OdometrySource`: the bag's Odometry topic, or KISS-ICP
over the clouds) for each cloud's pose and hands both to the product's
:class:`~solid_ros.core.flow.closure.LoopClosure` (detector and, with ``backend``, pose graph:
the flow solid_node runs on its two threads); it yields one :class:`ScanRecord` per message.
:meth:`ReplayPipeline.step` is the one place a scan goes through that chain. :class:`ScanLog`
keeps what the scoring, the trajectory and the report need.

Odometry pairing: a recorded Odometry topic is a :class:`StampedOdometry` over the whole
track, and each cloud gets the pose nearest its header stamp within ``odom_tolerance_sec``
(:func:`~solid_ros.core.odometry.track.nearest_stamp`, ties to the earlier). The node applies
the same nearest-within-tolerance rule to the odometry received so far (its newest 512
messages), waiting at most 0.25 s for one at or past the cloud's stamp; the two pair alike when
the odometry reaches the node within that wait, and only the replay pairs odometry that comes
later.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import TracebackType

from solid_ros.core.descriptor.sensor import CloudSample, measure
from solid_ros.core.descriptor.sensor_check import check_line
from solid_ros.core.errors import SolidError
from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.odometry.track import OdometrySource, OdomSample, StampedOdometry
from solid_ros.core.results import BackendState, LoopCandidate, ScanResult
from solid_ros.formats.bags import Bag, CloudScan, select_cloud_topic, select_odom_topic
from solid_ros.formats.poses import PoseTrack
from solid_ros.tools.options import ReplayOptions
from solid_ros.tools.progress import Progress

__all__ = ['STAGES', 'BagInputs', 'OdometryWrap', 'ReplayPipeline', 'ScanLog', 'ScanRecord',
           'published_best']

STAGES = ('describe', 'search', 'verify', 'step')  # the detector's stages, as in StageTimes
_KEEP_LINES = 200  # log lines (back-end events, odometry resets) kept for the report

# Wraps the odometry source the options chose (None: none), e.g. with a fixed transform.
OdometryWrap = Callable[[OdometrySource | None], OdometrySource | None]


@dataclass(frozen=True)
class ScanRecord:
    """One message of the cloud topic and what became of it.

    Attributes:
        seq: its position in the topic.
        stamp_ns: its header stamp.
        result: what the detector gave (None: skipped).
        odom: the odometry pose it was given (None: none).
        skipped: why it was skipped (undecodable, or refused by the detector), else ''.
        read_ms: time spent reading and decoding it.
        detect_ms: time spent detecting and in the back end.
        backend: the pose graph after it (None: back end off, or not a keyframe).
        odom_ms: time spent in the odometry source (KISS-ICP registers the cloud here).
    """

    seq: int
    stamp_ns: int
    result: ScanResult | None = None
    odom: OdomSample | None = None
    skipped: str = ''
    read_ms: float = 0.0
    detect_ms: float = 0.0
    backend: BackendState | None = None
    odom_ms: float = 0.0

    def log_lines(self) -> list[str]:
        """What to log of this scan: an odometry reset, the back end's events."""
        lines = [] if self.odom is None or self.odom.reason is None else [
            f'odometry reset at scan {self.seq}: {self.odom.reason}']
        if self.backend is not None:
            lines += [f'back end {e.kind}: {e.message}' for e in self.backend.events]
        return lines


def published_best(result: ScanResult) -> bool:
    """Whether a keyframe's best descriptor match is among its published loops."""
    top = result.best
    return top is not None and any(
        c.match_index == top.match_index and c.match_session == top.match_session
        for c in result.loops)


@dataclass
class ScanLog:
    """What a run gave, in scan order: counts, times, and the keyframes' results.

    Attributes:
        messages: cloud messages read.
        skipped: ``(seq, reason)`` of each skipped cloud.
        read_ms: per decoded scan, time spent reading and decoding it.
        detect_ms: per decoded scan, time spent detecting and in the back end.
        odom_ms: per decoded scan, time spent in the odometry source.
        backend_ms: per keyframe the back end took, its update time.
        keyframes: ``(seq, result)`` of each keyframe (results without their descriptors).
        keyframe_odom: each keyframe's odometry sample (None: none).
        candidates: the published loops in order (what the node would publish).
        posed: decoded scans that got an odometry pose.
        events: log lines by kind (``odometry_reset`` and the back end's event kinds).
        lines: the first log lines, for the report.
        sensor: what the first clouds show of the sensor ('' before they are read).
        sensor_check: the line saying where the settings contradict them ('' if nowhere).
    """

    messages: int = 0
    skipped: list[tuple[int, str]] = field(default_factory=list)
    read_ms: list[float] = field(default_factory=list)
    detect_ms: list[float] = field(default_factory=list)
    odom_ms: list[float] = field(default_factory=list)
    backend_ms: list[float] = field(default_factory=list)
    keyframes: list[tuple[int, ScanResult]] = field(default_factory=list)
    keyframe_odom: list[OdomSample | None] = field(default_factory=list)
    candidates: list[LoopCandidate] = field(default_factory=list)
    posed: int = 0
    events: Counter[str] = field(default_factory=Counter)
    lines: list[str] = field(default_factory=list)
    sensor: str = ''
    sensor_check: str = ''

    def add(self, record: ScanRecord) -> None:
        """Count one record; keep what scoring needs of a keyframe."""
        self.messages += 1
        res = record.result
        if record.odom is not None and record.odom.reason is not None:
            self.events['odometry_reset'] += 1
        if record.backend is not None:
            self.backend_ms.append(record.backend.update_ms)
            self.events.update(e.kind for e in record.backend.events)
        self.lines += record.log_lines()[:max(0, _KEEP_LINES - len(self.lines))]
        if res is None:
            self.skipped.append((record.seq, record.skipped))
            return
        self.read_ms.append(record.read_ms)
        self.detect_ms.append(record.detect_ms)
        self.odom_ms.append(record.odom_ms)
        self.posed += record.odom is not None
        if res.keyframe:  # a descriptor weighs 25 kB: a long bag must not keep them all
            self.keyframes.append((record.seq, replace(res, descriptor=None)))
            self.keyframe_odom.append(record.odom)
        self.candidates.extend(res.loops)

    @property
    def decoded(self) -> int:
        """Scans decoded and accepted by the detector."""
        return len(self.read_ms)

    @property
    def results(self) -> list[ScanResult]:
        """The keyframes' results in order."""
        return [res for _, res in self.keyframes]

    def stage_ms(self, stage: str) -> list[float]:
        """Per keyframe, the milliseconds of one stage (``describe``, ``search``, ``verify``;
        NaN where it did not run)."""
        return [float(getattr(res.times, stage)) for _, res in self.keyframes]


@dataclass(frozen=True)
class BagInputs:
    """What a replay read from its bag, for the report.

    Attributes:
        path: the bag.
        name: the bag as it was given (for the report).
        ros1: it is a ROS 1 bag.
        integrity: what the CRC check found.
        topic: the cloud topic replayed.
        count: clouds on that topic.
        odom_topic: the Odometry topic (None: none).
        odometry: that topic's poses (None: none).
        odometry_fed: the odometry went to the detector.
        odometry_source: what the odometry fed was: ``'bag'`` (the Odometry topic),
            ``'kiss-icp'`` (KISS-ICP over the clouds) or ``'none'``.
    """

    path: Path
    name: str
    ros1: bool
    integrity: str
    topic: str
    count: int
    odom_topic: str | None
    odometry: PoseTrack | None
    odometry_fed: bool
    odometry_source: str = 'none'


class ReplayPipeline:
    """Bag, odometry source and loop closure; :meth:`run` yields one :class:`ScanRecord` per
    cloud message. A context manager: the bag is open between ``__enter__`` and ``__exit__``.

    Args:
        bag: ROS 2 bag directory (MCAP or sqlite3) or ROS 1 .bag file.
        closure: the detector (and back end) the scans go to; its own ``odometry`` is not
            used: the pipeline pairs each scan itself.
        options: the topics and the odometry settings.
        wrap_odometry: applied to the odometry source the options chose (a plug-in, e.g.
            the odometry in another frame).

    Raises:
        SolidError: the bag cannot be read or lacks the topics, or KISS-ICP is missing (on
            ``__enter__``).
    """

    def __init__(self, bag: str | Path, closure: LoopClosure, options: ReplayOptions,
                 wrap_odometry: OdometryWrap | None = None) -> None:
        self.bag_path = bag
        self.closure = closure
        self.options = options
        self.odometry: OdometrySource | None = None
        self._wrap = wrap_odometry
        self._bag: Bag | None = None
        self._inputs: BagInputs | None = None
        self._sensor: CloudSample | None = CloudSample()

    @property
    def detector(self) -> LoopDetector:
        """The loop detector."""
        return self.closure.detector

    def __enter__(self) -> ReplayPipeline:
        opts = self.options
        self._bag = bag = Bag(self.bag_path)
        try:
            topic = select_cloud_topic(bag, opts.topic)
            odom_topic = select_odom_topic(bag, opts.odom_topic)
            track = bag.odometry(odom_topic) if odom_topic is not None else None
            self.odometry, source = self._source(track)
        except BaseException:
            bag.close()
            raise
        if self._wrap is not None:
            self.odometry = self._wrap(self.odometry)
        fed = self.odometry is not None
        self._inputs = BagInputs(Path(self.bag_path), str(self.bag_path), bag.is_ros1,
                                 bag.integrity, topic, bag.topics[topic].count, odom_topic,
                                 track, fed, source if fed else 'none')
        return self

    def _source(self, track: PoseTrack | None) -> tuple[OdometrySource | None, str]:
        """The odometry source the options ask for, and its name."""
        opts = self.options
        if not opts.feed_odom:
            return None, 'none'
        if opts.odometry_mode == 'kiss-icp':
            from solid_ros.core.odometry.kiss import KissOdometry

            return KissOdometry(opts.node_config), 'kiss-icp'
        if track is None:
            return None, 'none'
        assert track.stamps_ns is not None  # Odometry is stamped
        return StampedOdometry.from_track(track.stamps_ns, track.poses, opts.tolerance_ns,
                                          track.source), 'bag'

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._bag is not None:
            self._bag.close()

    @property
    def inputs(self) -> BagInputs:
        """What was read from the bag (after ``__enter__``)."""
        if self._inputs is None:
            raise SolidError('the replay pipeline is not open')
        return self._inputs

    def run(self) -> Iterator[ScanRecord]:
        """Yield one record per cloud message, in bag order."""
        if self._bag is None:
            raise SolidError('the replay pipeline is not open')
        clouds = self._bag.clouds(self.inputs.topic, self.options.node_config.kiss_time_field)
        while True:
            t0 = time.perf_counter()
            scan = next(clouds, None)
            if scan is None:
                return
            yield self.step(scan, (time.perf_counter() - t0) * 1e3)

    def step(self, scan: CloudScan, read_ms: float = 0.0) -> ScanRecord:
        """One scan: its odometry pose, then the loop closure (detector, back end)."""
        if scan.points is None:
            return ScanRecord(scan.seq, scan.stamp_ns, skipped=scan.error or 'undecodable')
        if self._sensor is not None:
            self._sensor.add(scan.points)
        t0 = time.perf_counter()
        odom = None
        if self.odometry is not None and scan.times is not None and getattr(
                self.odometry, 'takes_point_times', False):  # KISS-ICP deskews with them
            odom = self.odometry.pose_for(scan.stamp_ns, scan.points,
                                          point_times=scan.times)  # type: ignore[call-arg]
        elif self.odometry is not None:
            odom = self.odometry.pose_for(scan.stamp_ns, scan.points)
        t1 = time.perf_counter()
        try:
            step = self.closure.process(scan.points, scan.stamp_ns, odom)
        except SolidError as err:  # a cloud the core rejects is skipped, as the node does
            return ScanRecord(scan.seq, scan.stamp_ns, odom=odom, skipped=str(err))
        return ScanRecord(scan.seq, scan.stamp_ns, step.scan, odom, '', read_ms,
                          (time.perf_counter() - t1) * 1e3, step.backend, (t1 - t0) * 1e3)

    def collect(self, progress: Progress) -> ScanLog:
        """Run to the end of the bag, logging every record and reporting progress; the
        odometry resets and the back end's events go to the progress stream as lines."""
        log = ScanLog()
        try:
            for record in self.run():
                log.add(record)
                for line in record.log_lines():
                    progress.note(line)
                if self._sensor is not None and self._sensor.complete:
                    self._check_sensor(log, progress)
                progress.update(1, skipped=int(record.result is None))
        except BaseException:
            progress.clear()
            raise
        if self._sensor is not None:  # a bag shorter than the sample
            self._check_sensor(log, progress)
        progress.close()
        return log

    def _check_sensor(self, log: ScanLog, progress: Progress) -> None:
        """What the first clouds show, and the node's line where the settings contradict
        them (:func:`~solid_ros.core.descriptor.sensor_check.check_line`)."""
        sample, self._sensor = self._sensor, None
        view = measure(sample) if sample is not None else None
        if sample is None or view is None:
            return
        log.sensor = view.summary()
        log.sensor_check = check_line(sample, self.closure.config) or ''
        if log.sensor_check:
            progress.note(f'sensor check: {log.sensor_check}')
