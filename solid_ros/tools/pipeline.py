"""The replay's scan loop: bag -> odometry source -> detector, one record per cloud.

:class:`ReplayPipeline` reads the clouds of one topic, asks its odometry source
(:class:`~solid_ros.core.odometry.OdometrySource`) for each cloud's pose, hands both to the
detector and yields one :class:`ScanRecord` per message: the detector's
:class:`~solid_ros.core.detector.ScanResult` with the :class:`OdomSample` it was given.
:meth:`ReplayPipeline.step` is the one place a scan goes through that chain; a back end fed
keyframes and loops would take each record there, and another odometry (one computed from the
clouds) is another ``odometry`` source. :class:`ScanLog` keeps what the scoring needs.

Odometry pairing: a recorded Odometry topic is a :class:`StampedOdometry` over the whole
track, and each cloud gets the pose nearest its header stamp within ``odom_tolerance_sec``
(:func:`~solid_ros.core.odometry.nearest_stamp`, ties to the earlier). The node applies the same
nearest-within-tolerance rule to the odometry received so far (its newest 512 messages),
waiting at most 0.25 s for one at or past the cloud's stamp; the two pair alike when the
odometry reaches the node within that wait, and only the replay pairs odometry that comes later.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import TracebackType

from solid_ros.core.detector import LoopCandidate, LoopDetector, ScanResult
from solid_ros.core.errors import SolidError
from solid_ros.core.odometry import OdometrySource, OdomSample, StampedOdometry
from solid_ros.formats.bags import Bag, CloudScan, select_cloud_topic, select_odom_topic
from solid_ros.formats.poses import PoseTrack
from solid_ros.tools.options import ReplayOptions
from solid_ros.tools.progress import Progress

__all__ = ['STAGES', 'BagInputs', 'ReplayPipeline', 'ScanLog', 'ScanRecord', 'published_best']

STAGES = ('describe', 'search', 'verify')  # the detector's stages, as in StageTimes


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
        detect_ms: time spent pairing and detecting.
    """

    seq: int
    stamp_ns: int
    result: ScanResult | None = None
    odom: OdomSample | None = None
    skipped: str = ''
    read_ms: float = 0.0
    detect_ms: float = 0.0


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
        detect_ms: per decoded scan, time spent pairing and detecting.
        keyframes: ``(seq, result)`` of each keyframe (results without their descriptors).
        candidates: the published loops in order (what the node would publish).
    """

    messages: int = 0
    skipped: list[tuple[int, str]] = field(default_factory=list)
    read_ms: list[float] = field(default_factory=list)
    detect_ms: list[float] = field(default_factory=list)
    keyframes: list[tuple[int, ScanResult]] = field(default_factory=list)
    candidates: list[LoopCandidate] = field(default_factory=list)

    def add(self, record: ScanRecord) -> None:
        """Count one record; keep what scoring needs of a keyframe."""
        self.messages += 1
        res = record.result
        if res is None:
            self.skipped.append((record.seq, record.skipped))
            return
        self.read_ms.append(record.read_ms)
        self.detect_ms.append(record.detect_ms)
        if res.keyframe:  # a descriptor weighs 25 kB: a long bag must not keep them all
            self.keyframes.append((record.seq, replace(res, descriptor=None)))
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


class ReplayPipeline:
    """Bag, odometry source and detector; :meth:`run` yields one :class:`ScanRecord` per
    cloud message. A context manager: the bag is open between ``__enter__`` and ``__exit__``.

    Args:
        bag: ROS 2 bag directory (MCAP or sqlite3) or ROS 1 .bag file.
        detector: the detector the scans go to.
        options: the topics and the odometry settings.

    Raises:
        SolidError: the bag cannot be read or lacks the topics (on ``__enter__``).
    """

    def __init__(self, bag: str | Path, detector: LoopDetector, options: ReplayOptions) -> None:
        self.bag_path = bag
        self.detector = detector
        self.options = options
        self.odometry: OdometrySource | None = None
        self._bag: Bag | None = None
        self._inputs: BagInputs | None = None

    def __enter__(self) -> ReplayPipeline:
        opts = self.options
        self._bag = bag = Bag(self.bag_path)
        try:
            topic = select_cloud_topic(bag, opts.topic)
            odom_topic = select_odom_topic(bag, opts.odom_topic)
            track = bag.odometry(odom_topic) if odom_topic is not None else None
        except BaseException:
            bag.close()
            raise
        fed = opts.feed_odom and track is not None
        if fed:
            assert track is not None and track.stamps_ns is not None  # Odometry is stamped
            self.odometry = StampedOdometry.from_track(track.stamps_ns, track.poses,
                                                       opts.tolerance_ns, track.source)
        self._inputs = BagInputs(Path(self.bag_path), str(self.bag_path), bag.is_ros1,
                                 bag.integrity, topic, bag.topics[topic].count, odom_topic,
                                 track, fed)
        return self

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
        clouds = self._bag.clouds(self.inputs.topic)
        while True:
            t0 = time.perf_counter()
            scan = next(clouds, None)
            if scan is None:
                return
            yield self.step(scan, (time.perf_counter() - t0) * 1e3)

    def step(self, scan: CloudScan, read_ms: float = 0.0) -> ScanRecord:
        """One scan: its odometry pose, then the detector (a back end would come next)."""
        if scan.points is None:
            return ScanRecord(scan.seq, scan.stamp_ns, skipped=scan.error or 'undecodable')
        t0 = time.perf_counter()
        odom = (self.odometry.pose_for(scan.stamp_ns, scan.points)
                if self.odometry is not None else None)
        try:
            res = self.detector.process(scan.points, scan.stamp_ns,
                                        pose=None if odom is None else odom.pose)
        except SolidError as err:  # a cloud the core rejects is skipped, as the node does
            return ScanRecord(scan.seq, scan.stamp_ns, odom=odom, skipped=str(err))
        return ScanRecord(scan.seq, scan.stamp_ns, res, odom, '', read_ms,
                          (time.perf_counter() - t0) * 1e3)

    def collect(self, progress: Progress) -> ScanLog:
        """Run to the end of the bag, logging every record and reporting progress."""
        log = ScanLog()
        try:
            for record in self.run():
                log.add(record)
                progress.update(1, skipped=int(record.result is None))
        except BaseException:
            progress.clear()
            raise
        progress.close()
        return log
