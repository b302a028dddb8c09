"""Counters and stage times that solid_node reports on /diagnostics, without ROS."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ['NodeStats', 'StageTimings']

STAGES = ('describe', 'search', 'verify', 'step', 'odometry')


@dataclass
class NodeStats:
    """Counters reported on /diagnostics."""

    received: int = 0
    processed: int = 0
    skipped: int = 0
    rejected: int = 0
    failed: int = 0
    loops: int = 0
    without_odom: int = 0
    verify_skipped: int = 0
    odometry_skipped: int = 0  # of skipped: dropped before registration (KISS-ICP)
    inter_robot_loops: int = 0
    downsampled: int = 0
    odom_rejected: int = 0
    stamps_zero: int = 0
    stamps_repeated: int = 0
    stamps_backward: int = 0


class StageTimings:
    """Milliseconds of the newest scans: the whole describe stage (odometry pairing and the
    detector's descriptor stage), each of the detector's stages and the odometry stage's
    registration (KISS-ICP).

    Args:
        keep: newest times kept per series.
    """

    def __init__(self, keep: int = 1000) -> None:
        self._total: deque[float] = deque(maxlen=keep)
        self._stages: dict[str, deque[float]] = {s: deque(maxlen=keep) for s in STAGES}

    def add_total(self, ms: float) -> None:
        """Time of one scan through the describe stage."""
        self._total.append(ms)

    def add(self, stage: str, ms: float) -> None:
        """Time of one keyframe in ``stage`` (one of ``STAGES``)."""
        self._stages[stage].append(ms)

    def values(self) -> dict[str, str]:
        """The /diagnostics values: percentiles of each series ('nan' while empty)."""
        times = np.asarray(self._total, dtype=np.float64)
        pct = np.percentile(times, [50, 95, 99]) if times.size else np.full(3, np.nan)
        out = {'processing_ms_p50': f'{pct[0]:.2f}', 'processing_ms_p95': f'{pct[1]:.2f}',
               'processing_ms_p99': f'{pct[2]:.2f}',
               'processing_ms_max': f'{times.max():.2f}' if times.size else 'nan'}
        for stage, ms in self._stages.items():
            arr = np.asarray(ms, dtype=np.float64)
            p50, p95 = np.percentile(arr, [50, 95]) if arr.size else (math.nan, math.nan)
            out[f'{stage}_ms_p50'], out[f'{stage}_ms_p95'] = f'{p50:.2f}', f'{p95:.2f}'
        return out
