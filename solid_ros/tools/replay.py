"""solid_replay: run the node's loop detector over a recorded bag, with metrics and plots.

The detector is the node's: the same :class:`~solid_ros.core.flow.detector.LoopDetector`,
configured from the same parameter file by the node's rule (:func:`load_config`), fed the
same decoded clouds (:func:`~solid_ros.formats.pointcloud2.cloud_to_xyz`) and header stamps.
Odometry poses pair with clouds by the node's rule over the whole recorded track, which only
differs from the node for odometry that reaches it late (see :mod:`solid_ros.tools.pipeline`).

:func:`replay` is the run, a screen of calls: :class:`~solid_ros.tools.options.ReplayOptions`
say what to read, score and write; :class:`~solid_ros.tools.pipeline.ReplayPipeline` yields one
record per scan; :mod:`~solid_ros.tools.scoring`, :mod:`~solid_ros.tools.reports` and
:mod:`~solid_ros.tools.outputs` score, report and write it. Several bags are a fleet
(:mod:`solid_ros.tools.fleet`).

The scans go through the product's :class:`~solid_ros.core.flow.closure.LoopClosure`, the
per-scan flow the node runs on its two threads: the detector and, with ``backend: true``, the
pose graph (whose hint the next keyframe is verified with), whose corrected keyframe poses are
written as ``trajectory.tum`` / ``trajectory.kitti`` (:mod:`solid_ros.tools.trajectory`) and
scored (ATE, RPE) beside the odometry's. The odometry is the bag's Odometry topic or KISS-ICP
over the clouds (``--odometry kiss-icp``).

Usage: ``solid_replay BAG [--params FILE.yaml] [--set KEY=VALUE ...] [--topic /points]
[--odometry bag|kiss-icp] [--odom-topic T | --poses FILE [--times FILE]] [--out DIR [--map]]
[--load-db F] [--save-db F]``; ``solid_replay BAG --suggest-params [--topic T] [--params F]``
prints a parameter file for the bag's sensor (:mod:`solid_ros.tools.suggest`).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from solid_ros.core.backend.mapping import MapCloud, build_map, keyframe_clouds, mount_rotation
from solid_ros.core.config import NodeConfig, SolidConfig, check_parameters, load_parameter_file
from solid_ros.core.database.persistence import check_save_target
from solid_ros.core.errors import ConfigError, PoseError, SolidError
from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.formats.poses import PoseTrack, load_reference
from solid_ros.runtime import tune_allocator
from solid_ros.tools.fleet import fleet_summary_lines, replay_fleet, write_fleet_outputs
from solid_ros.tools.options import (
    ODOMETRY_CHOICES,
    ReplayOptions,
    check_degrees,
    check_fraction,
    check_metres,
    cli_number,
    fleet_note,
)
from solid_ros.tools.outputs import CSV_COLUMNS, write_outputs
from solid_ros.tools.pipeline import BagInputs, OdometryWrap, ReplayPipeline
from solid_ros.tools.progress import Progress
from solid_ros.tools.reports import PROG, closure_report, replay_report
from solid_ros.tools.result import ReplayResult
from solid_ros.tools.scoring import score
from solid_ros.tools.summary import summary_lines
from solid_ros.tools.trajectory import Trajectory, keyframe_trajectory, trajectory_errors

__all__ = ['CSV_COLUMNS', 'ReplayOptions', 'ReplayResult', 'build_parser',
           'expand_set_arguments', 'load_config', 'main', 'parse_arguments', 'replay',
           'summary_lines']


def load_config(params: str | Path | None, node_name: str = 'solid_node',
                overrides: dict[str, Any] | None = None) -> tuple[SolidConfig, NodeConfig]:
    """Read the detector and node settings from a parameter file, as the node does.

    The file passes the node's rule (:func:`~solid_ros.core.config.load_parameter_file`), and
    ``overrides`` (``--set``) the rule of the node's ``-p`` overrides.

    Raises:
        ConfigError: unreadable file, unknown key or invalid value (named).
    """
    values: dict[str, Any] = {}
    if params is not None:
        values = load_parameter_file(params, node_name)
    check_parameters(overrides or {}, '--set')
    values.update(overrides or {})
    return (SolidConfig.from_dict(values, strict=False),
            NodeConfig.from_dict(values, strict=False))


def replay(bag: str | Path, config: SolidConfig | None = None,
           options: ReplayOptions | None = None, wrap_odometry: OdometryWrap | None = None,
           **changes: Any) -> ReplayResult:
    """Replay a bag through the node's loop closure (detector, and the back end with
    ``config.backend``) and score it when reference poses are known.

    Args:
        bag: ROS 2 bag directory (MCAP or sqlite3) or ROS 1 .bag file.
        config: detector settings (default ``SolidConfig()``).
        options: what to read, how to score, where to write (default: the defaults).
        wrap_odometry: applied to the odometry source the options chose (a plug-in: e.g.
            the same odometry in another frame).
        **changes: :class:`ReplayOptions` fields replacing those of ``options``, e.g.
            ``replay(bag, cfg, poses='poses.txt', out_dir='out')``.

    Raises:
        SolidError: any problem with the inputs (BagError, ConfigError, DatabaseError,
            PoseError), with a one-line message.
        TypeError: a change names no option.
    """
    opts = ReplayOptions.of(options, **changes)
    cfg = (config if config is not None else SolidConfig()).for_odometry(
        opts.feed_odom and opts.odometry_mode == 'kiss-icp')
    poses = load_reference(opts.poses, opts.times) if opts.poses is not None else None
    if opts.save_db is not None:
        check_save_target(opts.save_db)  # refuse before the run, not after it
    closure = (LoopClosure.load(opts.load_db, cfg) if opts.load_db is not None
               else LoopClosure(LoopDetector(cfg)))
    t0 = time.perf_counter()
    with ReplayPipeline(bag, closure, opts, wrap_odometry) as pipeline:
        _check_pose_count(poses, pipeline.inputs)
        log = pipeline.collect(Progress(pipeline.inputs.count, opts.progress, opts.stream))
    wall = time.perf_counter() - t0
    if opts.save_db is not None:
        closure.save(opts.save_db)
    scores = score(log, poses if poses is not None else pipeline.inputs.odometry, cfg, opts)
    traj = keyframe_trajectory(log, closure)
    report = replay_report(pipeline.inputs, log, scores, closure.detector, opts, wall)
    report.update(closure_report(pipeline.inputs, log, closure, traj,
                                 trajectory_errors(traj, scores.reference)))
    result = ReplayResult(pipeline.inputs, cfg, log, scores, report, wall, traj,
                          _map(closure, traj, opts) if opts.map else None)
    if opts.out_dir is not None:
        result.files = write_outputs(Path(opts.out_dir), result, opts.plots)
    return result


def _map(closure: LoopClosure, traj: Trajectory, opts: ReplayOptions) -> MapCloud:
    """The kept keyframe clouds at their corrected poses, thinned as the node's map."""
    have = traj.posed
    poses = dict(zip(traj.indices[have].tolist(), traj.corrected[have]))
    ncfg = opts.node_config
    return build_map(keyframe_clouds(closure.detector, poses), mount_rotation(closure.config),
                     ncfg.map_voxel_size, ncfg.map_max_points)


