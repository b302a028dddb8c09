"""After a real odometry failure, how long is the new graph segment untied, and what does the
failure cost the corrected trajectory?

hku1 (``../shared/data``: Livox Avia, a 64 m loop whose keyframes ~274-313 revisit ~19-34) is
replayed as ``bench_real.py`` does (avia preset, KISS-ICP odometry over the clouds, the back
end on). A failure is spliced at cloud ``P``: ``--drop`` clouds are left out (a blackout) and
every later cloud is turned by ``--turn`` degrees about the sensor's z, as if the sensor came
back facing elsewhere: a jump KISS-ICP cannot follow (``test/core/odometry/test_kiss.py``
splices the same). The reference poses of the turned clouds turn with them, so the reference
stays right. KISS-ICP's checks reset the odometry, the back end starts a new graph segment at
the last pose, and nothing but a verified loop between the new segment and the old ones ties
it back (:mod:`solid_ros.core.backend.segments`).

Prints, per failure position and for the run without a failure: the odometry resets, the new
graph segments, each tie (the loop that placed a segment), the keyframes and seconds of bag
time from the first keyframe of the new segment to its tie, and the ATE (SE(3)-aligned, over
the keyframes) of the odometry and of the corrected trajectory against the reference.
``--report FILE`` writes what it printed (``doc/reports/bench_segments.md``).

Usage: ``python test/bench/bench_segments.py [--at 100,200,280] [--drop 20] [--turn 90]
[--report FILE]``.
"""

from __future__ import annotations

import argparse
import io
import re
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_odometry import load  # noqa: E402
from report import PrintedReport, bench_meta  # noqa: E402

from solid_ros.formats.bags import write_cloud_bag  # noqa: E402
from solid_ros.formats.poses import write_kitti_poses  # noqa: E402
from solid_ros.tools.replay import load_config, replay  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
FloatArray = npt.NDArray[np.float64]

_RESET = re.compile(r'odometry reset at scan (\d+): (.*)')
_SEGMENT = re.compile(r'back end segment: .* between keyframes (\d+) and (\d+): new graph '
                      r'segment (\d+)')
_TIE = re.compile(r'back end tie: segment\(s\) ([\d, ]+) placed by loop (\d+) -> session \S+ '
                  r'keyframe (\d+): map->odom moved ([\d.]+) m, ([\d.]+) deg')


@dataclass
class Run:
    """What one replay gave.

    Attributes:
        resets: (scan, reason) of each odometry reset.
        segments: (first keyframe, segment) of each new graph segment.
        ties: (segments placed, query keyframe, match keyframe, metres, degrees) per tie.
        stamps: keyframe index -> stamp, seconds.
        ate_odometry: odometry ATE, metres.
        ate_corrected: corrected ATE, metres.
        keyframes: keyframes in the run.
        loops: loops published, and of them false (beyond 1 m / 3 deg of the reference).
    """

    resets: list[tuple[int, str]] = field(default_factory=list)
    segments: list[tuple[int, int]] = field(default_factory=list)
    loops: tuple[int, int] = (0, 0)
    ties: list[tuple[list[int], int, int, float, float]] = field(default_factory=list)
    stamps: dict[int, float] = field(default_factory=dict)
    ate_odometry: float = float('nan')
    ate_corrected: float = float('nan')
    keyframes: int = 0


def splice(clouds: list[FloatArray], stamps: list[int], ref: FloatArray, at: int, drop: int,
           turn_deg: float) -> tuple[list[FloatArray], list[int], FloatArray]:
    """The recording with clouds ``at .. at + drop - 1`` left out and the later ones turned
    by ``turn_deg`` about the sensor's z (their reference poses turned to match)."""
    c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
    turn = np.eye(4)
    turn[:2, :2] = [[c, -s], [s, c]]
    keep = [i for i in range(len(clouds)) if not at <= i < at + drop]
    out_clouds, out_ref = [], []
    for i in keep:
        turned = i >= at
        out_clouds.append(clouds[i] @ turn[:3, :3].T if turned else clouds[i])
        # p' = R p, so world <- sensor' is ref @ R^T.
        out_ref.append(ref[i] @ turn.T if turned else ref[i])
    return out_clouds, [stamps[i] for i in keep], np.stack(out_ref)


