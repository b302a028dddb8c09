"""Offline multi-robot replay: several bags, one robot each, exchanging keyframes as nodes do.

Robot ``i`` replays bag ``i`` with ``session_id = i`` (the same settings for all, as a fleet
shares one descriptor fingerprint). The bags are merged by stamp; every keyframe a robot
stores is handed to the others as a peer keyframe (:meth:`LoopDetector.add_peer_keyframe`,
what ``/solid/descriptors`` carries), and a candidate against another robot gets that robot's
stored cloud at that moment (what ``/solid/cloud_requests`` fetches on a live system; an
evicted one is ``peer_evicted``). Each bag's Odometry topic is fed to its robot's detector and
gives the reference poses, which must share one world frame (true of the simulator's bags and
of one recording split into parts).

Metrics: a published loop of robot ``i`` against robot ``j`` is correct when its pose is
within the limits of ``inv(ref_j[m]) @ ref_i[q]``. A query has a true inter-robot loop when a
keyframe another robot stored before it lies within the radius; inter-robot recall is the
fraction of those queries with at least one correct inter-robot loop. Loops within one robot
are scored the same way and reported beside them.
"""

from __future__ import annotations

import csv
import heapq
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import NodeConfig, SolidConfig
from solid_ros.core.detector import LoopCandidate, LoopDetector
from solid_ros.core.errors import BagError, ConfigError, SolidError
from solid_ros.core.odometry import StampedOdometry, nearest_stamp
from solid_ros.core.reasons import Reason
from solid_ros.core.registration import KeyframeCloud
from solid_ros.formats.bags import Bag, CloudScan, select_cloud_topic, select_odom_topic
from solid_ros.formats.poses import PoseTrack
from solid_ros.tools.loops import pose_error
from solid_ros.tools.progress import Progress
from solid_ros.tools.reports import write_json

__all__ = ['FLEET_CSV_COLUMNS', 'FleetResult', 'fleet_summary_lines', 'replay_fleet',
           'write_fleet_outputs']

FLEET_CSV_COLUMNS = ('robot', 'query_index', 'query_stamp_ns', 'match_session', 'match_index',
                     'match_stamp_ns', 'distance', 'yaw', 'tx', 'ty', 'tz', 'qx', 'qy', 'qz',
                     'qw', 'fitness', 'rmse', 'overlap', 'inter_robot', 'trans_err_m',
                     'rot_err_deg', 'pose_correct')


@dataclass
class FleetResult:
    """Per robot: keyframe stamps, reference poses and published loops; the fleet metrics.

    Attributes:
        bags: one bag per robot; robot ``i`` is ``bags[i]`` (its ``session_id``).
        stamps: per robot, the stamp of each keyframe.
        reference: per robot, the reference pose of each keyframe (NaN where unknown).
        published: per robot, its published loops in order.
        errors: per robot, ``(trans_err_m, rot_err_deg)`` of each published loop.
        report: the JSON report.
    """

    bags: list[Path]
    stamps: list[list[int]] = field(default_factory=list)
    reference: list[npt.NDArray[np.float64]] = field(default_factory=list)
    published: list[list[LoopCandidate]] = field(default_factory=list)
    errors: list[list[tuple[float, float]]] = field(default_factory=list)
    report: dict[str, Any] = field(default_factory=dict)


def _scans(bag: Bag, topic: str, robot: int) -> Iterator[tuple[int, int, CloudScan]]:
    for scan in bag.clouds(topic):
        yield scan.stamp_ns, robot, scan


