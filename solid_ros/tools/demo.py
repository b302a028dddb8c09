"""The README's main command: simulate a drive with revisits, replay it, score it, plot it.

``solid_demo`` (or ``python -m solid_ros.tools.demo``) with no bag makes the built-in drive once
(cached under ``~/.cache/solid_ros/demo``, :mod:`solid_ros.tools.demo_cache`), replays it
through the node's loop closure with the shipped YAML (the drive's drifting odometry, the bag's
/odom, fed as the node's odom; the presets turn the pose graph on; scores against the reference
poses, poses.txt), prints the summary (ATE of the odometry and of the corrected keyframes
among it) and a per-revisit-kind table, and writes plots (trajectory.png: reference, odometry
and corrected). With a bag it is ``solid_replay`` on that bag (``--odometry kiss-icp`` too).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import SolidError
from solid_ros.core.odometry.track import nearest_stamp
from solid_ros.formats.poses import read_times
from solid_ros.runtime import tune_allocator
from solid_ros.tools.evaluation import relative_yaws
from solid_ros.tools.presets import shipped_config
from solid_ros.tools.replay import ReplayResult, load_config, replay, summary_lines
from solid_ros.tools.replay import main as replay_main

__all__ = ['config_overrides', 'drive_options', 'main', 'revisit_table', 'shipped_config']

PROG = 'solid_demo'
# Each simulated sensor and the shipped preset of its class.
SENSOR_PARAMS = {'hdl64': 'hdl64.yaml', 'avia_like': 'avia.yaml', 'ouster_like': 'ouster.yaml',
                 'vlp16_like': 'vlp16.yaml', 'mid360_like': 'mid360.yaml',
                 'hesai_like': 'hesai.yaml'}
ROUTE_CHOICES = ('revisits', 'no_revisit')
SCENE_CHOICES = ('varied', 'lookalike')


def _keyframe_scans(result: ReplayResult, times_path: Path) -> npt.NDArray[np.intp]:
    """Scan index of each keyframe, by stamp (keyframe gating may skip scans); -1: unknown.

    times.txt holds decimal seconds (float-rounded by the simulator), so stamps pair with the
    nearest scan within 1 ms.
    """
    scan_stamps = read_times(times_path)
    return nearest_stamp(scan_stamps, result.stamps_ns, 1_000_000)


def revisit_table(result: ReplayResult, labels_path: Path,
                  radius: float) -> list[tuple[str, int, int, float, int]]:
    """Per revisit kind: (kind, revisits, found, mean yaw error in degrees of the found,
    descriptor top-1 hits).

    A revisit (a keyframe whose scan is labelled other than ``new``) counts as found when a
    loop was published for it whose relative pose is correct (within the replay's pose limits
    of the reference); the yaw error is that loop's. Descriptor top-1: its best descriptor
    match, published or not, lies within the replay's radius. ``radius`` is kept for the
    caller's header.
    """
    rows = [line.split() for line in labels_path.read_text().splitlines() if line.strip()]
    labels = {int(r[0]): r[1] for r in rows}
    loops = result.report.get('loops')
    ev = result.evaluation
    if result.reference is None or loops is None or ev is None:
        return []
    scan_of = _keyframe_scans(result, labels_path.parent / 'times.txt')
    kinds = [labels.get(int(i), 'new') if i >= 0 else 'new' for i in scan_of]
    limits = (loops['max_error_m'], loops['max_error_deg'])
    published = {(c.query_index, c.match_index, c.match_session): c for c in result.candidates}
    rot = result.reference[:, :3, :3]
    seen: dict[str, int] = {}
    top1: dict[str, int] = {}
    errors: dict[str, dict[int, float]] = {}
    for q, kind in enumerate(kinds):
        if kind != 'new':
            seen[kind] = seen.get(kind, 0) + 1
            top1[kind] = top1.get(kind, 0) + int(ev.has_best[q] and ev.correct[q])
    for rec in result.records:
        kind = kinds[rec.query] if 0 <= rec.query < len(kinds) else 'new'
        if kind == 'new' or not rec.published or not rec.correct(*limits):
            continue
        c = published[(rec.query, rec.match, rec.session)]
        truth = float(relative_yaws(rot, [rec.query], [rec.match])[0])
        errors.setdefault(kind, {}).setdefault(
            rec.query, abs(math.degrees(math.remainder(c.yaw - truth, 2 * math.pi))))
    return [(k, n, len(errors.get(k, {})),
             float(np.mean(list(errors[k].values()))) if errors.get(k) else math.nan,
             top1.get(k, 0))
            for k, n in sorted(seen.items())]


def drive_options(args: argparse.Namespace) -> dict[str, Any]:
    """The simulated drive's options (:class:`solid_ros.sim.DriveConfig` fields) from the
    command line; options left at their defaults give the default drive (and cache entry)."""
    from solid_ros.sim.bagwriter import DEMO_SENSORS

    return {'seed': args.seed, 'sensor': DEMO_SENSORS[args.sensor], 'route': args.route,
            'scene': args.scene, 'facade_detail': args.facade_detail,
            'mount_roll_deg': args.tilt_roll_deg, 'mount_pitch_deg': args.tilt_pitch_deg}


def config_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """Detector settings the command line changes in the parameter file: ``--fov``."""
    return {} if args.fov is None else {'fov_width_deg': args.fov}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, usage='%(prog)s [options]  |  %(prog)s BAG [solid_replay options]',
        description='Show loop closure end to end. Without BAG: simulate a LiDAR '
        'drive that revisits places with drifting odometry (cached after the first run), '
        'replay it through the detector and the pose graph with the shipped YAML, print '
        'scores (loops, ATE of the odometry and of the corrected trajectory) and write plots. '
        'With BAG: the same as solid_replay BAG [options] (see solid_replay --help; e.g. '
        '--odometry kiss-icp).')
    p.add_argument('--sensor', choices=sorted(SENSOR_PARAMS), default='hdl64',
                   help='simulated sensor, replayed with the shipped preset of its class: '
                   '64-beam 360-degree (hdl64: +2/-24.8 deg; ouster_like: +-22.5 deg), 32-beam '
                   '(hesai_like: +15/-16 deg), 16-beam (vlp16_like: +-15 deg), 70-degree '
                   'solid-state (avia_like) or 360-degree non-repetitive (mid360_like: '
                   '-7/+52 deg) (default hdl64)')
    p.add_argument('--route', choices=ROUTE_CHOICES, default='revisits',
                   help='revisits: loops back to earlier places; no_revisit: a 2 km serpentine '
                   'that never returns, every scan new (default revisits)')
    p.add_argument('--scene', choices=SCENE_CHOICES, default='varied',
                   help='varied: every street its own character; lookalike: every street the '
                   'same character, places differ only in detail (default varied)')
    p.add_argument('--facade-detail', action='store_true',
                   help='give buildings entrances, bay fronts and stepped upper floors')
    p.add_argument('--tilt-roll-deg', type=float, default=None, metavar='DEG',
                   help='sensor mounting roll in degrees (default 0)')
    p.add_argument('--tilt-pitch-deg', type=float, default=None, metavar='DEG',
                   help='sensor mounting pitch in degrees, positive tips the front down '
                   '(default 0)')
    p.add_argument('--params', type=Path, default=None,
                   help='parameter YAML (default: the shipped preset for --sensor)')
    p.add_argument('--fov', type=float, default=None,
                   help='clip scans to this horizontal FOV in degrees (overrides the YAML)')
    p.add_argument('--seed', type=int, default=0, help='seed of the simulated world (default 0)')
    p.add_argument('--out', type=Path, default=Path('out/demo'),
                   help='directory for candidates.csv, report.json and plots (default out/demo)')
    p.add_argument('--cache-dir', type=Path, default=None,
                   help='where the simulated bag is kept (default ~/.cache/solid_ros/demo)')
    p.add_argument('--radius', type=float, default=5.0,
                   help='a match within this many metres is correct (default 5)')
    p.add_argument('-q', '--quiet', action='store_true', help='no progress output')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the demo; returns the exit status."""
    args_in = list(sys.argv[1:] if argv is None else argv)
    if args_in and not args_in[0].startswith('-'):
        return replay_main(args_in)  # a user's bag: exactly solid_replay
    args = _parser().parse_args(args_in)
    tune_allocator()
    try:
        from solid_ros.tools.demo_cache import ensure_demo_bag

        if not args.quiet:
            print(f'{PROG}: preparing the simulated drive ({args.sensor}, seed {args.seed})...',
                  file=sys.stderr, flush=True)
        bag = ensure_demo_bag(args.cache_dir, **drive_options(args))
        params = args.params or shipped_config(SENSOR_PARAMS[args.sensor])
        overrides = config_overrides(args)
        config, node_config = load_config(params, 'solid_node', overrides)
        result = replay(bag, config, node_config=node_config, poses=bag.parent / 'poses.txt',
                        times=bag.parent / 'times.txt', radius=args.radius,
                        out_dir=args.out, plots=True, progress='quiet' if args.quiet else 'auto',
                        params_file=params)
    except SolidError as err:
        print(f'{PROG}: error: {err}', file=sys.stderr)
        return 1
    for line in summary_lines(result):
        print(line)
    table = revisit_table(result, bag.parent / 'labels.txt', args.radius)
    if table:
        loops = result.report['loops']
        print('  revisits by kind  (found = a published loop with its pose within '
              f'{loops["max_error_m"]:g} m / {loops["max_error_deg"]:g} deg)')
        for kind, total, found, yaw_err, top1 in table:
            yaw = 'n/a' if math.isnan(yaw_err) else f'{yaw_err:.2f} deg'
            print(f'    {kind:<8} {found:4d} of {total:4d} found ({found / total:.2f}), '
                  f'yaw error mean {yaw}; descriptor top-1 within {args.radius:g} m '
                  f'{top1} ({top1 / total:.2f})')
    print(f'  simulated bag     {bag}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
