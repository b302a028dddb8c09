"""Scoring published loops by their relative pose, and the sweep for a target precision.

Definitions (keyframes numbered 0..K-1 in replay order; ``ref`` their reference poses):

* The reference relative pose of a loop (query q, match m) is ``T_ref = inv(ref[m]) @
  ref[q]``. A loop is correct when its pose ``T`` is within ``max_error_m`` metres and
  ``max_error_deg`` degrees of ``T_ref`` (translation of ``inv(T_ref) @ T`` and its rotation
  angle). A loop against a loaded session has no reference pose and counts as false.
* Precision: correct published loops / published loops.
* Recall: among queries with a true loop (an earlier keyframe outside the exclusion window
  within the radius; :func:`solid_ros.tools.evaluation.ground_truth`), the fraction with at
  least one correct published loop.
* Sweep (with verification): at a ``verify_min_overlap`` of ``t`` the published loops are
  taken to be the attempts that reached the overlap test and passed every other test (the
  published, verified ones) whose recorded structure overlap is at least ``t``; precision and
  recall are computed over them as above. At the configured value this is exactly what was
  published. The recommended ``verify_min_overlap`` is the smallest ``t`` (keeping a loop)
  whose precision reaches the target. It is estimated from the recorded scores: a stricter
  value could have let a later candidate of the same query be tried and verified, or (with
  ``min_loop_gap``) a later query publish, which the recording does not show; and values
  below the configured one cannot be estimated (candidates refused for low overlap were never
  put through the later tests).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ['LoopRecord', 'overlap_sweep', 'pose_error', 'score_loops']

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class LoopRecord:
    """One candidate a keyframe looked at, with its verdict and, when known, its error.

    Attributes:
        query: keyframe index of the query.
        match: keyframe index of the match (its own session's index).
        session: session of the match.
        published: the detector published it.
        verified: registration verified it.
        reason: the detector's reason (``verified``, ``descriptor`` or the failed test).
        overlap: structure overlap (NaN when no fine registration ran).
        distance: descriptor distance.
        trans_err_m: translation error against the reference (NaN: unknown).
        rot_err_deg: rotation error against the reference (NaN: unknown).
        gt_distance_m: reference distance between the two keyframes (NaN: unknown).
    """

    query: int
    match: int
    session: int
    published: bool
    verified: bool
    reason: str
    overlap: float
    distance: float
    trans_err_m: float
    rot_err_deg: float
    gt_distance_m: float

    def correct(self, max_error_m: float, max_error_deg: float) -> bool:
        """Whether its pose is within the limits of the reference pose."""
        return bool(self.trans_err_m < max_error_m and self.rot_err_deg < max_error_deg)


def pose_error(T: npt.ArrayLike, T_ref: npt.ArrayLike) -> tuple[float, float]:
    """Translation (m) and rotation angle (deg) of ``inv(T_ref) @ T``; NaN if unknown."""
    a = np.asarray(T, dtype=np.float64)
    b = np.asarray(T_ref, dtype=np.float64)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return math.nan, math.nan
    d = np.linalg.solve(b, a)
    cos = min(max((float(np.trace(d[:3, :3])) - 1.0) / 2.0, -1.0), 1.0)
    return float(np.linalg.norm(d[:3, 3])), math.degrees(math.acos(cos))


def _stats(values: Sequence[float]) -> dict[str, float | int | None]:
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return {'median': None, 'p95': None, 'max': None, 'count': 0}
    return {'median': float(np.median(v)), 'p95': float(np.percentile(v, 95)),
            'max': float(v.max()), 'count': int(v.size)}


def score_loops(records: Sequence[LoopRecord], positives: npt.ArrayLike, *,
                max_error_m: float = 1.0, max_error_deg: float = 3.0) -> dict[str, Any]:
    """Precision, recall and pose errors of the published loops (see module docstring).

    Args:
        records: every candidate looked at.
        positives: (K,) queries with a true loop.
        max_error_m: translation limit of a correct loop.
        max_error_deg: rotation limit of a correct loop.
    """
    pos = np.asarray(positives, dtype=bool)
    published = [r for r in records if r.published]
    good = [r for r in published if r.correct(max_error_m, max_error_deg)]
    found = {r.query for r in good if 0 <= r.query < len(pos) and pos[r.query]}
    n_pos = int(pos.sum())
    verified_rejected = Counter(r.reason for r in records)
    return {
        'published': len(published),
        'correct': len(good),
        'false': len(published) - len(good),
        'precision': len(good) / len(published) if published else None,
        'recall': len(found) / n_pos if n_pos else None,
        'queries_with_true_loop': n_pos,
        'queries_with_correct_loop': len(found),
        'max_error_m': max_error_m,
        'max_error_deg': max_error_deg,
        'trans_err_m': _stats([r.trans_err_m for r in good]),
        'rot_err_deg': _stats([r.rot_err_deg for r in good]),
        'reasons': dict(sorted(verified_rejected.items())),
    }


def overlap_sweep(records: Sequence[LoopRecord], positives: npt.ArrayLike, current: float, *,
                  target_precision: float = 1.0, max_error_m: float = 1.0,
                  max_error_deg: float = 3.0) -> dict[str, Any]:
    """Precision and recall as ``verify_min_overlap`` rises from ``current``.

    Returns:
        ``rows`` (threshold, precision, recall, tp, fp), ``recommended`` (the smallest
        threshold reaching ``target_precision``; None when none does) and ``recall`` (the
        recall there).
    """
    pos = np.asarray(positives, dtype=bool)
    n_pos = int(pos.sum())
    passed = [r for r in records if r.published and r.verified and math.isfinite(r.overlap)]
    levels = sorted({round(current, 4)} | {math.floor(r.overlap * 100) / 100 + 0.01
                                           for r in passed if r.overlap >= current})
    rows = []
    recommended = None
    recall: float | None = None
    for t in levels:
        kept = [r for r in passed if r.overlap >= t]
        good = [r for r in kept if r.correct(max_error_m, max_error_deg)]
        tp, fp = len(good), len(kept) - len(good)
        found = {r.query for r in good if 0 <= r.query < len(pos) and pos[r.query]}
        precision = tp / (tp + fp) if tp + fp else 1.0
        rows.append({'threshold': round(t, 4), 'precision': precision,
                     'recall': len(found) / n_pos if n_pos else 0.0, 'tp': tp, 'fp': fp})
        if recommended is None and precision >= target_precision and tp > 0:
            recommended = round(t, 4)
            recall = rows[-1]['recall']
    return {'parameter': 'verify_min_overlap', 'target_precision': target_precision,
            'rows': rows, 'recommended': recommended, 'recall': recall}