def replay_fleet(bags: Sequence[str | Path], config: SolidConfig | None = None, *,
                 node_config: NodeConfig | None = None, topic: str | None = None,
                 odom_topic: str | None = None, radius: float = 5.0,
                 max_pose_error_m: float = 1.0, max_pose_error_deg: float = 3.0,
                 progress: str = 'quiet', stream: TextIO | None = None) -> FleetResult:
    """Replay one bag per robot with descriptor exchange; see the module docstring.

    Args:
        bags: two or more bags (MCAP, sqlite3 or ROS 1), robot ``i`` = ``bags[i]``.
        config: the fleet's detector settings (``session_id`` is set per robot).
        node_config: node settings (the odometry pairing tolerance).
        topic: PointCloud2 topic in every bag (default: each bag's only one).
        odom_topic: Odometry topic in every bag (default: each bag's only one).
        radius: true-loop distance in metres.
        max_pose_error_m: a published loop is correct within this translation error.
        max_pose_error_deg: ... and this rotation error.
        progress: 'auto', 'bar', 'lines' or 'quiet'.
        stream: progress stream (default stderr).

    Raises:
        SolidError: fewer than two bags, a bag cannot be read, lacks the topics, or its
            odometry pairs with none of its clouds.
    """
    if len(bags) < 2:
        raise ConfigError('a fleet replay needs two or more bags, one per robot')
    cfg = config if config is not None else SolidConfig()
    ncfg = node_config if node_config is not None else NodeConfig()
    tol = int(round(ncfg.odom_tolerance_sec * 1e9))
    dets = [LoopDetector(cfg.replace(session_id=i)) for i in range(len(bags))]

    def fetch(robot: int, index: int, stamp_ns: int) -> KeyframeCloud | Reason:
        if not 0 <= robot < len(dets):
            return 'peer_gone'
        cloud = dets[robot].own_cloud(index)
        return cloud if cloud is not None else 'peer_evicted'

    for det in dets:
        det.fetch_cloud = fetch
    result = FleetResult([Path(b) for b in bags])
    opened: list[Bag] = []
    tracks: list[PoseTrack] = []
    skipped = [0] * len(bags)
    integrity = []
    try:
        streams = []
        total = 0
        for i, path in enumerate(bags):
            bag = Bag(path)
            opened.append(bag)
            integrity.append(bag.integrity)
            odom = select_odom_topic(bag, odom_topic)
            if odom is None:
                raise BagError(f'{path} has no nav_msgs/Odometry topic for the reference poses '
                               '(a fleet replay scores every robot against its odometry)')
            tracks.append(bag.odometry(odom))
            cloud_topic = select_cloud_topic(bag, topic)
            total += bag.topics[cloud_topic].count
            streams.append(_scans(bag, cloud_topic, i))
            result.stamps.append([])
            result.published.append([])
        sources = [StampedOdometry.from_track(_stamps(t), t.poses, tol, t.source) for t in tracks]
        prog = Progress(total, progress, stream)
        try:
            for stamp, robot, scan in heapq.merge(*streams, key=lambda e: (e[0], e[1])):
                if scan.points is None:
                    skipped[robot] += 1
                    prog.update(1, skipped=1)
                    continue
                paired = sources[robot].pose_for(stamp, scan.points)
                det = dets[robot]
                try:
                    proposal = det.propose(scan.points, stamp,
                                           paired.pose if paired is not None else None)
                except SolidError:  # a cloud the core refuses is skipped, as the node does
                    skipped[robot] += 1
                    prog.update(1, skipped=1)
                    continue
                prog.update(1)
                if proposal is None:  # not a keyframe
                    continue
                if proposal.r_solid is not None:
                    for j, other in enumerate(dets):
                        if j != robot:
                            other.add_peer_keyframe(robot, proposal.query_index, stamp,
                                                    proposal.r_solid, proposal.heading,
                                                    proposal.pose)
                result.stamps[robot].append(stamp)
                result.published[robot].extend(det.verify(proposal).loops)
        except BaseException:
            prog.clear()
            raise
        prog.close()
    finally:
        for bag in opened:
            bag.close()
    for i, track in enumerate(tracks):
        idx = nearest_stamp(_stamps(track), result.stamps[i], tol)
        if len(idx) and not (idx >= 0).any():
            raise BagError(f'{bags[i]}: no odometry pose lies within '
                           f'{ncfg.odom_tolerance_sec} s of a cloud stamp')
        ref = np.full((len(idx), 4, 4), np.nan)
        ref[idx >= 0] = track.poses[idx[idx >= 0]]
        result.reference.append(ref)
    result.errors = [[_error(result, i, c) for c in loops]
                     for i, loops in enumerate(result.published)]
    result.report = _report(result, dets, cfg, radius, max_pose_error_m, max_pose_error_deg,
                            skipped, integrity)
    return result


def _stamps(track: PoseTrack) -> npt.NDArray[np.int64]:
    if track.stamps_ns is None:  # odometry tracks always carry stamps
        raise BagError(f'{track.source}: odometry without stamps')
    return track.stamps_ns


def _error(r: FleetResult, robot: int, c: LoopCandidate) -> tuple[float, float]:
    """Translation and rotation error of a published loop against the reference poses."""
    j = c.match_session
    if not (0 <= j < len(r.reference) and 0 <= c.match_index < len(r.reference[j])
            and c.query_index < len(r.reference[robot])):
        return float('nan'), float('nan')
    ref = np.linalg.solve(r.reference[j][c.match_index], r.reference[robot][c.query_index])
    if not np.all(np.isfinite(ref)):
        return float('nan'), float('nan')
    te, re_ = pose_error(c.matrix(), ref)
    return float(te), float(re_)


def _positives(r: FleetResult, robot: int, radius: float, inter: bool,
               exclude: int) -> set[int]:
    """Queries of ``robot`` with a keyframe stored before them within ``radius``: of another
    robot (``inter``), or its own outside the newest ``exclude`` keyframes."""
    own = r.reference[robot][:, :3, 3]
    out: set[int] = set()
    for j, other in enumerate(r.reference):
        if (j == robot) == inter or not len(other):
            continue
        stamps = np.asarray(r.stamps[j], dtype=np.int64)
        pos = other[:, :3, 3]
        for q, (p, stamp) in enumerate(zip(own, r.stamps[robot])):
            if not np.all(np.isfinite(p)):
                continue
            mask = stamps < stamp
            if not inter:
                mask[max(q - exclude, 0):] = False
            d = np.linalg.norm(pos[mask] - p, axis=1)
            if d.size and np.nanmin(d) <= radius:
                out.add(q)
    return out


