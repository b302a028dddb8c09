"""What right alignments look like on this run, and what the odometry drifts: learned as it goes.

A fixed free-space bar tuned on one sensor refuses right poses on another: people and cars
move, vegetation is porous, glass and mixed pixels return ranges that no other scan confirms.
So, as KISS-ICP adapts its own threshold to the data, the run measures itself. Each keyframe
(every one until :data:`MIN_SAMPLES` pairs agreed with the odometry, then every
:data:`SAMPLE_EVERY`-th)
is registered to an earlier keyframe of this session a few metres back along the odometry
(:data:`PAIR_PATH_M`, at most :data:`PAIR_MAX_BACK` keyframes back and turned at most
:data:`PAIR_MAX_TURN_DEG`), started from the odometry's relative pose, by the same coarse and
fine stages as a loop.

- A pair whose registration converged within :data:`AGREE_M` / :data:`AGREE_DEG` of the
  odometry with at least ``verify_min_overlap`` of its structure supporting it is a right
  alignment of this sensor in this scene (over a few metres a tracking odometry is that good,
  and a wrong alignment lands farther: a slide along a corridor, a turned room): its
  free-space conflict joins the run's distribution, the newest :data:`WINDOW` kept.
- An odometry that is lost is no judge of that (KISS-ICP in quickshack's tight space is off
  by 2-36 degrees between neighbouring keyframes where the registration is right within a
  degree). A pair that converged with enough overlap but away from the odometry is then
  checked against two more registrations, none trusting the odometry's answer: the partner
  to its own partner, and the keyframe to that one. Where the three close
  (:func:`closes`: within :data:`CLOSE_M` / :data:`CLOSE_DEG`), the pair is a right alignment
  as well. Such pairs do not count as agreeing with the odometry
  (:attr:`Learned.odometry_agrees` stays what the odometry earned).
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
import numpy.typing as npt

from solid_ros.core.geometry import angle_deg

__all__ = ['AGREE_DEG', 'AGREE_M', 'AGREE_SHARE', 'CLOSE_DEG', 'CLOSE_M', 'MAX_DRIFT',
           'MIN_SAMPLES', 'PAIR_MAX_BACK', 'PAIR_MAX_TURN_DEG', 'PAIR_PATH_M', 'SAMPLE_EVERY',
           'WINDOW', 'Calibration', 'Learned', 'closes']

MIN_SAMPLES = 10  # right pairs before the run's own distribution replaces the settings
SAMPLE_EVERY = 5  # then every n-th keyframe: the scene changes slowly, the cost is a registration
WINDOW = 200  # newest samples kept: the scene changes along a run
PAIR_PATH_M = 2.0  # the partner lies this much odometry path back ...
PAIR_MAX_BACK = 10  # ... or this many keyframes back, whichever comes first,
PAIR_MAX_TURN_DEG = 30.0  # ... but turned no more than this: the view must overlap
AGREE_M = 0.3  # a registration this close to the odometry over a few metres is right
AGREE_DEG = 2.0
# Three registrations k->a, a->b, k->b whose composition closes within this are right (the
# odometry set only their starts). quickshack (test/bench/probe_calibration.py): all 19
# triangles that closed within it with KISS-ICP, and all 15 with the bag's odometry, had a
# k->a leg within 0.12 m / 0.8 deg of the reference. The margin is thin: a k->a leg 1.3 m off
# (both legs from k slid together) closed within 0.14 m / 0.7 deg, one 1.4 m off within
# 0.08 m / 1.7 deg.
CLOSE_M = 0.1
CLOSE_DEG = 1.0
# No odometry that still tracks drifts half the path: a verified pair that far from it slid
# along a street or a corridor (riv281, OS1-64 on a car: 2-12 m over 3-8 m, all fine rules
# passed); it says nothing about the drift.
MAX_DRIFT = 0.5
# The odometry tracks when at least this share of the pairs were right alignments where it put
# them (hku1, riv281 and quickshack with their reference odometry: 0.58-0.84; KISS-ICP lost in
# quickshack's tight space: 0.16).
AGREE_SHARE = 0.5
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
        agreed: right alignments where the odometry put them (the others closed a triangle).
        agreed_conflict_q75: upper quartile of the conflict of those (a registered step's,
            see :func:`~solid_ros.core.verification.judge.bars`).
    """

    tried: int = 0
    right: int = 0
    conflict_q75: float = math.nan
    drift_pairs: int = 0
    drift_per_m: float = math.nan
    agreed: int = 0
    agreed_conflict_q75: float = math.nan

    @property
    def odometry_agrees(self) -> bool:
        """Most pairs registered where the odometry put them (:data:`AGREE_SHARE`), enough of
        them: the odometry tracks, and a loop far from it is suspect."""
        return self.agreed >= MIN_SAMPLES and self.agreed >= AGREE_SHARE * self.tried

    def as_dict(self) -> dict[str, float | int]:
        """Plain values for the report and the diagnostics."""
        return {'tried': self.tried, 'right': self.right, 'agreed': self.agreed,
                'conflict_q75': self.conflict_q75,
                'agreed_conflict_q75': self.agreed_conflict_q75,
                'drift_pairs': self.drift_pairs, 'drift_per_m': self.drift_per_m}


