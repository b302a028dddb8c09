"""HeapTrim: a huge message makes trims due for a few seconds, at most one a second."""

from __future__ import annotations

from solid_ros.ros.memory import LARGE_BYTES, RENEW_GAP_SEC, TRIM_FOR_SEC, HeapTrim, Renewal


def test_trims_follow_large_messages_only() -> None:
    now = [0.0]
    calls: list[float] = []
    trim = HeapTrim(lambda: calls.append(now[0]), clock=lambda: now[0])
    trim.note(LARGE_BYTES - 1)
    assert not trim.maybe_trim()
    trim.note(LARGE_BYTES)
    assert trim.maybe_trim() and not trim.maybe_trim()  # once a second
    for _ in range(int(TRIM_FOR_SEC) + 3):
        now[0] += 1.0
        trim.maybe_trim()
    assert calls == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert HeapTrim().maybe_trim() is False  # glibc's own, nothing due


def test_trims_go_on_while_the_node_is_busy_with_what_followed() -> None:
    now = [0.0]
    busy = [True]
    calls: list[float] = []
    trim = HeapTrim(lambda: calls.append(now[0]), clock=lambda: now[0], busy=lambda: busy[0])
    trim.note(LARGE_BYTES)
    for _ in range(12):
        now[0] += 1.0
        trim.maybe_trim()
    busy[0] = False
    for _ in range(4):
        now[0] += 1.0
        trim.maybe_trim()
    assert calls == [float(t) for t in range(1, 15)]  # every second while busy, then twice


def test_a_subscription_is_renewed_when_asked_and_idle_at_most_every_gap() -> None:
    now = [0.0]
    made: list[int] = []
    gone: list[int] = []
    renewal = Renewal(lambda: made.append(len(made)) or len(made) - 1, gone.append,
                      clock=lambda: now[0])
    assert renewal.current == 0 and not renewal.maybe_renew()
    renewal.request()
    assert not renewal.maybe_renew(idle=False)  # busy: later
    assert renewal.maybe_renew() and (renewal.current, gone) == (1, [0])
    renewal.request()
    now[0] += RENEW_GAP_SEC - 1
    assert not renewal.maybe_renew()
    now[0] += 1
    assert renewal.maybe_renew() and renewal.renewals == 2 and gone == [0, 1]


def test_a_renewal_that_is_not_safe_now_is_dropped() -> None:
    """Under a multi-threaded executor a subscription is never destroyed from a callback."""
    made: list[int] = []
    renewal = Renewal(lambda: made.append(len(made)) or len(made) - 1, made.append,
                      safe=lambda: False)
    renewal.request()
    assert not renewal.maybe_renew() and renewal.renewals == 0 and made == [0]
    assert not renewal.maybe_renew()  # the request is gone, not retried each second