def _check_pose_count(poses: PoseTrack | None, inputs: BagInputs) -> None:
    """Poses without stamps pair with clouds by order: there must be one per cloud."""
    if poses is not None and poses.stamps_ns is None and len(poses) != inputs.count:
        raise PoseError(f'{poses.source} has {len(poses)} poses but {inputs.topic} has '
                        f'{inputs.count} clouds; pair them with --times')


# ------------------------------------------------------------------------------ command line


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # one line, no usage dump
        self.exit(2, f'{self.prog}: error: {message} (see --help)\n')


_METRES = cli_number(check_metres, 'metres')
_DEGREES = cli_number(check_degrees, 'degrees')
_FRACTION = cli_number(check_fraction, 'fraction')


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser (``solid_replay --help``)."""
    p = _Parser(
        prog=PROG,
        description='Replay a recorded bag through the same SOLiD loop detector and pose '
                    'graph the node runs (same parameter file), print loop candidates and, '
                    'given reference poses, evaluate them: Recall@1, PR curve, F1max and its '
                    'threshold, ROC AUC, yaw error, ATE / RPE of the odometry and of the '
                    'corrected trajectory; write candidates.csv, report.json, '
                    'trajectory.tum/.kitti with --out (and PNG plots with --plots).',
        epilog='With several bags (a fleet) --poses, --times, --load-db, --save-db '
               'and --map mean nothing and are ignored, one line each saying why; '
               'the other options apply to every robot; with the back end each robot places '
               "the others' maps in its own, and --out gets trajectory_robot<i>.tum in robot "
               "0's map and fleet_map.png. "
               'Reference poses come from --poses (KITTI 3x4 rows, paired with scans by order '
               'or by --times stamps; or TUM "stamp tx ty tz qx qy qz qw") or else from the '
               "bag's Odometry topic. A query has a true loop when an earlier scan outside the "
               'exclusion window lies within --radius metres. Exit status: 0 ok, 1 bad input '
               '(bag, poses, parameters, database), 2 bad command line.')
    p.add_argument('bag', nargs='+', metavar='BAG',
                   help='ROS 2 bag directory (MCAP or sqlite3) or ROS 1 .bag file; several '
                        'bags = a fleet, one robot each (robot i = session_id i), which share '
                        'keyframes as nodes with peers do and are scored on '
                        'inter-robot loops (each needs an Odometry topic in one world frame: the '
                        'reference)')
    p.add_argument('--params', metavar='FILE.yaml',
                   help='ROS 2 parameter file as given to the node (default: built-in '
                        "defaults = the SOLiD authors' parameters)")
    p.add_argument('--suggest-params', action='store_true',
                   help="print a parameter file for the bag's sensor and exit, without "
                        'replaying: its first clouds measured (field of view, ranges, rings), '
                        'the nearest shipped preset (or --params) changed where they '
                        'contradict it, with comments saying what was measured')
    p.add_argument('--node-name', default='solid_node', metavar='NAME',
                   help='node block read from --params (default: %(default)s)')
    p.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='override parameters after --params: one or more KEY=VALUE after one '
                        '--set, or --set repeated, e.g. --set fov_up_deg=52.0 '
                        'fov_down_deg=-7.0. After --set every argument NAME=VALUE (NAME of '
                        "letters, digits, '_' and '.') is an override, up to the first that is "
                        'not: a bag whose name looks like that goes before --set or is written '
                        './NAME=VALUE')
    p.add_argument('--topic', help='PointCloud2 topic (default: the only one in the bag; '
                                   'the choices are listed when there are several)')
    p.add_argument('--odom-topic', metavar='T',
                   help="nav_msgs/Odometry topic: fed to the detector like the node's odom and "
                        'used as reference poses unless --poses is given (default: the only '
                        'one in the bag, if any)')
    p.add_argument('--no-odom', action='store_true',
                   help='do not feed odometry to the detector (like use_odom: false)')
    p.add_argument('--odometry', choices=ODOMETRY_CHOICES, default=None,
                   help="odometry fed to the detector and the back end: 'bag' (the bag's "
                        "Odometry topic) or 'kiss-icp' (KISS-ICP registers the clouds, with "
                        "the kiss_* parameters; the Odometry topic, if any, is then only the "
                        "reference) (default: the parameter file's odometry_source, "
                        "'topic' = bag)")
    p.add_argument('--poses', metavar='FILE',
                   help='reference poses: KITTI 3x4 (one per scan, or per --times stamp) or TUM')
    p.add_argument('--times', metavar='FILE',
                   help='stamps in seconds, one per line, for a KITTI --poses file')
    _scoring_options(p)
    _output_options(p)
    return p


def _scoring_options(p: argparse.ArgumentParser) -> None:
    p.add_argument('--radius', type=_METRES, default=5.0, metavar='M',
                   help='true-loop distance in metres (default: %(default)s)')
    p.add_argument('--max-pose-error-m', type=_METRES, default=1.0, metavar='M',
                   help='a published loop is correct when its relative pose is within this '
                        'translation of the reference one (default: %(default)s)')
    p.add_argument('--max-pose-error-deg', type=_DEGREES, default=3.0, metavar='DEG',
                   help='... and within this rotation (default: %(default)s)')
    p.add_argument('--target-precision', type=_FRACTION, default=1.0, metavar='P',
                   help='the sweep recommends the setting that reaches this precision of '
                        'published loops (default: %(default)s = no false loop)')
    p.add_argument('--max-heading-deg', type=_DEGREES, metavar='DEG',
                   help='also require a heading difference below this for a true loop')


def _output_options(p: argparse.ArgumentParser) -> None:
    p.add_argument('--out', metavar='DIR',
                   help='write candidates.csv, report.json and the trajectories here')
    p.add_argument('--plots', action='store_true',
                   help='with --out, also write PNG plots (trajectory, verification, '
                        'histograms, precision-recall; needs matplotlib)')
    p.add_argument('--no-plots', action='store_true',
                   help='no PNG plots (the default; kept for scripts that pass it)')
    p.add_argument('--map', action='store_true',
                   help='also write map.pcd: the keyframe clouds at their corrected poses '
                        '(map_voxel_size, map_max_points)')
    p.add_argument('--load-db', metavar='F', help='database file to search as well (saved '
                                                  'by the node or --save-db)')
    p.add_argument('--save-db', metavar='F', help='save the database after the run')
    p.add_argument('--progress', choices=('auto', 'bar', 'lines'), default='auto',
                   help='progress display: bar on a terminal, plain lines otherwise '
                        '(default: %(default)s)')
    p.add_argument('-q', '--quiet', action='store_true',
                   help='no progress and no summary; errors only')


# An override that follows another after one --set: a parameter name, '=', its value.
_SETTING = re.compile(r'[A-Za-z_][A-Za-z0-9_.]*=')


def expand_set_arguments(argv: Sequence[str]) -> list[str]:
    """``--set a=1 b=2`` as ``--set a=1 --set b=2``, for argparse.

    The argument right after ``--set`` is its value, whatever it is (a bad one is refused
    with its own message); after it, every ``NAME=VALUE`` argument is one more override, up
    to the first that is not one (a bag, an option) or ``--``. Bags may contain '=' too,
    rarely: one with a '/' (``./run=3``) is never taken for an override.
    """
    args = list(argv)
    out: list[str] = []
    setting = False
    i = 0
    while i < len(args):
        arg = args[i]
        if arg == '--':
            out += args[i:]
            break
        if setting and _SETTING.match(arg):
            out += ['--set', arg]
        elif arg == '--set':
            out += args[i:i + 2]
            i += 1
            setting = True
        else:
            setting = arg.startswith('--set=')
            out.append(arg)
        i += 1
    return out


def parse_arguments(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line parsed: several overrides after one ``--set``, and bags before,
    between or after the options; exits 2 with one line for a bad one."""
    return build_parser().parse_intermixed_args(
        expand_set_arguments(sys.argv[1:] if argv is None else argv))


