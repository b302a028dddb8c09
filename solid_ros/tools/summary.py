"""The human summary printed at the end of a replay."""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

from solid_ros.tools.pipeline import STAGES
from solid_ros.tools.reports import PROG
from solid_ros.tools.result import ReplayResult

__all__ = ['summary_lines']


def _fmt(v: Any, spec: str = '.3f') -> str:
    if v is None:
        return 'n/a'
    if isinstance(v, float) and not math.isfinite(v):
        return 'inf'
    return format(v, spec)


def summary_lines(r: ReplayResult) -> list[str]:
    """The human summary printed at the end of a run."""
    lines = _run_lines(r) + _closure_lines(r.report)
    m = r.report['metrics']
    if m is None:
        lines.append('  evaluation        none (no reference poses: give --poses or an '
                     'Odometry topic)')
        if r.files:
            lines.append(f'  outputs           {", ".join(str(f) for f in r.files)}')
        return lines
    lines += _trajectory_lines(r.report['trajectory'])
    lines += _score_lines(r.report, r.config.verify)
    if r.report['loop_sweep'] is not None:
        lines += _sweep_lines(r.report['loop_sweep'], m['radius_m'], r.config.verify)
    if r.files:
        lines.append(f'  outputs           {", ".join(str(f) for f in r.files)}')
    return lines


