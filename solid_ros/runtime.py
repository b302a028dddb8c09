"""Process-level tuning applied by the executables (node, replay, demo), not by the library.

The library does not need it: ``describe()`` reuses its scan-sized scratch arrays and runs
as fast in a plain Python process as with this tuning (test/bench/bench_core.py). The node
still gains from :func:`tune_allocator`: measured with test/bench/bench_node_latency.py at
10 Hz (121k-point clouds, default transport), the median publish-to-candidate latency was
7.5-10.6 ms with it and 16.5-17.6 ms without, while the node's own processing time (p50
3.3-4.1 ms) was the same either way. The difference therefore lies in receiving the ~1.9 MB
messages: glibc serves blocks that size with fresh mmap() calls and returns them at free(),
so each message's buffers are page-faulted in again; raising the mmap and trim thresholds
keeps them in the heap for reuse.

A leaf at the package top: it imports nothing of solid_ros, so the node (ros) and the offline
tools, sibling adapters, both use it without one importing the other.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ['tune_allocator', 'tune_thread_switching']

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD = 32 * 1024 * 1024  # the largest glibc accepts on 64-bit systems
_TRIM_THRESHOLD = 256 * 1024 * 1024


def tune_allocator() -> bool:
    """Keep large message buffers in the glibc heap between clouds.

    Returns:
        True when glibc accepted the settings; False elsewhere (other C libraries), where
        nothing changes.
    """
    name = ctypes.util.find_library('c')
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD) == 1
    return bool(ok and mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD) == 1)


def tune_thread_switching(interval_sec: float = 0.0005) -> None:
    """Hand the GIL over more often than CPython's default 5 ms.

    The node runs the detector on a worker thread beside the executor. Each numpy call in the
    descriptor releases the GIL and must take it back; while another thread runs Python, every
    take-back waits a full switch interval, so one scan of ~60 numpy calls stalled for up to a
    second under a busy executor (seen in the in-process node tests). 0.5 ms bounds that.
    """
    sys.setswitchinterval(interval_sec)
