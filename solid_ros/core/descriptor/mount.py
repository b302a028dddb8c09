"""The sensor's mounting: from the sensor frame to the levelled frame the descriptor bins in.

A tilted mount (``mount_roll_deg``, ``mount_pitch_deg``, ``mount_yaw_deg``) is undone before
describing and registering, so that elevation bins and the coarse stage's ground see a level
sensor. Loops are found between levelled frames and reported between the sensor frames; this
module is the one place that converts points, poses and covariances between the two.

A sensor that tilts as it moves (carried by hand, on a legged robot) is levelled per scan only
for a tight-space keyframe cloud's voxel grid (:meth:`Mount.upright`); its frames stay those
above.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.geometry import matrix_to_vector, rot_z, rpy_matrix, vector_to_matrix, yaw_of

__all__ = ['Mount']

FloatArray = npt.NDArray[np.float64]

# Tilt of the levelled frame from the odometry's up below which the grid stays the sensor's:
# a car's or a level-held sensor's clouds are kept exactly as before.
UPRIGHT_MIN_DEG = 2.0


class Mount:
    """The mount rotation ``M`` (levelled = ``M`` sensor) of one configuration.

    Args:
        config: its ``mount_roll_deg``, ``mount_pitch_deg`` and ``mount_yaw_deg``.
    """

    def __init__(self, config: SolidConfig) -> None:
        self.R = rpy_matrix(math.radians(config.mount_roll_deg),
                            math.radians(config.mount_pitch_deg),
                            math.radians(config.mount_yaw_deg))
        self.levelled = not np.allclose(self.R, np.eye(3))

    def level(self, points: npt.ArrayLike) -> npt.ArrayLike:
        """Points (N, 3+) in the levelled frame (as given without a tilt; a malformed array
        as given, for describe() to report)."""
        if not self.levelled:
            return points
        arr = np.asarray(points)
        if arr.ndim != 2 or arr.shape[1] < 3:
            return arr
        out: FloatArray = arr[:, :3].astype(np.float64) @ self.R.T
        return out

    def upright(self, pose: FloatArray | None) -> FloatArray | None:
        """Rotation (3x3) from the levelled frame to the odometry's upright one at ``pose``
        (the sensor's, ``x y z qx qy qz qw``), None without a pose or under
        :data:`UPRIGHT_MIN_DEG` of tilt.

        A tight-space keyframe cloud is voxelised in that frame (and rotated back): on a grid
        that tilts with the hand, a vertical edge crosses the voxel columns at a slant, its
        centroids zigzag off the edge, and a right alignment of two scans held at different
        tilts looks like free-space conflict (simulated room walks with 8 degrees of hand
        tilt, see doc/verification.md, Tight spaces). Open scenes keep the sensor's grid: on hku1
        (hand-held, pitching by 20 degrees) an upright grid gave no more loops.
        """
        if pose is None:
            return None
        world_level = vector_to_matrix(pose)[:3, :3] @ self.R.T
        up: FloatArray = rot_z(yaw_of(world_level)).T @ world_level
        if float(up[2, 2]) > math.cos(math.radians(UPRIGHT_MIN_DEG)):
            return None
        return up

    def to_sensor(self, point: FloatArray) -> FloatArray:
        """A levelled-frame point (3-vector), or points (N, 3), in the sensor frame."""
        out: FloatArray = point @ self.R if self.levelled else point
        return out

    def level_pose(self, T: FloatArray) -> FloatArray:
        """A 4x4 pose between the sensor frames, expressed between the levelled frames."""
        return self._remount(T, inverse=False)

    def unlevel(self, T: FloatArray) -> FloatArray:
        """A 4x4 pose between levelled frames, expressed between the sensor frames."""
        return self._remount(T, inverse=True)

    def unlevel_pose(self, T: FloatArray) -> tuple[float, ...]:
        """:meth:`unlevel` as a pose vector ``(x, y, z, qx, qy, qz, qw)``."""
        return tuple(float(v) for v in matrix_to_vector(self.unlevel(T)))

    def unlevel_cov(self, cov: FloatArray) -> FloatArray:
        """A 6x6 covariance (ROS order, right perturbation) of a levelled-frame pose, for the
        same pose between the sensor frames."""
        if not self.levelled:
            return cov
        b = np.zeros((6, 6))
        b[:3, :3] = b[3:, 3:] = self.R.T
        out: FloatArray = b @ cov @ b.T
        return out

    def _remount(self, T: FloatArray, inverse: bool) -> FloatArray:
        """``M T M^-1`` (``M^-1 T M`` when ``inverse``)."""
        if not self.levelled:
            return T
        m = np.eye(4)
        m[:3, :3] = self.R.T if inverse else self.R
        out: FloatArray = m @ T @ m.T
        return out
