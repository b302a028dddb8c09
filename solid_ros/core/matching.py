"""Comparing descriptors: cosine distance of R-SOLiD, sub-bin heading from A-SOLiD."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import numpy.typing as npt

__all__ = ['cosine_distance', 'estimate_yaw', 'heading_hypotheses']

FloatArray = npt.NDArray[np.float64]


def cosine_distance(r_a: npt.ArrayLike, r_b: npt.ArrayLike) -> float:
    """Return 1 - cos(angle between r_a and r_b), in [0, 2].

    Two zero vectors are at distance 0; a zero vector and a non-zero one at distance 1.
    """
    a = np.asarray(r_a, dtype=np.float64)
    b = np.asarray(r_b, dtype=np.float64)
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if na == 0.0 or nb == 0.0:
        return 0.0 if na == nb else 1.0
    return min(max(1.0 - float(a @ b) / (na * nb), 0.0), 2.0)


def _shift_costs(a_query: npt.ArrayLike, a_candidate: npt.ArrayLike,
                 ) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """Score every circular shift; None when either signature is all zero.

    Returns:
        ``shifted`` (row s: the normalised query turned by s bins), the normalised
        candidate and the squared difference per shift.
    """
    a = np.asarray(a_query, dtype=np.float64)
    b = np.asarray(a_candidate, dtype=np.float64)
    n = a.shape[0]
    if a.shape != b.shape or a.ndim != 1 or n == 0:
        raise ValueError(f'A-SOLiD shapes differ or are not 1-D: {a.shape} vs {b.shape}')
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if na == 0.0 or nb == 0.0:
        return None
    shifted = (a / na)[_roll_index(n)]  # row s is the query turned by s bins
    b = b / nb
    cost = np.einsum('ij,ij->i', shifted - b, shifted - b)
    return shifted, b, cost


def _refine(shifted: FloatArray, b: FloatArray, cost: FloatArray, s: int) -> tuple[float, float]:
    """Sub-bin offset f in [-1, 1] at whole-bin shift s, and the cost of the blend there."""
    n = shifted.shape[0]
    best = shifted[s]
    resid = b - best
    frac, best_cost = 0.0, float(cost[s])
    for step in (1, -1):
        d = shifted[(s + step) % n] - best
        dd = float(d @ d)
        if dd <= 0.0:
            continue
        f = min(max(float(resid @ d) / dd, 0.0), 1.0)
        c = float(cost[s]) - f * f * dd
        if c < best_cost:
            frac, best_cost = step * f, c
    return frac, best_cost


def _shift_to_yaw(shift: float, n: int) -> float:
    deg = math.remainder(shift * 360.0 / n, 360.0)
    if deg <= -180.0:
        deg += 360.0
    return math.radians(deg)


def estimate_yaw(a_query: npt.ArrayLike, a_candidate: npt.ArrayLike) -> float:
    """Heading of the query sensor relative to the candidate, radians in (-pi, pi].

    Convention: p_candidate = Rz(yaw) p_query (CCW about +z), so an object the query sees at
    azimuth theta the candidate sees at theta + yaw.

    All N_a circular shifts are scored by the squared difference of the L2-normalised
    signatures; the best whole-bin shift s is then refined to s + f, f in [-1, 1], by the
    least-squares blend of the two neighbouring shifts, which is how a histogram changes when
    the scan turns by a fraction of a bin. The answer is therefore not quantised to 360/N_a.

    Args:
        a_query: A-SOLiD of the query scan, shape (N_a,).
        a_candidate: A-SOLiD of the candidate scan, same shape.

    Returns:
        Yaw in radians; 0.0 when either signature is all zero.
    """
    scored = _shift_costs(a_query, a_candidate)
    if scored is None:
        return 0.0
    shifted, b, cost = scored
    s = int(np.argmin(cost))
    frac, _ = _refine(shifted, b, cost, s)
    return _shift_to_yaw(s + frac, len(cost))


def heading_hypotheses(a_query: npt.ArrayLike, a_candidate: npt.ArrayLike,
                       count: int) -> list[tuple[float, float]]:
    """The ``count`` best distinct headings: local minima of the shift cost, best first.

    Every circular shift is scored as in :func:`estimate_yaw`; each local minimum of that
    circular cost curve (a plateau counts once) is refined below one bin the same way. They
    are ordered by the cost of their whole-bin shift, the order :func:`estimate_yaw` picks
    by, so the first yaw is exactly :func:`estimate_yaw`'s. Meant to seed registration with
    the alternatives when the best shift is wrong (repetitive scenes, narrow FOV).

    Args:
        a_query: heading signature of the query scan, shape (N_a,).
        a_candidate: heading signature of the candidate scan, same shape.
        count: most hypotheses returned (fewer when the curve has fewer minima).

    Returns:
        ``(yaw, cost)`` pairs: yaw in radians in (-pi, pi] with p_candidate = Rz(yaw)
        p_query, cost the squared difference of the normalised signatures at the refined
        shift, in [0, 4]. Empty when either signature is all zero or ``count`` < 1.

    Raises:
        ValueError: the signatures differ in shape or are not 1-D.
    """
    scored = _shift_costs(a_query, a_candidate)
    if scored is None or count < 1:
        return []
    shifted, b, cost = scored
    minima = _local_minima(cost)
    out = []
    for s in minima[:count]:
        frac, refined = _refine(shifted, b, cost, s)
        out.append((_shift_to_yaw(s + frac, len(cost)), max(refined, 0.0)))
    return out


def _local_minima(cost: FloatArray) -> list[int]:
    """Whole-bin shifts at local minima of the circular curve, lowest cost first.

    A run of equal values lower than the values on both sides counts once, at its lowest
    index; ties in cost go to the lower index, so the first entry is ``argmin(cost)``.
    """
    starts = np.flatnonzero(cost != np.roll(cost, 1)).tolist()
    if not starts:  # flat curve: every shift is as good
        return [0]
    minima = []
    for k, i in enumerate(starts):
        j = starts[(k + 1) % len(starts)]  # the run is i .. j - 1, circularly
        if cost[i - 1] > cost[i] and cost[j] > cost[i]:
            minima.append(0 if j <= i and j != 0 else i)  # a run through index 0 starts at 0
    minima.sort(key=lambda m: (float(cost[m]), m))
    return minima


@lru_cache(maxsize=8)
def _roll_index(n: int) -> npt.NDArray[np.intp]:
    """Index matrix whose row s gathers np.roll(v, s)."""
    i = np.arange(n)
    return (i[None, :] - i[:, None]) % n
