"""KISS-ICP in a process of its own, so that it never holds the describe and verify threads.

KISS-ICP 1.3's registration (``_align_points_to_map``, C++ through pybind11) holds the GIL for
the whole alignment: measured on hku1 (``test/bench/bench_kiss_overlap.py``, doc/reports), a
pure-Python thread kept 0.25 of its rate while it ran, and the loop closure's p95 per cloud went
from 104 ms alone to 814 ms with KISS-ICP on a thread of the same process (291 ms with KISS-ICP
in another process; a shared 2-core machine). So :class:`KissProcess` runs
:class:`~solid_ros.core.odometry.kiss.KissOdometry` in a child process (started with ``spawn``:
forking a process that runs DDS threads is not safe) and sends it each cloud over a pipe; the
caller's thread waits for the pose without the GIL. The child ends when the pipe closes
(:meth:`KissProcess.close`, or the parent dying).

A child that ends otherwise (killed, crashed) is restarted: the next cloud starts a fresh one,
which continues where the dead one stopped as a reset does (a new odometry segment at the last
pose, counted in ``reset_counts['restart']`` and :attr:`KissProcess.restarts`, its reason on
that cloud's sample), so the back end starts a new graph segment and keeps every keyframe. The
cloud that was in the child when it died is not sent again (it may be what killed it), and a
restart comes at most every :data:`RESTART_SEC`: until then :meth:`KissProcess.pose_for`
raises :class:`~solid_ros.core.errors.OdometryUnavailable` (the caller skips the cloud). What
the new child does not inherit: KISS-ICP's map and motion (as after any reset) and the overlap
check's history of the run (its bar is calibrated again).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import struct
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.connection import Connection
from multiprocessing.reduction import ForkingPickler
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import OdometryUnavailable, SolidError
from solid_ros.core.odometry.kiss import KissOdometry, load_kiss_icp
from solid_ros.core.odometry.track import OdomSample, Points

__all__ = ['RESTART_SEC', 'KissProcess']

_STARTUP_SEC = 120.0  # the child's first answer waits for its imports (seconds on a busy CPU)
RESTART_SEC = 5.0  # least time between two restarts: a child that dies at once is not respawned
# in a tight loop (its imports alone take a core for seconds)
_COUNTS = ('reset_counts', 'input_counts', 'recovered')
_TOTALS = ('registered', 'resets', 'deskewed')


def _send_once(conn: Connection, item: Any) -> None:
    """``conn.send(item)`` in one system call: the same bytes (Connection's length header and
    pickle), but ``Connection.send`` writes a pickle over 16 kB (a cloud) apart from its header,
    and the child waits for both. Each write gives up the GIL, and getting it back from a busy
    thread (the describe thread) takes up to the switch interval, 5 ms: with a spinning thread
    beside, the median time to the child went from 9.7-9.9 to 0.7-1.7 ms per hku1 cloud
    (test/bench/bench_kiss_overhead.py, two runs each at load 6-9); in the node on hku1 the
    hand-over p50 went from 4.0-4.9 to 3.2-3.7 ms (bench_node_kiss, load 8-9).

    Raises:
        BrokenPipeError: the child had ended (its end of the pipe was closed).
    """
    data = ForkingPickler.dumps(item)
    if len(data) > 0x7FFFFFFF:  # Connection's other header; never a cloud
        conn.send_bytes(data)
        return
    fd = conn.fileno()
    sent = os.writev(fd, [struct.pack('!i', len(data)), data])
    if sent < 4 + len(data):  # a short write (a signal): the rest as it comes
        rest = memoryview(data)[max(sent - 4, 0):]
        if sent < 4:
            os.write(fd, struct.pack('!i', len(data))[sent:])
        while len(rest):
            rest = rest[os.write(fd, rest):]


def _recv_once(conn: Connection) -> Any:
    """``conn.recv()`` of a small message in one system call: Connection reads its length and
    its pickle apart, and each read gives up the GIL (see :func:`_send_once`). Beside a
    spinning thread the pose's way back took 11.0 ms (p95 11.2: two switch intervals) at a
    load of 1.3 (test/bench/bench_kiss_overhead.py).

    Raises:
        EOFError: the other end closed the pipe.
    """
    fd = conn.fileno()
    buf = os.read(fd, 65536)  # the child's answer (about 1.6 kB) comes whole, at once
    while len(buf) < 4:
        more = os.read(fd, 65536)
        if not more:
            raise EOFError
        buf += more
    size, start = struct.unpack('!i', buf[:4])[0], 4
    if size == -1:  # an 8-byte length follows (over 2 GB: never an answer)
        while len(buf) < 12:
            more = os.read(fd, 65536)
            if not more:
                raise EOFError
            buf += more
        size, start = struct.unpack('!Q', buf[4:12])[0], 12
    parts, have = [buf[start:]], len(buf) - start
    while have < size:
        more = os.read(fd, size - have)
        if not more:
            raise EOFError
        parts.append(more)
        have += len(more)
    return ForkingPickler.loads(b''.join(parts))


def _state(kiss: KissOdometry) -> dict[str, Any]:
    """The counters the parent mirrors after each cloud."""
    return {'registered': kiss.registered, 'resets': kiss.resets, 'segment': kiss.segment,
            'deskewed': kiss.deskewed, 'reset_counts': dict(kiss.reset_counts),
            'input_counts': dict(kiss.input_counts), 'recovered': dict(kiss.recovered),
            'typical_overlap': kiss.typical_overlap, 'config': kiss.config}


def _serve(conn: Connection, config: NodeConfig, segment: int,
           pose: npt.NDArray[np.float64]) -> None:
    """The child: one pose per cloud until the pipe closes or a None arrives."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent's Ctrl-C ends it via the pipe
    try:
        kiss = KissOdometry(config, segment=segment, pose=pose)
        conn.send(('ready', None, _state(kiss)))
        while True:
            item = conn.recv()
            if item is None:
                return
            stamp_ns, points, times = item
            began = time.monotonic()  # system-wide: the parent splits its round trip with it
            try:
                sample = kiss.pose_for(stamp_ns, points, point_times=times)
            except Exception as err:  # reported to the caller, the child goes on
                conn.send(('error', f'{type(err).__name__}: {err}', _state(kiss)))
                continue
            conn.send(('pose', sample, _state(kiss) | {'span': (began, time.monotonic())}))
    except (EOFError, OSError, KeyboardInterrupt):
        return


