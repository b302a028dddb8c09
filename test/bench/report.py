"""What every bench report carries besides its figures: when, on which commit, on what machine.

``doc/`` quotes figures only from reports the bench scripts write, so each says where it came
from: the date, the commit (and whether the tree had uncommitted changes), the command and the
load of this shared machine while it ran.
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]


def _git(*args: str) -> str:
    try:
        out = subprocess.run(['git', *args], cwd=ROOT, capture_output=True, text=True,
                             check=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return ''
    return out.stdout.strip()


def bench_meta(bench: str, options: dict[str, Any]) -> dict[str, Any]:
    """The header of a bench report: bench name, date, commit, command, machine."""
    return {
        'bench': bench,
        'date': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
        'commit': _git('rev-parse', '--short', 'HEAD'),
        'dirty': bool(_git('status', '--porcelain', '--untracked-files=no')),
        'command': ' '.join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        'options': {k: str(v) if isinstance(v, Path) else v for k, v in options.items()},
        'machine': f'{platform.machine()}, {os.cpu_count()} cores, load '
                   f'{os.getloadavg()[0]:.1f}',
    }


def write_report(path: Path, meta: dict[str, Any], columns: list[str],
                 rows: list[list[Any]], data: dict[str, Any], notes: str = '') -> None:
    """Write a bench report: Markdown (``.md``: the header, then one table) for ``doc/``, or
    JSON (any other suffix: the header and ``data``)."""
    import json

    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix != '.md':
        path.write_text(json.dumps(meta | data, indent=1, default=str) + '\n')
        return
    lines = [f'# {meta["bench"]} report', '',
             f'Written by `test/bench/{meta["bench"]}.py` on {meta["date"]}, commit '
             f'`{meta["commit"]}`{" (with uncommitted changes)" if meta["dirty"] else ""}, '
             f'{meta["machine"]}. Command: `{meta["command"]}`. Regenerated, never edited by '
             'hand.', '']
    if notes:
        lines += [notes, '']
    lines += ['| ' + ' | '.join(columns) + ' |', '|' + ' --- |' * len(columns)]
    lines += ['| ' + ' | '.join(str(c) for c in row) + ' |' for row in rows]
    path.write_text('\n'.join(lines) + '\n')


class PrintedReport:
    """A report of what a script prints: its stdout, as printed, under the header.

    For the scripts whose figures are a printed table rather than rows: ``with
    PrintedReport(path, meta):`` around the run tees stdout and, when ``path`` is given,
    writes the header and the printed text (Markdown: a fenced block; else JSON).
    """

    def __init__(self, path: Path | None, meta: dict[str, Any]) -> None:
        self.path, self.meta = path, meta
        self._parts: list[str] = []
        self._stdout: Any = None

    def write(self, text: str) -> int:
        self._parts.append(text)
        return int(self._stdout.write(text))

    def flush(self) -> None:
        self._stdout.flush()

    def __enter__(self) -> PrintedReport:
        self._stdout, sys.stdout = sys.stdout, self  # type: ignore[assignment]
        return self

    def __exit__(self, kind: Any, *_: Any) -> None:
        sys.stdout = self._stdout
        if self.path is None or kind is not None:
            return
        import json

        text = ''.join(self._parts)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.suffix != '.md':
            self.path.write_text(json.dumps(self.meta | {'printed': text}, indent=1) + '\n')
            return
        m = self.meta
        self.path.write_text(
            f'# {m["bench"]} report\n\nWritten by `test/bench/{m["bench"]}.py` on {m["date"]}, '
            f'commit `{m["commit"]}`{" (with uncommitted changes)" if m["dirty"] else ""}, '
            f'{m["machine"]}. Command: `{m["command"]}`. Regenerated, never edited by hand. '
            'What the script printed:\n\n```text\n' + text.rstrip('\n') + '\n```\n')
