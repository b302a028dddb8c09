"""Compare the outputs of two solid_replay runs: did a change keep the behaviour?

Usage: ``python test/bench/compare_replays.py BEFORE_DIR AFTER_DIR [BEFORE_DIR AFTER_DIR ...]``

Each pair is two ``--out`` directories of the same command. ``candidates.csv`` must be
byte-identical; ``report.json`` must be equal apart from what differs from run to run
(``timings``, ``versions``, the peak RSS) and the output directory in ``files`` (compared by
file name). Prints one line per pair and exits 1 when any pair differs.
"""

from __future__ import annotations

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


def main(argv: list[str]) -> int:
    if not argv or len(argv) % 2:
        print(__doc__.strip().splitlines()[2], file=sys.stderr)
        return 2
    ok = True
    for before, after in zip(argv[::2], argv[1::2]):
        same, text = compare(Path(before), Path(after))
        ok &= same
        print(('OK   ' if same else 'FAIL ') + text)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
