"""Place-recognition metrics from reference poses (pure numpy).

Definitions (scans are numbered 0..N-1 in replay order; every scan is also a query):

* Eligible: scan j is eligible for query q when the detector could return it: j < q, j was
  stored in the database, at least ``exclude_frames`` stored scans lie between them (j is not
  among the ``exclude_frames`` most recent stored scans) and, with ``exclude_sec``,
  stamp_q - stamp_j >= exclude_sec.
* True match: positions of q and j within ``radius`` metres (and, if ``max_heading_deg`` is
  given, headings within that many degrees).
* Query with a true loop (positive): some eligible scan is a true match.
* Each query's best match is its lowest-distance candidate, accepted or not.
* Recall@1: among positives, the fraction whose best match is a true match.
* PR curve: the threshold tau sweeps over the best distances. At tau a query's best is a
  TP if distance <= tau and it is a true match, an FP if distance <= tau and it is not; every
  positive that is not a TP is an FN. precision = TP / (TP + FP) (1 when nothing is predicted),
  recall = TP / positives. F1max is the best F1 over the sweep; its threshold is that tau.
  The zero-FP threshold is the largest tau with no FP.
* ROC AUC: each query's best is a binary classifier with score -distance and label "is a true
  match"; AUC is the Mann-Whitney probability that a true match scores higher than a false one
  (ties count one half).
* Yaw error: |wrap(yaw_detector - yaw_reference)| in degrees over true matches, where
  yaw_reference is the z-rotation of R_match^T R_query (convention p_match = Rz(yaw) p_query).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    'Evaluation', 'GroundTruth', 'PRCurve', 'evaluate', 'ground_truth', 'pr_curve',
    'recommend_threshold', 'relative_yaws', 'roc_auc', 'sweep_table', 'yaw_error_stats',
]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]


@dataclass(frozen=True)
class GroundTruth:
    """Which queries have a true loop.

    Attributes:
        has_loop: (N,) positives.
        nearest: (N,) closest eligible true match per query, -1 when none.
        valid: (N,) queries with a finite reference position (others are left out).
    """

    has_loop: BoolArray
    nearest: IntArray
    valid: BoolArray

    @property
    def num_positive(self) -> int:
        """Number of queries with a true loop."""
        return int(self.has_loop.sum())


def _headings(rotations: FloatArray | None) -> FloatArray | None:
    if rotations is None:
        return None
    return np.arctan2(rotations[:, 1, 0], rotations[:, 0, 0])


def _wrap(rad: npt.ArrayLike) -> FloatArray:
    return (np.asarray(rad, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def ground_truth(positions: npt.ArrayLike, *, radius: float = 5.0,
                 stored: npt.ArrayLike | None = None, stamps_ns: npt.ArrayLike | None = None,
                 exclude_frames: int = 0, exclude_sec: float = 0.0,
                 rotations: npt.ArrayLike | None = None, max_heading_deg: float | None = None,
                 block: int = 1024) -> GroundTruth:
    """Find the queries that have a true loop (see module docstring).

    Args:
        positions: (N, 3) reference positions, NaN rows where unknown.
        radius: true-match distance in metres.
        stored: (N,) scans inserted into the database (default: all).
        stamps_ns: (N,) stamps, needed when ``exclude_sec`` > 0.
        exclude_frames: the detector's exclusion window in stored scans.
        exclude_sec: the detector's exclusion window in seconds.
        rotations: (N, 3, 3) reference rotations, needed with ``max_heading_deg``.
        max_heading_deg: also require headings within this many degrees.
        block: queries per vectorised block (memory is block x N floats).
    """
    _check_gates(radius, max_heading_deg)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(pos)
    keep = np.ones(n, bool) if stored is None else np.asarray(stored, dtype=bool)
    before = np.concatenate(([0], np.cumsum(keep)))[:-1]  # stored scans before each index
    valid: BoolArray = np.asarray(np.isfinite(pos).all(axis=1), dtype=bool)
    stamps = None if stamps_ns is None else np.asarray(stamps_ns, dtype=np.int64)
    if exclude_sec > 0.0 and stamps is None:
        raise ValueError('exclude_sec needs stamps_ns')
    heads = None
    if max_heading_deg is not None:
        if rotations is None:
            raise ValueError('max_heading_deg needs rotations')
        heads = _headings(np.asarray(rotations, dtype=np.float64))
    has_loop = np.zeros(n, bool)
    nearest = np.full(n, -1, dtype=np.intp)
    idx = np.arange(n)
    for lo in range(0, n, block):
        q = idx[lo:lo + block]
        with np.errstate(invalid='ignore'):
            d = np.linalg.norm(pos[q, None, :] - pos[None, :, :], axis=2)
        ok = (d <= radius) & keep[None, :] & (idx[None, :] < q[:, None])
        ok &= (before[q][:, None] - before[None, :]) > exclude_frames
        if exclude_sec > 0.0 and stamps is not None:
            ok &= (stamps[q][:, None] - stamps[None, :]) >= round(exclude_sec * 1e9)
        if heads is not None and max_heading_deg is not None:
            dh = np.abs(_wrap(heads[q][:, None] - heads[None, :]))
            ok &= dh <= math.radians(max_heading_deg)
        has_loop[q] = ok.any(axis=1)
        d = np.where(ok, d, np.inf)
        near = np.argmin(d, axis=1)
        nearest[q] = np.where(has_loop[q], near, -1)
    has_loop &= valid
    return GroundTruth(has_loop, nearest, valid)


def _check_gates(radius: float, max_heading_deg: float | None) -> None:
    """NaN, infinite or negative gates would silently change every score."""
    if not 0.0 < radius < math.inf:
        raise ValueError(f'radius must be a positive number of metres, got {radius}')
    if max_heading_deg is not None and not 0.0 < max_heading_deg <= 180.0:
        raise ValueError(f'max_heading_deg must be in (0, 180], got {max_heading_deg}')


def true_matches(positions: npt.ArrayLike, query: npt.ArrayLike, match: npt.ArrayLike, *,
                 radius: float, rotations: npt.ArrayLike | None = None,
                 max_heading_deg: float | None = None) -> BoolArray:
    """Whether each (query, match) pair is a true match; match -1 is never one."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(query, dtype=np.intp)
    m = np.asarray(match, dtype=np.intp)
    have = m >= 0
    safe = np.where(have, m, 0)
    with np.errstate(invalid='ignore'):
        ok = have & (np.linalg.norm(pos[q] - pos[safe], axis=1) <= radius)
    if max_heading_deg is not None and rotations is not None:
        heads = _headings(np.asarray(rotations, dtype=np.float64))
        assert heads is not None
        ok &= np.abs(_wrap(heads[q] - heads[safe])) <= math.radians(max_heading_deg)
    out: npt.NDArray[np.bool_] = ok
    return out


