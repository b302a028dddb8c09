"""Deskew on the simulator: a spinning sensor that moves during its sweep, with and without
per-point times, plain KISS-ICP beside solid_ros's odometry.

Sweeps come from :func:`solid_ros.sim.sweep.moving_sweep`: ``--sectors`` scans cast along the
motion from the previous pose to this one, each point in the sensor frame at its time, with
that time; the sweep's reference pose is the one at its end, the pose KISS-ICP 1.x deskews to
and reports (``test/sim/test_sweep.py`` holds both conventions). The ground is dropped: the
simulator's exact ground plane sampled in the same rings holds point-to-point ICP in place
(``test/core/odometry/test_kiss.py``). The drive is the first street of the default route
(straight for 100 m) at up to ``--spacing`` metres per sweep (1.5 m: 54 km/h at 10 Hz). It
starts standing (``--start rest``: 5 sweeps, then 4 m/s^2), as a recording does: KISS-ICP starts
with no motion, so a sensor at speed from its first sweep (``--start moving``, the bench's first
form) puts its first two sweeps into the local map with their full smear, where they stay
until they are ``max range`` behind (80 m: the whole run) and every later, deskewed sweep is
registered against them.

Rows: the same poses cast at once (no skew: the floor), plain KISS-ICP without times, with
times (its deskew: the previous sweep's motion, constant velocity), with times deskewed by the
true motion of the sweep (an oracle), with ``--start moving`` KISS-ICP's deskew with its first
two sweeps (which it deskews with no motion) deskewed by the true motion, and ours without and
with times (``kiss_deskew``).
Each: ATE (SE(3)-aligned), end error, the along-track step error (mean, sd), ms per cloud.

The simulated heading carries a jitter (:mod:`solid_ros.sim.trajectory`, 2.5 deg, a moving
average of white noise) whose turn rate changes from sweep to sweep: the yaw step of one sweep
says little about the next, and a constant-velocity deskew turns the sweep the wrong way.
``--heading smooth`` smooths the heading over the scans (Gaussian, ``--sigma`` scans) so the
turn rate changes as a vehicle's does (``both``, the default: one run of each); the printed
yaw-step figures show the difference.
Usage: ``python test/bench/bench_deskew.py [--scans 80] [--spacing 1.5] [--sectors 16]
[--start rest|moving] [--heading simulated|smooth|both] [--report FILE]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_kiss import trajectory_errors  # noqa: E402
from report import PrintedReport, bench_meta  # noqa: E402

from solid_ros.core.config import NodeConfig  # noqa: E402
from solid_ros.core.odometry.kiss import KissOdometry, derive_settings, load_kiss_icp  # noqa: E402
from solid_ros.sim import DEMO_SENSORS, Drive, DriveConfig  # noqa: E402
from solid_ros.sim.lidar import cast_scan  # noqa: E402
from solid_ros.sim.sweep import moving_sweep, pose_at, ramp  # noqa: E402

FloatArray = npt.NDArray[np.float64]
GROUND_Z = -1.4
ACCEL = 4.0  # m/s^2 from standing (--start rest): 0 to 54 km/h in under 4 s
Deskew = Callable[[int, FloatArray, FloatArray], FloatArray]


def smooth_heading(drive: Drive, sigma: float) -> None:
    """Replace the drive's headings by a Gaussian smoothing over ``sigma`` scans."""
    from scipy.ndimage import gaussian_filter1d

    t = drive.trajectory
    yaw = gaussian_filter1d(np.unwrap(t.yaw), sigma, mode='nearest')
    drive.__dict__['trajectory'] = dataclasses.replace(t, yaw=yaw)  # the cached property