class KissProcess:
    """:class:`~solid_ros.core.odometry.kiss.KissOdometry` run in a child process.

    It has KissOdometry's counters (as of the last answer, summed over the children it ran)
    and its :meth:`pose_for`.

    Args:
        config: node settings (``kiss_*``).
        restart_sec: least time between two restarts of a child that ended.
        clock: monotonic seconds (injectable for tests).

    Raises:
        SolidError: kiss-icp is not installed (checked here, before the child starts), or
            the child did not start (it is waited for: its imports take seconds).

    Attributes:
        restarts: children started after one ended.
        ended: children that ended while in use (noticed by :meth:`pose_for`).
        last_end: why the last one ended (exit code), or None.
        last_ms: the last cloud's round trip split in three, ms: to the child (copy, pipe,
            the child waking), in KissOdometry.pose_for there, and back (None before one).
    """

    name = 'kiss_icp'
    takes_point_times = True

    def __init__(self, config: NodeConfig, restart_sec: float = RESTART_SEC,
                 clock: Callable[[], float] = time.monotonic) -> None:
        load_kiss_icp()  # the install error at start, in the caller's process
        self.config = config
        self.registered = self.resets = self.segment = self.deskewed = 0
        self.reset_counts: Counter[str] = Counter()
        self.input_counts: Counter[str] = Counter()
        self.recovered: Counter[str] = Counter()
        self.typical_overlap: float | None = None
        self.restarts = self.ended = 0
        self.last_end: str | None = None
        self.last_ms: tuple[float, float, float] | None = None
        self._restart_sec, self._clock = float(restart_sec), clock
        self._restarted_at: float | None = None
        self._before: dict[str, Any] = {}  # the counters of the children that ended
        self._pose = np.eye(4)  # the last pose returned: where a restart starts
        self._pending: str | None = None  # the restart's reason for the next sample
        self._conn: Connection | None = None
        self._child: Any = None
        self._closed = False  # close() was called: no more restarts
        self._start(0)

    def _start(self, segment: int) -> None:
        """Start a child at ``segment`` and the last pose, and wait for its imports (now, not
        in the first cloud's latency: the queue would drop clouds)."""
        ctx = multiprocessing.get_context('spawn')
        conn, child = ctx.Pipe()
        self._child = ctx.Process(target=_serve, args=(child, self.config, segment, self._pose),
                                  name='solid_kiss_icp', daemon=True)
        self._child.start()
        child.close()
        self._conn = conn
        try:
            self._answer(conn, _STARTUP_SEC)
        except (EOFError, OSError) as err:
            code = self._child.exitcode
            self._stop_child(0.0)
            raise SolidError(f'the KISS-ICP process did not start (exit code {code}): '
                             f'{err or "pipe closed"}') from err

    @property
    def pid(self) -> int | None:
        """The child's process id (None while there is none: it ended)."""
        return None if self._conn is None else self._child.pid

    def pose_for(self, stamp_ns: int, points: Points | None = None,
                 point_times: npt.ArrayLike | None = None) -> OdomSample | None:
        """Register ``points`` in the child and return its pose (as KissOdometry does).

        Raises:
            OdometryUnavailable: the child ended with this cloud in it, or it ended earlier
                and the next restart is not due yet (skip the cloud).
            SolidError: KissOdometry raised in the child (the message says what).
        """
        if points is None:
            return None
        if self._closed:
            raise OdometryUnavailable('the KISS-ICP process was closed')
        xyz = np.ascontiguousarray(np.asarray(points)[:, :3])
        times = None if point_times is None else np.asarray(point_times, dtype=np.float64)
        item = (int(stamp_ns), xyz, times)
        conn, sent = self._send(item)
        try:
            kind, value, state = self._answer(conn, None)
        except (EOFError, OSError) as err:
            if self._closed:  # its end was asked for, not a crash
                raise OdometryUnavailable('the KISS-ICP process was closed') from err
            raise OdometryUnavailable(self._lost(err) + ': this cloud is skipped, the next '
                                      'one restarts it') from err
        if kind == 'error':
            raise SolidError(f'KISS-ICP failed: {value}')
        began, ended = state['span']
        self.last_ms = ((began - sent) * 1e3, (ended - began) * 1e3,
                        (time.monotonic() - ended) * 1e3)
        return self._returned(value)

    def _send(self, item: tuple[int, Any, Any]) -> tuple[Connection, float]:
        """Send a cloud to the child, to a new one if it had ended (the pipe said so: no
        check of its own per cloud, a system call that gives up the GIL); return the pipe and
        when it was sent.

        Raises:
            OdometryUnavailable: it had ended and the next restart is not due yet, or the
                new child ended too.
        """
        for attempt in range(2):
            if self._conn is None:
                self._restart()
            conn = self._conn  # close() on another thread may clear self._conn meanwhile
            assert conn is not None
            sent = time.monotonic()
            try:
                _send_once(conn, item)
                return conn, sent
            except OSError as err:  # it had ended: this cloud never reached it
                if self._closed:
                    raise OdometryUnavailable('the KISS-ICP process was closed') from err
                line = self._lost(None)
                if attempt:
                    raise OdometryUnavailable(f'{line}: the cloud is skipped') from err
        raise AssertionError('unreachable')

    def _returned(self, sample: OdomSample | None) -> OdomSample | None:
        """The child's sample, with the restart's reason on the first one after it."""
        if sample is None:
            return None
        self._pose = sample.pose
        if self._pending is not None:
            note = self._pending if sample.reason is None else f'{self._pending}; {sample.reason}'
            sample, self._pending = replace(sample, reason=note), None
        return sample

    def _lost(self, err: BaseException | None) -> str:
        """Record that the child ended; return a line saying so."""
        self._stop_child(1.0)
        self.ended += 1
        self.last_end = (f'exit code {self._child.exitcode}' if err is None else
                         f'exit code {self._child.exitcode}: {err or "pipe closed"}')
        return f'the KISS-ICP process ended ({self.last_end})'

    def _restart(self) -> None:
        """Start a fresh child in a new segment at the last pose (as a reset does), unless
        the last restart was less than ``restart_sec`` ago.

        Raises:
            OdometryUnavailable: not yet, or the new child did not start.
        """
        now = self._clock()
        if self._restarted_at is not None and now - self._restarted_at < self._restart_sec:
            wait = self._restart_sec - (now - self._restarted_at)
            raise OdometryUnavailable(f'the KISS-ICP process ended ({self.last_end}); it '
                                      f'restarts in {wait:.1f} s, the cloud is skipped')
        self._restarted_at = now
        self._before = {k: getattr(self, k) for k in (*_TOTALS, *_COUNTS)}
        self._before['resets'] += 1
        self._before['reset_counts'] = self.reset_counts + Counter(restart=1)
        segment = self.segment + 1
        try:
            self._start(segment)
        except SolidError as err:
            self.ended += 1
            self.last_end = str(err)
            raise OdometryUnavailable(f'{err}; the cloud is skipped') from err
        self.restarts += 1
        note = (f'odometry reset, segment {segment} starts: the KISS-ICP process was '
                f'restarted ({self.last_end})')
        self._pending = note if self._pending is None else f'{self._pending}; {note}'

    def _answer(self, conn: Connection,
                timeout: float | None) -> tuple[str, Any, dict[str, Any]]:
        if timeout is not None and not conn.poll(timeout):
            raise OSError(f'no answer in {timeout:g} s')
        kind, value, state = _recv_once(conn)
        self._mirror(state)
        return kind, value, state

    def _mirror(self, state: dict[str, Any]) -> None:
        before = self._before
        for key in _TOTALS:
            setattr(self, key, before.get(key, 0) + state[key])
        for key in _COUNTS:
            setattr(self, key, before.get(key, Counter()) + Counter(state[key]))
        self.segment = state['segment']
        self.typical_overlap, self.config = state['typical_overlap'], state['config']

    def _stop_child(self, timeout: float) -> None:
        """End the child (after the cloud it registers), killing it after ``timeout``."""
        if self._conn is None:
            return
        try:
            self._conn.send(None)
        except (OSError, ValueError):
            pass
        self._child.join(timeout)
        if self._child.is_alive():
            self._child.kill()
            self._child.join(max(timeout, 1.0))
        self._conn.close()
        self._conn = None

    def close(self, timeout: float = 5.0) -> None:
        """End the child (after the cloud it registers), killing it after ``timeout``; no
        restart after this."""
        self._closed = True
        self._stop_child(timeout)
