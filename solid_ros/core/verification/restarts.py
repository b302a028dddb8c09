"""Consistency restarts of the fine stage around a pose it settled on: is the pose a basin?

:func:`drift` (the ``unstable`` rule): the fine stage restarts from the pose moved one fine
voxel along the least constrained horizontal direction and turned, both ways, by 2 degrees or,
if less, the angle that moves the candidate's far points (the 90th percentile of their
horizontal range) by one fine voxel: together within the fine stage's reach of two voxels. A
true alignment sits in a basin and is found again, a spurious one slides away.

A second minimum along repeated structure (a street seen head-on, a row of shelves) 0.7-1.3 m
from the right pose holds its one-voxel basin as well as the right pose does, and passes: the
odometry check is the guard there (doc/verification.md, What no rule catches: why no search for
it runs).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from solid_ros.core.geometry import angle_deg, rot_z
from solid_ros.core.verification.judge import PROBE_DEG
from solid_ros.core.verification.prepared import Query, Source
from solid_ros.core.verification.registration import align_fine

__all__ = ['drift']

FloatArray = npt.NDArray[np.float64]

_PROBE_VOXELS = 1.0  # restart offset, in fine voxels (half the correspondence distance)
_FAR_PERCENTILE = 90.0  # the far points' range that bounds the turn


def drift(query: Query, src: Source, T_qm: FloatArray,
          info: FloatArray) -> tuple[float, float, float]:
    """Largest distance and angle between ``T_qm`` and two perturbed restarts, and the turn of
    the restarts in degrees: ``PROBE_DEG``, less where it would move the candidate's far points
    (90th percentile of their horizontal range from the query sensor) by more than
    ``_PROBE_VOXELS`` fine voxels: with the shift, no point moves beyond the fine stage's reach
    (two voxels); 2 degrees pushed the far structure of a narrow view that sees 30 m and more
    out of it, and right poses did not return.

    Args:
        query: the query on the pair's grid.
        src: the prepared candidate.
        T_qm: the pose (``p_query = T_qm p_match``).
        info: the support's rotation-first 6x6 information (sets the direction).
    """
    weak = _weak_direction(info)
    shift = _PROBE_VOXELS * query.settings.voxel
    xy = src.points[:, :2] @ T_qm[:2, :2].T + T_qm[:2, 3]
    far = float(np.percentile(np.linalg.norm(xy, axis=1), _FAR_PERCENTILE))
    turn = min(math.radians(PROBE_DEG), shift / max(far, 1e-6))
    worst_m = worst_deg = 0.0
    for sign in (1.0, -1.0):
        shake = np.eye(4)
        shake[:3, :3] = rot_z(sign * turn)
        shake[:2, 3] = sign * shift * weak
        again = align_fine(query, src, shake @ T_qm, query.settings)
        diff = np.linalg.inv(T_qm) @ again.T_qm
        worst_m = max(worst_m, float(np.linalg.norm(diff[:3, 3])))
        worst_deg = max(worst_deg, angle_deg(diff))
    return worst_m, worst_deg, math.degrees(turn)


def _weak_direction(info: FloatArray) -> FloatArray:
    """The least constrained horizontal direction (unit x, y) of a rotation-first 6x6
    information: where the restarts push."""
    out: FloatArray = np.linalg.eigh(info[3:5, 3:5])[1][:, 0]
    return out
