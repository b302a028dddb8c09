"""Progress reporting for long runs: a one-line bar on a terminal, plain lines otherwise.

Modes: ``'bar'`` redraws one line (count, percent, scans/s, ETA) at most ``redraw_sec`` apart;
``'lines'`` prints a plain line every ``interval_sec`` seconds (for logs and CI);
``'quiet'`` prints nothing; ``'auto'`` picks bar when the stream is a terminal, else lines.
:meth:`Progress.note` prints a log line in the same stream without breaking the bar.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

__all__ = ['Progress', 'format_duration']


def format_duration(seconds: float) -> str:
    """``m:ss`` (or ``h:mm:ss``) for a duration; ``--:--`` when unknown."""
    if not seconds >= 0.0 or seconds == float('inf'):
        return '--:--'
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f'{h}:{m:02d}:{sec:02d}' if h else f'{m}:{sec:02d}'


class Progress:
    """Count processed items and report rate and ETA.

    Args:
        total: expected number of items (None when unknown: no percent or ETA).
        mode: 'auto', 'bar', 'lines' or 'quiet'.
        stream: where to write (default stderr).
        label: word for the items in messages.
        interval_sec: period of plain lines.
        redraw_sec: minimum period of bar redraws.
        clock: time source (tests inject one).
    """

    def __init__(self, total: int | None, mode: str = 'auto', stream: TextIO | None = None,
                 label: str = 'scans', interval_sec: float = 5.0, redraw_sec: float = 0.1,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if mode not in ('auto', 'bar', 'lines', 'quiet'):
            raise ValueError(f'unknown progress mode {mode!r}')
        self.stream = stream if stream is not None else sys.stderr
        if mode == 'auto':
            isatty = getattr(self.stream, 'isatty', None)
            mode = 'bar' if callable(isatty) and isatty() else 'lines'
        self.mode = mode
        self.total = total
        self.label = label
        self.interval = interval_sec
        self.redraw = redraw_sec
        self._clock = clock
        self.count = 0
        self.skipped = 0
        self._start = clock()
        self._last = self._start
        self._drawn = False

    @property
    def elapsed(self) -> float:
        """Seconds since start."""
        return self._clock() - self._start

    def rate(self) -> float:
        """Items per second so far (0 before the first)."""
        dt = self.elapsed
        return self.count / dt if dt > 0 else 0.0

    def update(self, n: int = 1, skipped: int = 0) -> None:
        """Record ``n`` more items (``skipped`` of them skipped) and report if due."""
        self.count += n
        self.skipped += skipped
        if self.mode == 'quiet':
            return
        now = self._clock()
        due = self.redraw if self.mode == 'bar' else self.interval
        if now - self._last >= due:
            self._last = now
            self._emit(final=False)

    def text(self) -> str:
        """The current status as one line."""
        rate = self.rate()
        parts = [f'{self.count}' + (f'/{self.total}' if self.total else '') + f' {self.label}']
        if self.total:
            parts.append(f'{100.0 * min(self.count / self.total, 1.0):3.0f}%')
        parts.append(f'{rate:.1f} {self.label}/s')
        if self.total and rate > 0:
            parts.append('ETA ' + format_duration(max(self.total - self.count, 0) / rate))
        parts.append('elapsed ' + format_duration(self.elapsed))
        if self.skipped:
            parts.append(f'{self.skipped} skipped')
        return '  '.join(parts)

    def _bar(self, width: int = 24) -> str:
        if not self.total:
            return ''
        filled = int(width * min(self.count / self.total, 1.0))
        return '[' + '#' * filled + '.' * (width - filled) + '] '

    def _emit(self, final: bool) -> None:
        if self.mode == 'bar':
            self.stream.write('\r\x1b[K' + self._bar() + self.text() + ('\n' if final else ''))
            self._drawn = not final
        else:
            self.stream.write(self.text() + '\n')
        self.stream.flush()

    def note(self, line: str) -> None:
        """Print a log line between progress reports (a bar is redrawn below it on the next
        update); nothing when quiet."""
        if self.mode == 'quiet':
            return
        self.clear()
        self.stream.write(line + '\n')
        self.stream.flush()

    def close(self) -> None:
        """Print the final status (bar: finish the line)."""
        if self.mode != 'quiet':
            self._emit(final=True)

    def clear(self) -> None:
        """Erase a partly drawn bar (before printing an error)."""
        if self.mode == 'bar' and self._drawn:
            self.stream.write('\r\x1b[K')
            self.stream.flush()
            self._drawn = False
