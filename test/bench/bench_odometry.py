"""Built-in odometry against plain KISS-ICP on the same clouds, with the same settings.

For each real recording in ``../shared/data`` (hku1: Livox Avia, a loop; quickshack: Avia
hand-held in a tight space; riv281: Ouster OS1-64 on a car, keyframes 0.3-21 s and 2-60 m
apart) and each of the simulator's drives (``sim-avia_like``, ``sim-mid360_like``,
``sim-hdl64``: the sensor streaming at 10 Hz on a car at 2.5 m/s, ``--sim-clouds`` clouds
0.25 m apart along the demo's route, its reference poses exact) it runs, on the same clouds:

- ``plain``: KISS-ICP 1.3 called directly (``KissICP(config).register_frame(points, times)``
  per cloud, ``last_pose``), the way its own pipeline does;
- ``ours``: :class:`solid_ros.core.odometry.kiss.KissOdometry` (checks, resets included),

both with the same max range, min range, voxel size: those of ``--settings`` (``derived``:
what :func:`solid_ros.core.odometry.kiss.derive_settings` takes from the first clouds, the
default; ``preset``: the preset's ``kiss_*`` values), and the same deskew: ``--deskew on``
passes each cloud's per-point times (when the bag carries them) to both with deskew on,
``off`` (the default) passes none. hku1 and quickshack carry no per-point times (fields x y z
intensity): KISS-ICP then deskews nothing, on or off. Prints for each:

- ATE: RMSE of the positions after an SE(3) (Umeyama, no scale) alignment to
  optimized_poses.txt (the reference; the bag's odometry is the same drift-free trajectory),
  or to the simulator's poses;
- tracked: steps whose relative pose is within 0.3 m (or 10 % of the step) and 2 deg of the
  reference step;
- resets (ours) by kind, and how many fell on a step plain KISS-ICP tracked;
- ms per cloud (median, p95, wall) and the fraction of clouds a single worker would have
  processed in real time at the bag's stamps (a newer cloud replaces one still waiting).

Timings on a shared 2-core machine are noisy. ``--report FILE`` writes the figures with the
date and commit (Markdown for ``doc/reports/``, else JSON); ``--save DIR`` keeps the poses.
Usage: ``python test/bench/bench_odometry.py [--sets hku1,quickshack,riv281,sim-avia_like,...]
[--sim-clouds N] [--settings derived|preset] [--deskew on|off] [--voxel M] [--report FILE]
[--save DIR]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_kiss import trajectory_errors  # noqa: E402
from report import bench_meta, write_report  # noqa: E402

from solid_ros.core.config import NodeConfig, SolidConfig  # noqa: E402
from solid_ros.core.odometry.kiss import KissOdometry, derive_settings, load_kiss_icp  # noqa: E402
from solid_ros.formats.bags import Bag  # noqa: E402
from solid_ros.formats.poses import read_kitti_poses  # noqa: E402
from solid_ros.tools.replay import load_config  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
PRESETS = {'hku1': 'avia.yaml', 'quickshack': 'avia.yaml', 'riv281': 'ouster.yaml',
           'sim-avia_like': 'avia.yaml', 'sim-mid360_like': 'mid360.yaml',
           'sim-hdl64': 'hdl64.yaml'}
SIM = 'sim-'
FloatArray = npt.NDArray[np.float64]


def load(name: str, sim_clouds: int = 0) -> tuple[list[FloatArray], list[int], FloatArray]:
    """The recording's (or simulated drive's, ``sim_clouds`` of them) clouds (x, y, z), their
    stamps (ns) and the reference poses."""
    if name.startswith(SIM):
        from solid_ros.sim.drive import Drive, DriveConfig

        drive = Drive(DriveConfig(sensor=name[len(SIM):], spacing=0.25, speed=2.5))
        scans = [drive.scan(k) for k in range(sim_clouds)]
        return ([np.asarray(sc.points, dtype=np.float64) for sc in scans],
                [sc.stamp_ns for sc in scans], np.stack([sc.pose for sc in scans]))
    clouds, stamps = [], []
    with Bag(DATA / name / 'bag') as bag:
        for scan in bag.clouds('/points'):
            clouds.append(np.asarray(scan.points, dtype=np.float64)[:, :3])
            stamps.append(int(scan.stamp_ns))
    return clouds, stamps, read_kitti_poses(DATA / name / 'optimized_poses.txt')


def point_times(name: str) -> list[FloatArray | None]:
    """Each cloud's per-point times as the bag gives them (None: the cloud has none; the
    simulator's clouds have none: bench_deskew moves its sensor within a scan)."""
    if name.startswith(SIM):
        return []
    with Bag(DATA / name / 'bag') as bag:
        return [None if scan.times is None else np.asarray(scan.times, dtype=np.float64)
                for scan in bag.clouds('/points')]


