"""A spinning sensor's sweep that takes time: the sensor moves while it turns.

:func:`cast_scan` casts a scan at one pose, as if the sweep were instantaneous. A real
spinning LiDAR turns once per scan period while the vehicle moves, and its driver reports each
point in the sensor frame at the time the point was measured, with that time. :func:`moving_sweep`
builds such a sweep from ``sectors`` scans cast along the motion from one place on the route
to the next: sector k of the azimuth (starting behind the sensor, turning counter-clockwise) is
taken from the scan cast at time (k + 0.5) / sectors of the period, in the sensor frame of
that time, each point with its time in [0, 1] (its azimuth fraction, within half a sector of
the time it was cast at). The sweep ends at the pose :func:`pose_at` gives for its end: KISS-ICP
1.x deskews every point to the sweep's end (``SE3::exp((t - 1) log(delta))``, times normalised
to [0, 1] over the sweep) and reports that pose, so this is the reference to compare with.

Places on the route are fractional scan indices (2.5: halfway between scans 2 and 3), so a
drive can stand, start and speed up (:func:`ramp`): KISS-ICP starts with no motion, and a
sensor already at speed in its first sweep leaves that sweep's smear in its map.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from solid_ros.sim.drive import Drive, pose_matrix
from solid_ros.sim.lidar import cast_scan

__all__ = ['moving_sweep', 'pose_at', 'ramp']

FloatArray = npt.NDArray[np.float64]


def _place(drive: Drive, at: float) -> tuple[float, float, float]:
    """(x, y, yaw) at fractional scan index ``at``, interpolated between its two scans."""
    t = drive.trajectory
    i = min(int(np.floor(at)), len(t) - 2)
    f = at - i
    x, y = (1 - f) * t.xy[i] + f * t.xy[i + 1]
    # The shorter way round, so a heading across +-pi interpolates.
    dyaw = (t.yaw[i + 1] - t.yaw[i] + np.pi) % (2 * np.pi) - np.pi
    return float(x), float(y), float(t.yaw[i] + f * dyaw)


def pose_at(drive: Drive, at: float) -> FloatArray:
    """World <- sensor at fractional scan index ``at`` (a level sensor)."""
    x, y, yaw = _place(drive, at)
    return pose_matrix(x, y, drive.model.mount_height, yaw)


def ramp(spacing: float, sweeps: int, rest: int = 5, accel: float = 4.0,
         rate_hz: float = 10.0) -> FloatArray:
    """Where each of ``sweeps`` sweeps ends, as fractional scan indices of a drive whose scans
    are ``spacing`` metres apart: standing for ``rest`` sweeps, then speeding up at ``accel``
    m/s^2 to ``spacing`` metres per sweep (the drive's speed)."""
    dt = 1.0 / rate_hz
    speed = np.minimum(accel * dt * np.maximum(np.arange(sweeps) - rest + 1, 0), spacing / dt)
    return np.cumsum(speed * dt) / spacing


def moving_sweep(drive: Drive, end: float, sectors: int = 16, min_z: float | None = None,
                 start: float | None = None, rng: np.random.Generator | None = None
                 ) -> tuple[FloatArray, FloatArray]:
    """The sweep that ends at scan ``end`` of ``drive``, cast while moving from ``start``.

    Args:
        drive: the drive (a level sensor: its tilt is not applied here).
        end: where the sweep ends, a (fractional) scan index.
        sectors: azimuth sectors, each cast at its own pose (16 at 10 Hz: 6 ms apart).
        min_z: points at or below this height in the sensor frame are dropped (the
            simulator's exact ground plane holds point-to-point ICP in place); None keeps them.
        start: where it starts (None: ``end - 1``, one scan spacing before; ``end``: standing).
        rng: range noise and dropout (None: seeded by the drive's seed and ``end``).

    Returns:
        (N, 3) points, each in the sensor frame at its time, and (N,) times in [0, 1] of the
        sweep (0: its start, behind the sensor; 1: its end, at ``pose_at(drive, end)``).

    Raises:
        ValueError: ``start`` after ``end``, either off the route, or ``sectors`` < 1.
    """
    start = end - 1 if start is None else start
    if not 0 <= start <= end <= len(drive) - 1 or sectors < 1:
        raise ValueError(f'moving_sweep: from {start} to {end} of {len(drive)} scans with '
                         f'{sectors} sectors')
    if rng is None:
        rng = np.random.default_rng([drive.config.seed, int(round(1000 * end))])
    points, times = [], []
    for k in range(sectors):
        s = (k + 0.5) / sectors
        x, y, yaw = _place(drive, (1 - s) * start + s * end)
        xyz = cast_scan(drive.scene, drive.model, x, y, yaw, rng)[:, :3]
        xyz = xyz.astype(np.float64)
        azimuth = (np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi) / (2 * np.pi)  # 0 behind
        keep = (azimuth >= k / sectors) & (azimuth < (k + 1) / sectors)
        if min_z is not None:
            keep &= xyz[:, 2] > min_z
        points.append(xyz[keep])
        times.append(azimuth[keep])
    return np.concatenate(points), np.concatenate(times)
