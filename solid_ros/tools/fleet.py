"""Offline multi-robot replay: several bags, one robot each, exchanging keyframes as nodes do.

Robot ``i`` replays bag ``i`` with ``session_id = i`` (the same settings for all, as a fleet
shares one descriptor fingerprint). The bags are merged by stamp; every keyframe a robot
stores is handed to the others as a peer keyframe (:meth:`LoopDetector.add_peer_keyframe`,
what ``/solid/descriptors`` carries), and a candidate against another robot gets that robot's
stored cloud at that moment (what ``/solid/cloud_requests`` fetches on a live system; an
evicted one is ``peer_evicted``). Each bag's Odometry topic gives the reference poses, which
must share one world frame (true of the simulator's bags and of one recording split into
parts), and is fed to its robot's detector as in the one-bag replay: unless ``use_odom`` is
off, or ``odometry`` is ``'kiss-icp'`` (each robot's KISS-ICP over its own clouds instead).

Each robot's clouds go through the same chain as in the one-bag replay
(:mod:`solid_ros.tools.pipeline`: odometry pose by stamp, then the loop closure), with its
keyframe handed to the peers between the descriptor stage and verification. With the back
end on (``backend`` and odometry fed), each robot keeps its own pose graph and places the
others' maps in it from the inter-robot loops (:mod:`solid_ros.tools.fleet_map`); the
trajectories then come out in one fleet frame, robot 0's map. The scoring, the report and the
outputs are in :mod:`solid_ros.tools.fleet_scoring`.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.errors import BagError, ConfigError, PoseError, SolidError
from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.odometry.track import OdometrySource, StampedOdometry
from solid_ros.core.reasons import Reason
from solid_ros.core.results import LoopCandidate, ScanResult
from solid_ros.formats.bags import Bag, CloudScan, select_cloud_topic, select_odom_topic
from solid_ros.formats.peers import CloudReply, decode, encode
from solid_ros.formats.poses import PoseTrack
from solid_ros.tools.fleet_map import (
    FleetAligner,
    alignment_rows,
    fleet_errors,
    fleet_trajectories,
)
from solid_ros.tools.fleet_scoring import (
    FLEET_CSV_COLUMNS,
    FleetResult,
    RobotRun,
    fleet_report,
    fleet_summary_lines,
    loop_error,
    write_fleet_outputs,
)
from solid_ros.tools.options import ReplayOptions
from solid_ros.tools.pipeline import OdometryWrap
from solid_ros.tools.progress import Progress
from solid_ros.tools.scoring import reference_poses

__all__ = ['FLEET_CSV_COLUMNS', 'FleetResult', 'fleet_summary_lines', 'replay_fleet',
           'write_fleet_outputs']


@dataclass
class _Robot:
    """One robot of a fleet replay: its bag, its reference track, the odometry fed to its
    loop closure (None: none) and the loop closure."""

    index: int
    path: str | Path
    bag: Bag
    topic: str
    track: PoseTrack
    odometry: OdometrySource | None
    closure: LoopClosure
    skipped: int = 0

    @property
    def detector(self) -> LoopDetector:
        """Its loop detector."""
        return self.closure.detector

    def scans(self) -> Iterator[tuple[int, int, CloudScan]]:
        """``(stamp, robot, scan)`` of its clouds, to merge with the others' by stamp."""
        for scan in self.bag.clouds(self.topic):
            yield scan.stamp_ns, self.index, scan


