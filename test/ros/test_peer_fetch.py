"""CloudFetches without ROS: replies must match their request; silent peers are backed off."""

from __future__ import annotations

import threading
from collections import Counter

import numpy as np

from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.formats.peers import CloudReply
from solid_ros.ros.peer_fetch import MAX_TIMEOUTS, CloudFetches, Pending

CLOUD = KeyframeCloud(np.ones((10, 3), np.float32), 5)


def make(timeout: float = 0.05) -> tuple[CloudFetches, Counter[str], list[float]]:
    counts: Counter[str] = Counter()
    now = [0.0]

    def count(kind: str, n: int) -> None:
        counts[kind] += n

    f = CloudFetches(timeout, 30.0, count, clock=lambda: now[0])
    return f, counts, now


def test_only_a_reply_matching_owner_index_and_stamp_is_taken() -> None:
    f, counts, _ = make(timeout=5.0)
    p = f.start(4, 10, 777)
    assert isinstance(p, Pending) and f.pending == 1
    forged = [CloudReply(3, 0, 10, p.request_id, 777, CLOUD),   # another owner
              CloudReply(4, 0, 11, p.request_id, 777, CLOUD),   # another keyframe
              CloudReply(4, 0, 10, p.request_id, 778, CLOUD),   # another stamp
              CloudReply(4, 0, 10, p.request_id ^ 1, 777, CLOUD)]  # another request
    assert [f.deliver(r) for r in forged] == [False] * 4
    assert counts['replies_mismatched'] == 3 and counts['late_replies'] == 1
    real = CloudReply(4, 0, 10, p.request_id, 777, CLOUD)
    assert f.deliver(real) and not f.deliver(real)  # the first one only
    assert f.finish(p) is CLOUD and f.pending == 0
    # Request ids are random, not a count a bystander can predict.
    ids = {f.start(4, i, 0).request_id for i in range(50)}  # type: ignore[union-attr]
    assert len(ids) == 50 and not ids <= set(range(1000))


def test_a_silent_peer_is_backed_off_after_a_few_time_outs() -> None:
    f, counts, now = make()
    reasons = []
    for _ in range(MAX_TIMEOUTS):
        now[0] += 1.0
        reasons.append(f.finish(f.start(4, 1, 1)))  # it never answers
    assert reasons == ['peer_timeout'] * MAX_TIMEOUTS and counts['peers_backed_off'] == 1
    now[0] += 1.0
    assert f.start(4, 1, 1) == 'peer_gone'  # skipped during the back-off, no wait
    now[0] += 29.0
    assert f.finish(f.start(4, 1, 1)) == 'peer_timeout'  # one probe, then a longer back-off
    now[0] += 31.0
    assert f.start(4, 1, 1) == 'peer_gone'
    now[0] += 30.0
    p = f.start(4, 1, 1)
    assert isinstance(p, Pending)  # the next probe is answered: back-off over
    f.deliver(CloudReply(4, 0, 1, p.request_id, 1, CLOUD))
    assert f.finish(p) is CLOUD and isinstance(f.start(4, 1, 1), Pending)


def test_a_reply_arriving_while_waiting_wakes_the_collector() -> None:
    f, counts, _ = make(timeout=30.0)
    p = f.start(2, 3, 4)
    assert isinstance(p, Pending)
    threading.Timer(0.05, f.deliver, [CloudReply(2, 0, 3, p.request_id, 4, None)]).start()
    assert f.finish(p) == 'peer_evicted' and counts['clouds_evicted'] == 1


def test_a_request_without_a_reply_is_sent_again_twice_within_its_time_out() -> None:
    f, counts, _ = make(timeout=0.3)
    sent: list[int] = []
    p = f.start(2, 3, 4)
    assert isinstance(p, Pending)
    assert f.finish(p, lambda q: sent.append(q.request_id)) == 'peer_timeout'
    assert sent == [p.request_id] * 2 and counts['clouds_rerequested'] == 2
    q = f.start(2, 5, 6)
    assert isinstance(q, Pending)

    def answer(again: Pending) -> None:  # the resend is answered
        f.deliver(CloudReply(2, 0, 5, again.request_id, 6, CLOUD))

    assert f.finish(q, answer) is CLOUD


def test_requests_out_together_time_out_as_one() -> None:
    f, counts, now = make()
    for _ in range(MAX_TIMEOUTS - 1):
        now[0] += 1.0
        batch = [f.start(4, i, i) for i in range(8)]  # one keyframe's candidates
        assert [f.finish(p) for p in batch] == ['peer_timeout'] * 8
    assert counts['peers_backed_off'] == 0
    now[0] += 1.0
    assert f.finish(f.start(4, 9, 9)) == 'peer_timeout' and counts['peers_backed_off'] == 1
