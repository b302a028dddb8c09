"""Poses on the ground plane and position covariances, for tests of the graph's candidates."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from solid_ros.core.geometry import rot_z


def planar_pose(x: float, y: float = 0.0, yaw: float = 0.0) -> npt.NDArray[np.float64]:
    """4x4 pose at ``(x, y, 0)`` turned ``yaw`` radians about +z."""
    T = np.eye(4)
    T[:3, :3] = rot_z(yaw)
    T[:2, 3] = (x, y)
    return T


def position_cov(sigma_m: float) -> npt.NDArray[np.float64]:
    """6x6 covariance (ROS order): ``sigma_m`` on each position axis, 0.01 rad on rotations."""
    return np.diag([sigma_m ** 2] * 3 + [1e-4] * 3)