def settings(name: str, mode: str, clouds: list[FloatArray]) -> NodeConfig:
    """The odometry settings both runs use."""
    _, ncfg = load_config(ROOT / 'config' / PRESETS[name])
    if mode == 'derived':
        return derive_settings(replace(ncfg, kiss_max_range=0.0, kiss_voxel_size=0.0), clouds)
    return ncfg


def plain(clouds: list[FloatArray], cfg: NodeConfig,
          times: list[FloatArray | None]) -> tuple[FloatArray, list[float]]:
    """KISS-ICP called directly (deskewing as ``cfg`` says, with ``times``); poses and seconds
    per cloud."""
    KissICP, KISSConfig, _ = load_kiss_icp()
    kc = KISSConfig()
    kc.data.max_range, kc.data.min_range = cfg.kiss_max_range, cfg.kiss_min_range
    kc.data.deskew, kc.mapping.voxel_size = cfg.kiss_deskew, cfg.kiss_voxel_size
    kiss = KissICP(kc)
    poses, costs = [], []
    for points, point_times in zip(clouds, times):
        t0 = time.perf_counter()
        kiss.register_frame(points, np.zeros(0) if point_times is None else point_times)
        costs.append(time.perf_counter() - t0)
        poses.append(np.array(kiss.last_pose, dtype=np.float64))
    return np.stack(poses), costs


def ours(clouds: list[FloatArray], stamps: list[int], cfg: NodeConfig,
         times: list[FloatArray | None]) -> tuple[FloatArray, list[float], KissOdometry,
                                                   list[int]]:
    """The adapter; poses, seconds per cloud, the source and the clouds that reset it."""
    odo = KissOdometry(cfg)
    poses, costs, resets = [], [], []
    for i, (points, stamp, point_times) in enumerate(zip(clouds, stamps, times)):
        t0 = time.perf_counter()
        sample = odo.pose_for(stamp, points, point_times)
        costs.append(time.perf_counter() - t0)
        assert sample is not None
        if sample.reason:
            print(f'    cloud {i}: {sample.reason}', flush=True)
            resets.append(i)
        poses.append(sample.pose)
    return np.stack(poses), costs, odo, resets


def tracked(est: FloatArray, ref: FloatArray) -> npt.NDArray[np.bool_]:
    """Per step i -> i+1: is the estimated relative pose within 0.3 m (or 10 % of the step)
    and 2 deg of the reference's?"""
    out = []
    for i in range(len(ref) - 1):
        r = np.linalg.inv(ref[i]) @ ref[i + 1]
        e = np.linalg.inv(r) @ (np.linalg.inv(est[i]) @ est[i + 1])
        angle = np.degrees(np.arccos(np.clip((np.trace(e[:3, :3]) - 1) / 2, -1.0, 1.0)))
        limit = max(0.3, 0.1 * float(np.linalg.norm(r[:3, 3])))
        out.append(float(np.linalg.norm(e[:3, 3])) < limit and angle < 2.0)
    return np.asarray(out, dtype=bool)


def realtime_fraction(stamps: list[int], costs: list[float]) -> float:
    """Clouds one worker processes when they arrive at their stamps and a newer cloud replaces
    one still waiting (costs measured offline)."""
    t = (np.asarray(stamps, dtype=np.float64) - stamps[0]) * 1e-9
    free, done, waiting = 0.0, 0, None
    for i in range(len(t) + 1):
        now = t[i] if i < len(t) else np.inf
        while waiting is not None and free <= now:
            free = max(free, t[waiting]) + costs[waiting]
            done, waiting = done + 1, None
        if i < len(t):
            if free <= now:
                free, done = now + costs[i], done + 1
            else:
                waiting = i
    return done / len(t)


def run(name: str, mode: str, deskew: str, save: Path | None,
        voxel: float = 0.0, sim_clouds: int = 0) -> dict[str, Any]:
    clouds, stamps, ref = load(name, sim_clouds)
    cfg = replace(settings(name, mode, clouds), kiss_deskew=deskew == 'on')
    if voxel > 0:
        cfg = replace(cfg, kiss_voxel_size=voxel)
    times = (point_times(name) if deskew == 'on' else []) or [None] * len(clouds)
    timed = sum(t is not None for t in times)
    print(f'{name}: {len(clouds)} clouds; max range {cfg.kiss_max_range:.1f} m, min range '
          f'{cfg.kiss_min_range:.1f} m, voxel {cfg.kiss_voxel_size:.2f} m ({mode}); deskew '
          f'{deskew}, {timed} clouds with per-point times', flush=True)
    p_poses, p_costs = plain(clouds, cfg, times)
    o_poses, o_costs, odo, resets = ours(clouds, stamps, cfg, times)
    p_track, o_track = tracked(p_poses, ref), tracked(o_poses, ref)
    out: dict[str, Any] = {'clouds': len(clouds), 'timed_clouds': timed,
                           'deskew': deskew, 'max_range': cfg.kiss_max_range,
                           'voxel': cfg.kiss_voxel_size, 'resets': odo.resets,
                           'reset_kinds': dict(odo.reset_counts),
                           'resets_where_plain_tracks': int(sum(p_track[i - 1] for i in resets
                                                                if i > 0))}
    for who, poses, costs, track in (('plain', p_poses, p_costs, p_track),
                                     ('ours', o_poses, o_costs, o_track)):
        ate, end, path = trajectory_errors(poses, ref)
        ms = np.asarray(costs) * 1e3
        out[who] = {'ate_m': ate, 'end_m': end, 'path_m': path, 'tracked': float(track.mean()),
                    'ms_p50': float(np.median(ms)), 'ms_p95': float(np.percentile(ms, 95)),
                    'realtime': realtime_fraction(stamps, costs)}
    if save is not None:
        save.mkdir(parents=True, exist_ok=True)
        np.savez(save / f'{name}.npz', plain=p_poses, ours=o_poses, ref=ref, resets=resets)
    return out