@dataclass(frozen=True)
class PRCurve:
    """Precision and recall as the threshold sweeps over the sorted best distances.

    Entry k is the operating point tau = thresholds[k] (queries with distance <= tau are
    predicted). Ties share one entry.
    """

    thresholds: FloatArray
    precision: FloatArray
    recall: FloatArray
    tp: IntArray
    fp: IntArray
    num_positive: int

    @property
    def f1(self) -> FloatArray:
        """F1 at every operating point (0 where precision + recall is 0)."""
        s = self.precision + self.recall
        with np.errstate(invalid='ignore', divide='ignore'):
            return np.where(s > 0, 2 * self.precision * self.recall / np.where(s > 0, s, 1), 0.0)


def pr_curve(distance: npt.ArrayLike, correct: npt.ArrayLike, num_positive: int) -> PRCurve:
    """Build the PR curve (see module docstring).

    Args:
        distance: (M,) best distance of every query that has a best match.
        correct: (M,) whether that best match is a true match.
        num_positive: queries with a true loop (the recall denominator).
    """
    d = np.asarray(distance, dtype=np.float64)
    c = np.asarray(correct, dtype=bool)
    order = np.argsort(d, kind='stable')
    d, c = d[order], c[order]
    tp = np.cumsum(c)
    fp = np.cumsum(~c)
    last = np.flatnonzero(np.append(d[1:] != d[:-1], True)) if d.size else np.zeros(0, np.intp)
    tp, fp, thr = tp[last], fp[last], d[last]
    with np.errstate(invalid='ignore', divide='ignore'):
        precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), 1.0)
    recall = tp / num_positive if num_positive > 0 else np.zeros(len(tp))
    return PRCurve(thr, precision.astype(np.float64), recall.astype(np.float64),
                   tp.astype(np.intp), fp.astype(np.intp), int(num_positive))


def roc_auc(scores: npt.ArrayLike, labels: npt.ArrayLike) -> float:
    """Area under the ROC curve (Mann-Whitney, ties count 1/2); NaN with one class only."""
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return float('nan')
    order = np.argsort(s, kind='stable')
    ranks = np.empty(len(s))
    ss = s[order]
    # Average ranks over ties.
    starts = np.flatnonzero(np.concatenate(([True], ss[1:] != ss[:-1])))
    ends = np.append(starts[1:], len(ss))
    avg = (starts + ends - 1) / 2.0 + 1.0
    ranks[order] = np.repeat(avg, ends - starts)
    u = ranks[y].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def relative_yaws(rotations: npt.ArrayLike, query: npt.ArrayLike,
                  match: npt.ArrayLike) -> FloatArray:
    """Reference yaw z-rot(R_match^T R_query) for each pair, radians in (-pi, pi]."""
    r = np.asarray(rotations, dtype=np.float64)
    rel = np.einsum('nji,njk->nik', r[np.asarray(match)], r[np.asarray(query)])
    yaws: FloatArray = np.arctan2(rel[:, 1, 0], rel[:, 0, 0])
    return yaws


