"""Stamps as integer nanoseconds, and their one conversion to and from ROS ``(sec, nanosec)``.

The core, the formats and the node keep stamps as integer nanoseconds: exact, unlike float
seconds, so pairing by stamp and comparing stamps never suffer rounding. ROS messages carry
``builtin_interfaces/Time`` as whole seconds plus nanoseconds in ``[0, 1e9)``.
"""

from __future__ import annotations

from typing import Any

from solid_ros.core.errors import SolidError

__all__ = ['INT64', 'NS_PER_SEC', 'check_stamp', 'format_stamp', 'join_stamp', 'seconds_to_ns',
           'split_stamp']

NS_PER_SEC = 1_000_000_000
# Range of ROS int64 fields and of the database's stamp arrays.
INT64 = (-(2**63), 2**63 - 1)


def check_stamp(stamp_ns: Any) -> int:
    """The stamp as an int that the database's int64 arrays hold.

    Raises:
        SolidError: not an integer number of nanoseconds, or outside int64.
    """
    try:
        stamp = int(stamp_ns)
    except (TypeError, ValueError, OverflowError) as err:
        raise SolidError(f'stamp {stamp_ns!r} is not an integer number of nanoseconds') from err
    if not INT64[0] <= stamp <= INT64[1]:
        raise SolidError(f'stamp {stamp} ns is outside the int64 range')
    return stamp


def split_stamp(stamp_ns: int) -> tuple[int, int]:
    """Return ``(sec, nanosec)`` of a stamp in integer nanoseconds (nanosec in [0, 1e9))."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_SEC)
    return sec, nanosec


def join_stamp(sec: int, nanosec: int) -> int:
    """Integer nanoseconds of a ``(sec, nanosec)`` stamp, e.g. a message header's."""
    return int(sec) * NS_PER_SEC + int(nanosec)


def seconds_to_ns(seconds: float) -> int:
    """A duration in seconds (a tolerance, a window) as the nearest whole nanosecond."""
    return int(round(seconds * NS_PER_SEC))


def format_stamp(stamp_ns: int) -> str:
    """A stamp for log lines: ``'12.000000345 s'``, every digit kept."""
    sec, nanosec = split_stamp(stamp_ns)
    return f'{sec}.{nanosec:09d} s'
