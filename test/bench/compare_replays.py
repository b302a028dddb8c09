"""Compare the outputs of two solid_replay runs: did a change keep the behaviour?

Usage: ``python test/bench/compare_replays.py [--verdicts] BEFORE_DIR AFTER_DIR [...]``

Each pair is two ``--out`` directories of the same command. ``candidates.csv`` must be
byte-identical; ``report.json`` must be equal apart from what differs from run to run
(``timings``, ``versions``, the peak RSS) and the output directory in ``files`` (compared by
file name). Prints one line per pair and exits 1 when any pair differs.

``--verdicts`` compares what was decided instead, for a change of the output format: every
candidate (by query, match and session, in order) with the same verdict, pose, covariance and
acceptance, read by column name from both files; a reason may have been renamed where one
check was split into several (:data:`RENAMED`). With KISS-ICP's odometry two runs of the same
code already differ in the last digits of some poses (its threads), so judge those by their
verdicts.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path
from typing import Any

# Report entries that change from run to run (measured, or where the run wrote).
VOLATILE = ('timings', 'versions')


def _stable(report: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in report.items() if k not in VOLATILE}
    if isinstance(out.get('database'), dict):
        out['database'] = {k: v for k, v in out['database'].items() if k != 'peak_rss_mb'}
    if 'files' in out:
        out['files'] = [Path(f).name for f in out['files']]
    return out


def _diff(a: Any, b: Any, path: str = '') -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        found = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                found.append(f'{path}/{k}: only in {"after" if k in b else "before"}')
            else:
                found += _diff(a[k], b[k], f'{path}/{k}')
        return found
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _diff(x, y, f'{path}[{i}]')]
    return [] if a == b else [f'{path}: {a!r} != {b!r}']


def compare(before: Path, after: Path) -> tuple[bool, str]:
    """Whether two output directories agree, and a one-line account."""
    csv_a = (before / 'candidates.csv').read_bytes()
    csv_b = (after / 'candidates.csv').read_bytes()
    rows = csv_a.count(b'\n') - 1
    same_csv = csv_a == csv_b
    diffs = _diff(_stable(json.loads((before / 'report.json').read_text())),
                  _stable(json.loads((after / 'report.json').read_text())))
    files_a = sorted(p.name for p in before.iterdir())
    files_b = sorted(p.name for p in after.iterdir())
    ok = same_csv and not diffs and files_a == files_b
    text = (f'{before.name} vs {after.name}: candidates.csv {rows} rows '
            f'{"identical" if same_csv else "DIFFERENT"}; report.json '
            f'{"equal" if not diffs else f"{len(diffs)} differences: {diffs[:5]}"}'
            f' (timings, versions, peak RSS ignored); files '
            f'{"same" if files_a == files_b else f"{files_a} != {files_b}"}')
    return ok, text


# Reasons one check gave before the judge split it into rules of their own.
RENAMED = {'constraint': {'constraint', 'pinned', 'graph_constraint'},
           'odometry': {'odometry', 'graph_heading', 'graph_position'}}
_DECIDED = ('verified', 'accepted', 'tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw',
            *(f'cov_{i}' for i in range(36)))
_KEY = ('query_index', 'match_index', 'match_session')


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline='') as f:
        return list(csv.DictReader(f))


def compare_verdicts(before: Path, after: Path) -> tuple[bool, str]:
    """Whether two output directories decided alike (see the module docstring)."""
    a, b = _rows(before / 'candidates.csv'), _rows(after / 'candidates.csv')
    diffs = [] if len(a) == len(b) else [f'{len(a)} rows != {len(b)} rows']
    for i, (x, y) in enumerate(zip(a, b)):
        key = tuple(x[k] for k in _KEY)
        if key != tuple(y[k] for k in _KEY):
            diffs.append(f'row {i}: candidate {key} != {tuple(y[k] for k in _KEY)}')
            continue
        if y['reason'] not in RENAMED.get(x['reason'], {x['reason']}):
            diffs.append(f'row {i} {key}: reason {x["reason"]} -> {y["reason"]}')
        bad = [k for k in _DECIDED if k in x and k in y and x[k] != y[k]]
        if bad:
            diffs.append(f'row {i} {key}: {", ".join(bad[:4])} differ')
    renamed = sum(x['reason'] != y['reason'] for x, y in zip(a, b))
    text = (f'{before.name} vs {after.name}: {len(a)} candidates, '
            f'{"same verdicts" if not diffs else f"{len(diffs)} differences: {diffs[:5]}"}'
            f' ({renamed} reasons renamed)')
    return not diffs, text


def main(argv: list[str]) -> int:
    verdicts = '--verdicts' in argv
    argv = [a for a in argv if a != '--verdicts']
    if not argv or len(argv) % 2:
        print(__doc__.strip().splitlines()[2], file=sys.stderr)
        return 2
    ok = True
    for before, after in zip(argv[::2], argv[1::2]):
        same, text = (compare_verdicts if verdicts else compare)(Path(before), Path(after))
        ok &= same
        print(('OK   ' if same else 'FAIL ') + text)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
