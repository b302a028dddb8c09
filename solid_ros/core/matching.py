"""Comparing descriptors: cosine distance of R-SOLiD, sub-bin heading from A-SOLiD."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import numpy.typing as npt

__all__ = ['cosine_distance', 'estimate_yaw']


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
    a = np.asarray(a_query, dtype=np.float64)
    b = np.asarray(a_candidate, dtype=np.float64)
    n = a.shape[0]
    if a.shape != b.shape or a.ndim != 1 or n == 0:
        raise ValueError(f'A-SOLiD shapes differ or are not 1-D: {a.shape} vs {b.shape}')
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if na == 0.0 or nb == 0.0:
        return 0.0
    shifted = (a / na)[_roll_index(n)]  # row s is the query turned by s bins
    b = b / nb
    cost = np.einsum('ij,ij->i', shifted - b, shifted - b)
    s = int(np.argmin(cost))
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
    deg = math.remainder((s + frac) * 360.0 / n, 360.0)
    if deg <= -180.0:
        deg += 360.0
    return math.radians(deg)


@lru_cache(maxsize=8)
def _roll_index(n: int) -> npt.NDArray[np.intp]:
    """Index matrix whose row s gathers np.roll(v, s)."""
    i = np.arange(n)
    return (i[None, :] - i[:, None]) % n
