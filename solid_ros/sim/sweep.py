"""A spinning sensor's sweep that takes time: the sensor moves while it turns.

:func:`cast_scan` casts a scan at one pose, as if the sweep were instantaneous. A real
spinning LiDAR turns once per scan period while the vehicle moves, and its driver reports each
point in the sensor frame at the time the point was measured, with that time. :func:`moving_sweep`
builds such a sweep from ``sectors`` scans cast along the motion from scan ``index - 1`` to
scan ``index``: sector k of the azimuth (starting behind the sensor, turning counter-clockwise)
is taken from the scan cast at time (k + 0.5) / sectors of the period, in the sensor frame of
that time, each point with its time in [0, 1] (its azimuth fraction). The sweep ends at scan
``index``'s pose, the pose :meth:`Drive.pose` gives: KISS-ICP 1.x deskews every point to the
sweep's end (``SE3::exp((t - 1) log(delta))``, times normalised to [0, 1] over the sweep) and
reports that pose, so this is the reference it is compared with.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from solid_ros.sim.drive import Drive
from solid_ros.sim.lidar import cast_scan

__all__ = ['moving_sweep']

FloatArray = npt.NDArray[np.float64]


def moving_sweep(drive: Drive, index: int, sectors: int = 16,
                 min_z: float | None = None) -> tuple[FloatArray, FloatArray]:
    """The sweep that ends at scan ``index`` of ``drive``, cast while moving from scan
    ``index - 1``.

    Args:
        drive: the drive (a level sensor: its tilt is not applied here).
        index: the scan the sweep ends at (>= 1).
        sectors: azimuth sectors, each cast at its own pose (16 at 10 Hz: 6 ms apart).
        min_z: points at or below this height in the sensor frame are dropped (the
            simulator's exact ground plane holds point-to-point ICP in place); None keeps them.

    Returns:
        (N, 3) points, each in the sensor frame at its time, and (N,) times in [0, 1] of the
        sweep (0: its start, behind the sensor; 1: its end, at scan ``index``'s pose).

    Raises:
        ValueError: ``index`` < 1 or ``sectors`` < 1.
    """
    if index < 1 or sectors < 1:
        raise ValueError(f'moving_sweep: index {index} and sectors {sectors} must be >= 1')
    t = drive.trajectory
    rng = np.random.default_rng([drive.config.seed, index])
    # The shorter way round from the previous heading, so a heading across +-pi interpolates.
    dyaw = (t.yaw[index] - t.yaw[index - 1] + np.pi) % (2 * np.pi) - np.pi
    points, times = [], []
    for k in range(sectors):
        s = (k + 0.5) / sectors
        x, y = (1 - s) * t.xy[index - 1] + s * t.xy[index]
        yaw = float(t.yaw[index - 1] + s * dyaw)
        xyz = cast_scan(drive.scene, drive.model, float(x), float(y), yaw, rng)[:, :3]
        xyz = xyz.astype(np.float64)
        azimuth = (np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi) / (2 * np.pi)  # 0 behind
        keep = (azimuth >= k / sectors) & (azimuth < (k + 1) / sectors)
        if min_z is not None:
            keep &= xyz[:, 2] > min_z
        points.append(xyz[keep])
        times.append(azimuth[keep])
    return np.concatenate(points), np.concatenate(times)