def yaw_error_stats(errors_deg: npt.ArrayLike) -> dict[str, float | int | None]:
    """Mean, median, 95th percentile and max of absolute yaw errors (None when empty)."""
    e = np.abs(np.asarray(errors_deg, dtype=np.float64))
    if e.size == 0:
        return {'mean': None, 'median': None, 'p95': None, 'max': None, 'count': 0}
    return {'mean': float(e.mean()), 'median': float(np.median(e)),
            'p95': float(np.percentile(e, 95)), 'max': float(e.max()), 'count': int(e.size)}


def recommend_threshold(curve: PRCurve, k: int) -> float:
    """A round YAML value that keeps operating point k: strictly in (tau_k, tau_{k+1}).

    The value must accept tau_k and reject the next distance whether the detector compares
    with < or <=, so it lies strictly between them; the shortest such decimal is returned.
    """
    lo = float(curve.thresholds[k])
    hi = float(curve.thresholds[k + 1]) if k + 1 < len(curve.thresholds) else lo + 0.01
    for digits in range(2, 12):
        step = 10.0 ** -digits
        cand = math.floor(lo / step + 1.0) * step
        cand = round(cand, digits)
        if lo < cand < hi:
            return cand
    return (lo + hi) / 2.0


@dataclass
class Evaluation:
    """All metrics of one replay; ``metrics()`` gives the JSON-ready summary."""

    truth: GroundTruth
    curve: PRCurve
    distance: FloatArray  # (N,) best distance per query
    correct: BoolArray  # (N,) best match is a true match
    has_best: BoolArray  # (N,) query has a best match
    accepted: BoolArray  # (N,) best match was accepted by the detector
    yaw_error_deg: FloatArray  # (N,) NaN where not a true match
    radius: float
    max_heading_deg: float | None
    extra: dict[str, Any] = field(default_factory=dict)

    def f1_max(self) -> tuple[float, float | None, int]:
        """(F1max, its threshold tau, curve index); (0, None, -1) with no TP at all."""
        f1 = self.curve.f1
        if f1.size == 0 or float(f1.max()) <= 0.0:
            return 0.0, None, -1
        k = int(np.argmax(f1))
        return float(f1[k]), float(self.curve.thresholds[k]), k

    def zero_fp(self) -> tuple[float | None, float, int]:
        """(largest tau with no FP, recall there, curve index); tau None if the first is FP."""
        ok = np.flatnonzero(self.curve.fp == 0)
        if ok.size == 0:
            return None, 0.0, -1
        k = int(ok[-1])
        return float(self.curve.thresholds[k]), float(self.curve.recall[k]), k

    def metrics(self) -> dict[str, Any]:
        """JSON-ready metrics (keys documented in doc/replay.md)."""
        pos = self.truth.has_loop
        n_pos = int(pos.sum())
        valid = self.truth.valid
        f1, f1_thr, k = self.f1_max()
        zfp, zfp_recall, kz = self.zero_fp()
        acc = self.accepted & self.has_best & valid
        tp_acc = int((acc & self.correct).sum())
        fp_acc = int((acc & ~self.correct).sum())
        labels = self.correct[self.has_best & valid]
        scores = -self._distances()
        auc = roc_auc(scores, labels)
        true_err = self.yaw_error_deg[np.isfinite(self.yaw_error_deg)]
        acc_err = self.yaw_error_deg[acc & np.isfinite(self.yaw_error_deg)]
        return {
            'queries': int(valid.sum()),
            'queries_with_true_loop': n_pos,
            'radius_m': self.radius,
            'max_heading_deg': self.max_heading_deg,
            'recall_at_1': float((pos & self.correct).sum() / n_pos) if n_pos else None,
            'f1_max': f1,
            'f1_max_threshold': f1_thr,
            'f1_max_precision': float(self.curve.precision[k]) if k >= 0 else None,
            'f1_max_recall': float(self.curve.recall[k]) if k >= 0 else None,
            'recommended_distance_threshold': (recommend_threshold(self.curve, k)
                                               if k >= 0 else None),
            'zero_fp_threshold': zfp,
            'zero_fp_recall': zfp_recall,
            'recommended_zero_fp_threshold': (recommend_threshold(self.curve, kz)
                                              if kz >= 0 else None),
            'roc_auc': None if math.isnan(auc) else auc,
            'accepted': {'count': int(acc.sum()), 'true': tp_acc, 'false': fp_acc,
                         'precision': tp_acc / (tp_acc + fp_acc) if tp_acc + fp_acc else None,
                         'recall': tp_acc / n_pos if n_pos else None},
            'yaw_error_deg': yaw_error_stats(true_err),
            'yaw_error_deg_accepted': yaw_error_stats(acc_err),
            **self.extra,
        }

    def _distances(self) -> FloatArray:
        return np.asarray(self.distance[self.has_best & self.truth.valid])


