"""Tests of solid_ros.tools.progress: bar, plain lines, quiet, rate and ETA."""

from __future__ import annotations

import io

import pytest

from solid_ros.tools.progress import Progress, format_duration


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_format_duration() -> None:
    assert format_duration(0) == '0:00'
    assert format_duration(75.4) == '1:15'
    assert format_duration(3725) == '1:02:05'
    assert format_duration(float('inf')) == '--:--'
    assert format_duration(float('nan')) == '--:--'


def test_lines_every_interval_with_rate_and_eta() -> None:
    clock, out = _Clock(), io.StringIO()
    p = Progress(100, 'auto', out, interval_sec=5.0, clock=clock)
    assert p.mode == 'lines'  # StringIO is not a terminal
    for _ in range(39):
        clock.t += 0.125
        p.update()
    assert out.getvalue() == ''  # 4.875 s passed: not yet due
    clock.t += 0.125
    p.update()
    lines = out.getvalue().splitlines()
    assert lines == ['40/100 scans   40%  8.0 scans/s  ETA 0:08  elapsed 0:05']
    p.update(skipped=1)
    p.close()
    last = out.getvalue().splitlines()[-1]
    assert '41/100' in last and '1 skipped' in last


def test_bar_redraws_one_line() -> None:
    clock, out = _Clock(), _Tty()
    p = Progress(10, 'auto', out, clock=clock)
    assert p.mode == 'bar'
    for _ in range(10):
        clock.t += 0.5
        p.update()
    p.close()
    text = out.getvalue()
    assert text.count('\n') == 1 and text.endswith('\n')
    assert text.count('\r') >= 10
    assert '[########################] 10/10 scans  100%' in text


def test_quiet_and_unknown_total() -> None:
    out = io.StringIO()
    p = Progress(5, 'quiet', out)
    p.update(5)
    p.close()
    assert out.getvalue() == ''
    clock = _Clock()
    q = Progress(None, 'lines', out, clock=clock)
    clock.t += 2.0
    q.update(4)
    q.close()
    line = out.getvalue().strip()
    assert line.startswith('4 scans  2.0 scans/s') and 'ETA' not in line
    with pytest.raises(ValueError):
        Progress(1, 'loud')


def test_notes_are_lines_between_bar_redraws() -> None:
    clock, out = _Clock(), _Tty()
    p = Progress(4, 'bar', out, clock=clock)
    clock.t += 0.5
    p.update()
    p.note('back end tie: segment 1 placed')
    clock.t += 0.5
    p.update()
    p.close()
    text = out.getvalue()
    # The bar is erased before the line, and drawn again after it.
    assert '\r\x1b[Kback end tie: segment 1 placed\n\r\x1b[K[' in text
    quiet = io.StringIO()
    Progress(4, 'quiet', quiet).note('x')
    assert quiet.getvalue() == ''
    lines = io.StringIO()
    Progress(4, 'lines', lines).note('odometry reset')
    assert lines.getvalue() == 'odometry reset\n'
