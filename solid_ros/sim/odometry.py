"""The simulated drive's odometry: the reference motion with the errors of a real odometry.

A LiDAR(-inertial) odometry drifts by about 0.5-3 % of the path driven. The simulator's
odometry integrates the reference motion from scan to scan in the vehicle's level frame with:

- a scale error: every step is ``1 + scale_error`` times its true length;
- a heading bias: the heading turns ``heading_bias_deg_per_m`` degrees per metre driven (a
  gyro bias, or a LiDAR odometry that under-turns in one direction);
- random walks: the heading by ``heading_walk_deg`` and the position by ``position_walk_m``
  (standard deviations per square root of a metre driven, on each of x and y).

Height, roll and pitch stay exact. The odometry frame is the world frame at the first scan.
The same seed gives the same errors; :class:`~solid_ros.sim.drive.DriveConfig` holds the
values (``odom_*``) and ``perfect_odometry=True`` makes the odometry the reference poses.

The defaults (scale 1 %, heading bias 0.015 deg/m, walks 0.05 deg and 0.01 m per sqrt(m)) are
a plain LiDAR odometry's, worse than a good LiDAR-inertial one. On the demo's revisits drive
(50 m blocks, 1.13 km, seeds 0-4) the end error is 1.2-2.0 % of the path (mean 1.5 %; the
route ends where it started) and the error over 100-400 m stretches 1.1-1.5 %. The heading
bias makes longer drives drift more: 2.0-3.1 % at the end of the 1.8 km default drive (80 m
blocks), 4.2-5.3 % at the end of the 2 km no_revisit serpentine (test/bench/bench_kiss.py
prints these).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ['OdometryDrift', 'drift_planar']

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class OdometryDrift:
    """Error model of the simulated odometry (see the module docstring)."""

    scale_error: float
    heading_bias_deg_per_m: float
    heading_walk_deg: float
    position_walk_m: float


def drift_planar(xy: FloatArray, yaw: FloatArray, drift: OdometryDrift,
                 noise: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Integrate the reference planar motion with the drift model.

    Args:
        xy: (N, 2) reference positions, metres.
        yaw: (N,) reference headings, radians.
        drift: the error model.
        noise: (N, 3) standard normal draws (row k perturbs the step into pose k; row 0 is
            not used): heading, x, y.

    Returns:
        The odometry's (N, 2) positions and (N,) headings; pose 0 is the reference's.
    """
    n = len(yaw)
    if n < 2:
        return xy.copy(), yaw.copy()
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    d_world = np.diff(xy, axis=0)
    # Step k in the previous pose's frame, its length and the turn.
    step = np.c_[c * d_world[:, 0] + s * d_world[:, 1], -s * d_world[:, 0] + c * d_world[:, 1]]
    length = np.linalg.norm(step, axis=1)
    turn = np.angle(np.exp(1j * np.diff(yaw)))
    root = np.sqrt(length)
    turn = (turn + np.radians(drift.heading_bias_deg_per_m) * length
            + np.radians(drift.heading_walk_deg) * root * noise[1:, 0])
    step = (1.0 + drift.scale_error) * step + drift.position_walk_m * root[:, None] * noise[1:, 1:]
    heading = yaw[0] + np.r_[0.0, np.cumsum(turn)]
    c, s = np.cos(heading[:-1]), np.sin(heading[:-1])
    moved = np.c_[c * step[:, 0] - s * step[:, 1], s * step[:, 0] + c * step[:, 1]]
    out_xy = xy[0] + np.r_[np.zeros((1, 2)), np.cumsum(moved, axis=0)]
    return out_xy, np.angle(np.exp(1j * heading))