def replay_run(clouds: list[FloatArray], stamps: list[int], ref: FloatArray,
               work: Path) -> Run:
    """Replay the clouds as bench_real does (avia preset, KISS-ICP) and parse its log."""
    work.mkdir(parents=True)
    bag = write_cloud_bag(work / 'bag', [(p.astype(np.float32), t) for p, t in
                                         zip(clouds, stamps)], odom_topic=None,
                          frame_id='livox_frame')
    poses = write_kitti_poses(work / 'poses.txt', ref)
    cfg, ncfg = load_config(ROOT / 'config' / 'avia.yaml')
    log = io.StringIO()
    r = replay(bag, cfg, node_config=ncfg, odometry='kiss-icp', poses=poses,
               progress='lines', stream=log, plots=False)
    run = Run(keyframes=sum(1 for res in r.log.results if res.keyframe))
    for res in r.log.results:
        run.stamps[res.query_index] = res.stamp_ns * 1e-9
    traj = r.report['trajectory']
    run.ate_odometry = traj['odometry']['ate_m']
    run.ate_corrected = traj['corrected']['ate_m']
    run.loops = (r.report['loops']['published'], r.report['loops']['false'])
    for line in log.getvalue().splitlines():
        if m := _RESET.search(line):
            run.resets.append((int(m[1]), m[2]))
        elif m := _SEGMENT.search(line):
            run.segments.append((int(m[2]), int(m[3])))
        elif m := _TIE.search(line):
            run.ties.append(([int(x) for x in m[1].split(',')], int(m[2]), int(m[3]),
                             float(m[4]), float(m[5])))
    return run


def untied(run: Run) -> list[tuple[int, int, int | None, float | None]]:
    """Per new segment: (segment, first keyframe, keyframes until its tie, bag seconds until
    its tie); None: never tied."""
    out = []
    for first, seg in run.segments:
        tie = next((t for t in run.ties if seg in t[0]), None)
        if tie is None:
            out.append((seg, first, None, None))
            continue
        out.append((seg, first, tie[1] - first, run.stamps[tie[1]] - run.stamps[first]))
    return out


def lines(title: str, run: Run) -> list[str]:
    """The figures of one run as printed lines."""
    rows = [f'{title}: {run.keyframes} keyframes, {run.loops[0]} loops ({run.loops[1]} false); '
            f'ATE odometry {run.ate_odometry:.3f} m, corrected {run.ate_corrected:.3f} m']
    rows += [f'  odometry reset at cloud {s}: {why[:110]}' for s, why in run.resets]
    for seg, first, kfs, secs in untied(run):
        if kfs is None:
            rows.append(f'  segment {seg} from keyframe {first}: never tied')
            continue
        tie = next(t for t in run.ties if seg in t[0])
        rows.append(f'  segment {seg} from keyframe {first}: tied by loop {tie[1]} -> {tie[2]} '
                    f'after {kfs} keyframes, {secs:.1f} s of bag time (map->odom moved '
                    f'{tie[3]:.2f} m, {tie[4]:.1f} deg)')
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--at', default='100,200,280', help='clouds where the failure starts')
    p.add_argument('--drop', type=int, default=20, help='clouds left out at the failure')
    p.add_argument('--turn', type=float, default=90.0, help='degrees the later clouds turn')
    p.add_argument('--report', type=Path)
    args = p.parse_args()
    if not (DATA / 'hku1').is_dir():
        print(f'bench_segments: {DATA / "hku1"} is missing: nothing to run')
        return 0
    meta: dict[str, Any] = bench_meta('bench_segments', vars(args))
    clouds, stamps, ref = load('hku1')
    with PrintedReport(args.report, meta), tempfile.TemporaryDirectory() as tmp:
        print(f'hku1: {len(clouds)} clouds; failure: {args.drop} clouds left out, the rest '
              f'turned {args.turn:g} deg about z', flush=True)
        base = replay_run(clouds, stamps, ref, Path(tmp) / 'none')
        print('\n'.join(lines('no failure', base)), flush=True)
        for at in (int(x) for x in args.at.split(',')):
            run = replay_run(*splice(clouds, stamps, ref, at, args.drop, args.turn),
                             Path(tmp) / f'at{at}')
            print('\n'.join(lines(f'failure at cloud {at} ({(stamps[at] - stamps[0]) * 1e-9:.1f}'
                                  f' s)', run)), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
