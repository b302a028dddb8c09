"""Tests of solid_replay: bags in all formats, outputs, bad input, hku1, node parity."""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from bad_inputs import unusable_clouds
from project_paths import CONFIG_DIR  # noqa: E402

from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import ConfigError
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.reasons import RULE_REASONS as REASONS
from solid_ros.formats.bags import POINTCLOUD2, BagWriter, write_cloud_bag
from solid_ros.formats.pointcloud2 import CloudLayout, encode_points
from solid_ros.tools.plots import PLOT_FILES
from solid_ros.tools.replay import (
    CSV_COLUMNS,
    _options,
    build_parser,
    expand_set_arguments,
    main,
    parse_arguments,
    replay,
    summary_lines,
)

# 10 places along a line, then places 0..5 again; 3 scans may not match their neighbours.
ROUTE = list(range(10)) + list(range(6))
TEST_CFG = SolidConfig(exclude_recent_frames=3, distance_threshold=0.02)


def _place(k: int, n: int = 4000) -> np.ndarray:
    """A distinct synthetic scan per place: walls at place-specific ranges and headings."""
    rng = np.random.default_rng(1000 + k)
    centres = rng.uniform(5.0, 70.0, size=4)
    r = rng.choice(centres, size=n) + rng.normal(scale=1.0, size=n)
    az = rng.uniform(-np.pi, np.pi, size=n)
    el = np.radians(rng.uniform(-24.0, 1.5, size=n))
    pts = np.stack([r * np.cos(az) * np.cos(el), r * np.sin(az) * np.cos(el), r * np.sin(el),
                    rng.uniform(0, 100, size=n)], axis=1)
    return pts.astype(np.float32)


def _pose(k: int, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:3, 3] = [30.0 * k, 0.0, 0.0]
    return out


def _scans() -> list[tuple[np.ndarray, int, np.ndarray]]:
    rng = np.random.default_rng(7)
    out = []
    for i, k in enumerate(ROUTE):
        pts = _place(k).copy()
        pts[:, :3] += rng.normal(scale=0.02, size=(len(pts), 3)).astype(np.float32)
        out.append((pts, 10**18 + i * 100_000_000, _pose(k)))
    return out


@pytest.fixture(scope='module')
def scans() -> list[tuple[np.ndarray, int, np.ndarray]]:
    return _scans()


@pytest.fixture(scope='module')
def bags(tmp_path_factory: pytest.TempPathFactory,
         scans: list[tuple[np.ndarray, int, np.ndarray]]) -> dict[str, Path]:
    root = tmp_path_factory.mktemp('bags')
    return {fmt: write_cloud_bag(root / fmt, scans, fmt) for fmt in ('mcap', 'sqlite3', 'ros1')}


def _direct(scans: list[tuple[np.ndarray, int, np.ndarray]], cfg: SolidConfig) -> list[tuple]:
    det = LoopDetector(cfg)
    out = []
    for pts, stamp, pose in scans:
        for c in det.process(pts[:, :3], stamp, pose=pose).loops:
            out.append((c.query_index, c.match_index, c.query_stamp_ns, c.match_stamp_ns,
                        c.distance, c.yaw))
    return out


def _key(result) -> list[tuple]:  # type: ignore[no-untyped-def]
    return [(c.query_index, c.match_index, c.query_stamp_ns, c.match_stamp_ns, c.distance, c.yaw)
            for c in result.candidates]


@pytest.mark.parametrize('fmt', ['mcap', 'sqlite3', 'ros1'])
def test_replay_equals_detector_in_every_format(
        bags: dict[str, Path], scans: list[tuple[np.ndarray, int, np.ndarray]],
        fmt: str) -> None:
    result = replay(bags[fmt], TEST_CFG, progress='quiet')
    want = _direct(scans, TEST_CFG)
    assert _key(result) == want
    assert [(q, m) for q, m, *_ in want] == [(10 + k, k) for k in range(6)]
    assert result.messages == len(ROUTE) and result.skipped == 0
    assert result.report['odom_topic'] == '/odom' and result.report['odometry_fed_to_detector']
    m = result.metrics
    assert m is not None
    assert m['queries_with_true_loop'] == 6 and m['recall_at_1'] == 1.0
    assert m['f1_max'] == 1.0 and m['roc_auc'] == 1.0
    assert m['accepted'] == {'count': 6, 'true': 6, 'false': 0, 'precision': 1.0,
                             'recall': 1.0}
    assert m['yaw_error_deg']['max'] < 3.0


def test_best_matches_cover_rejected_queries(bags: dict[str, Path]) -> None:
    strict = TEST_CFG.replace(distance_threshold=1e-9)
    result = replay(bags['mcap'], strict, progress='quiet')
    assert result.candidates == []
    revisits = [b for b in result.best[10:] if b is not None]
    assert [(b.query_index, b.match_index) for b in revisits] == [(10 + k, k) for k in range(6)]
    assert not result.accepted.any()
    # Scans 0..3 have no eligible scan yet (exclusion window 3).
    assert result.best[:4] == [None] * 4 and all(b is not None for b in result.best[4:])
    assert result.metrics is not None and result.metrics['f1_max'] == 1.0