def static_scans(drive: Drive, ends: FloatArray) -> list[FloatArray]:
    """Scans cast at once where the sweeps end (no skew), without the ground."""
    out = []
    for k, end in enumerate(ends):
        pose = pose_at(drive, float(end))
        yaw = float(np.arctan2(pose[1, 0], pose[0, 0]))
        xyz = cast_scan(drive.scene, drive.model, float(pose[0, 3]), float(pose[1, 3]), yaw,
                        np.random.default_rng([drive.config.seed, k]))[:, :3]
        xyz = xyz.astype(np.float64)
        out.append(xyz[xyz[:, 2] > GROUND_Z])
    return out


def plain(clouds: list[FloatArray], times: list[FloatArray] | None, cfg: NodeConfig,
          oracle: Deskew | None = None, first: int | None = None
          ) -> tuple[FloatArray, list[float]]:
    """Plain KISS-ICP; with ``oracle`` each cloud (only the ``first`` ones, when given; KISS-ICP
    deskews the rest) is deskewed by it instead."""
    KissICP, KISSConfig, _ = load_kiss_icp()
    kc = KISSConfig()
    kc.data.max_range, kc.mapping.voxel_size = cfg.kiss_max_range, cfg.kiss_voxel_size
    kc.data.deskew = times is not None and (oracle is None or first is not None)
    kiss = KissICP(kc)
    poses, costs = [], []
    for i, points in enumerate(clouds):
        t0 = time.perf_counter()
        if oracle is not None and times is not None and (first is None or i < first):
            kiss.register_frame(oracle(i, points, times[i]), np.zeros(0))
        else:
            kiss.register_frame(points, np.zeros(0) if times is None else times[i])
        costs.append(time.perf_counter() - t0)
        poses.append(np.array(kiss.last_pose))
    return np.stack(poses), costs


def ours(clouds: list[FloatArray], times: list[FloatArray] | None,
         cfg: NodeConfig) -> tuple[FloatArray, list[float]]:
    odo = KissOdometry(cfg)
    poses, costs = [], []
    for i, points in enumerate(clouds):
        t0 = time.perf_counter()
        sample = odo.pose_for(i + 1, points, None if times is None else times[i])
        costs.append(time.perf_counter() - t0)
        assert sample is not None
        poses.append(sample.pose)
    if odo.resets:
        print(f'  (ours reset {odo.resets} times: {dict(odo.reset_counts)})')
    return np.stack(poses), costs


def true_deskew(ref: FloatArray, first: FloatArray) -> Deskew:
    """Deskew cloud i with its sweep's true motion (``ref[i - 1]`` to ``ref[i]``; the first
    from ``first``), by KISS-ICP's own formula (its preprocessor, ranges left open)."""
    from kiss_icp.preprocess import Preprocessor  # type: ignore[import-untyped]

    pre = Preprocessor(1e9, 0.0, True, 1)

    def deskew(i: int, points: FloatArray, times: FloatArray) -> FloatArray:
        step = np.linalg.inv(ref[i - 1] if i else first) @ ref[i]
        return np.asarray(pre.preprocess(points, times, step))
    return deskew


def yaw_steps(ref: FloatArray) -> FloatArray:
    """Yaw of each sweep's step, degrees."""
    steps = [np.linalg.inv(a) @ b for a, b in zip(ref[:-1], ref[1:])]
    return np.degrees([np.arctan2(s[1, 0], s[0, 0]) for s in steps])


def along_errors(est: FloatArray, ref: FloatArray) -> FloatArray:
    """Along-track error of each step (x of the relative pose), metres."""
    return np.array([(np.linalg.inv(est[k - 1]) @ est[k])[0, 3]
                     - (np.linalg.inv(ref[k - 1]) @ ref[k])[0, 3] for k in range(1, len(ref))])


