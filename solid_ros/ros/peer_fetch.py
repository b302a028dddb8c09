"""Cloud requests to peer robots in flight: matching replies, time-outs and back-off. No ROS.

A request is sent when its keyframe is described (:meth:`CloudFetches.start`) and collected
when the keyframe is verified (:meth:`CloudFetches.finish`), so the cloud travels while
earlier keyframes are verified, and no lock is held while waiting. A reply is taken only when
it matches a pending request in every field: its random request id, the owner asked, the
keyframe index and stamp, and this robot as requester; anything else is counted and dropped.

A request that has no reply after a third of the time-out is sent again (twice at most, same
id): a reply lost on a lossy link, or crowded out of the owner's reader by a flood, costs a
resend instead of the candidate.

Liveness: a robot that lets ``MAX_TIMEOUTS`` requests in a row time out (requests sent
together count as one) is skipped for ``backoff_sec`` (``'peer_gone'``), after which one
request probes it; each probe that times out doubles the back-off (up to
``MAX_BACKOFF_SEC``), a reply ends it. A robot that left, or one that never answers, costs a
few time-outs, not one per candidate. (Whether it is still heard from says nothing: a fake
robot keeps talking, and a robot that has stopped driving still answers but sends nothing.)
"""

from __future__ import annotations

import math
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.reasons import Reason
from solid_ros.formats.peers import CloudReply

__all__ = ['CloudFetches', 'Pending']

MAX_TIMEOUTS = 3  # time-outs in a row before a robot is backed off
SENDS = 3  # a request without a reply is sent again after 1/3 and 2/3 of the time-out
MAX_BACKOFF_SEC = 600.0
MAX_PENDING = 1024


@dataclass
class Pending:
    """One cloud request in flight."""

    robot: int
    index: int
    stamp_ns: int
    request_id: int
    sent: float
    deadline: float
    done: threading.Event = field(default_factory=threading.Event)
    reply: CloudReply | None = None


@dataclass
class _Health:
    timeouts: int = 0  # in a row
    silent_at: float = -math.inf  # its last time-out
    backoff_until: float = -math.inf
    backoff_sec: float = 0.0


class CloudFetches:
    """Requests in flight and the liveness of each robot asked.

    Args:
        timeout_sec: how long a request may wait for its reply (settable).
        backoff_sec: first back-off of a robot that keeps timing out.
        count: adds to a counter by name.
        clock: monotonic seconds.
    """

    def __init__(self, timeout_sec: float, backoff_sec: float,
                 count: Callable[[str, int], None],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.timeout_sec, self.backoff_sec = float(timeout_sec), float(backoff_sec)
        self._count, self._clock = count, clock
        self._lock = threading.Lock()
        self._pending: dict[int, Pending] = {}
        self._health: dict[int, _Health] = {}

    def start(self, robot: int, index: int, stamp_ns: int) -> Pending | Reason:
        """A new request to send, or why none is sent: ``'peer_gone'`` (backed off) or
        ``'peer_timeout'`` (too many requests in flight)."""
        now = self._clock()
        with self._lock:
            h = self._health.get(robot)
            if h is not None and now < h.backoff_until:
                self._count('clouds_peer_gone', 1)
                return 'peer_gone'
            if len(self._pending) >= MAX_PENDING:
                self._count('clouds_timed_out', 1)
                return 'peer_timeout'
            rid = secrets.randbits(32)
            while rid in self._pending:
                rid = secrets.randbits(32)
            p = Pending(int(robot), int(index), int(stamp_ns), rid, now, now + self.timeout_sec)
            self._pending[rid] = p
        self._count('clouds_requested', 1)
        return p

    def deliver(self, reply: CloudReply) -> bool:
        """Hand a reply addressed to this robot to its request; False when none matches
        (counted as ``late_replies`` or ``replies_mismatched``)."""
        with self._lock:
            p = self._pending.get(reply.request_id)
            if p is None or p.reply is not None:
                self._count('late_replies', 1)
                return False
            if (reply.owner, reply.index, reply.stamp_ns) != (p.robot, p.index, p.stamp_ns):
                self._count('replies_mismatched', 1)
                return False
            p.reply = reply
        p.done.set()
        return True

    def finish(self, p: Pending | Reason,
               resend: Callable[[Pending], None] | None = None) -> KeyframeCloud | Reason:
        """Wait (without any lock) until the request's reply or deadline, sending it again
        (``resend``) after each third of the time-out without a reply; the cloud or why there
        is none (``'peer_timeout'``, ``'peer_evicted'``, or the reason ``start`` gave)."""
        if isinstance(p, str):
            return p
        step = (p.deadline - p.sent) / SENDS
        for k in range(1, SENDS + 1):
            if p.done.wait(max(0.0, min(p.sent + k * step, p.deadline) - self._clock())):
                break
            if k < SENDS and resend is not None:
                self._count('clouds_rerequested', 1)
                resend(p)
        now = self._clock()
        with self._lock:
            self._pending.pop(p.request_id, None)
            reply = p.reply
            h = self._health.setdefault(p.robot, _Health())
            if reply is None:
                if h.silent_at < p.sent:  # requests out together time out as one
                    h.timeouts += 1
                h.silent_at = now
                if h.timeouts >= MAX_TIMEOUTS and now >= h.backoff_until:
                    h.backoff_sec = min(MAX_BACKOFF_SEC, max(self.backoff_sec,
                                                             2 * h.backoff_sec))
                    h.backoff_until = now + h.backoff_sec
                    h.timeouts = MAX_TIMEOUTS - 1  # after the back-off, one probe
                    self._count('peers_backed_off', 1)
            else:
                self._health.pop(p.robot, None)
        if reply is None:
            self._count('clouds_timed_out', 1)
            return 'peer_timeout'
        if reply.cloud is None:
            self._count('clouds_evicted', 1)
            return 'peer_evicted'
        self._count('clouds_received', 1)
        self._count('cloud_bytes_received', 12 * len(reply.cloud.points) + 44)
        self._count('cloud_wait_ms_total', int((now - p.sent) * 1e3))
        return reply.cloud

    def forget(self, robots: set[int]) -> None:
        """Drop the liveness records of robots no longer tracked (bounded memory)."""
        with self._lock:
            for r in [r for r in self._health if r not in robots]:
                del self._health[r]

    @property
    def pending(self) -> int:
        """Requests in flight."""
        return len(self._pending)
