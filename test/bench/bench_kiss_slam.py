"""solid_ros with KISS-ICP odometry against KISS-SLAM, the peer a clouds-only user tries instead.

For each real recording in ``../shared/data`` (hku1: Livox Avia, a loop; quickshack: Avia
hand-held in a tight space; riv281: Ouster OS1-64 on a car, no revisit) it runs, on the same
clouds with the same KISS-ICP settings (the preset's max range, min range and voxel, no deskew:
the bags carry no per-point times):

- ``KISS-ICP``: plain KISS-ICP 1.3 (``register_frame`` per cloud);
- ``KISS-SLAM``: KISS-SLAM 0.0.2 (KISS-ICP, MapClosures and a pose graph), as its own pipeline
  runs it (``process_scan`` per cloud, then the last local map closed and the fine-grained
  optimisation), with its default local maps (split 100 m from their start) and with local
  maps split every 25, 10 and 5 m (``--split``): its closures are found between local maps,
  so a 64 m loop closes nothing with the default;
- ``solid_ros``: ``solid_replay --odometry kiss-icp`` with the preset as shipped (the
  replay of ``bench_real.py``): the built-in odometry and the back end's corrected poses.

Prints the ATE (RMSE of positions after an SE(3) alignment to optimized_poses.txt) of each at
solid_ros's keyframes (the clouds it kept; the corrected poses exist there only) and, for the
two peers, over every cloud; KISS-SLAM's closures; seconds of wall time. The question is
issue 35's: is the corrected ATE below plain KISS-ICP's and below KISS-SLAM's?

KISS-SLAM is no dependency of solid_ros: ``pip install kiss-slam==0.0.2`` (it pulls open3d and
map_closures) into an environment that also runs solid_ros's replay (numpy, scipy, mcap,
rosbags, small-gicp, gtsam, kiss-icp). ``--report FILE`` writes the figures with the date and
commit (Markdown for ``doc/reports/``, else JSON).
Usage: ``python test/bench/bench_kiss_slam.py [--sets hku1,quickshack,riv281]
[--split 100,25,10,5] [--report FILE]``.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_odometry import load, plain  # noqa: E402
from bench_real import PRESETS  # noqa: E402
from report import bench_meta, write_report  # noqa: E402

from solid_ros.core.config import NodeConfig  # noqa: E402
from solid_ros.core.geometry import vector_to_matrix  # noqa: E402
from solid_ros.tools.replay import load_config, replay  # noqa: E402
from solid_ros.tools.trajectory_metrics import ate_rmse, path_length  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
FloatArray = npt.NDArray[np.float64]


def kiss_slam(clouds: list[FloatArray], cfg: NodeConfig, split_m: float
              ) -> tuple[FloatArray, int, float]:
    """KISS-SLAM over ``clouds`` with ``cfg``'s KISS-ICP settings and local maps split every
    ``split_m``: a pose per cloud, its closures, seconds."""
    from kiss_slam.config.config import KissSLAMConfig
    from kiss_slam.slam import KissSLAM

    c = KissSLAMConfig()
    c.odometry.preprocessing.max_range = cfg.kiss_max_range
    c.odometry.preprocessing.min_range = cfg.kiss_min_range
    c.odometry.preprocessing.deskew = False
    c.odometry.mapping.voxel_size = cfg.kiss_voxel_size
    c.local_mapper.splitting_distance = split_m
    t0 = time.perf_counter()
    with _quiet():  # its pose graph (g2o) prints every iteration
        slam = KissSLAM(c)
        for points in clouds:
            slam.process_scan(points, np.zeros(0))
        # The end of its own pipeline (kiss_slam.pipeline.SlamPipeline._run_pipeline).
        slam.generate_new_node()
        slam.local_map_graph.erase_last_local_map()
        poses, _ = slam.fine_grained_optimization()
    return np.stack(poses), len(slam.closures), time.perf_counter() - t0


@contextmanager
def _quiet() -> Iterator[None]:
    """Standard output and error of C++ code (file descriptors 1 and 2) to /dev/null."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, 'w') as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
        yield
    finally:
        ctypes.CDLL(None).fflush(None)  # C stdio buffers what it printed: empty it there
        for fd, copy in zip((1, 2), saved):
            os.dup2(copy, fd)
            os.close(copy)


def ours(name: str) -> tuple[dict[int, FloatArray], int, float, float]:
    """solid_replay with KISS-ICP odometry: corrected pose by keyframe stamp, loops, the
    replay's own corrected ATE and seconds."""
    cfg, ncfg = load_config(ROOT / 'config' / PRESETS[name])
    rec = DATA / name
    t0 = time.perf_counter()
    r = replay(rec / 'bag', cfg, node_config=ncfg, odometry='kiss-icp',
               poses=rec / 'optimized_poses.txt', times=rec / 'times.txt', progress='quiet',
               out_dir=None, plots=False)
    wall = time.perf_counter() - t0
    corrected = {int(k['stamp_ns']): vector_to_matrix(k['pose'])
                 for k in r.report['keyframes'] if k['pose'] is not None}
    return (corrected, int(r.report['loops']['published']),
            float(r.report['trajectory']['corrected']['ate_m']), wall)


