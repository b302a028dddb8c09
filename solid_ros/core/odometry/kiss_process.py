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
"""

from __future__ import annotations

import multiprocessing
import signal
from collections import Counter
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import SolidError
from solid_ros.core.odometry.kiss import KissOdometry, load_kiss_icp
from solid_ros.core.odometry.track import OdomSample, Points

__all__ = ['KissProcess']

_STARTUP_SEC = 120.0  # the child's first answer waits for its imports (seconds on a busy CPU)


def _state(kiss: KissOdometry) -> dict[str, Any]:
    """The counters the parent mirrors after each cloud."""
    return {'registered': kiss.registered, 'resets': kiss.resets, 'segment': kiss.segment,
            'deskewed': kiss.deskewed, 'reset_counts': dict(kiss.reset_counts),
            'input_counts': dict(kiss.input_counts), 'recovered': dict(kiss.recovered),
            'typical_overlap': kiss.typical_overlap, 'config': kiss.config}


def _serve(conn: Connection, config: NodeConfig) -> None:
    """The child: one pose per cloud until the pipe closes or a None arrives."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent's Ctrl-C ends it via the pipe
    try:
        kiss = KissOdometry(config)
        conn.send(('ready', None, _state(kiss)))
        while True:
            item = conn.recv()
            if item is None:
                return
            stamp_ns, points, times = item
            try:
                sample = kiss.pose_for(stamp_ns, points, point_times=times)
            except Exception as err:  # reported to the caller, the child goes on
                conn.send(('error', f'{type(err).__name__}: {err}', _state(kiss)))
                continue
            conn.send(('pose', sample, _state(kiss)))
    except (EOFError, OSError, KeyboardInterrupt):
        return


class KissProcess:
    """:class:`~solid_ros.core.odometry.kiss.KissOdometry` run in a child process.

    It has KissOdometry's counters (as of the last answer) and its :meth:`pose_for`.

    Args:
        config: node settings (``kiss_*``).

    Raises:
        SolidError: kiss-icp is not installed (checked here, before the child starts), or
            the child did not start (it is waited for: its imports take seconds).
    """

    name = 'kiss_icp'
    takes_point_times = True

    def __init__(self, config: NodeConfig) -> None:
        load_kiss_icp()  # the install error at start, in the caller's process
        self.config = config
        self.registered = self.resets = self.segment = self.deskewed = 0
        self.reset_counts: Counter[str] = Counter()
        self.input_counts: Counter[str] = Counter()
        self.recovered: Counter[str] = Counter()
        self.typical_overlap: float | None = None
        ctx = multiprocessing.get_context('spawn')
        self._conn, child = ctx.Pipe()
        self._child = ctx.Process(target=_serve, args=(child, config), name='solid_kiss_icp',
                                  daemon=True)
        self._child.start()
        child.close()
        # Its imports now, not in the first cloud's latency (the queue would drop clouds).
        self._wait_ready()

    def _wait_ready(self) -> None:
        try:
            self._answer(_STARTUP_SEC)
        except (EOFError, OSError) as err:
            raise SolidError(f'the KISS-ICP process did not start (exit code '
                             f'{self._child.exitcode}): {err or "pipe closed"}') from err

    @property
    def pid(self) -> int | None:
        """The child's process id."""
        return self._child.pid

    def pose_for(self, stamp_ns: int, points: Points | None = None,
                 point_times: npt.ArrayLike | None = None) -> OdomSample | None:
        """Register ``points`` in the child and return its pose (as KissOdometry does).

        Raises:
            SolidError: the child ended, or KissOdometry raised there (the message says which).
        """
        if points is None:
            return None
        xyz = np.ascontiguousarray(np.asarray(points)[:, :3])
        times = None if point_times is None else np.asarray(point_times, dtype=np.float64)
        try:
            self._conn.send((int(stamp_ns), xyz, times))
            kind, value, _ = self._answer(None)
        except (EOFError, OSError) as err:
            raise SolidError(f'the KISS-ICP process ended (exit code {self._child.exitcode}): '
                             f'{err or "pipe closed"}') from err
        if kind == 'error':
            raise SolidError(f'KISS-ICP failed: {value}')
        sample: OdomSample | None = value
        return sample

    def _answer(self, timeout: float | None) -> tuple[str, Any, dict[str, Any]]:
        if timeout is not None and not self._conn.poll(timeout):
            raise OSError(f'no answer in {timeout:g} s')
        kind, value, state = self._conn.recv()
        self._mirror(state)
        return kind, value, state

    def _mirror(self, state: dict[str, Any]) -> None:
        self.registered, self.resets = state['registered'], state['resets']
        self.segment, self.deskewed = state['segment'], state['deskewed']
        self.reset_counts = Counter(state['reset_counts'])
        self.input_counts = Counter(state['input_counts'])
        self.recovered = Counter(state['recovered'])
        self.typical_overlap, self.config = state['typical_overlap'], state['config']

    def close(self, timeout: float = 5.0) -> None:
        """End the child (after the cloud it registers), killing it after ``timeout``."""
        try:
            self._conn.send(None)
        except (OSError, ValueError):
            pass
        self._child.join(timeout)
        if self._child.is_alive():
            self._child.kill()
            self._child.join(timeout)
        self._conn.close()
