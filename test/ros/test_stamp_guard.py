"""StampGuard: trusted stamps pass unchanged; zero, repeated and backward ones become arrival
order, and published loops get the header stamps back."""

from __future__ import annotations

import dataclasses

import numpy as np

from solid_ros.core.config import SolidConfig
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.results import LoopCandidate, ScanResult
from solid_ros.ros.stamp_guard import StampGuard

SEC = 1_000_000_000


class Clock:
    def __init__(self) -> None:
        self.t = 10**12

    def __call__(self) -> int:
        return self.t


def feed(guard: StampGuard, clock: Clock, stamps: list[int], every_ns: int = SEC // 10,
         ) -> list[tuple[int, str | None]]:
    out = []
    for s in stamps:
        clock.t += every_ns
        out.append(guard.take(s))
    return out


def test_a_sane_stream_passes_unchanged() -> None:
    clock = Clock()
    guard = StampGuard(clock)
    stamps = [5 * SEC + i * SEC // 10 for i in range(50)]
    assert feed(guard, clock, stamps) == [(s, None) for s in stamps]
    assert not guard.shifted and guard.source(stamps[3]) == (stamps[3], True)


def test_zero_stamps_become_arrival_order_and_pair_the_newest_odometry() -> None:
    clock = Clock()
    guard = StampGuard(clock)
    got = []
    for i in range(5):
        clock.t += SEC // 10
        got.append(guard.take(0, lambda i=i: f'odometry {i}'))
    assert [p for _, p in got] == ['zero'] * 5
    # The odometry newest at arrival, once each.
    assert [guard.hint(s) for s, _ in got] == [f'odometry {i}' for i in range(5)]
    assert guard.hint(got[0][0]) is None
    assert [s for s, _ in got] == [0, SEC // 10, 2 * SEC // 10, 3 * SEC // 10, 4 * SEC // 10]
    assert all(guard.source(s) == (0, False) for s, _ in got)


def test_a_clock_that_jumps_back_keeps_going_forward() -> None:
    clock = Clock()
    guard = StampGuard(clock)
    before = feed(guard, clock, [300 * SEC + i * SEC // 10 for i in range(10)])
    jump = [100 * SEC + i * SEC // 10 for i in range(10)]  # 200 s back, then on
    after = feed(guard, clock, jump)
    assert after[0][1] == 'backward by 200.900 s' and all(p is None for _, p in after[1:])
    out = [s for s, _ in before + after]
    assert out == sorted(out) and len(set(out)) == len(out)
    # The spacing of the header stamps is kept after the jump, and they translate back.
    assert [b - a for a, b in zip(out[10:], out[11:])] == [SEC // 10] * 9
    assert [guard.source(s)[0] for s, _ in after] == jump
    assert guard.source(after[0][0])[1] is False and guard.source(after[1][0])[1] is True
    assert guard.source(before[4][0]) == (before[4][0], True)
    # Repeated stamps too.
    again = feed(guard, clock, [jump[-1], jump[-1]])
    assert [p for _, p in again] == ['repeated', 'repeated'] and again[1][0] > again[0][0]


def test_published_loops_carry_the_header_stamps() -> None:
    clock = Clock()
    guard = StampGuard(clock)
    first = feed(guard, clock, [300 * SEC])[0][0]
    query = feed(guard, clock, [100 * SEC])[0][0]  # went back
    c = LoopCandidate(7, 0, query, first, 0, 0.01, 0.0, 0.1)
    peer = dataclasses.replace(c, match_session=4, match_stamp_ns=123)
    result = ScanResult(query, True, 7, loops=(c, peer), attempts=(c,), best=c)
    back = guard.restore(result, session_id=0)
    assert back.stamp_ns == 100 * SEC
    assert (back.loops[0].query_stamp_ns, back.loops[0].match_stamp_ns) == (100 * SEC,
                                                                            300 * SEC)
    assert back.loops[1].match_stamp_ns == 123  # another robot's stamp is its own
    assert back.best is not None and back.best.query_stamp_ns == 100 * SEC


def _place(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-40, -40, -2], [40, 40, 6], size=(4000, 3))
    return pts[np.hypot(pts[:, 0], pts[:, 1]) > 4.0]


def test_a_clock_jumping_back_no_longer_hides_the_end_of_run_loop() -> None:
    """exclude_recent_sec 10: place 0 at t = 300 s, 30 other places, then the clock jumps
    back 200 s and place 0 comes again. With the header stamps the jump hides every earlier
    scan (the old node: no loop); through the guard the loop is found."""
    cfg = SolidConfig().replace(verify=False, distance_threshold=1e-6, exclude_recent_frames=0,
                                exclude_recent_sec=10.0)
    headers = [300 * SEC + i * SEC for i in range(31)] + [110 * SEC + i * SEC for i in range(5)]
    places = [0, *range(1, 31), 31, 32, 33, 34, 0]
    clouds = [_place(p) for p in places]
    raw = LoopDetector(cfg)
    loops_raw = [c for pts, h in zip(clouds, headers) for c in raw.process(pts, h).loops]
    assert loops_raw == []  # what the node did before
    clock = Clock()
    guard = StampGuard(clock)
    det = LoopDetector(cfg)
    found = []
    for pts, h in zip(clouds, headers):
        clock.t += SEC // 10
        stamp, _ = guard.take(h)
        found += [guard.restore(det.process(pts, stamp), 0).loops]
    last = found[-1]
    assert [(c.query_index, c.match_index) for c in last] == [(35, 0)]
    assert (last[0].query_stamp_ns, last[0].match_stamp_ns) == (114 * SEC, 300 * SEC)


def test_header_stamps_of_many_detector_stamps_at_once() -> None:
    # What the corrected path and trajectory are stamped with: source() of each.
    clock = Clock()
    guard = StampGuard(clock)
    assert guard.headers([3, 4]).tolist() == [3, 4]  # nothing shifted yet
    headers = [5 * SEC, 6 * SEC, 0, 0, 3 * SEC, 7 * SEC, 7 * SEC, 8 * SEC]
    got = [s for s, _ in feed(guard, clock, headers)]
    assert guard.shifted
    assert guard.headers(got).tolist() == [guard.source(s)[0] for s in got] == headers
    assert guard.headers(np.zeros(0, dtype=np.int64)).tolist() == []
