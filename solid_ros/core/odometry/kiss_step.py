"""One KISS-ICP step split in two, so a registration is checked before KISS-ICP keeps it.

``KissICP.register_frame`` deskews, voxelises, aligns the cloud to the local map from the
constant-velocity guess, then updates its threshold, map and motion. :func:`align` does the
first half and :func:`commit` the second, with KISS-ICP's own objects and in its order: a cloud
aligned from KISS-ICP's guess and committed gets exactly ``register_frame``'s pose. In between
the caller checks the registration; one that fails leaves no trace in the map, and it may be
aligned again from another guess (:func:`guesses`): the keyframes of a recording are not
evenly spaced in time (riv281: 0.3-21 s apart), and a constant velocity per cloud then guesses
the step several times too short or too long.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

__all__ = ['Aligned', 'align', 'commit', 'guesses', 'prepared']

FloatArray = npt.NDArray[np.float64]

_RATIO_APART = 0.25  # a time-scaled guess is tried when the spacing changed by more than this


@dataclass(frozen=True)
class Aligned:
    """A registration not yet kept.

    Attributes:
        pose: KISS-ICP frame <- sensor.
        guess: the initial guess it was aligned from.
        map_points: the cloud as KISS-ICP adds it to its map (deskewed, voxelised).
    """

    pose: FloatArray
    guess: FloatArray
    map_points: Any


def guesses(kiss: Any, ratio: float | None) -> list[tuple[str, FloatArray]]:
    """Initial guesses to align from, KISS-ICP's own first.

    Args:
        kiss: the KissICP object.
        ratio: time since the last cloud over the time between the two before (None:
            unknown).

    Returns:
        ('constant velocity', KISS-ICP's guess), then ('time-scaled', the same motion scaled
        by ``ratio``) when the spacing changed, and ('standstill', the last pose).
    """
    last = np.asarray(kiss.last_pose, dtype=np.float64)
    delta = np.asarray(kiss.last_delta, dtype=np.float64)
    out = [('constant velocity', last @ delta)]
    if ratio is not None and np.isfinite(ratio) and abs(ratio - 1.0) > _RATIO_APART:
        scaled = np.eye(4)
        rotvec = Rotation.from_matrix(delta[:3, :3]).as_rotvec()
        scaled[:3, :3] = Rotation.from_rotvec(rotvec * ratio).as_matrix()
        scaled[:3, 3] = delta[:3, 3] * ratio
        out.append(('time-scaled', last @ scaled))
    out.append(('standstill', last.copy()))
    return out


def prepared(kiss: Any, frame: FloatArray, times: FloatArray) -> tuple[Any, Any]:
    """KISS-ICP's deskew and voxelisation: (points to align, points for the map)."""
    deskewed = kiss.preprocessor.preprocess(frame, times, kiss.last_delta)
    source, map_points = kiss.voxelize(deskewed)
    return source, map_points


def align(kiss: Any, source: Any, map_points: Any, guess: FloatArray) -> Aligned:
    """Align ``source`` to KISS-ICP's map from ``guess``, as ``register_frame`` does."""
    sigma = kiss.adaptive_threshold.get_threshold()
    pose = kiss.registration.align_points_to_map(
        points=source, voxel_map=kiss.local_map, initial_guess=guess,
        max_correspondance_distance=3 * sigma, kernel=sigma)
    return Aligned(np.array(pose, dtype=np.float64), guess, map_points)


def commit(kiss: Any, step: Aligned, motion: bool = True) -> None:
    """Keep an aligned cloud: KISS-ICP's threshold, map, motion and pose updates (``motion``
    False: its motion stays what it was, for a standstill guess kept after a gap in time)."""
    kiss.adaptive_threshold.update_model_deviation(np.linalg.inv(step.guess) @ step.pose)
    kiss.local_map.update(step.map_points, step.pose)
    if motion:
        kiss.last_delta = np.linalg.inv(kiss.last_pose) @ step.pose
    kiss.last_pose = step.pose