def evaluate(positions: npt.ArrayLike, best_match: npt.ArrayLike, best_distance: npt.ArrayLike,
             best_yaw: npt.ArrayLike, accepted: npt.ArrayLike, *, radius: float = 5.0,
             rotations: npt.ArrayLike | None = None, max_heading_deg: float | None = None,
             stored: npt.ArrayLike | None = None, stamps_ns: npt.ArrayLike | None = None,
             exclude_frames: int = 0, exclude_sec: float = 0.0,
             foreign: npt.ArrayLike | None = None) -> Evaluation:
    """Evaluate every query's best match against reference poses.

    Args:
        positions: (N, 3) reference positions per scan (NaN where unknown).
        best_match: (N,) scan index of each query's best match, -1 when none.
        best_distance: (N,) its distance (ignored where best_match is -1).
        best_yaw: (N,) its yaw estimate in radians.
        accepted: (N,) whether the detector accepted it.
        radius: true-match distance in metres.
        rotations: (N, 3, 3) reference rotations (yaw errors; heading gate).
        max_heading_deg: optional heading gate of the ground truth.
        stored, stamps_ns, exclude_frames, exclude_sec: the detector's eligibility rules
            (see :func:`ground_truth`).
        foreign: (N,) best match lies outside these poses (e.g. a loaded session); such a
            match counts, and always as false.
    """
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(pos)
    match = np.asarray(best_match, dtype=np.intp)
    dist = np.asarray(best_distance, dtype=np.float64)
    yaw = np.asarray(best_yaw, dtype=np.float64)
    acc = np.asarray(accepted, dtype=bool)
    for name, arr in (('best_match', match), ('best_distance', dist), ('best_yaw', yaw),
                      ('accepted', acc)):
        if arr.shape != (n,):
            raise ValueError(f'{name} has shape {arr.shape}, expected ({n},)')
    rot = None if rotations is None else np.asarray(rotations, dtype=np.float64)
    truth = ground_truth(pos, radius=radius, stored=stored, stamps_ns=stamps_ns,
                         exclude_frames=exclude_frames, exclude_sec=exclude_sec,
                         rotations=rot, max_heading_deg=max_heading_deg)
    other = np.zeros(n, bool) if foreign is None else np.asarray(foreign, dtype=bool)
    match = np.where(other, -1, match)
    has_best = ((match >= 0) | other) & np.isfinite(dist)
    correct = true_matches(pos, np.arange(n), match, radius=radius, rotations=rot,
                           max_heading_deg=max_heading_deg) & has_best & truth.valid
    sel = has_best & truth.valid
    curve = pr_curve(dist[sel], correct[sel], truth.num_positive)
    yaw_err = np.full(n, np.nan)
    if rot is not None and correct.any():
        q = np.flatnonzero(correct)
        ref = relative_yaws(rot, q, match[q])
        yaw_err[q] = np.degrees(np.abs(_wrap(yaw[q] - ref)))
    return Evaluation(truth, curve, dist, correct, has_best, acc, yaw_err, radius,
                      max_heading_deg)


def sweep_table(ev: Evaluation, rows: int = 12) -> list[dict[str, float | int]]:
    """Operating points for a threshold table: evenly spread over recall, plus F1max and 0-FP.

    Each row has threshold (a pasteable YAML value), precision, recall, f1, tp, fp.
    """
    c = ev.curve
    if c.thresholds.size == 0:
        return []
    picks = set(np.unique(np.linspace(0, len(c.thresholds) - 1, rows).round().astype(int)))
    for k in (ev.f1_max()[2], ev.zero_fp()[2]):
        if k >= 0:
            picks.add(k)
    f1 = c.f1
    return [{'threshold': recommend_threshold(c, k), 'distance': float(c.thresholds[k]),
             'precision': float(c.precision[k]), 'recall': float(c.recall[k]),
             'f1': float(f1[k]), 'tp': int(c.tp[k]), 'fp': int(c.fp[k])}
            for k in sorted(picks)]
