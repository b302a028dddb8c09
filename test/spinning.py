"""Spinning an rclpy executor on a thread in the ROS tests, and stopping it cleanly.

``threading.Thread(target=executor.spin)`` stopped by ``executor.shutdown()`` races rclpy:
the spinning thread may be building its wait set while shutdown tears the executor's guard
condition down ('NoneType' object has no attribute 'handle', seen in the suite), or while a
node is destroyed ('cannot use Destroyable'). Here the thread spins one round at a time and
leaves before anything is shut down or destroyed.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from rclpy.executors import ExternalShutdownException


class Spinner:
    """Spin ``executor`` on a daemon thread until :meth:`stop`.

    Args:
        executor: an rclpy executor with its nodes added.
    """

    def __init__(self, executor: Any) -> None:
        self.executor = executor
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except ExternalShutdownException:
                return

    def stop(self) -> None:
        """Let the thread finish its round and leave, wait for the callbacks still running,
        then shut the executor down; the executor's nodes may then be destroyed."""
        self._stop.set()
        self.thread.join(timeout=10.0)
        # A MultiThreadedExecutor hands callbacks to a thread pool, and shutdown() does not
        # wait for them: a node destroyed under one fails it ('cannot use Destroyable',
        # reported as an exception never retrieved).
        deadline = time.monotonic() + 10.0
        failed = None
        for task in list(getattr(self.executor, '_futures', ())):
            while not task.done() and time.monotonic() < deadline:
                time.sleep(0.01)
            if task.done() and task.exception() is not None:
                failed = failed or task.exception()
        self.executor.shutdown()
        if failed is not None:  # a callback failed: the test's to report
            raise failed
