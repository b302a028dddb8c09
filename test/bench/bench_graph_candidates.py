"""Candidates by position from the pose graph: what they find and what they cost.

Runs the product's loop closure (detector and back end) twice per data set, with
``graph_candidates`` 0 (the descriptor's candidates only) and with the preset's value, and
prints per run: published loops (false ones), loops by source (descriptor / graph), the revisit
recall (:func:`solid_ros.tools.loops.revisits`: keyframes with an earlier one within 5 m after
at least 30 m of reference path, and the fraction of them with a correct loop), the ATE of the
odometry and of the corrected keyframes, and the verification time per keyframe (median, p95)
with the median of the per-keyframe difference to the run without them (the same keyframes).

Data sets:

- ``hku1``: ``solid_replay hku1/bag --params config/avia.yaml --odometry kiss-icp --poses
  optimized_poses.txt --times times.txt`` (``--hku1-odometry bag`` feeds the recorded
  odometry instead, which is the reference itself: faster, but no drift to correct).
- ``avia_like``, ``hdl64``: the demo's revisit drive (50 m blocks, a scan every 2 m) with the
  simulator's drifting odometry (about 1.5 % of the path), ``avia.yaml`` / ``hdl64.yaml``,
  ``--scans`` scans.

The runs alternate (off, on, off, on, ... ``--repeat`` times) and the process is pinned to one
core; the machine is shared (2 cores), so the load average is printed and the timings are
noisy. Usage: ``python test/bench/bench_graph_candidates.py [--sets hku1,avia_like,hdl64]
[--scans 400] [--repeat 1] [--hku1-odometry kiss-icp|bag]``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.core.flow.closure import LoopClosure  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402
from solid_ros.core.odometry.track import OdomSample  # noqa: E402
from solid_ros.sim import DEMO_DEFAULTS, DEMO_SENSORS, simulate  # noqa: E402
from solid_ros.tools.loops import (  # noqa: E402
    LoopRecord,
    pose_error,
    revisit_recall,
    revisits,
    score_loops,
)
from solid_ros.tools.replay import load_config, replay  # noqa: E402
from solid_ros.tools.trajectory_metrics import ate_rmse  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data' / 'hku1'
KITTI = ROOT.parent / 'shared' / 'data' / 'kitti' / 'pcd'
PRESET = {'avia_like': 'avia.yaml', 'hdl64': 'hdl64.yaml'}


def load() -> str:
    return f'load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores'


def hku1(graph: int | None, odometry: str) -> dict[str, Any]:
    sets = None if graph is None else {'graph_candidates': graph}
    cfg, ncfg = load_config(ROOT / 'config' / 'avia.yaml', overrides=sets)
    r = replay(DATA / 'bag', cfg, node_config=ncfg, odometry=odometry,
               poses=DATA / 'optimized_poses.txt', times=DATA / 'times.txt', progress='quiet')
    loops, traj = r.report['loops'], r.report['trajectory']
    return {'keyframes': len(r.log.results), 'published': loops['published'],
            'false': loops['false'], 'by_source': loops['by_source'],
            'revisits': loops['revisits'], 'verify': [res.times.verify for res in r.log.results],
            'ate': (traj['odometry']['ate_m'], traj['corrected']['ate_m'])}


def sim(sensor: str, graph: int | None, scans: int) -> dict[str, Any]:
    cfg = SolidConfig.from_yaml(ROOT / 'config' / PRESET[sensor])
    if graph is not None:
        cfg = cfg.replace(graph_candidates=graph)
    closure = LoopClosure(LoopDetector(cfg))
    ref, odo, verify, attempts, published = [], [], [], [], set()
    corrected: dict[int, np.ndarray] = {}
    for scan in simulate(seed=0, sensor=DEMO_SENSORS[sensor], num_scans=scans,
                         block=DEMO_DEFAULTS['block'], spacing=DEMO_DEFAULTS['spacing']):
        step = closure.process(scan.points, scan.stamp_ns, OdomSample(scan.stamp_ns, scan.odom))
        res = step.scan
        if not res.keyframe:
            continue
        ref.append(scan.pose)
        odo.append(scan.odom)
        verify.append(res.times.verify)
        attempts += res.attempts
        published.update(id(c) for c in res.loops)
    assert closure.graph is not None
    corrected = closure.graph.poses()
    ref_a = np.asarray(ref)
    records = []
    for c in attempts:
        q, m = ref_a[c.query_index], ref_a[c.match_index]
        te, re_ = pose_error(c.matrix(), np.linalg.solve(m, q))
        records.append(LoopRecord(c.query_index, c.match_index, c.match_session,
                                  id(c) in published, c.verified, c.reason, c.overlap,
                                  c.distance, te, re_, float(np.linalg.norm(q[:3, 3] - m[:3, 3])),
                                  c.source))
    scores = score_loops(records, np.zeros(len(ref), bool))
    est = np.asarray([corrected[i] for i in range(len(ref))])
    return {'keyframes': len(ref), 'published': scores['published'], 'false': scores['false'],
            'by_source': scores['by_source'],
            'revisits': revisit_recall(records, revisits(ref_a[:, :3, 3])), 'verify': verify,
            'ate': (ate_rmse(np.asarray(odo), ref_a), ate_rmse(est, ref_a))}


def line(name: str, graph: str, out: dict[str, Any], base: list[float] | None) -> str:
    v = np.asarray([t for t in out['verify'] if math.isfinite(t)])
    rv = out['revisits']
    src = ', '.join(f'{k} {s["published"]}' for k, s in out['by_source'].items()) or 'none'
    diff = ''
    if base is not None and len(base) == len(out['verify']):
        d = np.asarray(out['verify']) - np.asarray(base)
        diff = f'  +{np.nanmedian(d):5.1f} ms median per keyframe'
    return (f'{name:10s} graph_candidates {graph:>7s}: {out["keyframes"]:4d} keyframes, '
            f'{out["published"]:3d} loops ({out["false"]} false; {src}), revisit recall '
            f'{rv["found"]}/{rv["revisiting"]} = '
            f'{rv["recall"] if rv["recall"] is None else round(rv["recall"], 3)}, ATE '
            f'{out["ate"][0]:.3f} -> {out["ate"][1]:.3f} m; verify ms p50 '
            f'{np.median(v):5.1f} p95 {np.percentile(v, 95):5.1f}{diff}')


def main() -> int:
    p = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    p.add_argument('--sets', default='hku1,avia_like,hdl64')
    p.add_argument('--scans', type=int, default=400, help='simulated scans per drive')
    p.add_argument('--repeat', type=int, default=1, help='off/on pairs per data set')
    p.add_argument('--hku1-odometry', choices=('kiss-icp', 'bag'), default='kiss-icp')
    p.add_argument('--no-cpp', action='store_true',
                   help="skip the authors' C++ reference (absolute times only)")
    args = p.parse_args()
    if hasattr(os, 'sched_setaffinity'):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    print(f'bench_graph_candidates: {load()}; pinned to one core', flush=True)
    with tempfile.TemporaryDirectory(prefix='solid_bench_') as tmp:
        exe = _cpp(Path(tmp), args.no_cpp)
        ref = [] if exe is None else [_cpp_describe_ms(exe)]
        added = _runs(args)
        if exe is not None:
            ref.append(_cpp_describe_ms(exe))
    if ref:
        c = float(np.median(ref))
        print(f"the authors' C++ describe of KITTI 313 in this run: {c:.2f} ms CPU (before "
              f'{ref[0]:.2f}, after {ref[-1]:.2f}); verification added per keyframe (median of '
              'the per-keyframe difference) as a multiple of it (goal 10 ms):')
        for name, ms in added.items():
            print(f'  {name:10s} {ms / c:+5.2f}x ({ms:+.1f} ms)')
    return 0


def _cpp(tmp: Path, skip: bool) -> Path | None:
    """The authors' C++ timing driver built into ``tmp`` (None: skipped or not buildable)."""
    if skip or not (KITTI / '000313.pcd').is_file():
        return None
    from bench_core import _build_cpp

    exe, reason = _build_cpp(tmp)
    if exe is None:
        print(f'C++ reference skipped: {reason}')
    return exe


