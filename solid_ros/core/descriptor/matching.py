"""Comparing descriptors: cosine distance of R-SOLiD, sub-bin heading from A-SOLiD."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import numpy.typing as npt

__all__ = ['HEADING_MODES', 'cosine_distance', 'estimate_yaw', 'heading_hypotheses']

FloatArray = npt.NDArray[np.float64]


def cosine_distance(r_a: npt.ArrayLike, r_b: npt.ArrayLike) -> float:
    """Return 1 - cos(angle between r_a and r_b), in [0, 2].

    Two zero vectors are at distance 0; a zero vector and a non-zero one at distance 1.
    """
    a = np.asarray(r_a, dtype=np.float64)
    b = np.asarray(r_b, dtype=np.float64)
    # Scalar math on three dot products: numpy's per-call overhead dominates 40 bins.
    aa, bb = float(a.dot(a)), float(b.dot(b))
    if aa == 0.0 or bb == 0.0:
        return 0.0 if aa == bb else 1.0
    return min(max(1.0 - float(a.dot(b)) / (math.sqrt(aa) * math.sqrt(bb)), 0.0), 2.0)


class _ShiftScores:
    """Cost of every circular shift of the query signature against the candidate's.

    With u_s the L2-normalised query turned by s bins and v the normalised candidate, the
    cost of shift s is |u_s - v|^2 = 2 - 2 u_s . v, so one matrix-vector product of the
    shifted query with the candidate scores all shifts. The sub-bin refinement needs only
    these correlations and the query's lag-1 autocorrelation rho = u_s . u_(s+1), the same
    for every s (see :meth:`refine`).
    """

    __slots__ = ('corr', 'rho', 'n')

    def __init__(self, a: FloatArray, b: FloatArray, aa: float, bb: float) -> None:
        self.n = a.shape[0]
        shifted = a[_roll_index(self.n)]  # row s is the query turned by s bins
        self.corr: FloatArray = shifted.dot(b)
        self.corr *= 1.0 / (math.sqrt(aa) * math.sqrt(bb))
        self.rho = float(shifted[1].dot(a)) / aa if self.n > 1 else 1.0

    def cost(self) -> FloatArray:
        """Cost per whole-bin shift, in [0, 4]."""
        out: FloatArray = 2.0 - 2.0 * self.corr
        return out

    def best(self) -> int:
        """The whole-bin shift of least cost."""
        return int(self.corr.argmax())

    def refine(self, s: int) -> tuple[float, float]:
        """Sub-bin offset f in [-1, 1] at shift s, and the cost there.

        The candidate is fitted by the blend (1 - |f|) u_s + |f| u_(s+-1), which is how a
        histogram changes when the scan turns by a fraction of a bin. With d = u_(s+-1) - u_s
        and r = v - u_s: d . d = 2 - 2 rho, r . d = corr(s+-1) - corr(s) - rho + 1, and the
        least-squares f = clip(r . d / d . d, 0, 1) lowers the cost by f^2 d . d.
        """
        corr, n = self.corr, self.n
        c0 = float(corr[s])
        cost0 = 2.0 - 2.0 * c0
        dd = 2.0 - 2.0 * self.rho
        frac, best_cost = 0.0, cost0
        if dd <= 0.0:
            return frac, best_cost
        for step in (1, -1):
            f = min(max((float(corr[(s + step) % n]) - c0 - self.rho + 1.0) / dd, 0.0), 1.0)
            c = cost0 - f * f * dd
            if c < best_cost:
                frac, best_cost = step * f, c
        return frac, best_cost


class _OverlapScores:
    """Shift scores over the bins both scans see, for views narrower than 360 degrees.

    The whole-signature cost favours the shift that lines up the two fields of view rather
    than the scenes in them: when the heading changed by more than about half the FOV, the
    true shift overlaps the views only in part and loses to shift 0. Here shift s is scored
    only on the bins where the turned query and the candidate are both non-zero, by the
    Pearson correlation r of the two over those k bins, as the Fisher z-score
    atanh(r) * sqrt(k - 2): a correlation over few bins counts for less, and shifts with
    fewer than ``min_bins`` common bins are not considered. The best shift is refined below
    one bin like the full search, with the blend restricted to the common bins.
    """

    __slots__ = ('a', 'b', 'shifted', 'seen', 'score', 'n')

    def __init__(self, a: FloatArray, b: FloatArray, min_bins: int) -> None:
        n = self.n = a.shape[0]
        idx = _roll_index(n)
        self.a, self.b = a, b
        self.shifted = a[idx]
        seen_a = (a > 0.0).astype(np.float64)
        seen_b = (b > 0.0).astype(np.float64)
        self.seen = seen_a[idx] * seen_b  # row s: bins both see at shift s
        k = self.seen.sum(axis=1)
        sx = self.shifted.dot(seen_b)  # the query is zero outside its own view
        sxx = (self.shifted * self.shifted).dot(seen_b)
        sy = seen_a[idx].dot(b)
        syy = seen_a[idx].dot(b * b)
        sxy = self.shifted.dot(b)
        vx = k * sxx - sx * sx
        vy = k * syy - sy * sy
        valid = (k >= min_bins) & (vx > 1e-12 * k * sxx) & (vy > 1e-12 * k * syy)
        score = np.full(n, -np.inf)
        r = (k * sxy - sx * sy)[valid] / np.sqrt(vx[valid] * vy[valid])
        score[valid] = np.arctanh(np.clip(r, -1.0 + 1e-12, 1.0 - 1e-12)) * np.sqrt(
            k[valid] - 2.0)
        self.score = score

    def usable(self) -> bool:
        """Whether any shift has enough common bins with some variation in them."""
        return bool(np.isfinite(self.score).any())

    def best(self) -> int:
        """The whole-bin shift of highest score."""
        return int(self.score.argmax())

    def refine(self, s: int) -> tuple[float, float]:
        """Sub-bin offset f in [-1, 1] at shift s and the squared difference there.

        The blend of :meth:`_ShiftScores.refine`, on the bins seen at both s and s +- 1,
        each vector L2-normalised over those bins.
        """
        frac, gain, cost = 0.0, 0.0, math.nan
        for step in (1, -1):
            t = (s + step) % self.n
            common = (self.seen[s] * self.seen[t]) > 0.0
            u0, u1, v = self.shifted[s, common], self.shifted[t, common], self.b[common]
            n0, n1, nv = (math.sqrt(float(w.dot(w))) for w in (u0, u1, v))
            if min(n0, n1, nv) == 0.0:
                continue
            resid, d = v / nv - u0 / n0, u1 / n1 - u0 / n0
            cost0, dd = float(resid.dot(resid)), float(d.dot(d))
            if math.isnan(cost):
                cost = cost0
            if dd > 0.0:
                f = min(max(float(resid.dot(d)) / dd, 0.0), 1.0)
                if f * f * dd > gain:
                    frac, gain, cost = step * f, f * f * dd, cost0 - f * f * dd
        return frac, (2.0 if math.isnan(cost) else cost)


HEADING_MODES = ('full', 'overlap')


def _scores(a_query: npt.ArrayLike, a_candidate: npt.ArrayLike, mode: str,
            min_overlap_deg: float) -> _ShiftScores | _OverlapScores | None:
    """Score every shift; None when either signature is all zero."""
    a = np.asarray(a_query, dtype=np.float64)
    b = np.asarray(a_candidate, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or a.shape[0] == 0:
        raise ValueError(f'A-SOLiD shapes differ or are not 1-D: {a.shape} vs {b.shape}')
    if mode not in HEADING_MODES:
        raise ValueError(f'heading mode {mode!r} is not one of {HEADING_MODES}')
    aa, bb = float(a.dot(a)), float(b.dot(b))
    if aa == 0.0 or bb == 0.0:
        return None
    # Both views all around: every bin is common, and the paper's search is the answer.
    if mode == 'overlap' and not (a.all() and b.all()):
        n = a.shape[0]
        min_bins = max(3, math.ceil(min_overlap_deg * n / 360.0 - 1e-9))
        overlap = _OverlapScores(a, b, min_bins)
        if overlap.usable():
            return overlap
    return _ShiftScores(a, b, aa, bb)


def _shift_to_yaw(shift: float, n: int) -> float:
    deg = math.remainder(shift * 360.0 / n, 360.0)
    if deg <= -180.0:
        deg += 360.0
    return math.radians(deg)


def estimate_yaw(a_query: npt.ArrayLike, a_candidate: npt.ArrayLike, mode: str = 'full',
                 min_overlap_deg: float = 24.0) -> float:
    """Heading of the query sensor relative to the candidate, radians in (-pi, pi].

    Convention: p_candidate = Rz(yaw) p_query (CCW about +z), so an object the query sees at
    azimuth theta the candidate sees at theta + yaw.

    ``mode='full'`` (the paper): all N_a circular shifts are scored by the squared
    difference of the L2-normalised signatures; the best whole-bin shift s is then refined
    to s + f, f in [-1, 1], by the least-squares blend of the two neighbouring shifts, which
    is how a histogram changes when the scan turns by a fraction of a bin. The answer is
    therefore not quantised to 360/N_a.

    ``mode='overlap'`` (narrow fields of view): each shift is scored only on the bins both
    scans see (non-zero in both), by a correlation that counts fewer common bins for less;
    shifts with less than ``min_overlap_deg`` in common are skipped (see
    :class:`_OverlapScores`). When both signatures are non-zero all around, or no shift has
    enough in common, it is the full search.

    Args:
        a_query: A-SOLiD (heading signature) of the query scan, shape (N_a,).
        a_candidate: that of the candidate scan, same shape.
        mode: 'full' or 'overlap'.
        min_overlap_deg: with 'overlap', least common view of a shift, degrees (at least
            3 bins).

    Returns:
        Yaw in radians; 0.0 when either signature is all zero.

    Raises:
        ValueError: the signatures differ in shape or are not 1-D, or an unknown mode.
    """
    scores = _scores(a_query, a_candidate, mode, min_overlap_deg)
    if scores is None:
        return 0.0
    s = scores.best()
    frac, _ = scores.refine(s)
    return _shift_to_yaw(s + frac, scores.n)


def heading_hypotheses(a_query: npt.ArrayLike, a_candidate: npt.ArrayLike, count: int,
                       mode: str = 'full',
                       min_overlap_deg: float = 24.0) -> list[tuple[float, float]]:
    """The ``count`` best distinct headings: local minima of the shift cost, best first.

    Every circular shift is scored as in :func:`estimate_yaw` (same ``mode``); each local
    optimum of that circular curve (a plateau counts once) is refined below one bin the same
    way. They are ordered by the score of their whole-bin shift, the order
    :func:`estimate_yaw` picks by, so the first yaw is exactly :func:`estimate_yaw`'s. Meant
    to seed registration with the alternatives when the best shift is wrong (repetitive
    scenes, narrow FOV).

    Args:
        a_query: heading signature of the query scan, shape (N_a,).
        a_candidate: heading signature of the candidate scan, same shape.
        count: most hypotheses returned (fewer when the curve has fewer optima).
        mode: 'full' or 'overlap', as in :func:`estimate_yaw`.
        min_overlap_deg: as in :func:`estimate_yaw`.

    Returns:
        ``(yaw, cost)`` pairs: yaw in radians in (-pi, pi] with p_candidate = Rz(yaw)
        p_query, cost the squared difference of the normalised signatures at the refined
        shift (with 'overlap', over the bins both see there), in [0, 4]. Empty when either
        signature is all zero or ``count`` < 1.

    Raises:
        ValueError: the signatures differ in shape or are not 1-D, or an unknown mode.
    """
    scores = _scores(a_query, a_candidate, mode, min_overlap_deg)
    if scores is None or count < 1:
        return []
    curve = scores.cost() if isinstance(scores, _ShiftScores) else -scores.score
    out: list[tuple[float, float]] = []
    for s in _local_minima(curve):
        if len(out) == count or not math.isfinite(float(curve[s])):
            break
        frac, refined = scores.refine(s)
        out.append((_shift_to_yaw(s + frac, scores.n), max(refined, 0.0)))
    return out


def _local_minima(cost: FloatArray) -> list[int]:
    """Whole-bin shifts at local minima of the circular curve, lowest cost first.

    A run of equal values lower than the values on both sides counts once, at its lowest
    index; ties in cost go to the lower index, so the first entry is ``argmin(cost)``.
    """
    c = cost.tolist()  # Python floats: the scan below reads single values
    starts = [i for i in range(len(c)) if c[i] != c[i - 1]]
    if not starts:  # flat curve: every shift is as good
        return [0]
    minima = []
    for k, i in enumerate(starts):
        j = starts[(k + 1) % len(starts)]  # the run is i .. j - 1, circularly
        if c[i - 1] > c[i] and c[j] > c[i]:
            minima.append(0 if j <= i and j != 0 else i)  # a run through index 0 starts at 0
    minima.sort(key=lambda m: (c[m], m))
    return minima


@lru_cache(maxsize=8)
def _roll_index(n: int) -> npt.NDArray[np.intp]:
    """Index matrix whose row s gathers np.roll(v, s)."""
    i = np.arange(n)
    return (i[None, :] - i[:, None]) % n
