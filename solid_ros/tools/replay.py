"""solid_replay: run the node's loop detector over a recorded bag, with metrics and plots.

The detector is the node's: the same :class:`~solid_ros.detector.LoopDetector`, configured by
:meth:`SolidConfig.from_yaml` from the same parameter file, fed the same decoded clouds
(:func:`~solid_ros.pointcloud2.cloud_to_xyz`), header stamps, and odometry poses paired within
``odom_tolerance_sec`` exactly as the node pairs them.

Usage: ``solid_replay BAG [--params FILE.yaml] [--topic /points]
[--odom-topic T | --poses FILE [--times FILE]] [--out DIR] [--load-db F] [--save-db F]``.
"""

from __future__ import annotations

import argparse
import csv
import math
import platform
import resource
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import NodeConfig, SolidConfig, check_parameters, load_parameter_file
from solid_ros.core.detector import LoopCandidate, LoopDetector
from solid_ros.core.errors import ConfigError, SolidError
from solid_ros.core.odometry import StampedOdometry, nearest_stamp
from solid_ros.core.persistence import check_save_target
from solid_ros.formats.bags import Bag, select_cloud_topic, select_odom_topic
from solid_ros.formats.poses import PoseError, load_reference
from solid_ros.runtime import tune_allocator
from solid_ros.tools.evaluation import Evaluation, evaluate, recommend_threshold, sweep_table
from solid_ros.tools.fleet import fleet_summary_lines, replay_fleet, write_fleet_outputs
from solid_ros.tools.loops import LoopRecord, overlap_sweep, pose_error, score_loops
from solid_ros.tools.progress import Progress
from solid_ros.tools.reports import write_json

__all__ = ['ReplayResult', 'build_parser', 'main', 'replay']

PROG = 'solid_replay'
CSV_COLUMNS = ('query_index', 'match_index', 'query_stamp_ns', 'match_stamp_ns',
               'match_session', 'distance', 'yaw', 'margin', 'accepted', 'best',
               'true_match', 'gt_distance_m', 'yaw_gt', 'verified', 'reason', 'tx', 'ty', 'tz',
               'qx', 'qy', 'qz', 'qw', 'fitness', 'rmse', 'overlap', 'conflict', 'constraint',
               'spread', 'trans_err_m',
               'rot_err_deg', 'pose_correct') + tuple(f'cov_{i}' for i in range(36))


@dataclass
class ReplayResult:
    """Everything one replay produced.

    Attributes:
        candidates: accepted loop candidates in order (what the node would publish).
        best: per keyframe, its best match accepted or not (None when the database had no
            eligible scan).
        accepted: per keyframe, whether its best match was accepted.
        stamps_ns: per keyframe, its stamp.
        reference: per keyframe, the reference pose (NaN where unknown), or None.
        evaluation: metrics object when reference poses were available.
        attempts: per keyframe, every candidate it looked at (published or not).
        records: the attempts scored against the reference poses (empty without them).
        report: the JSON report (also written to ``out_dir/report.json``).
        files: files written.
    """

    bag: Path
    topic: str
    config: SolidConfig
    messages: int
    skipped: int
    keyframes: int
    candidates: list[LoopCandidate]
    best: list[LoopCandidate | None]
    accepted: npt.NDArray[np.bool_]
    stamps_ns: npt.NDArray[np.int64]
    reference: npt.NDArray[np.float64] | None
    evaluation: Evaluation | None
    report: dict[str, Any]
    wall_sec: float
    attempts: list[list[LoopCandidate]] = field(default_factory=list)
    records: list[LoopRecord] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)

    @property
    def metrics(self) -> dict[str, Any] | None:
        """``report['metrics']`` (None without reference poses)."""
        return self.report.get('metrics')

    @property
    def scans_per_sec(self) -> float:
        """End-to-end throughput (read + decode + detect) over decoded scans."""
        return (self.messages - self.skipped) / self.wall_sec if self.wall_sec > 0 else 0.0


def _percentiles(ms: Sequence[float]) -> dict[str, float | None]:
    if not ms:
        return {'mean': None, 'p50': None, 'p90': None, 'p99': None, 'max': None}
    a = np.asarray(ms, dtype=np.float64)
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return {'mean': float(a.mean()), 'p50': float(p50), 'p90': float(p90),
            'p99': float(p99), 'max': float(a.max())}


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    import solid_ros

    out = {'solid_ros': solid_ros.__version__, 'python': platform.python_version()}
    for pkg in ('numpy', 'scipy', 'rosbags', 'matplotlib'):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = 'absent'
    return out


