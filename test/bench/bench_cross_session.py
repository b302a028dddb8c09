"""A second session in a saved map: hku1 cut in two, the second half relocalising in the first.

Session 0 replays the first half of ``../shared/data/hku1`` (bag odometry, back end on) and
saves its database with the map poses; session 1 loads it and replays the second half with
KISS-ICP odometry over the clouds (its own frame and its own drift), as a robot that comes back
another day. Printed for session 1: its loops into the saved map (published, false: pose beyond
1 m / 3 deg of the reference relative pose; by source), and the cross-session revisit recall:
its keyframes with a saved keyframe within 5 m (reference poses) that got a right loop into the
map, and for each one that did not, its candidates into the map at a right pose and the rule
that refused each. ``--no-map-candidates`` runs session 1 without the saved map's keyframes as
candidates by position or view (only the descriptor proposes from the map), for comparison;
``--both`` runs with and without them. ``--report FILE`` writes what it printed with the date
and commit.

Usage: ``python test/bench/bench_cross_session.py [--split 157] [--no-map-candidates | --both]
[--report FILE]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(Path(__file__).resolve().parent))
from report import PrintedReport, bench_meta  # noqa: E402

from solid_ros.core.errors import SolidError  # noqa: E402
from solid_ros.core.flow.closure import LoopClosure  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402
from solid_ros.core.odometry.kiss import KissOdometry  # noqa: E402
from solid_ros.core.odometry.track import StampedOdometry  # noqa: E402
from solid_ros.formats.bags import Bag, select_cloud_topic, select_odom_topic  # noqa: E402
from solid_ros.formats.poses import load_reference  # noqa: E402
from solid_ros.tools.loops import pose_error  # noqa: E402
from solid_ros.tools.replay import load_config  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data' / 'hku1'


def _reference() -> tuple[np.ndarray, np.ndarray]:
    ref = load_reference(DATA / 'optimized_poses.txt', DATA / 'times.txt')
    assert ref.stamps_ns is not None
    return np.asarray(ref.stamps_ns), np.asarray(ref.poses)


def _pose_at(stamps: np.ndarray, poses: np.ndarray, stamp: int) -> np.ndarray:
    return poses[int(np.argmin(np.abs(stamps - stamp)))]


def run(split: int, map_candidates: bool) -> None:
    cfg, ncfg = load_config(ROOT / 'config' / 'avia.yaml')
    stamps, poses = _reference()
    with Bag(DATA / 'bag') as bag:
        topic = select_cloud_topic(bag, None)
        track = bag.odometry(select_odom_topic(bag, None))
        scans = [s for s in bag.clouds(topic) if s.points is not None]
    assert track.stamps_ns is not None
    odom = StampedOdometry.from_track(track.stamps_ns, track.poses, int(0.05e9), 'bag')
    first = LoopClosure(LoopDetector(cfg), odometry=odom)
    for s in scans[:split]:
        first.process(s.points, s.stamp_ns)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / 'map.npz'
        first.save(path)
        second = LoopClosure.load(path, cfg.replace(session_id=1), KissOdometry(ncfg))
    if not map_candidates:
        second.detector._stage.map_seqs = {}
    saved = np.array([_pose_at(stamps, poses, int(st))[:3, 3] for st in
                      [first.detector.database.match_info(q)[2]
                       for q in first.detector.database.stored_seqs()]])
    loops, revisiting, found = [], 0, 0
    misses: list[str] = []
    for s in scans[split:]:
        try:
            step = second.process(s.points, s.stamp_ns)
        except SolidError:
            continue
        if not step.scan.keyframe:
            continue
        here = _pose_at(stamps, poses, s.stamp_ns)
        revisit = bool(np.min(np.linalg.norm(saved - here[:3, 3], axis=1)) <= 5.0)
        revisiting += revisit
        right = False
        for c in step.scan.loops:
            if c.match_session != 0:
                continue
            ref = np.linalg.solve(_pose_at(stamps, poses, c.match_stamp_ns), here)
            t, r = pose_error(c.matrix(), ref)
            loops.append((c.source, t < 1.0 and r < 3.0))
            right |= t < 1.0 and r < 3.0
        found += revisit and right
        if revisit and not right:
            misses.append(_missed(step.scan, here, stamps, poses))
    graph = second.graph
    print(f"hku1 cut at cloud {split}: session 1 (KISS-ICP) in session 0's saved map, "
          f'map candidates {"on" if map_candidates else "off"}')
    print(f'  relocalised      {graph is not None and graph.anchored}')
    print(f'  loops into map   {len(loops)} published, {sum(not ok for _, ok in loops)} false; '
          f'by source {dict(Counter(src for src, _ in loops))}')
    print(f'  revisit recall   {found}/{revisiting} = '
          f'{found / revisiting if revisiting else float("nan"):.3f}')
    for line in misses:
        print(f'  missed           {line}')


def _missed(scan: Any, here: np.ndarray, stamps: np.ndarray, poses: np.ndarray) -> str:
    """A revisiting keyframe without a right loop into the map: the candidates into the map
    whose registered pose was right (within 1 m / 3 deg of the reference) and the rule that
    refused each, or that none was."""
    right = []
    for c in scan.attempts:
        if c.match_session != 0:
            continue
        ref = np.linalg.solve(_pose_at(stamps, poses, c.match_stamp_ns), here)
        t, r = pose_error(c.matrix(), ref)
        if t < 1.0 and r < 3.0:
            right.append(f'map keyframe {c.match_index} ({c.source}) {t:.2f} m / {r:.1f} deg '
                         f'off, refused: {c.detail or c.reason}')
    return (f'keyframe {scan.query_index}: '
            + ('; '.join(right) if right else 'no candidate into the map at a right pose'))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--split', type=int, default=157)
    group = p.add_mutually_exclusive_group()
    group.add_argument('--no-map-candidates', action='store_true')
    group.add_argument('--both', action='store_true',
                       help='with the map candidates, then without them')
    p.add_argument('--report', type=Path, help='write the printed figures (.md or JSON)')
    args = p.parse_args()
    if not DATA.is_dir():
        print(f'bench_cross_session: {DATA} is missing: nothing to run')
        return 0
    modes = [True, False] if args.both else [not args.no_map_candidates]
    with PrintedReport(args.report, bench_meta('bench_cross_session', vars(args))):
        for map_candidates in modes:
            run(args.split, map_candidates)
    return 0


if __name__ == '__main__':
    sys.exit(main())