@pytest.mark.slow
def test_outputs(tmp_path: Path, bags: dict[str, Path]) -> None:
    out = tmp_path / 'out'
    result = replay(bags['sqlite3'], TEST_CFG, out_dir=out, plots=True, progress='quiet')
    with (out / 'candidates.csv').open() as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == CSV_COLUMNS
    best_rows = [r for r in rows if r['best'] == '1']
    assert len(best_rows) == sum(b is not None for b in result.best)
    acc = [r for r in rows if r['accepted'] == '1']
    assert [(int(r['query_index']), int(r['match_index'])) for r in acc] == \
        [(10 + k, k) for k in range(6)]
    assert all(r['true_match'] == '1' and float(r['gt_distance_m']) < 1e-6 for r in acc)
    report = json.loads((out / 'report.json').read_text())
    for key in ('recall_at_1', 'f1_max', 'f1_max_threshold', 'roc_auc'):
        assert key in report['metrics']
    assert set(report['metrics']['yaw_error_deg']) >= {'mean', 'median', 'p95', 'max'}
    # The settings in force: 'auto' resolved for the bag's odometry (not a scan-only one).
    assert report['config'] == TEST_CFG.for_odometry(scan_only=False).to_dict()
    assert report['versions']['solid_ros'] and report['timings']['detect_ms']['p50'] > 0
    assert report['database']['size'] == len(ROUTE)
    for name in PLOT_FILES:
        data = (out / name).read_bytes()
        assert data[:8] == b'\x89PNG\r\n\x1a\n' and len(data) > 10_000


@pytest.mark.slow
def test_reference_from_pose_files(tmp_path: Path, bags: dict[str, Path],
                                   scans: list[tuple[np.ndarray, int, np.ndarray]]) -> None:
    kitti = tmp_path / 'poses.txt'
    np.savetxt(kitti, np.stack([p[:3, :] for _, _, p in scans]).reshape(-1, 12))
    times = tmp_path / 'times.txt'
    times.write_text(''.join(f'{s // 10**9}.{s % 10**9:09d}\n' for _, s, _ in scans))
    by_order = replay(bags['ros1'], TEST_CFG, poses=kitti, use_odom=False, progress='quiet')
    by_stamp = replay(bags['ros1'], TEST_CFG, poses=kitti, times=times, progress='quiet')
    tum = tmp_path / 'traj.tum'
    tum.write_text(''.join(f'{s / 1e9:.9f} {p[0, 3]} {p[1, 3]} {p[2, 3]} 0 0 0 1\n'
                           for _, s, p in scans))
    by_tum = replay(bags['ros1'], TEST_CFG, poses=tum, progress='quiet')
    for r in (by_order, by_stamp, by_tum):
        assert r.metrics is not None and r.metrics['recall_at_1'] == 1.0
        assert r.report['reference'] != '/odom'
    assert not by_order.report['odometry_fed_to_detector']


def test_malformed_clouds_are_skipped_and_counted(tmp_path: Path,
                                                  scans: list[tuple]) -> None:
    good = encode_points(np.ones((10, 3)))
    short = CloudLayout(fields=good.fields, width=50, point_step=good.point_step,
                        row_step=good.point_step * 50, data=good.data)
    path = tmp_path / 'bad_inside'
    with BagWriter(path, 'mcap') as w:
        w.add_topic('/points', POINTCLOUD2)
        for i, (pts, stamp, _) in enumerate(scans):
            if i in (3, 12):
                w.write('/points', stamp - 1, w.cloud_msg(short, stamp - 1))
            if i == 7:
                w.write_raw('/points', stamp - 1, b'\x00\x01\x00\x00broken')
            w.write('/points', stamp, w.cloud_msg(pts, stamp))
    result = replay(path, TEST_CFG, progress='quiet')
    assert result.messages == len(scans) + 3 and result.skipped == 3
    assert len(result.report['scans']['skip_reasons']) == 3
    assert [(c.query_index, c.match_index) for c in result.candidates] == \
        [(10 + k, k) for k in range(6)]