def replay_fleet(bags: Sequence[str | Path], config: SolidConfig | None = None,
                 options: ReplayOptions | None = None,
                 wrap_odometry: Sequence[OdometryWrap | None] | None = None,
                 **changes: Any) -> FleetResult:
    """Replay one bag per robot with descriptor exchange; see the module docstring.

    Args:
        bags: two or more bags (MCAP, sqlite3 or ROS 1), robot ``i`` = ``bags[i]``.
        config: the fleet's detector settings (``session_id`` is set per robot).
        options: what a fleet takes of the replay options: ``node_config`` (the odometry
            pairing tolerance, ``use_odom``, ``odometry_source``), ``topic`` and
            ``odom_topic`` (in every bag; default: each bag's only one), ``use_odom``,
            ``odometry``, ``radius``, ``max_heading_deg``, ``max_pose_error_m``,
            ``max_pose_error_deg``, ``plots``, ``progress`` (default 'quiet') and ``stream``;
            the others belong to one bag and are refused (the command line drops them with a
            note, :meth:`ReplayOptions.for_fleet`).
        wrap_odometry: per robot, applied to the odometry source the options chose (a
            plug-in, as :func:`solid_ros.tools.replay.replay` takes one: e.g. the same odometry
            in another frame, drifting); the bag's Odometry stays the reference.
        **changes: :class:`ReplayOptions` fields replacing those of ``options``.

    Raises:
        SolidError: fewer than two bags, an option of one bag only, a bag cannot be read,
            lacks the topics, or its odometry pairs with none of its clouds.
    """
    if len(bags) < 2:
        raise ConfigError('a fleet replay needs two or more bags, one per robot')
    opts = (ReplayOptions.of(options, **changes) if options is not None
            else ReplayOptions.of(**{'progress': 'quiet', **changes}))
    single = [name for name, _ in opts.single_bag()]
    if single:
        raise ConfigError(f'{", ".join(single)}: for one bag only; a fleet replay has '
                          f'{len(bags)} bags')
    cfg = (config if config is not None else SolidConfig()).for_odometry(
        opts.feed_odom and opts.odometry_mode == 'kiss-icp')
    result = FleetResult([Path(b) for b in bags])
    robots: list[_Robot] = []
    try:
        wraps = list(wrap_odometry or [])
        for path in bags:
            wrap = wraps[len(robots)] if len(robots) < len(wraps) else None
            robots.append(_open(path, len(robots), cfg, opts, wrap))
        _connect(robots)
        aligner = FleetAligner([r.closure for r in robots])
        result.stamps, result.published = _run(robots, opts, aligner)
    finally:
        for robot in robots:
            robot.bag.close()
    result.reference = [_reference(r, result.stamps[r.index], opts) for r in robots]
    if any(r.closure.graph is not None for r in robots):
        result.trajectories = fleet_trajectories(aligner.closures)
        result.alignment_events = aligner.events
    result.errors = [[loop_error(result, i, c) for c in loops]
                     for i, loops in enumerate(result.published)]
    runs = [RobotRun(r.bag.integrity, r.skipped, r.detector.reasons) for r in robots]
    result.report = fleet_report(result, runs, cfg, opts)
    if result.trajectories:
        result.report['fleet_map'] = {
            **fleet_errors(result.trajectories, result.stamps, result.reference),
            'alignments': alignment_rows(aligner.closures)}
    return result


def _open(path: str | Path, index: int, cfg: SolidConfig, opts: ReplayOptions,
          wrap: OdometryWrap | None = None) -> _Robot:
    """Robot ``index``: its bag open, its topics chosen, its odometry read, its loop closure
    (with the back end when ``backend`` is on and it has odometry).

    Raises:
        SolidError: the bag cannot be read, or lacks a cloud or an Odometry topic.
    """
    bag = Bag(path)
    try:
        odom = select_odom_topic(bag, opts.odom_topic)
        if odom is None:
            raise BagError(f'{path} has no nav_msgs/Odometry topic for the reference poses '
                           '(a fleet replay scores every robot against its odometry)')
        track = bag.odometry(odom)
        topic = select_cloud_topic(bag, opts.topic)
        source = _source(track, opts)
        if wrap is not None:
            source = wrap(source)
    except BaseException:
        bag.close()
        raise
    closure = LoopClosure(LoopDetector(cfg.replace(session_id=index)),
                          backend=cfg.backend and source is not None)
    return _Robot(index, path, bag, topic, track, source, closure)


