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
* Revisit recall (:func:`revisits`, :func:`revisit_recall`): a keyframe revisits when an
  earlier keyframe lies within ``radius`` (5 m) of it in the reference poses after at least
  ``min_path_m`` (30 m) of reference path driven from that keyframe to it (optionally also
  within ``max_heading_deg``); revisit recall is the fraction of revisiting keyframes with at
  least one correct published loop (to any keyframe). It does not depend on the detector's
  exclusion window, so runs with different settings, and other systems, count alike.
* By source: published and correct loops per :attr:`LoopRecord.source` (``descriptor`` or
  ``graph``, :mod:`solid_ros.core.candidates.position`).
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

__all__ = ['REVISIT_MIN_PATH_M', 'REVISIT_RADIUS_M', 'LoopRecord', 'overlap_sweep',
           'pose_error', 'revisit_recall', 'revisits', 'score_loops']

REVISIT_RADIUS_M = 5.0
REVISIT_MIN_PATH_M = 30.0

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
        source: what proposed it (``descriptor`` or ``graph``).
        coarse_overlap: the coarse stage's overlap (NaN: not registered). Zero: the
            registration found nothing in common, so its pose is its unmoved start (the
            graph's guess), not a measurement.
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
    source: str = 'descriptor'
    coarse_overlap: float = math.nan

    def correct(self, max_error_m: float, max_error_deg: float) -> bool:
        """Whether its pose is within the limits of the reference pose."""
        return bool(self.trans_err_m < max_error_m and self.rot_err_deg < max_error_deg)

    @property
    def measured(self) -> bool:
        """Whether its pose came from a registration that found common structure (a pair
        that shares no view keeps the start it was given: no measured pose)."""
        return not self.coarse_overlap == 0.0


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
    by_source = {src: {'published': sum(r.source == src for r in published),
                       'correct': sum(r.source == src for r in good)}
                 for src in sorted({r.source for r in published})}
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
        'by_source': by_source,
    }


def revisits(positions: npt.ArrayLike, *, radius: float = REVISIT_RADIUS_M,
             min_path_m: float = REVISIT_MIN_PATH_M, rotations: npt.ArrayLike | None = None,
             max_heading_deg: float | None = None) -> npt.NDArray[np.bool_]:
    """Which keyframes revisit a place (see the module docstring).

    Args:
        positions: (K, 3) reference positions in keyframe order (NaN rows: unknown; the path
            over them is the straight line between the known neighbours).
        radius: an earlier keyframe this close is the same place, metres.
        min_path_m: ... once at least this much reference path was driven since it.
        rotations: (K, 3, 3) reference rotations, needed with ``max_heading_deg``.
        max_heading_deg: also require headings within this many degrees.
    """
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    known = np.isfinite(pos).all(axis=1)
    path = np.full(len(pos), np.nan)
    if known.any():
        p = pos[known]
        path[known] = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0),
                                                                      axis=1))))
    heads = None
    if max_heading_deg is not None and rotations is not None:
        r = np.asarray(rotations, dtype=np.float64)
        heads = np.arctan2(r[:, 1, 0], r[:, 0, 0])
    out = np.zeros(len(pos), dtype=bool)
    for q in np.flatnonzero(known):
        with np.errstate(invalid='ignore'):
            ok = (np.linalg.norm(pos[:q] - pos[q], axis=1) <= radius) & (
                path[q] - path[:q] >= min_path_m)
            if heads is not None and max_heading_deg is not None:
                turn = np.abs((heads[:q] - heads[q] + np.pi) % (2 * np.pi) - np.pi)
                ok &= turn <= math.radians(max_heading_deg)
        out[q] = bool(ok.any())
    return out


def revisit_recall(records: Sequence[LoopRecord], revisiting: npt.ArrayLike, *,
                   max_error_m: float = 1.0, max_error_deg: float = 3.0) -> dict[str, Any]:
    """Revisiting keyframes, those with a correct published loop, and their ratio."""
    rev = np.asarray(revisiting, dtype=bool)
    found = {r.query for r in records if r.published and r.correct(max_error_m, max_error_deg)
             and 0 <= r.query < len(rev) and rev[r.query]}
    n = int(rev.sum())
    return {'revisiting': n, 'found': len(found), 'recall': len(found) / n if n else None}


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
