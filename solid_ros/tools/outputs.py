"""What a replay writes into ``--out``: candidates.csv, report.json, the keyframe trajectory
(trajectory.tum, trajectory.kitti), map.pcd with ``--map``, and the plots.

The CSV columns are derived from :class:`~solid_ros.core.results.LoopCandidate`
(:func:`~solid_ros.formats.candidates.candidate_columns`): a layout names the fields in column
order with the tool's own columns between them, and :func:`candidate_cells` fills a row the
same way, so the fleet replay's CSV, the replay's and the node's message share one mapping.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import SolidError
from solid_ros.core.results import LoopCandidate
from solid_ros.formats.candidates import candidate_columns, candidate_values
from solid_ros.formats.pointfiles import write_pcd
from solid_ros.tools.loops import LoopRecord
from solid_ros.tools.reports import write_json
from solid_ros.tools.result import ReplayResult
from solid_ros.tools.trajectory import aligned_positions, write_trajectory

__all__ = ['CSV_COLUMNS', 'CSV_EXTRA', 'CSV_LAYOUT', 'candidate_cells', 'write_outputs']

# candidates.csv: every LoopCandidate field, with the replay's verdicts between them (the
# doc/replay.md lists the columns); a field added to LoopCandidate must be placed here.
CSV_EXTRA = ('accepted', 'best', 'true_match', 'gt_distance_m', 'yaw_gt', 'trans_err_m',
             'rot_err_deg', 'pose_correct')
# The evidence the judge read spans one column per field (rmse among them).
CSV_LAYOUT = ('query_index', 'match_index', 'query_stamp_ns', 'match_stamp_ns',
              'match_session', 'distance', 'yaw', 'margin', 'accepted', 'best', 'true_match',
              'gt_distance_m', 'yaw_gt', 'verified', 'reason', 'detail', 'pose', 'fitness',
              'evidence', 'trans_err_m', 'rot_err_deg', 'pose_correct', 'covariance', 'source')
CSV_COLUMNS = candidate_columns(CSV_LAYOUT, extra=CSV_EXTRA)

Format = Callable[[Any], Any]


def _fixed(v: float) -> str:
    return f'{v:.6f}'


def _num(v: float) -> str:
    """Six significant digits; 'inf', or empty for NaN (not measured)."""
    return f'{v:.6g}' if math.isfinite(v) else ('inf' if v > 0 else '')


def _margin(v: float) -> str:
    """'inf' when no other place was found, empty when not measured (a graph candidate)."""
    return f'{v:.6f}' if math.isfinite(v) else ('' if math.isnan(v) else 'inf')


_FORMATS: dict[str, Format] = {
    'distance': _fixed, 'yaw': _fixed, 'margin': _margin, 'verified': int, 'pose': _fixed,
    **dict.fromkeys(('fitness', 'rmse', 'evidence', 'covariance'), _num)}


def candidate_cells(c: LoopCandidate, layout: Sequence[str], formats: Mapping[str, Format],
                    extra: Mapping[str, Any]) -> list[Any]:
    """One CSV row in ``layout`` order (see :func:`candidate_columns`).

    Args:
        c: the candidate.
        layout: field names and names of ``extra``.
        formats: per field, how each of its values is written (as it is without one).
        extra: the cells that are not fields, by name.
    """
    row: list[Any] = []
    for name in layout:
        if name in extra:
            row.append(extra[name])
            continue
        fmt = formats.get(name)
        values = candidate_values(c, name)
        row.extend(values if fmt is None else (fmt(v) for v in values))
    return row


def write_outputs(out: Path, r: ReplayResult, plots: bool) -> list[Path]:
    """Write candidates.csv, the trajectory files (keyframes with a pose), map.pcd (when
    built), the plots (with reference poses) and report.json into ``out``.

    Raises:
        SolidError: the directory or a file cannot be written.
    """
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise SolidError(f'cannot create output directory {out}: {err.strerror}') from err
    files = [out / 'candidates.csv', out / 'report.json']
    try:
        _write_csv(files[0], r)
        if r.trajectory.posed.any():
            files += write_trajectory(out, r.trajectory)
        if r.map is not None:
            files.append(write_pcd(out / 'map.pcd', r.map.points))
        if plots and r.evaluation is not None and r.reference is not None:
            from solid_ros.tools.plots import write_plots

            loops = r.report['loops']
            files += write_plots(out, r.evaluation, r.reference[:, :3, 3], _match_rows(r),
                                 threshold=r.config.distance_threshold, records=r.records,
                                 max_error=(loops['max_error_m'], loops['max_error_deg']),
                                 min_overlap=r.config.verify_min_overlap if r.config.verify
                                 else None,
                                 estimates=aligned_positions(r.trajectory, r.reference))
        r.report['files'] = [str(f) for f in files]
        write_json(files[1], r.report)
    except OSError as err:
        raise SolidError(f'cannot write to {out}: {err.strerror or err}') from err
    return files


def _match_rows(r: ReplayResult) -> npt.NDArray[np.intp]:
    best = r.best
    out = np.full(len(best), -1, dtype=np.intp)
    for i, b in enumerate(best):
        if b is not None and b.match_session == r.config.session_id:
            out[i] = b.match_index
    return out


def _same_place(a: LoopCandidate, b: LoopCandidate | None) -> bool:
    return b is not None and (a.match_index, a.match_session) == (b.match_index, b.match_session)


def _rows(r: ReplayResult) -> Iterator[tuple[LoopCandidate, bool, bool, LoopRecord | None]]:
    """``(candidate, published, is_best, record)`` per row: every candidate a keyframe looked
    at, after its best descriptor match when that was not looked at."""
    published = {id(c) for c in r.candidates}
    scored = iter(r.records)
    for res in r.log.results:
        b = res.best
        if b is not None and not any(_same_place(c, b) for c in res.attempts):
            yield b, False, True, None
        for c in res.attempts:
            yield c, id(c) in published, _same_place(c, b), next(scored) if r.records else None


def _write_csv(path: Path, r: ReplayResult) -> None:
    """One row per candidate a keyframe looked at, plus its best descriptor match when that
    was not looked at (see doc/replay.md for the columns)."""
    loops = r.report['loops']
    limits = (loops['max_error_m'], loops['max_error_deg']) if loops is not None else None
    with path.open('w', newline='', encoding='utf-8') as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for c, accepted, is_best, rec in _rows(r):
            extra = {'accepted': int(accepted), 'best': int(is_best), **_truth(r, c),
                     'trans_err_m': '', 'rot_err_deg': '', 'pose_correct': ''}
            if rec is not None and limits is not None and math.isfinite(rec.trans_err_m):
                extra.update(trans_err_m=f'{rec.trans_err_m:.4f}',
                             rot_err_deg=f'{rec.rot_err_deg:.4f}',
                             pose_correct=str(int(rec.correct(*limits))))
            w.writerow(candidate_cells(c, CSV_LAYOUT, _FORMATS, extra))


def _truth(r: ReplayResult, c: LoopCandidate) -> dict[str, str]:
    """The reference's verdict on a candidate's place: true_match, gt_distance_m, yaw_gt."""
    ev, ref = r.evaluation, r.reference
    out = {'true_match': '', 'gt_distance_m': '', 'yaw_gt': ''}
    if ev is None or ref is None or c.match_session != r.config.session_id \
            or not 0 <= c.match_index < len(ref):
        return out
    q, m = ref[c.query_index], ref[c.match_index]
    d = float(np.linalg.norm(q[:3, 3] - m[:3, 3]))
    if math.isfinite(d):
        rel = m[:3, :3].T @ q[:3, :3]
        yaw_gt = math.atan2(rel[1, 0], rel[0, 0])
        ok = d <= ev.radius and (ev.max_heading_deg is None
                                 or abs(math.degrees(yaw_gt)) <= ev.max_heading_deg)
        out.update(true_match=str(int(ok)), gt_distance_m=f'{d:.3f}', yaw_gt=f'{yaw_gt:.6f}')
    return out