class Calibration:
    """The run's samples, newest :data:`WINDOW` of each kind."""

    def __init__(self) -> None:
        self._conflict: deque[float] = deque(maxlen=WINDOW)
        self._drift: deque[float] = deque(maxlen=WINDOW)
        self._tried = 0
        self._agreed: deque[bool] = deque(maxlen=WINDOW)  # per right sample: odometry's
        self._learned = Learned()

    def wants(self, query_index: int) -> bool:
        """Whether keyframe ``query_index`` should be registered to a partner: every one until
        :data:`MIN_SAMPLES` pairs agreed with the odometry (their conflict sets a registered
        step's bar, as fast as where every right pair agreed), then every
        :data:`SAMPLE_EVERY`-th."""
        return self._learned.agreed < MIN_SAMPLES or query_index % SAMPLE_EVERY == 0

    def wants_triangle(self, query_index: int) -> bool:
        """Whether a pair of keyframe ``query_index`` away from the odometry should be checked
        by a triangle (two more registrations): until :data:`MIN_SAMPLES` right pairs, then
        every :data:`SAMPLE_EVERY`-th keyframe (a lost odometry would triple the cost)."""
        return len(self._conflict) < MIN_SAMPLES or query_index % SAMPLE_EVERY == 0

    def add(self, right: bool, conflict: float, verified: bool, odom_error_m: float,
            path_m: float, agreed: bool | None = None) -> None:
        """One registered pair: whether it was a right alignment and its conflict; whether
        the judge verified it, the odometry's translation error and the path between;
        ``agreed``: right where the odometry put it (None: as ``right``; False for a pair
        only a closed triangle showed right)."""
        self._tried += 1
        if right and math.isfinite(conflict):
            self._conflict.append(conflict)
            self._agreed.append(right if agreed is None else agreed)
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
        agreed = [c for c, a in zip(self._conflict, self._agreed) if a]
        agreed_q75 = (float(np.percentile(agreed, _CONFLICT_QUANTILE))
                      if len(agreed) >= MIN_SAMPLES else math.nan)
        return Learned(self._tried, len(self._conflict), conflict, len(self._drift), drift,
                       len(agreed), agreed_q75)

    def clear(self) -> None:
        """Forget everything (after a reset)."""
        self._conflict.clear()
        self._drift.clear()
        self._agreed.clear()
        self._tried = 0
        self._learned = Learned()


def closes(T_ak: npt.ArrayLike, T_ba: npt.ArrayLike, T_bk: npt.ArrayLike) -> bool:
    """Whether three registered poses (4x4, ``p_a = T_ak p_k`` and so on) close a triangle
    within :data:`CLOSE_M` / :data:`CLOSE_DEG`: going k->a->b lands where k->b does."""
    off = np.linalg.solve(np.asarray(T_bk, dtype=np.float64),
                          np.asarray(T_ba, dtype=np.float64) @ np.asarray(T_ak, dtype=np.float64))
    return bool(float(np.linalg.norm(off[:3, 3])) < CLOSE_M and angle_deg(off) < CLOSE_DEG)
