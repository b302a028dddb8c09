"""HeapTrim: a huge message makes trims due for a few seconds, at most one a second."""

from __future__ import annotations

from solid_ros.ros.memory import LARGE_BYTES, TRIM_FOR_SEC, HeapTrim


def test_trims_follow_large_messages_only() -> None:
    now = [0.0]
    calls: list[float] = []
    trim = HeapTrim(lambda: calls.append(now[0]), clock=lambda: now[0])
    trim.note(LARGE_BYTES - 1)
    assert not trim.maybe_trim()
    trim.note(LARGE_BYTES)
    assert trim.maybe_trim() and not trim.maybe_trim()  # once a second
    for _ in range(int(TRIM_FOR_SEC) + 3):
        now[0] += 1.0
        trim.maybe_trim()
    assert calls == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert HeapTrim().maybe_trim() is False  # glibc's own, nothing due
