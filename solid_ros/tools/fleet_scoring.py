"""Scoring, report, CSV and summary of a fleet replay (:mod:`solid_ros.tools.fleet`).

A published loop of robot ``i`` against robot ``j`` is correct when its pose is within the
limits of ``inv(ref_j[m]) @ ref_i[q]``. A query has a true inter-robot loop when a keyframe
another robot stored before it lies within the radius (and, with ``max_heading_deg``, its
heading within that many degrees); inter-robot recall is the fraction of
those queries with at least one correct inter-robot loop. Loops within one robot are scored
the same way and reported beside them.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import SolidError
from solid_ros.core.results import LoopCandidate
from solid_ros.formats.candidates import candidate_columns
from solid_ros.formats.poses import write_tum_poses
from solid_ros.tools.fleet_map import FleetTrajectory
from solid_ros.tools.loops import pose_error
from solid_ros.tools.options import ReplayOptions
from solid_ros.tools.outputs import candidate_cells
from solid_ros.tools.reports import write_json

__all__ = ['FLEET_CSV_COLUMNS', 'FleetResult', 'RobotRun', 'fleet_report',
           'fleet_summary_lines', 'loop_error', 'write_fleet_outputs']

# candidates.csv of a fleet: LoopCandidate fields (see solid_ros.tools.outputs) and the fleet's
# own columns, one row per published loop.
_CSV_EXTRA = ('robot', 'inter_robot', 'trans_err_m', 'rot_err_deg', 'pose_correct')
_CSV_LAYOUT = ('robot', 'query_index', 'query_stamp_ns', 'match_session', 'match_index',
               'match_stamp_ns', 'distance', 'yaw', 'pose', 'fitness', 'rmse', 'overlap',
               'inter_robot', 'trans_err_m', 'rot_err_deg', 'pose_correct')
FLEET_CSV_COLUMNS = candidate_columns(_CSV_LAYOUT, extra=_CSV_EXTRA)


def _g6(v: float) -> str:
    return f'{v:.6g}'


def _g9(v: float) -> str:
    return f'{v:.9g}'


_CSV_FORMATS = {'distance': _g6, 'yaw': _g6, 'pose': _g9, 'fitness': _g6, 'rmse': _g6,
                'overlap': _g6}


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
        trajectories: with the back end, every robot's keyframes in the fleet frame (robot
            0's map; :mod:`solid_ros.tools.fleet_map`); empty without.
        alignment_events: with the back end, ``(robot, stamp_ns, line)`` of each alignment
            event (a peer aligned, an alignment that jumped).
    """

    bags: list[Path]
    stamps: list[list[int]] = field(default_factory=list)
    reference: list[npt.NDArray[np.float64]] = field(default_factory=list)
    published: list[list[LoopCandidate]] = field(default_factory=list)
    errors: list[list[tuple[float, float]]] = field(default_factory=list)
    report: dict[str, Any] = field(default_factory=dict)
    trajectories: list[FleetTrajectory] = field(default_factory=list)
    alignment_events: list[tuple[int, int, str]] = field(default_factory=list)


@dataclass(frozen=True)
class RobotRun:
    """What one robot's run gave besides its keyframes and loops.

    Attributes:
        integrity: what the CRC check of its bag found.
        skipped: clouds skipped (undecodable or refused by the detector).
        reasons: its detector's verification outcomes.
    """

    integrity: str
    skipped: int
    reasons: Mapping[str, int]


def loop_error(r: FleetResult, robot: int, c: LoopCandidate) -> tuple[float, float]:
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


