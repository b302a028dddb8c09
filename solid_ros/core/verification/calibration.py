"""What right alignments look like on this run, and what the odometry drifts: learned as it goes.

A fixed free-space bar tuned on one sensor refuses right poses on another: people and cars
move, vegetation is porous, glass and mixed pixels return ranges that no other scan confirms.
So, as KISS-ICP adapts its own threshold to the data, the run measures itself. Each keyframe
(every one until :data:`MIN_SAMPLES` pairs were measured, then every :data:`SAMPLE_EVERY`-th)
is registered to an earlier keyframe of this session a few metres back along the odometry
(:data:`PAIR_PATH_M`, at most :data:`PAIR_MAX_BACK` keyframes back and turned at most
:data:`PAIR_MAX_TURN_DEG`), started from the odometry's relative pose, by the same coarse and
fine stages as a loop.

- A pair whose registration converged within :data:`AGREE_M` / :data:`AGREE_DEG` of the
  odometry with at least ``verify_min_overlap`` of its structure supporting it is a right
  alignment of this sensor in this scene (over a few metres the odometry is that good, and a
  wrong alignment lands farther: a slide along a corridor, a turned room): its free-space
  conflict joins the run's distribution, the newest :data:`WINDOW` kept.
- A pair the judge's fine rules verified tells how far the odometry's step is from the
  registered one per metre driven (at least a metre): the odometry's drift, unless it is
  :data:`MAX_DRIFT` of the path or more.

:class:`Learned` is what the calibration learned; :func:`~solid_ros.core.verification.judge.bars`
turns it into the conflict bar and the odometry allowance, and the report and ``/diagnostics``
show it.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ['AGREE_DEG', 'AGREE_M', 'MAX_DRIFT', 'MIN_SAMPLES', 'PAIR_MAX_BACK',
           'PAIR_MAX_TURN_DEG',
           'PAIR_PATH_M', 'SAMPLE_EVERY', 'WINDOW', 'Calibration', 'Learned']

MIN_SAMPLES = 10  # right pairs before the run's own distribution replaces the settings
SAMPLE_EVERY = 5  # then every n-th keyframe: the scene changes slowly, the cost is a registration
WINDOW = 200  # newest samples kept: the scene changes along a run
PAIR_PATH_M = 2.0  # the partner lies this much odometry path back ...
PAIR_MAX_BACK = 10  # ... or this many keyframes back, whichever comes first,
PAIR_MAX_TURN_DEG = 30.0  # ... but turned no more than this: the view must overlap
AGREE_M = 0.3  # a registration this close to the odometry over a few metres is right
AGREE_DEG = 2.0
# No odometry that still tracks drifts half the path: a verified pair that far from it slid
# along a street or a corridor (riv281, OS1-64 on a car: 2-12 m over 3-8 m, all fine rules
# passed); it says nothing about the drift.
MAX_DRIFT = 0.5
_CONFLICT_QUANTILE = 75.0
_DRIFT_QUANTILE = 90.0


@dataclass(frozen=True)
class Learned:
    """What the run taught so far (NaN: not enough samples yet).

    Attributes:
        tried: calibration pairs registered.
        right: pairs that were right alignments (their conflict is in ``conflict_q75``).
        conflict_q75: upper quartile of the right alignments' free-space conflict.
        drift_pairs: pairs the judge verified (their drift is in ``drift_per_m``).
        drift_per_m: 90th percentile of the odometry's translation error per metre of path.
    """

    tried: int = 0
    right: int = 0
    conflict_q75: float = math.nan
    drift_pairs: int = 0
    drift_per_m: float = math.nan

    def as_dict(self) -> dict[str, float | int]:
        """Plain values for the report and the diagnostics."""
        return {'tried': self.tried, 'right': self.right, 'conflict_q75': self.conflict_q75,
                'drift_pairs': self.drift_pairs, 'drift_per_m': self.drift_per_m}


class Calibration:
    """The run's samples, newest :data:`WINDOW` of each kind."""

    def __init__(self) -> None:
        self._conflict: deque[float] = deque(maxlen=WINDOW)
        self._drift: deque[float] = deque(maxlen=WINDOW)
        self._tried = 0
        self._learned = Learned()

    def wants(self, query_index: int) -> bool:
        """Whether keyframe ``query_index`` should be registered to a partner."""
        return len(self._conflict) < MIN_SAMPLES or query_index % SAMPLE_EVERY == 0

    def add(self, right: bool, conflict: float, verified: bool, odom_error_m: float,
            path_m: float) -> None:
        """One registered pair: whether it was a right alignment and its conflict; whether
        the judge verified it, the odometry's translation error and the path between."""
        self._tried += 1
        if right and math.isfinite(conflict):
            self._conflict.append(conflict)
        rate = odom_error_m / max(path_m, 1.0)
        if verified and math.isfinite(rate) and rate < MAX_DRIFT:
            self._drift.append(rate)
        self._learned = self._learn()

    @property
    def learned(self) -> Learned:
        """What the samples say now."""
        return self._learned

    def _learn(self) -> Learned:
        conflict = (float(np.percentile(self._conflict, _CONFLICT_QUANTILE))
                    if len(self._conflict) >= MIN_SAMPLES else math.nan)
        drift = (float(np.percentile(self._drift, _DRIFT_QUANTILE))
                 if len(self._drift) >= MIN_SAMPLES else math.nan)
        return Learned(self._tried, len(self._conflict), conflict, len(self._drift), drift)

    def clear(self) -> None:
        """Forget everything (after a reset)."""
        self._conflict.clear()
        self._drift.clear()
        self._tried = 0
        self._learned = Learned()
