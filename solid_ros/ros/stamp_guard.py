"""Cloud stamps that cannot be trusted: zero, repeated or going back. No ROS import.

The detector gates keyframes and excludes recent scans by stamp, so a driver that stamps
every cloud 0 left one keyframe, and a clock that jumped back made the exclusion window hide
every older scan. :class:`StampGuard` sees each cloud's header stamp in arrival order (the
subscription callback) and gives the detector a stamp that always increases:

- A stamp greater than the previous cloud's is trusted: the detector gets it plus the current
  offset (0 until the first anomaly, so a sane stream is passed through unchanged).
- A stamp that is 0, equal to the previous one (repeated) or smaller (backward) is not: the
  detector gets the previous detector stamp plus the time between the two arrivals (at least
  1 ns), i.e. arrival order on the monotonic clock, and the offset becomes that stamp minus
  the header's, so the clouds after a jump keep their spacing and stay after the ones before.

An untrusted cloud is paired with the odometry that was newest when it arrived (``hint`` of
:meth:`StampGuard.take`), instead of the odometry of its stamp.
Published loops carry the header stamps again (:meth:`StampGuard.restore`), so a back end
finds its keyframes, and so do the corrected path and trajectory (:meth:`StampGuard.headers`);
a saved database and the node's own pose graph keep the detector's stamps. Each switch of the
offset is remembered (the newest ``MAX_SEGMENTS``) to translate back.
"""

from __future__ import annotations

import bisect
import dataclasses
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.results import LoopCandidate, ScanResult
from solid_ros.core.stamps import NS_PER_SEC

__all__ = ['StampGuard']

MAX_SEGMENTS = 100_000
MAX_HINTS = 4096  # untrusted clouds waiting for the describe stage


class StampGuard:
    """Detector stamps from header stamps (see the module docstring).

    Args:
        clock: monotonic nanoseconds (injectable for tests).
    """

    def __init__(self, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._last_in: int | None = None
        self._last_out: int | None = None
        self._last_arrival = 0
        self._offset = 0
        # Detector stamps where the offset changed, the offsets, and which starts were
        # untrusted clouds (sorted: detector stamps only increase).
        self._starts: list[int] = []
        self._offsets: list[int] = []
        self._untrusted: list[bool] = []
        self._hints: OrderedDict[int, Any] = OrderedDict()

    def take(self, header_ns: int, hint: Callable[[], Any] | None = None,
             ) -> tuple[int, str | None]:
        """The detector stamp of a cloud that arrived now, and why its header stamp is not
        trusted: None, ``'zero'``, ``'repeated'`` or ``'backward by N s'``. For an untrusted
        one ``hint()`` is called now and kept for :meth:`hint` (the newest odometry)."""
        now = self._clock()
        header = int(header_ns)
        with self._lock:
            last_in, last_out = self._last_in, self._last_out
            problem = None
            if header == 0:
                problem = 'zero'
            elif last_in is not None and header == last_in:
                problem = 'repeated'
            elif last_in is not None and header < last_in:
                problem = f'backward by {(last_in - header) / NS_PER_SEC:.3f} s'
            if problem is None:
                out = header + self._offset
                if last_out is not None and out <= last_out:  # after an untrusted stretch
                    out = last_out + 1
                    self._switch(out, out - header, False)
            else:
                out = header if last_out is None else last_out + max(now - self._last_arrival,
                                                                     1)
                self._switch(out, out - header, True)
                if hint is not None:
                    self._hints[out] = hint()
                    while len(self._hints) > MAX_HINTS:
                        self._hints.popitem(last=False)
            self._last_in, self._last_out, self._last_arrival = header, out, now
        return out, problem

    def hint(self, stamp_ns: int) -> Any:
        """What ``hint()`` gave when the untrusted cloud of detector stamp ``stamp_ns``
        arrived (once; None when there was none)."""
        with self._lock:
            return self._hints.pop(stamp_ns, None)

    def _switch(self, start: int, offset: int, untrusted: bool) -> None:
        self._offset = offset
        self._starts.append(start)
        self._offsets.append(offset)
        self._untrusted.append(untrusted)
        if len(self._starts) > MAX_SEGMENTS:
            drop = len(self._starts) - MAX_SEGMENTS // 2
            del self._starts[:drop], self._offsets[:drop], self._untrusted[:drop]

    def source(self, stamp_ns: int) -> tuple[int, bool]:
        """The header stamp of the cloud the detector saw at ``stamp_ns``, and whether it was
        trusted (pair odometry by stamp) or not (pair the newest odometry)."""
        with self._lock:
            k = bisect.bisect_right(self._starts, stamp_ns) - 1
            if k < 0:
                return stamp_ns, True
            untrusted = self._untrusted[k] and self._starts[k] == stamp_ns
            return stamp_ns - self._offsets[k], not untrusted

    def headers(self, stamps_ns: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """The header stamps of the clouds the detector saw at ``stamps_ns``
        (:meth:`source` of many)."""
        stamps = np.array(stamps_ns, dtype=np.int64)
        if not self.shifted:
            return stamps
        with self._lock:
            starts = np.array(self._starts, dtype=np.int64)
            offsets = np.array(self._offsets, dtype=np.int64)
        k = np.searchsorted(starts, stamps, side='right') - 1
        shift: npt.NDArray[np.int64] = np.where(k >= 0, offsets[np.maximum(k, 0)], 0)
        return stamps - shift

    @property
    def shifted(self) -> bool:
        """Whether any detector stamp differs from its header stamp."""
        return bool(self._starts)

    def restore(self, result: ScanResult, session_id: int) -> ScanResult:
        """``result`` with the header stamps of this session's scans (its own, and matches
        in this session) in place of the detector's."""
        if not self.shifted:
            return result

        def fix(c: LoopCandidate) -> LoopCandidate:
            match = (self.source(c.match_stamp_ns)[0] if c.match_session == session_id
                     else c.match_stamp_ns)
            return dataclasses.replace(c, query_stamp_ns=self.source(c.query_stamp_ns)[0],
                                       match_stamp_ns=match)

        return dataclasses.replace(
            result, stamp_ns=self.source(result.stamp_ns)[0],
            loops=tuple(fix(c) for c in result.loops),
            attempts=tuple(fix(c) for c in result.attempts),
            best=None if result.best is None else fix(result.best))