def _headings(poses: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    out: npt.NDArray[np.float64] = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    return out


def _positives(r: FleetResult, robot: int, radius: float, inter: bool, exclude: int,
               max_heading_deg: float | None = None) -> set[int]:
    """Queries of ``robot`` with a keyframe stored before them within ``radius`` (and
    ``max_heading_deg`` of heading, when given): of another robot (``inter``), or its own
    outside the newest ``exclude`` keyframes."""
    own = r.reference[robot][:, :3, 3]
    own_heads = _headings(r.reference[robot])
    out: set[int] = set()
    for j, other in enumerate(r.reference):
        if (j == robot) == inter or not len(other):
            continue
        stamps = np.asarray(r.stamps[j], dtype=np.int64)
        pos, heads = other[:, :3, 3], _headings(other)
        for q, (p, stamp) in enumerate(zip(own, r.stamps[robot])):
            if not np.all(np.isfinite(p)):
                continue
            mask = stamps < stamp
            if not inter:
                mask[max(q - exclude, 0):] = False
            with np.errstate(invalid='ignore'):  # NaN poses are never near
                near = np.linalg.norm(pos[mask] - p, axis=1) <= radius
                if max_heading_deg is not None:
                    turn = (heads[mask] - own_heads[q] + math.pi) % (2 * math.pi) - math.pi
                    near &= np.abs(turn) <= math.radians(max_heading_deg)
            if near.any():
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


def fleet_report(r: FleetResult, runs: Sequence[RobotRun], cfg: SolidConfig,
                 opts: ReplayOptions) -> dict[str, Any]:
    """The fleet's ``report.json``: per robot and in total, inter-robot and own loops."""
    radius, max_m, max_deg = opts.radius, opts.max_pose_error_m, opts.max_pose_error_deg
    heading = opts.max_heading_deg
    per_robot: list[dict[str, Any]] = []
    for i, run in enumerate(runs):
        inter = _score(r, i, True, max_m, max_deg, _positives(r, i, radius, True, 0, heading))
        own = _score(r, i, False, max_m, max_deg,
                     _positives(r, i, radius, False, cfg.exclude_recent_frames, heading))
        per_robot.append({'robot': i, 'bag': str(r.bags[i]), 'integrity': run.integrity,
                          'keyframes': len(r.stamps[i]), 'skipped_clouds': run.skipped,
                          'published': len(r.published[i]), 'inter_robot': inter,
                          'own': own, 'reasons': dict(sorted(run.reasons.items()))})
    totals: dict[str, Any] = {}
    for key in ('inter_robot', 'own'):
        s: dict[str, Any] = {k: sum(rb[key][k] for rb in per_robot)
                             for k in ('published', 'correct', 'false',
                                       'queries_with_true_loop', 'queries_found')}
        s['precision'] = s['correct'] / s['published'] if s['published'] else None
        s['recall'] = (s['queries_found'] / s['queries_with_true_loop']
                       if s['queries_with_true_loop'] else None)
        totals[key] = s
    return {'tool': 'solid_replay (fleet)', 'robots': per_robot, 'radius_m': radius,
            'max_heading_deg': heading, 'max_pose_error_m': max_m, 'max_pose_error_deg': max_deg,
            'odometry_fed': opts.odometry_mode if opts.feed_odom else 'none',
            'config': cfg.to_dict(), 'config_fingerprint': cfg.fingerprint(), **totals}


def write_fleet_outputs(out: str | Path, result: FleetResult, plots: bool = True) -> list[Path]:
    """Write ``report.json`` and ``candidates.csv`` (every published loop, one row each); with
    the back end also ``trajectory_robot<i>.tum`` for every robot placed in the fleet frame
    (robot 0's map) and, with ``plots``, the plot of their paths and inter-robot loops.

    Raises:
        SolidError: the directory or files cannot be written.
    """
    out = Path(out)
    files = _write_tables(out, result)
    for t in result.trajectories:
        if t.placed and len(t.poses):
            files.append(write_tum_poses(out / f'trajectory_robot{t.robot}.tum', t.stamps_ns,
                                         t.poses))
    if plots and result.trajectories:
        from solid_ros.tools.fleet_plot import FLEET_PLOT, write_fleet_plot

        rep = result.report
        files.append(write_fleet_plot(out / FLEET_PLOT, result.trajectories, result.published,
                                      result.errors, (rep['max_pose_error_m'],
                                                      rep['max_pose_error_deg'])))
    return files


def _write_tables(out: Path, result: FleetResult) -> list[Path]:
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
                    extra = {'robot': robot, 'inter_robot': int(c.match_session != robot),
                             'trans_err_m': f'{te:.6g}', 'rot_err_deg': f'{re_:.6g}',
                             'pose_correct': int(te < lim_m and re_ < lim_deg)}
                    w.writerow(candidate_cells(c, _CSV_LAYOUT, _CSV_FORMATS, extra))
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
                     f'true loop within {rep["radius_m"]} m{_heading_text(rep)})')
    lines.append(f'  correct          pose within {rep["max_pose_error_m"]} m and '
                 f'{rep["max_pose_error_deg"]} deg of the reference relative pose')
    lines.append(f'  odometry fed     {rep["odometry_fed"]} (the reference: each bag\'s '
                 'Odometry topic)')
    return lines + _fleet_map_lines(result)


def _fleet_map_lines(result: FleetResult) -> list[str]:
    """The alignment events and the fleet map's errors (back end on)."""
    fm = result.report.get('fleet_map')
    if fm is None:
        return []
    lines = [f'  robot {robot}          {line}' for robot, _, line in result.alignment_events]
    for al in fm.get('alignments', []):
        lines.append(f'  alignment        robot {al["robot"]} of robot {al["peer"]}: '
                     + (f'aligned by {al["inliers"]} of {al["loops"]} loops' if al['aligned']
                        else f'unaligned ({al["loops"]} loops)')
                     + f', rival {al["rival"]}, jumps {al["jumps"]}')
    for rb in fm['robots']:
        where = ("in robot 0's map" if rb['placed'] else 'not placed (no consistent set of '
                 'inter-robot loops joins it to robot 0)')
        lines.append(f'  fleet map        robot {rb["robot"]}: {rb["keyframes"]} keyframes '
                     f'{where}, ATE {_fmt(rb["ate_m"])} m, odometry '
                     f'{_fmt(rb["odometry_ate_m"])} m (each its own SE(3) alignment)')
    lines.append(f'  fleet map        joint ATE {_fmt(fm["joint_ate_m"])} m (every placed '
                 'robot under one SE(3) alignment to the reference)')
    return lines


def _heading_text(rep: Mapping[str, Any]) -> str:
    heading = rep.get('max_heading_deg')
    return '' if heading is None else f' and {heading} deg of heading'
