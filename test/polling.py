"""Waiting in the ROS tests: poll a condition until it holds or a time-out, one helper for all."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_until(pred: Callable[[], bool], what: str, timeout: float,
               step: Callable[[], object] = lambda: time.sleep(0.02),
               check: Callable[[], object] | None = None) -> None:
    """Call ``step`` (sleep, or spin an executor) until ``pred()`` holds.

    Args:
        pred: the condition.
        what: named in the time-out's message.
        timeout: seconds.
        step: what to do between two polls.
        check: called before each poll; raises when waiting is pointless (a process died).

    Raises:
        AssertionError: ``timeout`` passed first.
    """
    deadline = time.monotonic() + timeout
    while not pred():
        if check is not None:
            check()
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out waiting for {what}')
        step()
