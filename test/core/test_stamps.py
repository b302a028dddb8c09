"""Integer-nanosecond stamps: split, join, seconds, log format."""

from __future__ import annotations

import pytest

from solid_ros.core.stamps import (
    NS_PER_SEC,
    format_stamp,
    join_stamp,
    seconds_to_ns,
    split_stamp,
)


@pytest.mark.parametrize('stamp', [0, 1, NS_PER_SEC - 1, NS_PER_SEC, 1_700_000_000_123_456_789,
                                   -1, -NS_PER_SEC - 5, 2**63 - 1, -(2**63)])
def test_split_and_join_are_inverse(stamp: int) -> None:
    sec, nanosec = split_stamp(stamp)
    assert 0 <= nanosec < NS_PER_SEC
    assert join_stamp(sec, nanosec) == stamp


def test_split_keeps_every_digit_of_large_stamps() -> None:
    # Float seconds would round these (a double holds ~16 digits).
    assert split_stamp(1_700_000_000_123_456_789) == (1_700_000_000, 123_456_789)
    assert split_stamp(-1) == (-1, NS_PER_SEC - 1)


def test_seconds_to_ns_rounds_to_the_nearest_nanosecond() -> None:
    assert seconds_to_ns(0.05) == 50_000_000
    assert seconds_to_ns(0.3) == 300_000_000  # 0.3 * 1e9 is 300000000.00000006
    assert seconds_to_ns(0.7) == 700_000_000
    assert seconds_to_ns(1e-9) == 1 and seconds_to_ns(0.0) == 0


def test_format_stamp() -> None:
    assert format_stamp(12 * NS_PER_SEC + 345) == '12.000000345 s'
    assert format_stamp(0) == '0.000000000 s'
