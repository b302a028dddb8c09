"""What each refusing rule read on the right poses it refused and on the wrong poses it stopped:
could a bar derived from the data let the right ones through while the wrong ones still fail?

Reads the ``candidates.csv`` of replays scored against reference poses (``bench_real.py --out
DIR`` keeps ``DIR/<recording>/candidates.csv``). A pose is right within ``bench_real``'s 1 m /
3 deg of the reference and measured (its coarse overlap is not 0: a pair that shares no view
keeps its start, see :attr:`~solid_ros.tools.loops.LoopRecord.measured`); any other measured
pose is wrong. Per rule that refused (its reason), per field the rule reads
(:data:`~solid_ros.core.verification.judge.RULES`), it prints the right and the wrong poses'
readings (count, min, quartiles, max) and ``lets``: how many of the refused right poses a bar
on that field alone, set just short of the nearest wrong reading, would let through while
every wrong pose this rule stopped still fails (the wrong poses are only those it stopped: a
looser bar also hands wrong poses to the rules after it, so this is an upper bound). Verified
wrong poses (false loops) are listed with every reading the judge took.

Usage: ``python test/bench/refused_evidence.py DIR [DIR ...] [--rows N]`` (``DIR``: a
replay's output directory, or a ``bench_real.py --out`` directory of several; ``--rows``:
also print the N right poses of each rule nearest its bar).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from solid_ros.core.verification.judge import RULES  # noqa: E402

MAX_M, MAX_DEG = 1.0, 3.0  # bench_real's right pose
# Fields a rule passes below its bar (the others pass above it); 0/1 flags have no bar.
LOWER_PASSES = frozenset({'rmse', 'conflict', 'conflict_points', 'drift_m', 'drift_deg',
                          'pinned_m', 'pinned_deg', 'odom_error_m', 'graph_turn_deg',
                          'graph_stray_m'})
FLAGS = frozenset({'cloud', 'usable', 'converged', 'known_place', 'graph', 'step'})
# What the place allows or how far the restarts turned: the bar itself, not a reading.
ALLOWANCES = frozenset({'odom_allowed_m', 'graph_turn_tol_deg', 'graph_stray_allowed_m',
                        'drift_turn_deg'})

Row = dict[str, str]


def value(row: Row, name: str) -> float:
    """A numeric column (NaN: empty or missing)."""
    try:
        return float(row.get(name, ''))
    except ValueError:
        return math.nan


def right(row: Row) -> bool:
    """A measured pose within MAX_M / MAX_DEG of the reference."""
    return (value(row, 'trans_err_m') < MAX_M and value(row, 'rot_err_deg') < MAX_DEG
            and value(row, 'coarse_overlap') != 0.0)


def measured(row: Row) -> bool:
    """A pose the registration found (scored, with common structure)."""
    return math.isfinite(value(row, 'trans_err_m')) and value(row, 'coarse_overlap') != 0.0


def summary(values: list[float]) -> str:
    """Count, min, quartiles and max of the finite values."""
    v = np.array([x for x in values if math.isfinite(x)])
    if len(v) == 0:
        return f'{len(values):4d}  -'
    q = np.percentile(v, [0, 25, 50, 75, 100])
    return f'{len(values):4d}  ' + ' '.join(f'{x:8.4f}' for x in q)


def lets_through(name: str, right_values: list[float], wrong_values: list[float]) -> int:
    """How many right readings pass a bar on ``name`` set just short of the nearest wrong
    reading (every wrong reading still fails); all of them when no wrong pose was stopped."""
    r = [x for x in right_values if math.isfinite(x)]
    w = [x for x in wrong_values if math.isfinite(x)]
    if not w:
        return len(r)
    if name in LOWER_PASSES:
        return sum(x < min(w) for x in r)
    return sum(x > max(w) for x in r)


def by_rule(rows: list[Row], rows_shown: int) -> list[str]:
    """Per refusing rule, the readings of its fields on right and on wrong poses."""
    out = []
    for rule in RULES:
        hit = [r for r in rows if r['reason'] == rule.reason and measured(r)]
        good = [r for r in hit if right(r)]
        bad = [r for r in hit if not right(r)]
        if not good:
            continue
        out.append(f'{rule.reason}: refused {len(good)} right, {len(bad)} wrong poses'
                   f'  ({rule.doc})')
        out.append(f'    {"field":16s} {"":5s}    n       min       q25       q50       q75'
                   f'       max')
        for name in rule.reads:
            if name in FLAGS:
                share = [sum(value(r, name) == 1.0 for r in g) for g in (good, bad)]
                out.append(f'    {name:16s} flag set on {share[0]} right, {share[1]} wrong')
                continue
            rv = [value(r, name) for r in good]
            wv = [value(r, name) for r in bad]
            lets = ('' if name in ALLOWANCES
                    else f'   lets {lets_through(name, rv, wv)} of {len(good)}')
            out.append(f'    {name:16s} right {summary(rv)}')
            out.append(f'    {"":16s} wrong {summary(wv)}{lets}')
        for r in good[:rows_shown]:
            out.append(f'      q{r["query_index"]} m{r["match_index"]}: {r["detail"]}')
    return out


def false_loops(rows: list[Row]) -> list[str]:
    """The verified wrong poses with every reading the judge took."""
    out = []
    names = [n for rule in RULES for n in rule.reads]
    for r in rows:
        if r['reason'] == 'verified' and measured(r) and not right(r):
            read = ', '.join(f'{n} {value(r, n):.4g}' for n in dict.fromkeys(names)
                             if math.isfinite(value(r, n)))
            out.append(f'FALSE q{r["query_index"]} m{r["match_index"]} '
                       f'{value(r, "trans_err_m"):.2f} m / {value(r, "rot_err_deg"):.1f} deg: '
                       f'{read}')
    return out


def report(csv_path: Path, rows_shown: int = 0) -> list[str]:
    """The printed lines of one replay's candidates."""
    with csv_path.open(newline='') as f:
        rows = list(csv.DictReader(f))
    head = f'== {csv_path.parent.name} ({csv_path}): {len(rows)} candidates'
    return [head, *false_loops(rows), *by_rule(rows, rows_shown)]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('dirs', nargs='+', type=Path, help='replay output directories')
    p.add_argument('--rows', type=int, default=0, help='right poses listed per rule')
    args = p.parse_args()
    found = [c for d in args.dirs
             for c in ([d / 'candidates.csv'] if (d / 'candidates.csv').is_file()
                       else sorted(d.glob('*/candidates.csv')))]
    if not found:
        p.error('no candidates.csv in ' + ', '.join(map(str, args.dirs)))
    for path in found:
        print('\n'.join(report(path, args.rows)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