def _start(args: argparse.Namespace) -> str:
    return (f'standing 5 sweeps, then {ACCEL:g} m/s^2' if args.start == 'rest'
            else 'at speed from the first sweep')


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--sensor', default='hdl64', choices=sorted(DEMO_SENSORS))
    p.add_argument('--scans', type=int, default=80)
    p.add_argument('--spacing', type=float, default=1.5)
    p.add_argument('--sectors', type=int, default=16)
    p.add_argument('--start', choices=('rest', 'moving'), default='rest')
    p.add_argument('--heading', choices=('simulated', 'smooth', 'both'), default='both')
    p.add_argument('--sigma', type=float, default=4.0, help='scans (--heading smooth)')
    p.add_argument('--report', type=Path)
    args = p.parse_args()
    headings = ['simulated', 'smooth'] if args.heading == 'both' else [args.heading]
    with PrintedReport(args.report, bench_meta('bench_deskew', vars(args))):
        for heading in headings:
            drive = Drive(DriveConfig(seed=0, sensor=DEMO_SENSORS[args.sensor], block=50.0,
                                      spacing=args.spacing))
            if heading == 'smooth':
                smooth_heading(drive, args.sigma)
            run(drive, args, heading)
    return 0


def run(drive: Drive, args: argparse.Namespace, heading: str) -> None:
    """Build the sweeps, run every row, print."""
    if args.start == 'rest':
        ends = ramp(args.spacing, args.scans, rest=5, accel=ACCEL)
    else:
        ends = np.arange(1.0, args.scans + 1.0)
    ends = ends[ends <= len(drive) - 1]
    starts = np.r_[ends[0] - 1.0 if args.start == 'moving' else 0.0, ends[:-1]]
    data = [moving_sweep(drive, float(b), args.sectors, GROUND_Z, float(a),
                         np.random.default_rng([drive.config.seed, k]))
            for k, (a, b) in enumerate(zip(starts, ends))]
    clouds, times = [d[0] for d in data], [d[1] for d in data]
    ref = np.stack([pose_at(drive, float(e)) for e in ends])
    cfg = derive_settings(NodeConfig(), clouds)
    yaw = yaw_steps(ref)
    moving = np.diff(ends) > 0.999
    print(f'simulator {args.sensor}: {len(ends)} sweeps of {args.sectors} sectors, '
          f'{args.spacing} m per sweep at speed, start {_start(args)}, heading {heading}; '
          f'max range {cfg.kiss_max_range:g} m, voxel {cfg.kiss_voxel_size:g} m\n'
          f'at speed, yaw per sweep: sd {np.std(yaw[moving]):.2f} deg; its change from one '
          f'sweep to the next: sd {np.std(np.diff(yaw[moving])):.2f} deg (what a '
          'constant-velocity deskew gets wrong)')
    rows: list[tuple[str, Callable[[], tuple[FloatArray, list[float]]]]] = [
        ('no skew (cast at once)', lambda: plain(static_scans(drive, ends), None, cfg)),
        ('plain, no times', lambda: plain(clouds, None, cfg)),
        ('plain, deskew', lambda: plain(clouds, times, cfg)),
        ('plain, true-motion deskew',
         lambda: plain(clouds, times, cfg, true_deskew(ref, pose_at(drive, float(starts[0]))))),
        ('ours, no times', lambda: ours(clouds, None, cfg)),
        ('ours, deskew', lambda: ours(clouds, times, cfg))]
    if args.start == 'moving':  # KISS-ICP's first two sweeps (no motion yet) by the truth
        rows.insert(4, ('plain, deskew, first 2 true', lambda: plain(
            clouds, times, cfg, true_deskew(ref, pose_at(drive, float(starts[0]))), 2)))
    for name, row in rows:
        est, costs = row()
        ate, end, path = trajectory_errors(est, ref)
        along = along_errors(est, ref)
        print(f'  {name:26s} ATE {ate:.3f} m  end {end:.2f} m of {path:.0f} m  step along '
              f'{along.mean():+.3f} +- {along.std():.3f} m  {1e3 * np.median(costs):.1f} '
              'ms/cloud', flush=True)


if __name__ == '__main__':
    sys.exit(main())
