"""One worker thread over a bounded keep-newest queue: each stage of solid_node is one.

Whoever hands work over (the subscription callback, the describe stage) never waits:
:meth:`Worker.put` drops the oldest waiting item when the queue is full and says so, so that
the caller counts and reports it. The thread handles the items one at a time, oldest first;
an exception from one item goes to ``on_error`` and the thread goes on with the next.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

__all__ = ['Worker']

T = TypeVar('T')


class Worker(Generic[T]):
    """A daemon thread that hands each queued item to ``handle``.

    Args:
        name: the thread's name.
        handle: called on the thread with each item.
        capacity: items that may wait; beyond it the oldest is dropped.
        on_error: called on the thread with any exception ``handle`` raised.
        prepare: called once on the thread before the first item (e.g. slow imports).
    """

    def __init__(self, name: str, handle: Callable[[T], None], capacity: int,
                 on_error: Callable[[Exception], None],
                 prepare: Callable[[], None] | None = None) -> None:
        self.capacity = max(int(capacity), 1)
        self._handle, self._on_error, self._prepare = handle, on_error, prepare
        self._cv = threading.Condition()
        self._queue: deque[T] = deque()
        self._busy = False
        self._stop = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def put(self, item: T) -> bool:
        """Queue ``item``; return True when the oldest waiting item was dropped for it."""
        with self._cv:
            dropped = len(self._queue) >= self.capacity
            if dropped:
                self._queue.popleft()
            self._queue.append(item)
            self._cv.notify_all()
        return dropped

    def __len__(self) -> int:
        """Items waiting (not counting the one being handled)."""
        return len(self._queue)

    def clear(self) -> None:
        """Forget the waiting items (the one being handled finishes)."""
        with self._cv:
            self._queue.clear()

    @property
    def idle(self) -> bool:
        """Nothing waiting and nothing being handled."""
        with self._cv:
            return not self._queue and not self._busy

    def wait_idle(self, timeout: float) -> bool:
        """Block until idle; return False when ``timeout`` seconds pass first."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while self._queue or self._busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    def stop(self) -> None:
        """Ask the thread to end after the item it handles (waiting items are left)."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()

    def join(self, timeout: float) -> None:
        """Wait for the thread to end (not from the thread itself)."""
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=timeout)

    def _run(self) -> None:
        if self._prepare is not None:
            self._prepare()
        while True:
            with self._cv:
                while not self._queue and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                item = self._queue.popleft()
                self._busy = True
            try:
                self._handle(item)
            except Exception as err:  # the thread must survive any bad item
                self._on_error(err)
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()