def _source(track: PoseTrack, opts: ReplayOptions) -> OdometrySource | None:
    """The odometry fed to a robot's detector, as the one-bag replay chooses it.

    Raises:
        SolidError: the track has no stamps, or KISS-ICP is not installed.
    """
    if track.stamps_ns is None:  # odometry tracks always carry stamps
        raise BagError(f'{track.source}: odometry without stamps')
    if not opts.feed_odom:
        return None
    if opts.odometry_mode == 'kiss-icp':
        from solid_ros.core.odometry.kiss import KissOdometry

        return KissOdometry(opts.node_config)
    return StampedOdometry.from_track(track.stamps_ns, track.poses, opts.tolerance_ns,
                                      track.source)


def _connect(robots: list[_Robot]) -> None:
    """Let each robot's detector fetch the others' keyframe clouds, as a node asks a peer:
    through the cloud reply's bytes (ground thinned, quantised: what a peer receives)."""
    def fetch(robot: int, index: int, stamp_ns: int) -> KeyframeCloud | Reason:
        if not 0 <= robot < len(robots):
            return 'peer_gone'
        own = robots[robot].detector.peer_cloud(index)
        reply = decode(encode(CloudReply(robot, 0, index, 0, stamp_ns, own)))
        cloud = reply.cloud if isinstance(reply, CloudReply) else None
        return cloud if cloud is not None else 'peer_evicted'

    for robot in robots:
        robot.detector.fetch_cloud = fetch


def _run(robots: list[_Robot], opts: ReplayOptions, aligner: FleetAligner
         ) -> tuple[list[list[int]], list[list[LoopCandidate]]]:
    """Every robot's clouds merged by stamp; per robot its keyframe stamps and its loops
    (with the back end, the robots' alignments decided as loops come and at the end)."""
    stamps: list[list[int]] = [[] for _ in robots]
    published: list[list[LoopCandidate]] = [[] for _ in robots]
    prog = Progress(sum(r.bag.topics[r.topic].count for r in robots), opts.progress,
                    opts.stream)
    try:
        for stamp, i, scan in heapq.merge(*(r.scans() for r in robots),
                                          key=lambda e: (e[0], e[1])):
            res = _step(robots, robots[i], stamp, scan)
            prog.update(1, skipped=int(res is None))
            if res is not None and res.keyframe:
                stamps[i].append(stamp)
                published[i].extend(res.loops)
                aligner.loops(i, res.loops)
                aligner.align(stamp)
        aligner.align(max((s[-1] for s in stamps if s), default=0), everyone=True)
    except BaseException:
        prog.clear()
        raise
    prog.close()
    return stamps, published


def _step(robots: list[_Robot], robot: _Robot, stamp: int,
          scan: CloudScan) -> ScanResult | None:
    """One cloud of ``robot``: odometry, descriptor, keyframe to the peers, verification.

    Returns:
        Its result (``keyframe`` False: gated out), or None when it was skipped.
    """
    if scan.points is None:
        robot.skipped += 1
        return None
    paired = (robot.odometry.pose_for(stamp, scan.points) if robot.odometry is not None
              else None)
    try:
        proposal = robot.closure.propose(scan.points, stamp, paired)
    except SolidError:  # a cloud the core refuses is skipped, as the node does
        robot.skipped += 1
        return None
    if proposal is None:  # not a keyframe
        return ScanResult(stamp)
    if proposal.r_solid is not None:
        for other in robots:
            if other is not robot:
                other.detector.add_peer_keyframe(robot.index, proposal.query_index, stamp,
                                                 proposal.r_solid, proposal.heading,
                                                 proposal.pose)
    return robot.closure.finish(proposal, paired).scan


def _reference(robot: _Robot, stamps: list[int], opts: ReplayOptions) -> npt.NDArray[np.float64]:
    """The robot's odometry pose for each of its keyframes (NaN where none pairs)."""
    tol_sec = opts.node_config.odom_tolerance_sec
    try:
        return reference_poses(robot.track, range(len(stamps)), stamps, opts.tolerance_ns,
                               tol_sec)
    except PoseError as err:
        raise BagError(f'{robot.path}: no odometry pose lies within {tol_sec} s of a cloud '
                       'stamp') from err