def _overrides(items: list[str]) -> dict[str, Any]:
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition('=')
        if not sep or not key:
            raise ConfigError(f'--set expects KEY=VALUE, got {item!r}')
        try:
            out[key.strip()] = yaml.safe_load(text)
        except yaml.YAMLError as err:
            raise ConfigError(f'--set {key}: cannot parse {text!r}') from err
    return out


def _options(args: argparse.Namespace) -> ReplayOptions:
    """The replay options the command line gives (the node settings come later)."""
    return ReplayOptions(
        topic=args.topic, odom_topic=args.odom_topic, use_odom=False if args.no_odom else None,
        odometry=args.odometry, map=args.map, poses=args.poses, times=args.times,
        radius=args.radius,
        max_heading_deg=args.max_heading_deg, max_pose_error_m=args.max_pose_error_m,
        max_pose_error_deg=args.max_pose_error_deg, target_precision=args.target_precision,
        out_dir=args.out, plots=args.plots and not args.no_plots, load_db=args.load_db,
        save_db=args.save_db, params_file=args.params,
        progress='quiet' if args.quiet else args.progress)


def _fleet_options(args: argparse.Namespace) -> ReplayOptions:
    """The options of a fleet replay; one line on stderr, even with -q, for each option
    given that means nothing to a fleet (ignored, not refused)."""
    notes: list[str] = []
    if args.times and not args.poses:  # alone, a bad option everywhere else
        notes.append(fleet_note('--times'))
        args.times = None
    options, ignored = _options(args).for_fleet()
    for line in notes + ignored:
        print(f'{PROG}: {line}', file=sys.stderr)
    return options


