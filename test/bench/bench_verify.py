"""Verification cost per keyframe and memory per stored keyframe, on one core.

Runs the detector with a shipped preset over simulated drives (Avia-like and 64-beam, the
built-in simulator) and, when ``../shared/data`` is present, over hku1 (real Livox Avia). Every
keyframe verifies all its ``num_candidates`` descriptor candidates with all heading
hypotheses (``distance_threshold`` 2.0 lets every candidate through), the most work the
preset can do per keyframe. Prints the verification time per keyframe (median, p95), the other
stages, and the memory one stored keyframe takes (descriptor row plus keyframe cloud).

Usage: ``python test/bench/bench_verify.py [--scans N]`` (pinned to one CPU core).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'test'))

from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.core.detector import LoopDetector  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'


def _sim(sensor: str, scans: int) -> list[np.ndarray]:
    from solid_ros.sim import simulate

    return [s.points.copy() for s in simulate(seed=0, sensor=sensor, num_scans=scans)]


def _hku1() -> list[np.ndarray] | None:
    if not (DATA / 'hku1' / 'bag').is_dir():
        return None
    from hku1_data import hku1_scans

    return list(hku1_scans(DATA)[0])


def run(name: str, clouds: list[np.ndarray], preset: str) -> None:
    cfg = SolidConfig.from_yaml(ROOT / 'config' / preset).replace(distance_threshold=2.0)
    det = LoopDetector(cfg)
    verify, describe, search = [], [], []
    t0 = time.perf_counter()
    for i, pts in enumerate(clouds):
        det.process(pts, i * 100_000_000)
        if det.last_was_keyframe:
            verify.append(det.times.verify)
            describe.append(det.times.describe)
            search.append(det.times.search)
    wall = time.perf_counter() - t0
    v = np.asarray(verify[cfg.exclude_recent_frames:])  # keyframes that have candidates
    pts = np.mean([len(c.points) for _, c in det.clouds.items()])
    per_kf = det.clouds.nbytes / max(len(det.clouds), 1) + det.database.bytes_per_scan
    print(f'{name:28s} {preset:12s} {len(clouds):4d} scans  verify ms/keyframe median '
          f'{np.median(v):5.1f} p95 {np.percentile(v, 95):5.1f} (k={cfg.num_candidates}, '
          f'{cfg.verify_hypotheses} hypotheses)  describe {np.median(describe):4.1f}  search '
          f'{np.median(search):4.2f}  | cloud {pts:5.0f} points, {per_kf / 1024:6.1f} KiB per '
          f'keyframe  | {wall:5.1f} s')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scans', type=int, default=400, help='simulated scans per drive')
    args = parser.parse_args()
    if hasattr(os, 'sched_setaffinity'):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    hku1 = _hku1()
    if hku1 is not None:
        run('hku1 (real Avia)', hku1, 'avia.yaml')
    else:
        print(f'hku1 skipped: no data at {DATA}')
    run('simulated avia_like', _sim('avia_like', args.scans), 'avia.yaml')
    run('simulated hdl64 (64-beam)', _sim('hdl64', args.scans), 'hdl64.yaml')
    return 0


if __name__ == '__main__':
    sys.exit(main())