def lines(name: str, s: dict[str, Any]) -> list[str]:
    rows = [f'  {who:5s} ATE {s[who]["ate_m"]:8.3f} m  end {s[who]["end_m"]:8.2f} m of '
            f'{s[who]["path_m"]:.0f} m  tracked {100 * s[who]["tracked"]:5.1f} % of steps  '
            f'{s[who]["ms_p50"]:6.1f} ms/cloud (p95 {s[who]["ms_p95"]:6.1f})  real time '
            f'{100 * s[who]["realtime"]:5.1f} % processed' for who in ('plain', 'ours')]
    ratio = s['ours']['ate_m'] / max(s['plain']['ate_m'], 1e-9)
    rows.append(f'  ours/plain ATE {ratio:.2f}; resets {s["resets"]} {s["reset_kinds"]}, '
                f'{s["resets_where_plain_tracks"]} where plain KISS-ICP tracks')
    return rows


COLUMNS = ['recording', 'max range / voxel', 'ATE plain', 'ATE ours', 'ours/plain',
           'tracked plain / ours', 'resets (where plain tracks)', 'ms/cloud plain / ours',
           'real time plain / ours']
NOTES = ("ATE after SE(3) alignment to optimized_poses.txt (sim-: to the simulator's poses; "
         'the sensor streaming at 10 Hz, 0.25 m apart). Tracked: steps within 0.3 m (or '
         '10 % of the step) and 2 deg of the reference step. Real time: clouds one worker '
         'keeps up with at the bag stamps. Shared 2-core machine: timings are noisy.')


def _row(name: str, s: dict[str, Any]) -> list[Any]:
    p, o = s['plain'], s['ours']
    return [name, f'{s["max_range"]:.1f} / {s["voxel"]:.2f} m', f'{p["ate_m"]:.3f} m',
            f'{o["ate_m"]:.3f} m', f'{o["ate_m"] / max(p["ate_m"], 1e-9):.2f}',
            f'{100 * p["tracked"]:.0f} / {100 * o["tracked"]:.0f} %',
            f'{s["resets"]} ({s["resets_where_plain_tracks"]})',
            f'{p["ms_p50"]:.0f} / {o["ms_p50"]:.0f}',
            f'{100 * p["realtime"]:.0f} / {100 * o["realtime"]:.0f} %']


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--sets', default=','.join(PRESETS))
    p.add_argument('--settings', choices=('derived', 'preset'), default='derived')
    p.add_argument('--deskew', choices=('on', 'off'), default='off')
    p.add_argument('--voxel', type=float, default=0.0,
                   help="KISS-ICP's voxel for both, metres, instead of --settings' (0: theirs)")
    p.add_argument('--sim-clouds', type=int, default=300,
                   help='clouds of each simulated drive (0.25 m apart)')
    p.add_argument('--report', type=Path)
    p.add_argument('--save', type=Path)
    args = p.parse_args()
    names = args.sets.split(',')
    if unknown := [n for n in names if n not in PRESETS]:
        p.error(f'unknown sets {unknown}; known: {",".join(PRESETS)}')
    if not DATA.is_dir():
        print(f'bench_odometry: {DATA} is missing: the real recordings are skipped')
        names = [n for n in names if n.startswith(SIM)]
    SolidConfig()  # the project imports cleanly before the long runs
    figures = {}
    for name in names:
        figures[name] = run(name, args.settings, args.deskew, args.save, args.voxel,
                            args.sim_clouds)
        print('\n'.join(lines(name, figures[name])), flush=True)
    if args.report is not None:
        meta = bench_meta('bench_odometry', vars(args) | {'sets': names})
        write_report(args.report, meta, COLUMNS, [_row(k, v) for k, v in figures.items()],
                     {'recordings': figures}, NOTES)
    return 0


if __name__ == '__main__':
    sys.exit(main())