def _run_fleet(bags: list[str], config: SolidConfig, options: ReplayOptions,
               quiet: bool) -> int:
    fleet = replay_fleet(bags, config, options)
    files = (write_fleet_outputs(options.out_dir, fleet, options.plots) if options.out_dir
             else [])
    if not quiet:
        print('\n'.join(fleet_summary_lines(fleet, PROG)))
        if files:
            print(f'  outputs          {", ".join(str(f) for f in files)}')
    return 0


def _suggest(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """``--suggest-params``: the suggested parameter file on stdout."""
    if len(args.bag) > 1:
        parser.error('--suggest-params takes one bag')
    from solid_ros.tools.suggest import suggest_parameters

    try:
        text = suggest_parameters(args.bag[0], args.topic, args.params)
    except SolidError as err:
        print(f'{PROG}: error: {" ".join(str(err).split())}', file=sys.stderr)
        return 1
    sys.stdout.write(text)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``solid_replay``; returns the exit status."""
    parser = build_parser()
    args = parse_arguments(argv)
    fleet = len(args.bag) > 1
    if args.times and not args.poses and not fleet:
        parser.error('--times needs --poses')
    if args.map and not args.out and not fleet:
        parser.error('--map needs --out')
    if args.no_odom and args.odometry is not None:
        parser.error('--no-odom and --odometry exclude each other')
    if args.suggest_params:
        return _suggest(args, parser)
    options = _fleet_options(args) if fleet else _options(args)
    tune_allocator()
    try:
        cfg, ncfg = load_config(args.params, args.node_name, _overrides(args.set))
        options = replace(options, node_config=ncfg)
        if len(args.bag) > 1:
            return _run_fleet(args.bag, cfg, options, args.quiet)
        result = replay(args.bag[0], cfg, options)
    except SolidError as err:
        print(f'{PROG}: error: {" ".join(str(err).split())}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted', file=sys.stderr)
        return 130
    if not args.quiet:
        print('\n'.join(summary_lines(result)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
