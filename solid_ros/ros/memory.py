"""Giving memory back after a huge message. No ROS import.

:func:`~solid_ros.runtime.tune_allocator` keeps freed buffers in the glibc heap (up to a 256 MB
trim threshold) because the node reuses them for every cloud. After a message far larger than
usual (an 80 MB cloud, a 100 MB message on a peer topic) that memory would stay resident for
the rest of the run; :class:`HeapTrim` notes such messages and asks glibc to return what is
free (``malloc_trim``) once a second for ``TRIM_FOR_SEC`` after the last one, so that the
message and the work on it (a describe stage running meanwhile) are given back too.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
import time
from collections.abc import Callable

__all__ = ['HeapTrim', 'LARGE_BYTES']

LARGE_BYTES = 16 * 1024 * 1024  # a message this large is trimmed after
TRIM_FOR_SEC = 5.0
_MIN_GAP_SEC = 1.0


def _malloc_trim() -> Callable[[], None] | None:
    name = ctypes.util.find_library('c')
    if name is None:
        return None
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None  # not glibc
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int

    def call() -> None:
        trim(0)
    return call


class HeapTrim:
    """Notes large messages; :meth:`maybe_trim` (from a timer) trims after them.

    Args:
        trim: the trim call (glibc's ``malloc_trim(0)`` by default; None: none available).
        clock: monotonic seconds.
    """

    def __init__(self, trim: Callable[[], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._trim = trim if trim is not None else _malloc_trim()
        self._clock = clock
        self._due_until = -float('inf')
        self._last = -float('inf')
        self._lock = threading.Lock()
        self.trims = 0

    def note(self, nbytes: int) -> None:
        """A message of ``nbytes`` arrived (large ones make a trim due)."""
        if nbytes >= LARGE_BYTES:
            with self._lock:
                self._due_until = self._clock() + TRIM_FOR_SEC

    def maybe_trim(self) -> bool:
        """Trim if a large message came in the last ``TRIM_FOR_SEC`` (at most once a second);
        return whether it did. Call it from a timer, not while a large message is held."""
        now = self._clock()
        with self._lock:
            if now > self._due_until or self._trim is None or now - self._last < _MIN_GAP_SEC:
                return False
            self._last = now
        self._trim()
        self.trims += 1
        return True