def load_config(params: str | Path | None, node_name: str = 'solid_node',
                overrides: dict[str, Any] | None = None) -> tuple[SolidConfig, NodeConfig]:
    """Read the detector and node settings from a parameter file, as the node does.

    The file passes the node's rule (:func:`~solid_ros.core.config.load_parameter_file`), and
    ``overrides`` (``--set``) the rule of the node's ``-p`` overrides.

    Raises:
        ConfigError: unreadable file, unknown key or invalid value (named).
    """
    values: dict[str, Any] = {}
    if params is not None:
        values = load_parameter_file(params, node_name)
    check_parameters(overrides or {}, '--set')
    values.update(overrides or {})
    return (SolidConfig.from_dict(values, strict=False),
            NodeConfig.from_dict(values, strict=False))


def replay(bag: str | Path, config: SolidConfig | None = None, *,
           node_config: NodeConfig | None = None, topic: str | None = None,
           odom_topic: str | None = None, use_odom: bool | None = None,
           poses: str | Path | None = None, times: str | Path | None = None,
           radius: float = 5.0, max_heading_deg: float | None = None,
           out_dir: str | Path | None = None, load_db: str | Path | None = None,
           save_db: str | Path | None = None, progress: str = 'auto',
           plots: bool = True, params_file: str | Path | None = None,
           stream: TextIO | None = None, max_pose_error_m: float = 1.0,
           max_pose_error_deg: float = 3.0, target_precision: float = 1.0) -> ReplayResult:
    """Replay a bag through the node's detector and evaluate it when poses are known.

    Args:
        bag: ROS 2 bag directory (MCAP or sqlite3) or ROS 1 .bag file.
        config: detector settings (default ``SolidConfig()``).
        node_config: node settings (odometry use and pairing tolerance).
        topic: PointCloud2 topic (default: the bag's only one).
        odom_topic: Odometry topic fed to the detector as the node's ``odom`` (default: the
            bag's only one, if any) and used as reference when ``poses`` is not given.
        use_odom: feed odometry to the detector (default ``node_config.use_odom``).
        poses: reference poses file (KITTI 3x4 or TUM); KITTI files pair with scans by order
            unless ``times`` gives their stamps.
        times: stamps of a KITTI poses file.
        radius: true-loop distance in metres.
        max_heading_deg: also require headings within this many degrees for a true loop.
        out_dir: where to write candidates.csv, report.json and plots (None: nothing).
        load_db: database file to load before the run (its scans are searched too).
        save_db: where to save the database after the run.
        progress: 'auto', 'bar', 'lines' or 'quiet'.
        plots: write PNG plots to ``out_dir`` when poses are available.
        params_file: recorded in the report.
        stream: progress stream (default stderr).
        max_pose_error_m: a published loop is correct within this translation error.
        max_pose_error_deg: ... and this rotation error of the reference relative pose.
        target_precision: the sweep recommends the setting reaching this precision.

    Raises:
        SolidError: any problem with the inputs (BagError, ConfigError, DatabaseError,
            PoseError), with a one-line message.
    """
    cfg = config if config is not None else SolidConfig()
    ncfg = node_config if node_config is not None else NodeConfig()
    feed_odom = ncfg.use_odom if use_odom is None else use_odom
    if times is not None and poses is None:
        raise PoseError('--times needs --poses')
    if not 0.0 < radius < math.inf:
        raise ConfigError(f'--radius must be a positive number of metres, got {radius}')
    if max_heading_deg is not None and not 0.0 < max_heading_deg <= 180.0:
        raise ConfigError(f'--max-heading-deg must be in (0, 180] degrees, got '
                          f'{max_heading_deg}')
    file_track = load_reference(poses, times) if poses is not None else None
    if save_db is not None:
        check_save_target(save_db)  # refuse before the run, not after it
    detector = LoopDetector.load(load_db, cfg) if load_db is not None else LoopDetector(cfg)
    t_start = time.perf_counter()
    with Bag(bag) as b:
        cloud_topic = select_cloud_topic(b, topic)
        odom_name = select_odom_topic(b, odom_topic)
        odom_track = b.odometry(odom_name) if odom_name is not None else None
        total = b.topics[cloud_topic].count
        if file_track is not None and file_track.stamps_ns is None and len(file_track) != total:
            raise PoseError(f'{file_track.source} has {len(file_track)} poses but '
                            f'{cloud_topic} has {total} clouds; pair them with --times')
        prog = Progress(total, progress, stream)
        tol = int(round(ncfg.odom_tolerance_sec * 1e9))
        source = None
        if feed_odom and odom_track is not None:
            assert odom_track.stamps_ns is not None  # odometry topics are stamped
            source = StampedOdometry.from_track(odom_track.stamps_ns, odom_track.poses, tol,
                                                odom_track.source)
        stamps: list[int] = []
        seqs: list[int] = []
        kf_stamps: list[int] = []
        kf_seq: list[int] = []
        best: list[LoopCandidate | None] = []
        accepted: list[bool] = []
        candidates: list[LoopCandidate] = []
        skipped: list[tuple[int, str]] = []
        read_ms: list[float] = []
        detect_ms: list[float] = []
        stage_ms: dict[str, list[float]] = {'describe': [], 'search': [], 'verify': []}
        attempts: list[list[LoopCandidate]] = []
        messages = 0
        clouds = b.clouds(cloud_topic)
        try:
            while True:
                t0 = time.perf_counter()
                scan = next(clouds, None)
                t1 = time.perf_counter()
                if scan is None:
                    break
                messages += 1
                if scan.points is None:
                    skipped.append((scan.seq, scan.error or 'undecodable'))
                    prog.update(1, skipped=1)
                    continue
                odom = source.pose_for(scan.stamp_ns, scan.points) if source is not None else None
                try:
                    res = detector.process(scan.points, scan.stamp_ns,
                                           pose=None if odom is None else odom.pose)
                except SolidError as err:  # a cloud the core rejects is skipped like the node
                    skipped.append((scan.seq, str(err)))
                    prog.update(1, skipped=1)
                    continue
                t2 = time.perf_counter()
                read_ms.append((t1 - t0) * 1e3)
                detect_ms.append((t2 - t1) * 1e3)
                stamps.append(scan.stamp_ns)
                seqs.append(scan.seq)
                if res.keyframe:
                    kf_stamps.append(scan.stamp_ns)
                    kf_seq.append(scan.seq)
                    attempts.append(list(res.attempts))
                    for stage in stage_ms:
                        stage_ms[stage].append(getattr(res.times, stage))
                    top = res.best
                    best.append(top)
                    accepted.append(top is not None and any(
                        c.match_index == top.match_index and c.match_session == top.match_session
                        for c in res.loops))
                candidates.extend(res.loops)
                prog.update(1)
        except BaseException:
            prog.clear()
            raise
        prog.close()
    wall = time.perf_counter() - t_start
    if save_db is not None:
        detector.save(save_db)

    # Reference pose per keyframe.
    kf_stamp_arr = np.asarray(kf_stamps, dtype=np.int64)
    track = file_track if file_track is not None else odom_track
    reference = None
    if track is not None:
        if track.stamps_ns is None:
            idx = np.asarray(kf_seq, dtype=np.intp)
        else:
            idx = nearest_stamp(track.stamps_ns, kf_stamp_arr, tol)
        reference = np.full((len(kf_seq), 4, 4), np.nan)
        have = idx >= 0
        reference[have] = track.poses[idx[have]]
        if len(kf_seq) and not have.any():
            raise PoseError(f'no reference pose of {track.source} lies within '
                            f'{ncfg.odom_tolerance_sec} s of a scan stamp')

    acc = np.asarray(accepted, dtype=bool)
    ev = None
    if reference is not None:
        ev = _evaluate(cfg, best, acc, kf_stamp_arr, reference, radius, max_heading_deg)
    records: list[LoopRecord] = []
    if reference is not None:
        records = _records(cfg, attempts, candidates, reference)
    db = detector.database
    kf_clouds = detector.clouds
    report: dict[str, Any] = {
        'tool': PROG,
        'versions': _versions(),
        'bag': str(bag),
        'format': 'ros1' if b.is_ros1 else 'ros2',
        'integrity': b.integrity,
        'topic': cloud_topic,
        'odom_topic': odom_name,
        'odometry_fed_to_detector': bool(feed_odom and odom_track is not None),
        'reference': None if track is None else track.source,
        'params_file': None if params_file is None else str(params_file),
        'config': cfg.to_dict(),
        'config_fingerprint': cfg.fingerprint(),
        'node_config': ncfg.to_dict(),
        'scans': {'messages': messages, 'decoded': len(stamps), 'skipped': len(skipped),
                  'keyframes': len(kf_stamps), 'accepted_loops': len(candidates),
                  'skip_reasons': [{'seq': s, 'reason': r} for s, r in skipped[:20]]},
        'timings': {'wall_sec': wall,
                    'scans_per_sec': len(stamps) / wall if wall > 0 else None,
                    'read_decode_ms': _percentiles(read_ms),
                    'detect_ms': _percentiles(detect_ms),
                    **{f'{k}_ms': _percentiles([v for v in ms if math.isfinite(v)])
                       for k, ms in stage_ms.items()}},
        'keyframe_clouds': {'kept': len(kf_clouds), 'mb': kf_clouds.nbytes / 1e6,
                            'dropped': kf_clouds.dropped,
                            'bytes_per_keyframe': kf_clouds.nbytes / max(len(kf_clouds), 1)},
        'verification': {'enabled': cfg.verify, 'reasons': dict(sorted(detector.reasons.items()))},
        'loops': None,
        'loop_sweep': None,
        'database': {'size': db.size, 'bytes': db.stored_bytes,
                     'allocated_bytes': db.nbytes, 'bytes_per_scan': db.bytes_per_scan,
                     'peak_rss_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0},
        'metrics': None,
        'threshold_sweep': None,
        'loaded_database': None if load_db is None else str(load_db),
        'saved_database': None if save_db is None else str(save_db),
    }
    if ev is not None:
        report['metrics'] = ev.metrics()
        report['threshold_sweep'] = sweep_table(ev)
        report['loops'] = score_loops(records, ev.truth.has_loop, max_error_m=max_pose_error_m,
                                      max_error_deg=max_pose_error_deg)
        report['loop_sweep'] = (
            overlap_sweep(records, ev.truth.has_loop, cfg.verify_min_overlap,
                          target_precision=target_precision, max_error_m=max_pose_error_m,
                          max_error_deg=max_pose_error_deg) if cfg.verify
            else _distance_for_precision(ev, target_precision))
    result = ReplayResult(Path(bag), cloud_topic, cfg, messages, len(skipped), len(kf_stamps),
                          candidates, best, acc, kf_stamp_arr, reference, ev, report, wall,
                          attempts, records)
    if out_dir is not None:
        result.files = _write_outputs(Path(out_dir), result, plots)
    return result


def _records(cfg: SolidConfig, attempts: list[list[LoopCandidate]],
             published: list[LoopCandidate],
             reference: npt.NDArray[np.float64]) -> list[LoopRecord]:
    """Every attempt scored against the reference relative pose."""
    shown = {id(c) for c in published}
    out = []
    for tried in attempts:
        for c in tried:
            te = re_ = gd = math.nan
            if c.match_session == cfg.session_id and 0 <= c.match_index < len(reference):
                q, m = reference[c.query_index], reference[c.match_index]
                te, re_ = pose_error(c.matrix(), np.linalg.solve(m, q))
                gd = float(np.linalg.norm(q[:3, 3] - m[:3, 3]))
            out.append(LoopRecord(c.query_index, c.match_index, c.match_session,
                                  id(c) in shown, c.verified, c.reason, c.overlap, c.distance,
                                  te, re_, gd))
    return out


def _distance_for_precision(ev: Evaluation, target: float) -> dict[str, Any]:
    """Descriptor-only mode: the largest distance_threshold whose precision reaches ``target``
    (places within the radius count as correct, as in the PR curve)."""
    c = ev.curve
    ok = np.flatnonzero(c.precision >= target)
    k = int(ok[-1]) if ok.size else -1
    return {'parameter': 'distance_threshold', 'target_precision': target,
            'recommended': recommend_threshold(c, k) if k >= 0 else None,
            'recall': float(c.recall[k]) if k >= 0 else None}


def _evaluate(cfg: SolidConfig, best: list[LoopCandidate | None], acc: npt.NDArray[np.bool_],
              stamps: npt.NDArray[np.int64], reference: npt.NDArray[np.float64], radius: float,
              max_heading_deg: float | None) -> Evaluation:
    n = len(best)
    match = np.full(n, -1, dtype=np.intp)
    dist = np.full(n, np.nan)
    yaw = np.zeros(n)
    foreign = np.zeros(n, bool)
    for i, b in enumerate(best):
        if b is None:
            continue
        dist[i], yaw[i] = b.distance, b.yaw
        if b.match_session == cfg.session_id and 0 <= b.match_index < n:
            match[i] = b.match_index
        else:  # a loaded session: no reference pose, so it counts as false
            foreign[i] = True
    return evaluate(reference[:, :3, 3], match, dist, yaw, acc, radius=radius,
                    rotations=reference[:, :3, :3], max_heading_deg=max_heading_deg,
                    stamps_ns=stamps, exclude_frames=cfg.exclude_recent_frames,
                    exclude_sec=cfg.exclude_recent_sec, foreign=foreign)


def _write_outputs(out: Path, r: ReplayResult, plots: bool) -> list[Path]:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise SolidError(f'cannot create output directory {out}: {err.strerror}') from err
    files = [out / 'candidates.csv', out / 'report.json']
    try:
        _write_csv(files[0], r)
        if plots and r.evaluation is not None and r.reference is not None:
            from solid_ros.tools.plots import write_plots

            loops = r.report['loops']
            files += write_plots(out, r.evaluation, r.reference[:, :3, 3], _match_rows(r),
                                 threshold=r.config.distance_threshold, records=r.records,
                                 max_error=(loops['max_error_m'], loops['max_error_deg']),
                                 min_overlap=r.config.verify_min_overlap if r.config.verify
                                 else None)
        r.report['files'] = [str(f) for f in files]
        write_json(files[1], r.report)
    except OSError as err:
        raise SolidError(f'cannot write to {out}: {err.strerror or err}') from err
    return files


def _match_rows(r: ReplayResult) -> npt.NDArray[np.intp]:
    out = np.full(len(r.best), -1, dtype=np.intp)
    for i, b in enumerate(r.best):
        if b is not None and b.match_session == r.config.session_id:
            out[i] = b.match_index
    return out


def _write_csv(path: Path, r: ReplayResult) -> None:
    """One row per candidate a keyframe looked at, plus its best descriptor match when that
    was not looked at (see the README for the columns)."""
    ev, ref = r.evaluation, r.reference
    published = {id(c) for c in r.candidates}
    scored = iter(r.records)
    with path.open('w', newline='', encoding='utf-8') as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for i, b in enumerate(r.best):
            tried = r.attempts[i] if i < len(r.attempts) else []
            rows: list[tuple[LoopCandidate, bool, LoopRecord | None]] = []
            for c in tried:
                rows.append((c, id(c) in published, next(scored) if r.records else None))
            if b is not None and not any((c.match_index, c.match_session)
                                         == (b.match_index, b.match_session) for c in tried):
                rows.insert(0, (b, False, None))
            for c, acc, rec in rows:
                is_best = b is not None and (c.match_index, c.match_session) == (
                    b.match_index, b.match_session)
                w.writerow(_csv_row(r, c, acc, is_best, rec, ev, ref))


def _csv_row(r: ReplayResult, c: LoopCandidate, acc: bool, is_best: bool,
             rec: LoopRecord | None, ev: Evaluation | None,
             ref: npt.NDArray[np.float64] | None) -> list[Any]:
    true, gtd, gty = '', '', ''
    if ev is not None and ref is not None and c.match_session == r.config.session_id \
            and 0 <= c.match_index < len(ref):
        q, m = ref[c.query_index], ref[c.match_index]
        d = float(np.linalg.norm(q[:3, 3] - m[:3, 3]))
        if math.isfinite(d):
            rel = m[:3, :3].T @ q[:3, :3]
            yaw_gt = math.atan2(rel[1, 0], rel[0, 0])
            ok = d <= ev.radius and (ev.max_heading_deg is None or abs(
                math.degrees(yaw_gt)) <= ev.max_heading_deg)
            true, gtd, gty = str(int(ok)), f'{d:.3f}', f'{yaw_gt:.6f}'
    te = re_ = correct = ''
    if rec is not None and math.isfinite(rec.trans_err_m):
        te, re_ = f'{rec.trans_err_m:.4f}', f'{rec.rot_err_deg:.4f}'
        correct = str(int(rec.trans_err_m < r.report['loops']['max_error_m']
                          and rec.rot_err_deg < r.report['loops']['max_error_deg']))

    def num(v: float) -> str:
        return f'{v:.6g}' if math.isfinite(v) else ('inf' if v > 0 else '')

    return [c.query_index, c.match_index, c.query_stamp_ns, c.match_stamp_ns, c.match_session,
            f'{c.distance:.6f}', f'{c.yaw:.6f}',
            f'{c.margin:.6f}' if math.isfinite(c.margin) else 'inf', int(acc), int(is_best),
            true, gtd, gty, int(c.verified), c.reason, *(f'{v:.6f}' for v in c.pose),
            num(c.fitness), num(c.rmse), num(c.overlap), num(c.conflict), num(c.constraint),
            num(c.spread), te, re_, correct,
            *(num(v) for v in c.covariance)]


# ------------------------------------------------------------------------------ command line


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # one line, no usage dump
        self.exit(2, f'{self.prog}: error: {message} (see --help)\n')


def _radius(text: str) -> float:
    value = float(text)
    if not 0.0 < value < math.inf:
        raise argparse.ArgumentTypeError(f'must be a positive number of metres, got {text!r}')
    return value


def _heading(text: str) -> float:
    value = float(text)
    if not 0.0 < value <= 180.0:
        raise argparse.ArgumentTypeError(f'must be in (0, 180] degrees, got {text!r}')
    return value


def _fraction(text: str) -> float:
    value = float(text)
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f'must be in (0, 1], got {text!r}')
    return value


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser (``solid_replay --help``)."""
    p = _Parser(
        prog=PROG,
        description='Replay a recorded bag through the same SOLiD loop detector the node runs '
                    '(same parameter file), print loop candidates and, given reference poses, '
                    'evaluate them: Recall@1, PR curve, F1max and its threshold, ROC AUC, yaw '
                    'error; write candidates.csv, report.json and plots with --out.',
        epilog='With several bags only --params, --node-name, --set, --topic, --odom-topic, '
               '--radius, --max-pose-error-m/-deg, --out, --progress and -q apply. '
               'Reference poses come from --poses (KITTI 3x4 rows, paired with scans by order '
               'or by --times stamps; or TUM "stamp tx ty tz qx qy qz qw") or else from the '
               "bag's Odometry topic. A query has a true loop when an earlier scan outside the "
               'exclusion window lies within --radius metres. Exit status: 0 ok, 1 bad input '
               '(bag, poses, parameters, database), 2 bad command line.')
    p.add_argument('bag', nargs='+', metavar='BAG',
                   help='ROS 2 bag directory (MCAP or sqlite3) or ROS 1 .bag file; several '
                        'bags = a fleet, one robot each (robot i = session_id i), which share '
                        'keyframes as nodes with peers: true do and are scored on '
                        'inter-robot loops (each needs an Odometry topic in one world frame)')
    p.add_argument('--params', metavar='FILE.yaml',
                   help='ROS 2 parameter file as given to the node (default: built-in '
                        "defaults = the SOLiD authors' parameters)")
    p.add_argument('--node-name', default='solid_node', metavar='NAME',
                   help='node block read from --params (default: %(default)s)')
    p.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='override one parameter after --params (repeatable), e.g. '
                        '--set distance_threshold=0.08')
    p.add_argument('--topic', help='PointCloud2 topic (default: the only one in the bag; '
                                   'the choices are listed when there are several)')
    p.add_argument('--odom-topic', metavar='T',
                   help="nav_msgs/Odometry topic: fed to the detector like the node's odom and "
                        'used as reference poses unless --poses is given (default: the only '
                        'one in the bag, if any)')
    p.add_argument('--no-odom', action='store_true',
                   help='do not feed odometry to the detector (like use_odom: false)')
    p.add_argument('--poses', metavar='FILE',
                   help='reference poses: KITTI 3x4 (one per scan, or per --times stamp) or TUM')
    p.add_argument('--times', metavar='FILE',
                   help='stamps in seconds, one per line, for a KITTI --poses file')
    p.add_argument('--radius', type=_radius, default=5.0, metavar='M',
                   help='true-loop distance in metres (default: %(default)s)')
    p.add_argument('--max-pose-error-m', type=_radius, default=1.0, metavar='M',
                   help='a published loop is correct when its relative pose is within this '
                        'translation of the reference one (default: %(default)s)')
    p.add_argument('--max-pose-error-deg', type=_heading, default=3.0, metavar='DEG',
                   help='... and within this rotation (default: %(default)s)')
    p.add_argument('--target-precision', type=_fraction, default=1.0, metavar='P',
                   help='the sweep recommends the setting that reaches this precision of '
                        'published loops (default: %(default)s = no false loop)')
    p.add_argument('--max-heading-deg', type=_heading, metavar='DEG',
                   help='also require a heading difference below this for a true loop')
    p.add_argument('--out', metavar='DIR',
                   help='write candidates.csv, report.json and PNG plots here')
    p.add_argument('--no-plots', action='store_true', help='skip the PNG plots')
    p.add_argument('--load-db', metavar='F', help='database file to search as well (saved '
                                                  'by the node or --save-db)')
    p.add_argument('--save-db', metavar='F', help='save the database after the run')
    p.add_argument('--progress', choices=('auto', 'bar', 'lines'), default='auto',
                   help='progress display: bar on a terminal, plain lines otherwise '
                        '(default: %(default)s)')
    p.add_argument('-q', '--quiet', action='store_true',
                   help='no progress and no summary; errors only')
    return p


def _overrides(items: list[str]) -> dict[str, Any]:
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition('=')
        if not sep or not key:
            raise ConfigError(f'--set expects KEY=VALUE, got {item!r}')
        try:
            out[key.strip()] = yaml.safe_load(text)
        except yaml.YAMLError as err:
            raise ConfigError(f'--set {key}: cannot parse {text!r}') from err
    return out


def _fmt(v: Any, spec: str = '.3f') -> str:
    if v is None:
        return 'n/a'
    if isinstance(v, float) and not math.isfinite(v):
        return 'inf'
    return format(v, spec)


def summary_lines(r: ReplayResult) -> list[str]:
    """The human summary printed at the end of a run."""
    rep = r.report
    t = rep['timings']
    cfg = r.config
    stages = '  '.join(f'{k} {_fmt(t[f"{k}_ms"]["p50"], ".2f")}'
                       for k in ('describe', 'search', 'verify'))
    clouds = rep['keyframe_clouds']
    lines = [
        f'{PROG} summary',
        f'  bag               {r.bag} ({rep["format"]}, {r.topic})',
        f'  integrity         {rep["integrity"]}',
        f'  scans             {r.messages} read, {r.skipped} skipped, {r.keyframes} keyframes',
        f'  loops published   {len(r.candidates)} ('
        + (f'verified by registration; {_reasons(rep["verification"]["reasons"])})'
           if cfg.verify else f'descriptor only, distance_threshold {cfg.distance_threshold})'),
        f'  throughput        {_fmt(t["scans_per_sec"], ".1f")} scans/s end to end '
        f'({t["wall_sec"]:.2f} s)',
        f'  stage ms p50      {stages}',
        f'  database          {rep["database"]["size"]} scans, '
        f'{rep["database"]["bytes"] / 1e6:.2f} MB ({rep["database"]["bytes_per_scan"]} bytes '
        f'per scan); keyframe clouds {clouds["kept"]}, {clouds["mb"]:.2f} MB, '
        f'{clouds["dropped"]} dropped',
    ]
    m = rep['metrics']
    if m is None:
        lines.append('  evaluation        none (no reference poses: give --poses or an '
                     'Odometry topic)')
        return lines
    loops = rep['loops']
    te, re_ = loops['trans_err_m'], loops['rot_err_deg']
    lines += [
        f'  reference         {rep["reference"]} (radius {m["radius_m"]} m; '
        f'{m["queries_with_true_loop"]} of {m["queries"]} queries have a true loop)',
        f'  published loops   {loops["correct"]} correct, {loops["false"]} false (pose within '
        f'{loops["max_error_m"]} m / {loops["max_error_deg"]} deg): precision '
        f'{_fmt(loops["precision"])}, recall {_fmt(loops["recall"])}',
        f'  pose error        median {_fmt(te["median"], ".3f")} m, {_fmt(re_["median"], ".2f")}'
        f' deg; p95 {_fmt(te["p95"], ".3f")} m, {_fmt(re_["p95"], ".2f")} deg '
        f'(n={te["count"]})',
        f'  descriptor        Recall@1 {_fmt(m["recall_at_1"])}, F1max {_fmt(m["f1_max"])}, '
        f'ROC AUC {_fmt(m["roc_auc"])}',
    ]
    if not cfg.verify:  # the pose is only a yaw: also score the places, as the back end will
        acc = m['accepted']
        lines.append(f'  by place          {acc["true"]} true, {acc["false"]} false best matches '
                     f'within {m["radius_m"]} m: precision {_fmt(acc["precision"])}, recall '
                     f'{_fmt(acc["recall"])} (descriptor only: the pose carries no translation)')
    sweep = rep['loop_sweep']
    if sweep is not None:
        rows = sweep.get('rows', [])
        if rows:
            lines.append(f'  {sweep["parameter"]} sweep   threshold  precision  recall  tp   fp')
            step = max(1, len(rows) // 10)
            for row in rows[::step]:
                lines.append(f'                    {row["threshold"]:<9}  '
                             f'{row["precision"]:.3f}      {row["recall"]:.3f}   '
                             f'{row["tp"]:<4} {row["fp"]}')
        target = sweep['target_precision']
        if sweep['recommended'] is not None:
            basis = ('of published loops by pose' if cfg.verify
                     else f'of best matches within {m["radius_m"]} m')
            lines.append('  paste into YAML:')
            lines.append(f'    {sweep["parameter"]}: {sweep["recommended"]}   # precision >= '
                         f'{target} {basis} on this data, recall {_fmt(sweep["recall"])}')
        else:
            lines.append(f'  no {sweep["parameter"]} reaches precision {target} on this data')
    if r.files:
        lines.append(f'  outputs           {", ".join(str(f) for f in r.files)}')
    return lines


def _reasons(counts: dict[str, int]) -> str:
    return ', '.join(f'{k} {v}' for k, v in sorted(counts.items(), key=lambda kv: -kv[1])) \
        or 'nothing tried'


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``solid_replay``; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.times and not args.poses:
        parser.error('--times needs --poses')
    if len(args.bag) > 1:
        single = [name for name, on in (
            ('--poses', args.poses), ('--times', args.times), ('--load-db', args.load_db),
            ('--save-db', args.save_db), ('--no-odom', args.no_odom),
            ('--max-heading-deg', args.max_heading_deg is not None),
            ('--no-plots', args.no_plots)) if on]
        if single:
            parser.error(f'{", ".join(single)} take one bag; {len(args.bag)} were given')
    progress = 'quiet' if args.quiet else args.progress
    tune_allocator()
    try:
        cfg, ncfg = load_config(args.params, args.node_name, _overrides(args.set))
        if len(args.bag) > 1:
            fleet = replay_fleet(args.bag, cfg, node_config=ncfg, topic=args.topic,
                                 odom_topic=args.odom_topic, radius=args.radius,
                                 max_pose_error_m=args.max_pose_error_m,
                                 max_pose_error_deg=args.max_pose_error_deg, progress=progress)
            files = write_fleet_outputs(args.out, fleet) if args.out else []
            if not args.quiet:
                print('\n'.join(fleet_summary_lines(fleet, PROG)))
                if files:
                    print(f'  outputs          {", ".join(str(f) for f in files)}')
            return 0
        result = replay(args.bag[0], cfg, node_config=ncfg, topic=args.topic,
                        odom_topic=args.odom_topic, use_odom=False if args.no_odom else None,
                        poses=args.poses, times=args.times, radius=args.radius,
                        max_heading_deg=args.max_heading_deg, out_dir=args.out,
                        load_db=args.load_db, save_db=args.save_db, progress=progress,
                        plots=not args.no_plots, params_file=args.params,
                        max_pose_error_m=args.max_pose_error_m,
                        max_pose_error_deg=args.max_pose_error_deg,
                        target_precision=args.target_precision)
    except SolidError as err:
        print(f'{PROG}: error: {" ".join(str(err).split())}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted', file=sys.stderr)
        return 130
    if not args.quiet:
        print('\n'.join(summary_lines(result)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
