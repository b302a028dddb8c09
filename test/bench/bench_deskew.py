"""Deskew on the simulator: a spinning sensor that moves during its sweep, with and without
per-point times, plain KISS-ICP beside solid_ros's odometry.

The simulator casts a scan at one pose. A sweep that takes time is built from ``--sectors``
scans cast along the motion from the previous pose to this one: sector k of the azimuth
(starting behind the sensor, turning counter-clockwise) is taken from the scan at time
(k + 0.5) / sectors, in the sensor frame of that time, as a sensor reports it, each point with
its time; the sweep's reference pose is the one at its end. KISS-ICP registers the sweeps
with their times (deskew) or without (as a driver without a time field gives them). The
ground is dropped: the simulator's exact ground plane sampled in the same rings holds
point-to-point ICP in place (``test/core/odometry/test_kiss.py``). The drive turns at its
first crossing (the street block is 50 m), at ``--spacing`` metres per sweep (1.5 m: 54 km/h
at 10 Hz). Measured on 2026-11-28 (doc/odometry.md), deskew made both worse here: an open
question.

Prints ATE (SE(3)-aligned) and end error for: plain KISS-ICP without times, plain with times,
ours without times, ours with times (``kiss_deskew`` on, the default), and ms per cloud.
Usage: ``python test/bench/bench_deskew.py [--sensor hdl64] [--scans 60] [--spacing 1.5]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_kiss import trajectory_errors  # noqa: E402

from solid_ros.core.config import NodeConfig  # noqa: E402
from solid_ros.core.odometry.kiss import KissOdometry, derive_settings, load_kiss_icp  # noqa: E402
from solid_ros.sim import DEMO_SENSORS, Drive, DriveConfig  # noqa: E402
from solid_ros.sim.lidar import cast_scan  # noqa: E402

FloatArray = npt.NDArray[np.float64]


def sweep(drive: Drive, index: int, sectors: int) -> tuple[FloatArray, FloatArray]:
    """Points of sweep ``index``, each in the sensor frame at its time, and their times in
    [0, 1]."""
    t = drive.trajectory
    rng = np.random.default_rng([drive.config.seed, index])
    points, times = [], []
    for k in range(sectors):
        s = (k + 0.5) / sectors
        x, y = (1 - s) * t.xy[index - 1] + s * t.xy[index]
        dyaw = (t.yaw[index] - t.yaw[index - 1] + np.pi) % (2 * np.pi) - np.pi
        yaw = float(t.yaw[index - 1] + s * dyaw)
        cloud = cast_scan(drive.scene, drive.model, float(x), float(y), yaw, rng)
        xyz = cloud[:, :3].astype(np.float64)
        azimuth = (np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi) / (2 * np.pi)  # 0 behind
        keep = (azimuth >= k / sectors) & (azimuth < (k + 1) / sectors) & (xyz[:, 2] > -1.4)
        points.append(xyz[keep])  # as the sensor reports them: in its frame at their time
        times.append(azimuth[keep])
    return np.concatenate(points), np.concatenate(times)


def plain(clouds: list[FloatArray], times: list[FloatArray] | None,
          cfg: NodeConfig) -> tuple[FloatArray, list[float]]:
    KissICP, KISSConfig, _ = load_kiss_icp()
    kc = KISSConfig()
    kc.data.max_range, kc.mapping.voxel_size = cfg.kiss_max_range, cfg.kiss_voxel_size
    kc.data.deskew = times is not None
    kiss = KissICP(kc)
    poses, costs = [], []
    for i, points in enumerate(clouds):
        t0 = time.perf_counter()
        kiss.register_frame(points, np.zeros(0) if times is None else times[i])
        costs.append(time.perf_counter() - t0)
        poses.append(np.array(kiss.last_pose))
    return np.stack(poses), costs


def ours(clouds: list[FloatArray], times: list[FloatArray] | None,
         cfg: NodeConfig) -> tuple[FloatArray, list[float], int]:
    odo = KissOdometry(cfg)
    poses, costs = [], []
    for i, points in enumerate(clouds):
        t0 = time.perf_counter()
        sample = odo.pose_for(i + 1, points, None if times is None else times[i])
        costs.append(time.perf_counter() - t0)
        assert sample is not None
        poses.append(sample.pose)
    return np.stack(poses), costs, odo.resets


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--sensor', default='hdl64', choices=sorted(DEMO_SENSORS))
    p.add_argument('--scans', type=int, default=60)
    p.add_argument('--spacing', type=float, default=1.5)
    p.add_argument('--sectors', type=int, default=16)
    args = p.parse_args()
    drive = Drive(DriveConfig(seed=0, sensor=DEMO_SENSORS[args.sensor], block=50.0,
                              spacing=args.spacing))
    n = min(args.scans, len(drive) - 1)
    data = [sweep(drive, i, args.sectors) for i in range(1, n + 1)]
    clouds, times = [d[0] for d in data], [d[1] for d in data]
    ref = np.stack([drive.pose(i) for i in range(1, n + 1)])
    turn = np.degrees(abs(drive.trajectory.yaw[n] - drive.trajectory.yaw[1]))
    cfg = derive_settings(NodeConfig(), clouds)
    print(f'simulator {args.sensor}: {n} sweeps of {args.sectors} sectors, {args.spacing} m '
          f'per sweep, {turn:.0f} deg turned; max range {cfg.kiss_max_range:g} m, voxel '
          f'{cfg.kiss_voxel_size:g} m')
    for name, run in (('plain, no times', lambda: plain(clouds, None, cfg)),
                      ('plain, deskew', lambda: plain(clouds, times, cfg)),
                      ('ours, no times', lambda: ours(clouds, None, cfg)),
                      ('ours, deskew', lambda: ours(clouds, times, cfg))):
        out = run()
        ate, end, path = trajectory_errors(out[0], ref)
        resets = f', resets {out[2]}' if len(out) > 2 else ''
        print(f'  {name:16s} ATE {ate:.3f} m  end {end:.2f} m of {path:.0f} m  '
              f'{1e3 * np.median(out[1]):.1f} ms/cloud{resets}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