def test_clouds_without_a_usable_point_are_skipped_and_counted(
        tmp_path: Path, scans: list[tuple], bags: dict[str, Path]) -> None:
    # They decode, but the detector refuses them (CloudError): skipped like undecodable ones,
    # so no index and no loop moves.
    bad = list(unusable_clouds(300, TEST_CFG.max_range).values())
    path = tmp_path / 'unusable_inside'
    with BagWriter(path, 'mcap') as w:
        w.add_topic('/points', POINTCLOUD2)
        for i, (pts, stamp, _) in enumerate(scans):
            if i % 2 == 0:
                cloud = bad[(i // 2) % len(bad)]
                w.write('/points', stamp - 1, w.cloud_msg(cloud.astype(np.float32), stamp - 1))
            w.write('/points', stamp, w.cloud_msg(pts, stamp))
    n_bad = (len(scans) + 1) // 2
    out = tmp_path / 'out'
    result = replay(path, TEST_CFG, out_dir=out, progress='quiet')
    clean = replay(bags['mcap'], TEST_CFG, progress='quiet')
    assert result.messages == len(scans) + n_bad and result.skipped == n_bad
    assert result.keyframes == clean.keyframes == len(scans)
    assert _key(result) == _key(clean) and _key(clean)
    report = json.loads((out / 'report.json').read_text())
    assert report['scans']['skipped'] == n_bad
    assert report['scans']['decoded'] == len(scans)
    reasons = [r['reason'] for r in report['scans']['skip_reasons']]
    assert reasons and all(r.startswith('no usable point: ') for r in reasons)


def test_save_and_load_database(tmp_path: Path, bags: dict[str, Path]) -> None:
    db = tmp_path / 'db.npz'
    first = replay(bags['mcap'], TEST_CFG, save_db=db, progress='quiet')
    assert db.is_file() and first.report['saved_database'] == str(db)
    second = replay(bags['mcap'], TEST_CFG.replace(session_id=1), load_db=db, progress='quiet')
    # Every scan of the second session finds itself in the loaded session 0.
    foreign = [c for c in second.candidates if c.match_session == 0]
    assert len(foreign) >= len(ROUTE) - 1
    assert second.metrics is not None  # foreign matches count as false, but it runs


# -- command line -------------------------------------------------------------------------------


def test_help_explains_every_option(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(['--help'])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for action in build_parser()._actions:
        for opt in action.option_strings:
            assert opt in text
        assert action.help, action.dest


@pytest.mark.slow
def test_cli_runs_and_prints_summary(tmp_path: Path, bags: dict[str, Path],
                                     capsys: pytest.CaptureFixture[str]) -> None:
    params = tmp_path / 'p.yaml'
    params.write_text('solid_node:\n  ros__parameters:\n    exclude_recent_frames: 3\n')
    code = main([str(bags['mcap']), '--params', str(params), '--set',
                 'distance_threshold=0.02', '--out', str(tmp_path / 'o'), '--progress',
                 'lines'])
    out, err = capsys.readouterr()
    assert code == 0
    assert 'Recall@1 1.000' in out and 'published loops' in out and 'verify_min_overlap' in out
    assert f'{len(ROUTE)}/{len(ROUTE)} scans' in err  # the final progress line
    report = json.loads((tmp_path / 'o' / 'report.json').read_text())
    assert report['config']['exclude_recent_frames'] == 3
    assert report['config']['distance_threshold'] == 0.02
    assert report['params_file'] == str(params)
    # What the first clouds show of the sensor, in the summary and the report.
    assert '  sensor            360-degree' in out
    assert report['sensor']['measured'].startswith('360-degree')
    assert not list((tmp_path / 'o').glob('*.png'))  # plots only with --plots


def test_plots_are_opt_in() -> None:
    def plots(*argv: str) -> bool:
        return _options(parse_arguments(['B', '--out', 'o', *argv])).plots

    assert (plots(), plots('--plots'), plots('--no-plots')) == (False, True, False)


@pytest.mark.parametrize('argv', [
    ['BAG', '--set', 'fov_up_deg=52.0', 'fov_down_deg=-7.0'],
    ['--set', 'fov_up_deg=52.0', 'fov_down_deg=-7.0', 'BAG'],
    ['--set', 'fov_up_deg=52.0', '--set', 'fov_down_deg=-7.0', 'BAG'],
    ['--set=fov_up_deg=52.0', 'fov_down_deg=-7.0', 'BAG', '-q'],
    ['--set', 'fov_up_deg=52.0', '-q', 'BAG', '--set', 'fov_down_deg=-7.0'],
], ids=['after the bag', 'before the bag', 'repeated', 'with =', 'split'])
def test_set_takes_several_pairs_or_repeats(argv: list[str]) -> None:
    args = parse_arguments(argv)
    assert args.bag == ['BAG'] and args.set == ['fov_up_deg=52.0', 'fov_down_deg=-7.0']


def test_set_leaves_bags_and_options_alone() -> None:
    # A fleet's bags on either side of the overrides.
    for argv in (['A', 'B', '--set', 'a=1', 'b=2'], ['--set', 'a=1', 'b=2', 'A', 'B'],
                 ['A', '--set', 'a=1', 'b=2', 'B']):
        args = parse_arguments(argv)
        assert (args.bag, args.set) == (['A', 'B'], ['a=1', 'b=2']), argv
    # A bag with '=' in its name: written with a path, or before --set, or after '--'.
    args = parse_arguments(['--set', 'a=1', './run=3', 'B'])
    assert (args.bag, args.set) == (['./run=3', 'B'], ['a=1'])
    assert parse_arguments(['run=3', '--set', 'a=1']).bag == ['run=3']
    assert parse_arguments(['--set', 'a=1', '--', 'run=3']).bag == ['run=3']
    # The value right after --set is its own, whatever it is; the next option ends the run.
    args = parse_arguments(['--set', 'oops', 'a=1', '--radius', '2', 'B'])
    assert (args.bag, args.set, args.radius) == (['B'], ['oops', 'a=1'], 2.0)
    assert expand_set_arguments(['--set']) == ['--set']


def test_set_pairs_reach_the_replay(tmp_path: Path, bags: dict[str, Path],
                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / 'o'
    code = main(['--set', 'fov_up_deg=5.0', 'fov_down_deg=-30.0', str(bags['mcap']),
                 '--out', str(out), '--no-plots', '-q'])
    assert code == 0, capsys.readouterr().err
    config = json.loads((out / 'report.json').read_text())['config']
    assert (config['fov_up_deg'], config['fov_down_deg']) == (5.0, -30.0)
    # A typo among several pairs: one line naming it, exit 1.
    assert main([str(bags['mcap']), '--set', 'fov_up_deg=5.0', 'fov_dwon_deg=-30.0']) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "unknown parameter 'fov_dwon_deg'" in err[0], err
    # No pair at all after --set.
    with pytest.raises(SystemExit) as exc:
        main([str(bags['mcap']), '--set'])
    assert exc.value.code == 2


def test_cli_quiet(bags: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(bags['mcap']), '--quiet']) == 0
    assert capsys.readouterr() == ('', '')


def _bad_inputs(tmp_path: Path, bags: dict[str, Path]) -> dict[str, tuple[list[str], str]]:
    notbag = tmp_path / 'notes.txt'
    notbag.write_text('hello')
    trunc = tmp_path / 'trunc'
    trunc.mkdir()
    src = bags['mcap']
    (trunc / 'metadata.yaml').write_bytes((src / 'metadata.yaml').read_bytes())
    data = (src / 'mcap.mcap').read_bytes()
    (trunc / 'mcap.mcap').write_bytes(data[:len(data) // 3])
    damaged, flipped = tmp_path / 'damaged', tmp_path / 'flipped'
    for bag, pos, blob in ((damaged, len(data) // 2, os.urandom(64)),
                           (flipped, len(data) // 3, bytes([data[len(data) // 3] ^ 4]))):
        bag.mkdir()
        (bag / 'metadata.yaml').write_bytes((src / 'metadata.yaml').read_bytes())
        (bag / 'mcap.mcap').write_bytes(data[:pos] + blob + data[pos + len(blob):])
    ros1 = tmp_path / 'cut.bag'
    ros1.write_bytes(bags['ros1'].read_bytes()[:5000])
    poses = tmp_path / 'poses.txt'
    poses.write_text('1 0 0 0 0 1 0 0 0 0 1 0\n' * 5)
    times = tmp_path / 'times.txt'
    times.write_text('1.0\n2.0\n')
    params = tmp_path / 'bad.yaml'
    params.write_text('solid_node:\n  ros__parameters:\n    num_range: -3\n')
    binary = tmp_path / 'binary.yaml'
    binary.write_bytes(bytes(range(256)))
    integer = tmp_path / 'integer.yaml'
    integer.write_text('solid_node:\n  ros__parameters:\n    fov_width_deg: 90\n')
    n = len(ROUTE)
    poses16 = tmp_path / 'poses16.txt'
    poses16.write_text('1 0 0 0 0 1 0 0 0 0 1 0\n' * n)
    zero_rot = tmp_path / 'zero_rot.txt'
    zero_rot.write_text('1 0 0 0 0 1 0 0 0 0 1 0\n' * (n - 1) + '0 0 0 1 0 0 0 2 0 0 0 3\n')
    repeated = tmp_path / 'repeated.txt'
    repeated.write_text(''.join(f'{t}.5\n' for t in [0, 1, 2, 2] + list(range(4, n))))
    back = tmp_path / 'back.txt'
    back.write_text(''.join(f'{t}.5\n' for t in [0, 2, 1] + list(range(3, n))))
    tum = tmp_path / 'tum.txt'
    tum.write_text(''.join(f'{t} 0 0 0 0 0 0 1\n' for t in [3, 2] + list(range(4, n + 2))))
    b = str(bags['mcap'])
    return {
        'missing path': ([str(tmp_path / 'nope')], 'no such file or directory'),
        'not a bag': ([str(notbag)], 'not a bag'),
        'truncated mcap': ([str(trunc)], 'truncated MCAP file'),
        'overwritten bytes in a chunk': ([str(damaged)], 'fails its CRC check'),
        'one bit flipped': ([str(flipped)], 'fails its CRC check'),
        'truncated ros1': ([str(ros1)], 'cut.bag'),
        'topic absent': ([b, '--topic', '/lidar'], 'topic /lidar not in bag'),
        'wrong type': ([b, '--topic', '/odom'], 'has type nav_msgs/msg/Odometry'),
        'wrong odom type': ([b, '--odom-topic', '/points'], 'expected nav_msgs/msg/Odometry'),
        'poses/times mismatch': ([b, '--poses', str(poses), '--times', str(times)],
                                 'has 5 poses but'),
        'poses/scans mismatch': ([b, '--poses', str(poses)], f'has {len(ROUTE)} clouds'),
        'missing poses': ([b, '--poses', str(tmp_path / 'none.txt')], 'cannot read poses'),
        'bad params': ([b, '--params', str(params)], 'num_range'),
        'bad --set': ([b, '--set', 'distance_threshold=abc'], 'distance_threshold'),
        'unknown --set': ([b, '--set', 'nope=1'], "unknown parameter 'nope'"),
        'bad database': ([b, '--load-db', str(notbag)], 'notes.txt'),
        'database over a text file': ([b, '--save-db', str(notbag)],
                                      'notes.txt exists and is not a solid_ros database'),
        'binary params': ([b, '--params', str(binary)], 'is not UTF-8 text'),
        'integer for float': ([b, '--params', str(integer)], 'write 90.0'),
        'repeated times': ([b, '--poses', str(poses16), '--times', str(repeated)],
                           'repeats the previous one'),
        'times going back': ([b, '--poses', str(poses16), '--times', str(back)],
                             'is before the previous one'),
        'zero rotation': ([b, '--poses', str(zero_rot)], 'not a rotation matrix'),
        'TUM stamps going back': ([b, '--poses', str(tum)], 'is before the previous one'),
    }


def test_bad_input_gives_one_line_error(tmp_path: Path, bags: dict[str, Path],
                                        capsys: pytest.CaptureFixture[str]) -> None:
    for name, (argv, expect) in _bad_inputs(tmp_path, bags).items():
        code = main(argv + ['--quiet'])
        out, err = capsys.readouterr()
        lines = err.strip().splitlines()
        assert code == 1, (name, err)
        assert len(lines) == 1 and lines[0].startswith('solid_replay: error: '), (name, err)
        assert expect in lines[0], (name, lines[0])
        assert 'Traceback' not in err and out == ''
    assert (tmp_path / 'notes.txt').read_text() == 'hello'  # never replaced by --save-db


def test_bad_command_line_exits_2(capsys: pytest.CaptureFixture[str],
                                  bags: dict[str, Path]) -> None:
    b = str(bags['mcap'])
    for argv in ([], [b, '--times', 't.txt'], [b, '--radius', 'far'], [b, '--radius', 'inf'],
                 [b, '--radius', '-1'], [b, '--max-heading-deg', 'nan'],
                 [b, '--max-heading-deg', '-5'], [b, '--max-heading-deg', '0']):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith('solid_replay: error: ')


# -- real data ----------------------------------------------------------------------------------


def test_hku1_with_reference_poses(shared_data: Path, tmp_path: Path) -> None:
    hku = shared_data / 'hku1'
    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml')
    result = replay(hku / 'bag', cfg, poses=hku / 'optimized_poses.txt',
                    times=hku / 'times.txt', out_dir=tmp_path, progress='quiet')
    assert result.messages == 314 and result.skipped == 0
    assert result.report['topic'] == '/points' and result.report['odom_topic'] == '/odom_slam'
    # The replayed candidates are exactly those of the loop closure (the detector with the
    # pose graph's hint: the preset's back end is on) on the bag's clouds and odometry.
    from solid_ros.core.flow.closure import LoopClosure
    from solid_ros.core.odometry.track import OdomSample
    from solid_ros.formats.bags import Bag

    closure = LoopClosure(LoopDetector(cfg))
    det = closure.detector
    want = []
    with Bag(hku / 'bag') as bag:
        odom = bag.odometry('/odom_slam')
        assert odom.stamps_ns is not None
        poses = dict(zip(odom.stamps_ns.tolist(), odom.poses))
        for scan in bag.clouds('/points'):
            assert scan.points is not None
            pose = poses.get(scan.stamp_ns)
            odom_sample = None if pose is None else OdomSample(scan.stamp_ns, pose)
            want += closure.process(scan.points, scan.stamp_ns, odom_sample).scan.loops
    assert result.candidates == want
    # The preset's keyframe gating (0.5 m, 10 deg on the bag's odometry) keeps fewer scans.
    assert result.keyframes == det.num_keyframes < 314
    m = result.metrics
    assert m is not None
    assert m['queries_with_true_loop'] > 30
    # The revisit (keyframes ~274-313 see ~19-34) is retrieved: well above chance (0.54,
    # 0.64 and 0.42 at 70b1272; a descriptor no better than chance scores 0.5 in ROC AUC).
    assert m['recall_at_1'] > 0.45 and m['roc_auc'] > 0.6
    assert m['f1_max'] > 0.35 and m['f1_max_threshold'] is not None
    # Published loops with the shipped preset: verified, with a usable relative pose.
    loops = result.report['loops']
    assert loops['precision'] >= 0.98 and loops['recall'] >= 0.5, loops
    assert loops['trans_err_m']['median'] < 0.5 and loops['rot_err_deg']['median'] < 1.5
    assert result.report['loop_sweep']['recommended'] is not None
    with (tmp_path / 'candidates.csv').open() as fh:
        rows = list(csv.DictReader(fh))
    published = [r for r in rows if r['accepted'] == '1']
    assert len(published) == loops['published']
    assert all(r['verified'] == '1' and r['pose_correct'] == '1' for r in published)
    assert {r['reason'] for r in rows} >= {'verified', 'coarse_overlap'}
    # The odometry topic as reference gives the same ground truth within a few queries.
    via_odom = replay(hku / 'bag', cfg, progress='quiet')
    assert via_odom.metrics is not None
    assert abs(via_odom.metrics['queries_with_true_loop'] - m['queries_with_true_loop']) <= 15


# -- parity with the node -----------------------------------------------------------------------


def _node_candidates(bag: Path, params: Path) -> list[tuple[int, int, int, int, int]]:
    """Publish a bag's clouds and odometry to an in-process solid_node; collect its output."""
    import os
    import random
    import sys
    import time

    rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')
    from nav_msgs.msg import Odometry
    from rclpy.context import Context
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy_msgs import make_cloud
    from sensor_msgs.msg import PointCloud2
    from spinning import Spinner
    from std_msgs.msg import Float64MultiArray

    from solid_ros.core.geometry import matrix_to_quaternion
    from solid_ros.formats.bags import Bag
    from solid_ros.formats.candidates import decode_candidates
    from solid_ros.ros.node import SolidNode
    from solid_ros.runtime import tune_thread_switching

    msgs: list[tuple[str, object]] = []
    with Bag(bag) as b:
        track = b.odometry('/odom')
        assert track.stamps_ns is not None
        odom = dict(zip(track.stamps_ns.tolist(), track.poses))
        for scan in b.clouds('/points'):
            assert scan.points is not None
            cloud = make_cloud(scan.points, scan.stamp_ns, scan.frame_id)
            pose = odom[scan.stamp_ns]
            o = Odometry()
            o.header = cloud.header
            o.header.frame_id = 'map'
            p = o.pose.pose
            p.position.x, p.position.y, p.position.z = (float(v) for v in pose[:3, 3])
            q = matrix_to_quaternion(pose[:3, :3])
            p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = q
            msgs += [('odom', o), ('points', cloud)]

    old_domain = os.environ.get('ROS_DOMAIN_ID')
    os.environ['ROS_DOMAIN_ID'] = str(random.randint(101, 200))
    old_interval = sys.getswitchinterval()
    tune_thread_switching()  # as solid_node's main() does
    ctx = Context()
    rclpy.init(context=ctx)
    got: list[dict] = []
    try:
        node = SolidNode(context=ctx, cli_args=['--ros-args', '--params-file', str(params),
                                                '-r', 'odom:=/odom'])
        client = Node('replay_parity_client', context=ctx)
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        pub_points = client.create_publisher(PointCloud2, '/points', qos)
        pub_odom = client.create_publisher(Odometry, '/odom', qos)
        client.create_subscription(Float64MultiArray, '/solid_node/loop_candidates',
                                   lambda m: got.extend(decode_candidates(m)), qos)
        executor = MultiThreadedExecutor(num_threads=3, context=ctx)
        executor.add_node(node)
        executor.add_node(client)
        spinner = Spinner(executor)

        def wait(pred, what: str, timeout: float = 120.0) -> None:  # type: ignore[no-untyped-def]
            deadline = time.monotonic() + timeout
            while not pred():
                assert time.monotonic() < deadline, f'timed out waiting for {what}'
                time.sleep(0.02)

        try:
            wait(lambda: pub_points.get_subscription_count() > 0
                 and pub_odom.get_subscription_count() > 0, 'subscriptions')
            sent = 0
            for kind, msg in msgs:
                (pub_odom if kind == 'odom' else pub_points).publish(msg)
                if kind == 'points':
                    sent += 1
                    wait(lambda s=sent: node.stats.received >= s, 'delivery')
            assert node.wait_idle(120.0)
            wait(lambda: len(got) >= node.stats.loops, 'every published candidate')
        finally:
            spinner.stop()  # out of the wait set before the nodes go
            node.destroy_node()
            client.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
        sys.setswitchinterval(old_interval)
        if old_domain is None:
            os.environ.pop('ROS_DOMAIN_ID', None)
        else:
            os.environ['ROS_DOMAIN_ID'] = old_domain
    return [(int(c['query_index']), int(c['match_index']), int(c['query_stamp_ns']),
             int(c['match_stamp_ns']), int(c['match_session'])) for c in got]


def test_node_and_replay_give_identical_candidates(tmp_path: Path,
                                                   bags: dict[str, Path]) -> None:
    params = tmp_path / 'params.yaml'
    params.write_text('solid_node:\n  ros__parameters:\n'
                      '    exclude_recent_frames: 3\n    distance_threshold: 0.02\n'
                      '    keyframe_min_distance: 1.0\n'
                      "    qos_reliability: 'reliable'\n    qos_depth: 1000\n"
                      '    queue_size: 1000\n')
    node = _node_candidates(bags['mcap'], params)
    assert main([str(bags['mcap']), '--params', str(params), '--out', str(tmp_path / 'o'),
                 '--quiet', '--no-plots']) == 0
    with (tmp_path / 'o' / 'candidates.csv').open() as fh:
        rows = [r for r in csv.DictReader(fh) if r['accepted'] == '1']
    offline = [(int(r['query_index']), int(r['match_index']), int(r['query_stamp_ns']),
                int(r['match_stamp_ns']), int(r['match_session'])) for r in rows]
    assert node == offline
    assert len(offline) == 6  # the revisits of places 0..5


def test_hku1_avia_preset_beats_authors_defaults(shared_data: Path) -> None:
    """The shipped Avia preset (YAML settings only) beats SolidConfig(), the authors' recipe."""
    hku = shared_data / 'hku1'
    refs = {'poses': hku / 'optimized_poses.txt', 'times': hku / 'times.txt'}
    plain = replay(hku / 'bag', SolidConfig(), progress='quiet', **refs)
    mine = replay(hku / 'bag', SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml'),
                  progress='quiet', **refs)
    assert plain.metrics is not None and mine.metrics is not None
    assert mine.metrics['f1_max'] > plain.metrics['f1_max']
    assert mine.metrics['recall_at_1'] > plain.metrics['recall_at_1']


# -- verified loops: pose, scores and pose errors in every output ------------------------------

# Scans 0..9 of the simulated drive, then 166..175: the same street driven again in another
# lane (the demo's 'same' revisits of 0..9), so every revisit has a real relative pose.
SIM_SCANS = list(range(10)) + list(range(166, 176))
SIM_CFG = SolidConfig.from_yaml(CONFIG_DIR / 'hdl64.yaml').replace(exclude_recent_frames=5)


@pytest.fixture(scope='module')
def sim_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip('small_gicp', reason='small-gicp is not installed')
    from solid_ros.sim.bagwriter import DEMO_DEFAULTS
    from solid_ros.sim.drive import Drive, DriveConfig

    drive = Drive(DriveConfig(**DEMO_DEFAULTS))
    items = []
    for i, k in enumerate(SIM_SCANS):
        scan = drive.scan(k)
        items.append((scan.points.copy(), 10**18 + i * 200_000_000, scan.pose))
    return write_cloud_bag(tmp_path_factory.mktemp('sim') / 'bag', items, 'mcap')


@pytest.mark.slow
def test_published_loops_carry_a_correct_relative_pose(tmp_path: Path, sim_bag: Path) -> None:
    out = tmp_path / 'out'
    result = replay(sim_bag, SIM_CFG, out_dir=out, plots=True, progress='quiet')
    assert result.reference is not None
    loops = result.report['loops']
    assert loops['published'] >= 8 and loops['precision'] == 1.0, loops
    assert loops['recall'] >= 0.8 and loops['trans_err_m']['median'] < 0.1
    with (out / 'candidates.csv').open() as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == CSV_COLUMNS
    published = [r for r in rows if r['accepted'] == '1']
    assert len(published) == len(result.candidates) == loops['published']
    ref = result.reference
    offsets = []
    for r, c in zip(published, result.candidates):
        assert (int(r['query_index']), int(r['match_index'])) == (c.query_index, c.match_index)
        assert r['verified'] == '1' and r['reason'] == 'verified' and r['pose_correct'] == '1'
        # The CSV pose is the published one, scored against inv(P_match) @ P_query.
        pose = [float(r[k]) for k in ('tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw')]
        assert pose == pytest.approx(c.pose, abs=1e-6)
        T_ref = np.linalg.solve(ref[c.match_index], ref[c.query_index])
        d = np.linalg.solve(T_ref, c.matrix())
        assert float(r['trans_err_m']) == pytest.approx(np.linalg.norm(d[:3, 3]), abs=1e-4)
        assert float(r['trans_err_m']) < 0.1 and float(r['rot_err_deg']) < 0.5
        offsets.append(float(np.linalg.norm(T_ref[:3, 3])))
        assert 0.0 < float(r['fitness']) <= 1.0 and float(r['rmse']) < 0.1
        assert 0.0 < float(r['overlap']) <= 1.0
        cov = np.array([float(r[f'cov_{i}']) for i in range(36)]).reshape(6, 6)
        assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0.0)
    # Another lane: the convention is exercised by real offsets, not identity poses.
    assert max(offsets) > 1.0
    # Every attempt has a row with its reason; unpublished rows are never marked accepted.
    reasons = {r['reason'] for r in rows}
    assert reasons <= {'verified', 'best', *REASONS} and 'verified' in reasons
    attempts = sum(len(a) for a in result.attempts)
    best_only = [r for r in rows if r['reason'] == 'best']
    assert len(rows) == attempts + len(best_only)
    assert all(r['accepted'] == '0' and r['verified'] == '0' and r['best'] == '1'
               for r in best_only)
    # report.json: memory of the keyframe clouds, per-stage times, reasons, the sweep.
    report = json.loads((out / 'report.json').read_text())
    clouds = report['keyframe_clouds']
    assert clouds['kept'] == result.keyframes and clouds['mb'] > 0 and clouds['dropped'] == 0
    for stage in ('describe', 'search', 'verify'):
        assert report['timings'][f'{stage}_ms']['p50'] > 0.0
    assert report['verification']['reasons']['verified'] == loops['published']
    assert report['loops']['reasons'] == dict(sorted(
        {k: sum(1 for r in rows if r['reason'] == k) for k in reasons - {'best'}}.items()))
    sweep = report['loop_sweep']
    assert sweep['parameter'] == 'verify_min_overlap' and sweep['target_precision'] == 1.0
    assert sweep['rows'][0]['threshold'] == SIM_CFG.verify_min_overlap
    assert sweep['rows'][0]['tp'] == loops['correct'] and sweep['recommended'] is not None
    for name in PLOT_FILES:
        assert (out / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_pose_limits_and_target_precision_are_options(tmp_path: Path, sim_bag: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    # Limits tighter than any registration: every published loop counts as false.
    preset = ['--params', str(CONFIG_DIR / 'hdl64.yaml'), '--set', 'exclude_recent_frames=5']
    assert main([str(sim_bag), *preset, '--max-pose-error-m', '0.0000001',
                 '--max-pose-error-deg', '0.00001', '--out', str(tmp_path / 'o'), '--no-plots',
                 '-q']) == 0
    report = json.loads((tmp_path / 'o' / 'report.json').read_text())
    loops = report['loops']
    assert loops['published'] > 0 and loops['correct'] == 0 and loops['precision'] == 0.0
    assert (loops['max_error_m'], loops['max_error_deg']) == (1e-7, 1e-5)
    assert report['loop_sweep']['recommended'] is None
    # With the default limits a lower target is met at the configured value, and printed.
    assert main([str(sim_bag), *preset, '--target-precision', '0.5', '--progress',
                 'lines']) == 0
    out = capsys.readouterr().out
    assert 'verify_min_overlap: 0.35   # precision >= 0.5 of published loops by pose' in out


def test_descriptor_only_sweeps_the_distance_threshold(tmp_path: Path, bags: dict[str, Path],
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    cfg = TEST_CFG.replace(verify=False)
    result = replay(bags['mcap'], cfg, out_dir=tmp_path, progress='quiet')
    assert [(c.query_index, c.match_index) for c in result.candidates] == \
        [(10 + k, k) for k in range(6)]
    assert all(c.reason == 'descriptor' and not c.verified for c in result.candidates)
    sweep = result.report['loop_sweep']
    assert sweep['parameter'] == 'distance_threshold' and sweep['recommended'] is not None
    assert sweep['recall'] == 1.0
    with (tmp_path / 'candidates.csv').open() as fh:
        rows = [r for r in csv.DictReader(fh) if r['accepted'] == '1']
    # The pose is the descriptor's yaw only; same place, so it is also pose-correct here.
    assert all(r['reason'] == 'descriptor' and r['verified'] == '0' and r['tx'] == '0.000000'
               and r['cov_0'] == '' for r in rows)
    assert result.report['loops']['precision'] == 1.0
    text = '\n'.join(summary_lines(result))
    assert 'by place' in text and 'distance_threshold: ' in text
    assert 'of best matches within 5.0 m' in text


def test_bad_options_are_refused_before_the_bag_is_read(tmp_path: Path) -> None:
    # The same checks as the command line's (test_options.py), for the API.
    for change, flag in (({'radius': -1.0}, '--radius'), ({'target_precision': 2.0},
                                                           '--target-precision')):
        with pytest.raises(ConfigError, match=f'^{flag} must be'):
            replay(tmp_path / 'no_bag', TEST_CFG, **change)


def test_bad_replay_options_exit_2(capsys: pytest.CaptureFixture[str],
                                   bags: dict[str, Path]) -> None:
    b = str(bags['mcap'])
    for argv in ([b, '--target-precision', '0'], [b, '--target-precision', '1.5'],
                 [b, '--target-precision', 'nan'], [b, '--max-pose-error-m', '-1'],
                 [b, '--max-pose-error-m', 'inf'], [b, '--max-pose-error-deg', '0'],
                 [b, '--max-pose-error-deg', '200']):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith('solid_replay: error: '), argv