def run(name: str, splits: list[float]) -> dict[str, Any]:
    """Every method on one recording."""
    clouds, stamps, ref = load(name)
    _, ncfg = load_config(ROOT / 'config' / PRESETS[name])
    corrected, loops, replay_ate, wall = ours(name)
    at = {s: i for i, s in enumerate(stamps)}
    kf = np.array(sorted(at[s] for s in corrected if s in at), dtype=np.intp)
    mine = np.stack([corrected[stamps[i]] for i in kf])
    out: dict[str, Any] = {
        'clouds': len(clouds), 'keyframes': len(kf), 'path_m': float(path_length(ref)[-1]),
        'solid_ros': {'ate_keyframes_m': ate_rmse(mine, ref[kf]), 'loops': loops,
                      'replay_ate_m': replay_ate, 'wall_s': wall}}
    t0 = time.perf_counter()
    poses, _ = plain(clouds, ncfg, [None] * len(clouds))
    out['kiss_icp'] = {'ate_keyframes_m': ate_rmse(poses[kf], ref[kf]),
                       'ate_all_m': ate_rmse(poses, ref), 'wall_s': time.perf_counter() - t0}
    for split in splits:
        poses, closures, secs = kiss_slam(clouds, ncfg, split)
        out[f'kiss_slam_{split:g}'] = {
            'ate_keyframes_m': ate_rmse(poses[kf], ref[kf]), 'ate_all_m': ate_rmse(poses, ref),
            'closures': closures, 'wall_s': secs, 'split_m': split}
    return out


def lines(name: str, s: dict[str, Any], splits: list[float]) -> list[str]:
    """The figures of one recording as printed lines."""
    me, kiss = s['solid_ros'], s['kiss_icp']
    out = [f'{name} ({PRESETS[name]}): {s["clouds"]} clouds, {s["keyframes"]} keyframes of '
           f'solid_ros, {s["path_m"]:.0f} m; ATE at those keyframes (over every cloud)',
           f'  KISS-ICP            {kiss["ate_keyframes_m"]:8.3f} m ({kiss["ate_all_m"]:.3f} m)'
           f'   {kiss["wall_s"]:6.1f} s']
    for split in splits:
        k = s[f'kiss_slam_{split:g}']
        out.append(f'  KISS-SLAM split {split:>3g} m {k["ate_keyframes_m"]:8.3f} m '
                   f'({k["ate_all_m"]:.3f} m)   {k["wall_s"]:6.1f} s, {k["closures"]} closures')
    best = min(s[f'kiss_slam_{split:g}']['ate_keyframes_m'] for split in splits)
    ate = me['ate_keyframes_m']
    out.append(f'  solid_ros corrected {ate:8.3f} m{"":12s}{me["wall_s"]:6.1f} s, '
               f'{me["loops"]} loops; {ate / kiss["ate_keyframes_m"]:.2f}x KISS-ICP, '
               f'{ate / best:.2f}x the best KISS-SLAM')
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--sets', default=','.join(PRESETS))
    p.add_argument('--split', default='100,25,10,5',
                   help="KISS-SLAM's local map splitting distances, metres (100: its default)")
    p.add_argument('--report', type=Path, help='write the figures here (.md or JSON)')
    args = p.parse_args()
    if not DATA.is_dir():
        print(f'bench_kiss_slam: {DATA} is missing: nothing to run')
        return 0
    try:
        import kiss_slam  # noqa: F401
    except ImportError:
        print('bench_kiss_slam: KISS-SLAM is not installed: pip install kiss-slam==0.0.2')
        return 1
    splits = [float(x) for x in args.split.split(',')]
    figures = {}
    for name in args.sets.split(','):
        figures[name] = run(name, splits)
        print('\n'.join(lines(name, figures[name], splits)), flush=True)
    if args.report is not None:
        meta = bench_meta('bench_kiss_slam', vars(args) | {'sets': args.sets.split(',')})
        columns = (['recording', 'keyframes', 'KISS-ICP ATE']
                   + [f'KISS-SLAM split {x:g} m ATE (closures)' for x in splits]
                   + ['solid_ros corrected ATE (loops)', 'vs KISS-ICP', 'vs best KISS-SLAM'])
        write_report(args.report, meta, columns,
                     [_row(k, v, splits) for k, v in figures.items()],
                     {'recordings': figures}, NOTES)
    return 0


NOTES = ('ATE: RMSE of the positions after an SE(3) alignment to optimized_poses.txt, at the '
         "keyframes solid_ros kept (its corrected poses exist there only); every method ran "
         "on the same clouds with the preset's KISS-ICP max range, min range and voxel, no "
         "deskew. KISS-SLAM 0.0.2 as its own pipeline runs it; 'split': its local maps' "
         'splitting distance (100 m: its default).')


def _row(name: str, s: dict[str, Any], splits: list[float]) -> list[Any]:
    me, kiss = s['solid_ros'], s['kiss_icp']
    slam = [s[f'kiss_slam_{x:g}'] for x in splits]
    best = min(k['ate_keyframes_m'] for k in slam)
    return ([name, s['keyframes'], f'{kiss["ate_keyframes_m"]:.3f} m']
            + [f'{k["ate_keyframes_m"]:.3f} m ({k["closures"]})' for k in slam]
            + [f'{me["ate_keyframes_m"]:.3f} m ({me["loops"]})',
               f'{me["ate_keyframes_m"] / kiss["ate_keyframes_m"]:.2f}x',
               f'{me["ate_keyframes_m"] / best:.2f}x'])


if __name__ == '__main__':
    sys.exit(main())
