"""Loop closure on the real recordings in ``../shared/data``: the bench every acceptance change
is judged on first.

Per recording (``hku1``: Livox Avia, a loop; ``quickshack``: Avia hand-held in a tight space,
no revisit; ``riv281``: Ouster OS1-64 on a car, 2.4 km, no revisit) it replays the bag with
the shipped preset nearest its sensor and drifting odometry (KISS-ICP over the clouds; the
bag's odometry is the reference trajectory itself, ``--odometry bag`` uses it anyway), scores
every candidate against the reference poses and prints:

- ``loops``: published loops, how many are false (pose beyond 1 m / 3 deg of the reference
  relative pose), and the precision;
- ``revisit``: revisiting keyframes (an earlier keyframe within 5 m after 30 m of path) with a
  right loop (:func:`solid_ros.tools.loops.revisits`);
- ``right refused``: candidates whose (rejected) pose lies within 1 m / 3 deg of the
  reference, by the reason that refused them, and how many right poses there were: a test
  that refuses many right poses is too strict for this sensor and scene; ``wrong stopped``:
  the other candidates, by the reason that refused them: what each test earns here (the
  first test that fails is named, so a later one is credited only with what passed the
  earlier ones). Only measured poses
  count (:attr:`~solid_ros.tools.loops.LoopRecord.measured`): a pair whose views share no
  structure (a narrow sensor standing in the same spot, looking 100-135 degrees away, on
  quickshack) keeps the graph's guess as its pose, which with the bag's odometry is the
  reference itself; those are printed apart as ``no common view``;
- ``ATE``: odometry and corrected keyframe ATE; ``verify``: median and p95 ms per keyframe;
  ``scans/s``: the whole replay, start-up included.

``--out DIR`` keeps each replay's output directory (``DIR/<recording>``: candidates.csv,
report.json), so ``compare_replays.py`` can tell whether a change kept the behaviour.
``--report FILE`` writes the figures with the date and commit: Markdown for ``doc/reports/``
(``.md``), else JSON.

Usage: ``python test/bench/bench_real.py [--sets hku1,quickshack,riv281] [--odometry
kiss-icp|bag] [--out DIR] [--report FILE] [--set KEY=VALUE ...] [--preset NAME=FILE ...]``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from solid_ros.tools.replay import _overrides, load_config, replay  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from report import bench_meta, write_report  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
# Recording -> the shipped preset nearest its sensor.
PRESETS = {'hku1': 'avia.yaml', 'quickshack': 'avia.yaml', 'riv281': 'ouster.yaml'}
MAX_M, MAX_DEG = 1.0, 3.0


def run(name: str, odometry: str, out: Path | None, sets: dict[str, Any],
        preset: str | None = None) -> dict[str, Any]:
    """Replay one recording with its preset (or ``preset``, a file in config/) and score it."""
    preset = preset or PRESETS[name]
    cfg, ncfg = load_config(ROOT / 'config' / preset, overrides=sets)
    rec = DATA / name
    t0 = time.perf_counter()
    r = replay(rec / 'bag', cfg, node_config=ncfg, odometry=odometry,
               poses=rec / 'optimized_poses.txt', times=rec / 'times.txt', progress='quiet',
               out_dir=None if out is None else out / name, plots=False)
    wall = time.perf_counter() - t0
    loops, traj = r.report['loops'], r.report['trajectory']
    right = [x for x in r.scores.records if x.correct(MAX_M, MAX_DEG) and x.measured]
    unseen = sum(1 for x in r.scores.records if not x.measured)
    refused = Counter(x.reason for x in right if not x.published)
    wrong = [x for x in r.scores.records if x.measured and not x.correct(MAX_M, MAX_DEG)]
    stopped = Counter(x.reason for x in wrong if not x.published)
    verify = np.array([res.times.verify for res in r.log.results if res.keyframe])
    verify = verify[np.isfinite(verify)]
    return {
        'preset': preset, 'odometry': odometry, 'clouds': r.inputs.count,
        'keyframes': sum(1 for res in r.log.results if res.keyframe),
        'published': loops['published'], 'false': loops['false'],
        'precision': loops.get('precision'), 'revisits': loops['revisits'],
        'right_poses': len(right), 'right_refused': dict(refused.most_common()),
        'no_common_view': unseen, 'wrong_poses': len(wrong),
        'wrong_stopped': dict(stopped.most_common()),
        'ate_odometry_m': traj['odometry']['ate_m'],
        'ate_corrected_m': traj['corrected']['ate_m'],
        'verify_p50_ms': float(np.median(verify)) if len(verify) else math.nan,
        'verify_p95_ms': float(np.percentile(verify, 95)) if len(verify) else math.nan,
        'scans_per_s': r.inputs.count / wall, 'wall_s': wall,
        'calibration': r.report['verification'].get('calibration', {}),
        'max_conflict': r.report['verification'].get('max_conflict'),
    }


def lines(name: str, s: dict[str, Any]) -> list[str]:
    """The figures of one recording as printed lines."""
    rv = s['revisits']
    recall = (f'{rv["found"]}/{rv["revisiting"]} = {rv["recall"]:.3f}' if rv['revisiting']
              else 'none (no revisit)')
    refused = _by_reason(s['right_refused'])
    prec = s['precision']
    return [
        f'{name} ({s["preset"]}, odometry {s["odometry"]}): {s["keyframes"]} keyframes of '
        f'{s["clouds"]} clouds',
        f'  loops          {s["published"]} published, {s["false"]} false, precision '
        f'{"-" if prec is None else f"{prec:.3f}"}',
        f'  revisit recall {recall}',
        f'  right refused  {sum(s["right_refused"].values())} of {s["right_poses"]} right '
        f'poses: {refused}; no common view {s.get("no_common_view", 0)}',
        f'  wrong stopped  {sum(s["wrong_stopped"].values())} of {s["wrong_poses"]} wrong '
        f'poses: {_by_reason(s["wrong_stopped"])}',
        f'  ATE            odometry {_m(s["ate_odometry_m"])}, corrected '
        f'{_m(s["ate_corrected_m"])}',
        f'  calibration    {_calibration(s)}',
        f'  cost           verify p50 {s["verify_p50_ms"]:.1f} ms, p95 '
        f'{s["verify_p95_ms"]:.1f} ms per keyframe; {s["scans_per_s"]:.1f} scans/s '
        f'({s["wall_s"]:.1f} s)',
    ]


def _by_reason(counts: dict[str, int]) -> str:
    return ', '.join(f'{k} {v}' for k, v in counts.items()) or 'none'


def _calibration(s: dict[str, Any]) -> str:
    c = s['calibration']
    if not c:
        return '-'
    agreed = f' ({c["agreed"]} where the odometry put them)' if 'agreed' in c else ''
    return (f'{c["right"]} right{agreed} of {c["tried"]} pairs, conflict q75 '
            f'{c["conflict_q75"]:.3f} '
            f'-> bar {s["max_conflict"]:.3f}; odometry drift {c["drift_per_m"]:.4f} per m '
            f'({c["drift_pairs"]} pairs)')


def _m(value: float | None) -> str:
    return '-' if value is None or not math.isfinite(value) else f'{value:.3f} m'


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--sets', default=','.join(PRESETS))
    p.add_argument('--odometry', choices=('kiss-icp', 'bag'), default='kiss-icp')
    p.add_argument('--out', type=Path, help='keep each replay output in OUT/<recording>')
    p.add_argument('--report', type=Path, help='write the figures as JSON here')
    p.add_argument('--set', nargs='+', action='extend', default=[], metavar='KEY=VALUE',
                   help='override preset parameters (all recordings)')
    p.add_argument('--preset', action='append', default=[], metavar='NAME=FILE',
                   help='replay recording NAME with config/FILE instead of its preset, e.g. '
                        'riv281=ouster.yaml')
    args = p.parse_args()
    chosen = dict(item.partition('=')[::2] for item in args.preset)
    if set(chosen) - set(PRESETS) or not all((ROOT / 'config' / f).is_file()
                                              for f in chosen.values() if f):
        p.error(f'--preset: NAME one of {", ".join(PRESETS)}, FILE in config/')
    if not DATA.is_dir():
        print(f'bench_real: {DATA} is missing: nothing to run')
        return 0
    sets = _overrides(args.set)
    figures = {}
    for name in args.sets.split(','):
        figures[name] = run(name, args.odometry, args.out, sets, chosen.get(name) or None)
        print('\n'.join(lines(name, figures[name])), flush=True)
    if args.report is not None:
        meta = bench_meta('bench_real', vars(args) | {'sets': args.sets.split(',')})
        write_report(args.report, meta, COLUMNS, [_row(k, v) for k, v in figures.items()],
                     {'recordings': figures}, NOTES)
    return 0


COLUMNS = ['recording', 'preset', 'odometry', 'keyframes', 'loops', 'false', 'precision',
           'revisit recall', 'right poses refused', 'refused by', 'wrong poses stopped',
           'stopped by', 'ATE odometry / corrected',
           'calibration', 'verify p50 / p95 ms', 'scans/s']
NOTES = ('Loops are false when their pose is beyond 1 m / 3 deg of the reference relative '
         'pose. A right pose refused is a candidate whose (rejected) pose lies within that of '
         'the reference; a wrong pose stopped is one beyond it that a test refused (named: '
         'the first that failed). Calibration: right alignments of the run / pairs tried, the '
         'conflict bar they set, the odometry drift measured per metre.')


def _row(name: str, s: dict[str, Any]) -> list[Any]:
    rv = s['revisits']
    refused = sum(s['right_refused'].values())
    c = s['calibration']
    return [name, s['preset'], s['odometry'], s['keyframes'], s['published'], s['false'],
            '-' if s['precision'] is None else f'{s["precision"]:.3f}',
            f'{rv["found"]}/{rv["revisiting"]}' if rv['revisiting'] else 'no revisit',
            f'{refused}/{s["right_poses"]}',
            _by_reason(s['right_refused']),
            f'{sum(s["wrong_stopped"].values())}/{s["wrong_poses"]}',
            _by_reason(s['wrong_stopped']),
            f'{_m(s["ate_odometry_m"])} / {_m(s["ate_corrected_m"])}',
            (f'{c["right"]}/{c["tried"]}, bar {s["max_conflict"]:.3f}, drift '
             f'{c["drift_per_m"]:.3f}/m') if c else '-',
            f'{s["verify_p50_ms"]:.1f} / {s["verify_p95_ms"]:.1f}', f'{s["scans_per_s"]:.1f}']


if __name__ == '__main__':
    sys.exit(main())
