"""Giving memory back after a huge message. No ROS import.

:func:`~solid_ros.runtime.tune_allocator` keeps freed buffers in the glibc heap (up to a 256 MB
trim threshold) because the node reuses them for every cloud. After a message far larger than
usual (an 80 MB cloud, a 100 MB message on a peer topic) that memory would stay resident for
the rest of the run; :class:`HeapTrim` notes such messages and asks glibc to return what is
free (``malloc_trim``) once a second until ``TRIM_FOR_SEC`` after the last one, and for as
long as the node is still busy with the work that followed (``busy``), so that the message
and what describing and verifying it took are given back too.

The DDS reader keeps the largest payload it received for reuse (measured with a plain rclpy
subscriber: +58 MB after three 60 MB clouds, given back only when the subscription goes), so
a subscription that received a message beyond the node's limits (a cloud over
``max_points_per_cloud``, an oversized peer message) is re-created once it is idle, at most
every ``RENEW_GAP_SEC`` (:class:`Renewal`); a message in flight at that moment may be lost.
Only under a single-threaded executor (``rclpy.spin``, as ``solid_node`` runs): under a
multi-threaded one another thread may be adding the subscription's QoS event handler to its
wait set while it is destroyed, and rclpy's executor then dies with ``InvalidHandle`` (seen in
the tests), so there the reader keeps its buffer (``safe``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
import time
from collections.abc import Callable
from typing import Any

__all__ = ['HeapTrim', 'LARGE_BYTES', 'Renewal']

LARGE_BYTES = 16 * 1024 * 1024  # a message this large is trimmed after
TRIM_FOR_SEC = 5.0
_MIN_GAP_SEC = 1.0
RENEW_GAP_SEC = 10.0


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
        busy: whether work queued since may still hold what a large message brought.
    """

    def __init__(self, trim: Callable[[], None] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 busy: Callable[[], bool] = lambda: False) -> None:
        self._trim = trim if trim is not None else _malloc_trim()
        self._clock = clock
        self._busy = busy
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
            if now <= self._due_until and self._busy():
                self._due_until = now + 2.5 * _MIN_GAP_SEC  # on when the work is done
            if now > self._due_until or self._trim is None or now - self._last < _MIN_GAP_SEC:
                return False
            self._last = now
        self._trim()
        self.trims += 1
        return True


class Renewal:
    """A subscription that can be re-created to free what its DDS reader keeps.

    Args:
        create: makes the subscription (called now and at each renewal).
        destroy: destroys one.
        clock: monotonic seconds.
        safe: whether destroying a subscription is safe now (else a request is dropped).
    """

    def __init__(self, create: Callable[[], Any], destroy: Callable[[Any], object],
                 clock: Callable[[], float] = time.monotonic,
                 safe: Callable[[], bool] = lambda: True) -> None:
        self._create, self._destroy, self._clock, self._safe = create, destroy, clock, safe
        self.current = create()
        self._due = False
        self._last = -float('inf')
        self.renewals = 0

    def request(self) -> None:
        """A message beyond the limits came: renew when idle (see :meth:`maybe_renew`)."""
        self._due = True

    def maybe_renew(self, idle: bool = True) -> bool:
        """Re-create the subscription if asked, ``idle`` and ``RENEW_GAP_SEC`` passed since
        the last time; return whether it did. Call from a timer, never from the
        subscription's own callback."""
        now = self._clock()
        if not self._due or not idle or now - self._last < RENEW_GAP_SEC:
            return False
        if not self._safe():
            self._due = False
            return False
        self._due, self._last = False, now
        self._destroy(self.current)
        self.current = self._create()
        self.renewals += 1
        return True