def _cpp_describe_ms(exe: Path) -> float:
    """The authors' C++ describe of KITTI 313 (gate + voxel grid + descriptor), CPU ms."""
    from bench_core import _run_cpp

    return float(_run_cpp(exe, KITTI / '000313.pcd', KITTI / '000314.pcd', 50)['cpu_total'])


def _runs(args: argparse.Namespace) -> dict[str, float]:
    """Each data set off / on; the median verification added per keyframe, by data set."""
    added: dict[str, float] = {}
    for name in [s for s in args.sets.split(',') if s]:
        if name == 'hku1' and not (DATA / 'bag').is_dir():
            print(f'hku1 skipped: no data at {DATA}')
            continue
        p50: Counter[str] = Counter()
        for _ in range(args.repeat):
            base = None
            for graph in (0, None):
                t0 = time.perf_counter()
                out = (hku1(graph, args.hku1_odometry) if name == 'hku1'
                       else sim(name, graph, args.scans))
                label = 'off (0)' if graph == 0 else 'preset'
                print(line(name, label, out, base) + f'  ({time.perf_counter() - t0:.0f} s, '
                      f'{load()})', flush=True)
                if graph == 0:
                    base = out['verify']
                elif base is not None and len(base) == len(out['verify']):
                    d = np.asarray(out['verify']) - np.asarray(base)
                    added[name] = added.get(name, 0.0) + float(np.nanmedian(d)) / args.repeat
                p50[label] += float(np.nanmedian(out['verify'])) / args.repeat
        print(f'{name:10s} verify p50 over {args.repeat} pair(s): off {p50["off (0)"]:.1f} ms, '
              f'preset {p50["preset"]:.1f} ms (+{p50["preset"] - p50["off (0)"]:.1f} ms)',
              flush=True)
    return added


if __name__ == '__main__':
    sys.exit(main())