def _run_lines(r: ReplayResult) -> list[str]:
    """What was read, published and how fast."""
    rep = r.report
    t = rep['timings']
    cfg = r.config
    stages = '  '.join(f'{k} {_fmt(t[f"{k}_ms"]["p50"], ".2f")}' for k in STAGES)
    clouds = rep['keyframe_clouds']
    lines = [
        f'{PROG} summary',
        f'  bag               {r.bag} ({rep["format"]}, {r.topic})',
        f'  integrity         {rep["integrity"]}',
        f'  scans             {r.messages} read, {r.skipped} skipped, {r.keyframes} keyframes',
        f'  loops published   {len(r.candidates)} ({_sources(r)}'
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
    sensor = rep.get('sensor') or {}
    if sensor.get('measured'):
        lines.append(f'  sensor            {sensor["measured"]}')
    if sensor.get('contradiction'):
        lines.append(f'  sensor check      {sensor["contradiction"]}')
    return lines


_SOURCES = {'bag': "the bag's Odometry topic", 'kiss-icp': 'KISS-ICP over the clouds',
            'none': 'none (no pose: keyframes by time only, no odometry check, no back end)'}


def _closure_lines(rep: dict[str, Any]) -> list[str]:
    """Which odometry fed the detector, and what the back end did with the loops."""
    odo = rep['odometry']
    src = _SOURCES.get(odo['source'], odo['source'])
    if odo['source'] == 'bag':
        src += f' {odo["topic"]}'
    if odo['source'] == 'kiss-icp':
        src += f', {odo["resets"]} resets'
    lines = [f'  odometry          {src}']
    be = rep['backend']
    if be is None:
        return [*lines, '  back end          off (backend: false)']
    loops = ', '.join(f'{k} {v}' for k, v in be['loops'].items()) or 'no loop'
    events = {k: v for k, v in rep['events']['counts'].items() if k != 'odometry_reset'}
    lines.append(f'  back end          {be["loops_in_graph"]} loops in the graph ({loops}); '
                 f'{be["segments"]} segment(s)'
                 + (f', {be["steps"]} registered steps' if be.get('steps') else '')
                 + (', anchored in the loaded map' if be['anchored'] else '')
                 + (f'; events {", ".join(f"{k} {v}" for k, v in events.items())}'
                    if events else ''))
    return lines


def _trajectory_lines(t: dict[str, Any] | None) -> list[str]:
    """ATE / RPE / drift of the odometry and of the corrected keyframes."""
    if t is None:
        return ['  trajectory        n/a (fewer than two keyframes with odometry and '
                'reference poses)']
    o, c = t['odometry'], t['corrected']
    return [
        f'  trajectory        ATE odometry {_fmt(o["ate_m"])} m -> corrected '
        f'{_fmt(c["ate_m"])} m ({_fmt(t["ate_ratio"], ".1f")}x lower; SE(3)-aligned, '
        f'{t["keyframes"]} keyframes, {t["path_m"]:.1f} m)',
        f'                    RPE per {t["rpe_delta_m"]:g} m odometry {_fmt(o["rpe_m"])} m '
        f'{_fmt(o["rpe_deg"], ".2f")} deg -> corrected {_fmt(c["rpe_m"])} m '
        f'{_fmt(c["rpe_deg"], ".2f")} deg; odometry drift {_fmt(o["drift_pct"], ".2f")} % '
        f'(end error {_fmt(o["end_error_m"])} m)',
    ]


def _score_lines(rep: dict[str, Any], verify: bool) -> list[str]:
    """The scores against the reference poses."""
    m = rep['metrics']
    loops = rep['loops']
    te, re_ = loops['trans_err_m'], loops['rot_err_deg']
    lines = [
        f'  reference         {rep["reference"]} (radius {m["radius_m"]} m; '
        f'{m["queries_with_true_loop"]} of {m["queries"]} queries have a true loop)',
        f'  published loops   {loops["correct"]} correct, {loops["false"]} false (pose within '
        f'{loops["max_error_m"]} m / {loops["max_error_deg"]} deg): precision '
        f'{_fmt(loops["precision"])}, recall {_fmt(loops["recall"])}',
        *_revisit_lines(loops),
        f'  pose error        median {_fmt(te["median"], ".3f")} m, {_fmt(re_["median"], ".2f")}'
        f' deg; p95 {_fmt(te["p95"], ".3f")} m, {_fmt(re_["p95"], ".2f")} deg '
        f'(n={te["count"]})',
        f'  descriptor        Recall@1 {_fmt(m["recall_at_1"])}, F1max {_fmt(m["f1_max"])}, '
        f'ROC AUC {_fmt(m["roc_auc"])}',
    ]
    if not verify:  # the pose is only a yaw: also score the places, as the back end will
        acc = m['accepted']
        lines.append(f'  by place          {acc["true"]} true, {acc["false"]} false best matches '
                     f'within {m["radius_m"]} m: precision {_fmt(acc["precision"])}, recall '
                     f'{_fmt(acc["recall"])} (descriptor only: the pose carries no translation)')
    return lines


def _revisit_lines(loops: dict[str, Any]) -> list[str]:
    """Revisit recall and the published loops by what proposed them."""
    rv = loops.get('revisits')
    lines = []
    if rv is not None:
        lines.append(f'  revisit recall    {_fmt(rv["recall"])} ({rv["found"]} of '
                     f'{rv["revisiting"]} keyframes with an earlier one within '
                     f'{rv["radius_m"]:g} m after >= {rv["min_path_m"]:g} m driven got a '
                     'correct loop)')
    src = loops.get('by_source') or {}
    if src:
        lines.append('  loops by source   ' + ', '.join(
            f'{k} {v["published"]} ({v["correct"]} correct)' for k, v in src.items()))
    return lines


def _sweep_lines(sweep: dict[str, Any], radius_m: float, verify: bool) -> list[str]:
    """The sweep for the target precision and the line to paste."""
    lines = []
    rows = sweep.get('rows', [])
    if rows:
        lines.append(f'  {sweep["parameter"]} sweep   threshold  precision  recall  tp   fp')
        step = max(1, len(rows) // 10)
        for row in rows[::step]:
            lines.append(f'                    {row["threshold"]:<9}  '
                         f'{row["precision"]:.3f}      {row["recall"]:.3f}   '
                         f'{row["tp"]:<4} {row["fp"]}')
    target = sweep['target_precision']
    if sweep['recommended'] is None:
        lines.append(f'  no {sweep["parameter"]} reaches precision {target} on this data')
        return lines
    basis = 'of published loops by pose' if verify else f'of best matches within {radius_m} m'
    lines.append('  paste into YAML:')
    lines.append(f'    {sweep["parameter"]}: {sweep["recommended"]}   # precision >= '
                 f'{target} {basis} on this data, recall {_fmt(sweep["recall"])}')
    return lines


def _sources(r: ReplayResult) -> str:
    """'graph N, descriptor M; ' when the pose graph proposed some of the loops."""
    counts = Counter(c.source for c in r.candidates)
    if not counts['graph']:
        return ''
    return f'descriptor {counts["descriptor"]}, graph {counts["graph"]}; '


def _reasons(counts: dict[str, int]) -> str:
    return ', '.join(f'{k} {v}' for k, v in sorted(counts.items(), key=lambda kv: -kv[1])) \
        or 'nothing tried'