def _score(r: FleetResult, robot: int, inter: bool, max_m: float, max_deg: float,
           positives: set[int]) -> dict[str, Any]:
    good = 0
    found: set[int] = set()
    n = 0
    for c, (te, re_) in zip(r.published[robot], r.errors[robot]):
        if (c.match_session != robot) != inter:
            continue
        n += 1
        if te < max_m and re_ < max_deg:
            good += 1
            found.add(c.query_index)
    return {'published': n, 'correct': good, 'false': n - good,
            'precision': good / n if n else None,
            'queries_with_true_loop': len(positives),
            'queries_found': len(found & positives),
            'recall': len(found & positives) / len(positives) if positives else None}


def _report(r: FleetResult, dets: list[LoopDetector], cfg: SolidConfig, radius: float,
            max_m: float, max_deg: float, skipped: list[int],
            integrity: list[str]) -> dict[str, Any]:
    robots: list[dict[str, Any]] = []
    for i in range(len(r.bags)):
        inter = _score(r, i, True, max_m, max_deg, _positives(r, i, radius, True, 0))
        own = _score(r, i, False, max_m, max_deg,
                     _positives(r, i, radius, False, cfg.exclude_recent_frames))
        robots.append({'robot': i, 'bag': str(r.bags[i]), 'integrity': integrity[i],
                       'keyframes': len(r.stamps[i]), 'skipped_clouds': skipped[i],
                       'published': len(r.published[i]), 'inter_robot': inter,
                       'own': own, 'reasons': dict(sorted(dets[i].reasons.items()))})
    totals: dict[str, Any] = {}
    for key in ('inter_robot', 'own'):
        s: dict[str, Any] = {k: sum(rb[key][k] for rb in robots)
                             for k in ('published', 'correct', 'false',
                                       'queries_with_true_loop', 'queries_found')}
        s['precision'] = s['correct'] / s['published'] if s['published'] else None
        s['recall'] = (s['queries_found'] / s['queries_with_true_loop']
                       if s['queries_with_true_loop'] else None)
        totals[key] = s
    return {'tool': 'solid_replay (fleet)', 'robots': robots, 'radius_m': radius,
            'max_pose_error_m': max_m, 'max_pose_error_deg': max_deg,
            'config': cfg.to_dict(), 'config_fingerprint': cfg.fingerprint(), **totals}


def write_fleet_outputs(out: str | Path, result: FleetResult) -> list[Path]:
    """Write ``report.json`` and ``candidates.csv`` (every published loop, one row each).

    Raises:
        SolidError: the directory or files cannot be written.
    """
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        report = out / 'report.json'
        write_json(report, result.report)
        rows = out / 'candidates.csv'
        with rows.open('w', newline='', encoding='utf-8') as fh:
            w = csv.writer(fh)
            w.writerow(FLEET_CSV_COLUMNS)
            lim_m, lim_deg = result.report['max_pose_error_m'], result.report['max_pose_error_deg']
            for robot, loops in enumerate(result.published):
                for c, (te, re_) in zip(loops, result.errors[robot]):
                    w.writerow([robot, c.query_index, c.query_stamp_ns, c.match_session,
                                c.match_index, c.match_stamp_ns, f'{c.distance:.6g}',
                                f'{c.yaw:.6g}', *(f'{v:.9g}' for v in c.pose),
                                f'{c.fitness:.6g}', f'{c.rmse:.6g}', f'{c.overlap:.6g}',
                                int(c.match_session != robot), f'{te:.6g}', f'{re_:.6g}',
                                int(te < lim_m and re_ < lim_deg)])
    except OSError as err:
        raise SolidError(f'cannot write the outputs to {out}: {err}') from err
    return [report, rows]


def _fmt(v: float | None) -> str:
    return 'n/a' if v is None else f'{v:.3f}'


def fleet_summary_lines(result: FleetResult, prog: str = 'solid_replay') -> list[str]:
    """The human summary of a fleet replay."""
    rep = result.report
    lines = [f'{prog} fleet summary ({len(result.bags)} robots, robot i = bag i = session_id i)']
    for rb in rep['robots']:
        ir, own = rb['inter_robot'], rb['own']
        lines.append(f'  robot {rb["robot"]}  {rb["keyframes"]} keyframes, {rb["skipped_clouds"]}'
                     f' clouds skipped; against other robots {ir["correct"]} correct, '
                     f'{ir["false"]} false; own {own["correct"]} correct, {own["false"]} false '
                     f'({rb["bag"]})')
    for key, name in (('inter_robot', 'inter-robot'), ('own', 'within robots')):
        s = rep[key]
        lines.append(f'  {name:<14} {s["published"]} published: precision '
                     f'{_fmt(s["precision"])}, recall {_fmt(s["recall"])} '
                     f'({s["queries_found"]} of {s["queries_with_true_loop"]} queries with a '
                     f'true loop within {rep["radius_m"]} m)')
    lines.append(f'  correct          pose within {rep["max_pose_error_m"]} m and '
                 f'{rep["max_pose_error_deg"]} deg of the reference relative pose')
    return lines
