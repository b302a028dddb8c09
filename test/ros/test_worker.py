"""Worker: one thread over a bounded keep-newest queue, surviving failing items."""

from __future__ import annotations

import threading

import pytest

from solid_ros.ros.worker import Worker


def test_handles_items_in_order_and_drops_the_oldest_when_full() -> None:
    gate, holding = threading.Event(), threading.Event()
    seen: list[int] = []

    def handle(item: int) -> None:
        if item == 0:
            holding.set()
            gate.wait(10.0)  # hold the thread so that the queue fills
        seen.append(item)

    worker: Worker[int] = Worker('test_worker', handle, 2, lambda err: None)
    worker.start()
    try:
        assert worker.put(0) is False
        assert holding.wait(10.0)  # the thread holds item 0: queue beyond the capacity
        assert [worker.put(i) for i in (1, 2, 3, 4)] == [False, False, True, True]
        assert len(worker) == 2
        assert not worker.wait_idle(0.05)  # busy: times out
        gate.set()
        assert worker.wait_idle(10.0)
        assert seen == [0, 3, 4]  # keep newest: 1 and 2 were dropped
    finally:
        worker.stop()
        worker.join(5.0)


def test_an_exception_goes_to_on_error_and_the_thread_goes_on() -> None:
    errors: list[Exception] = []
    seen: list[int] = []

    def handle(item: int) -> None:
        if item == 1:
            raise RuntimeError('bad item')
        seen.append(item)

    worker: Worker[int] = Worker('test_worker', handle, 10, errors.append)
    worker.start()
    try:
        for i in range(3):
            worker.put(i)
        assert worker.wait_idle(10.0)
    finally:
        worker.stop()
        worker.join(5.0)
    assert seen == [0, 2]
    assert [str(e) for e in errors] == ['bad item']


def test_prepare_runs_on_the_thread_first_and_clear_forgets_waiting_items() -> None:
    gate = threading.Event()
    order: list[str] = []

    def prepare() -> None:
        order.append(threading.current_thread().name)
        gate.wait(10.0)

    worker: Worker[str] = Worker('prepared', order.append, 10, lambda err: None,
                                 prepare=prepare)
    worker.start()
    worker.put('dropped by clear')
    worker.clear()
    worker.put('kept')
    gate.set()
    try:
        assert worker.wait_idle(10.0)
    finally:
        worker.stop()
        worker.join(5.0)
    assert order == ['prepared', 'kept']


@pytest.mark.parametrize('busy', [False, True])
def test_stop_ends_the_thread(busy: bool) -> None:
    gate = threading.Event()
    worker: Worker[int] = Worker('test_worker', lambda i: gate.wait(10.0) and None, 5,
                                 lambda err: None)
    worker.start()
    if busy:
        worker.put(1)
        worker.put(2)  # still waiting when stopped: left undone
    worker.stop()
    gate.set()
    worker.join(5.0)
    assert not worker._thread.is_alive()
