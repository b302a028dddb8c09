"""Benchmark of the core: ms per scan for KITTI scan 313 and per heading search.

Run: .venv/bin/python test/bench/bench_core.py [--repeat N]
Single-threaded (one BLAS thread, no parallel code), so it uses one core; prints medians
and 90th percentiles. Run it on an otherwise idle machine.
"""

from __future__ import annotations

import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from solid_ros import SolidConfig, describe, estimate_yaw  # noqa: E402
from solid_ros.formats.pointfiles import read_pcd  # noqa: E402
from solid_ros.tools.runtime import tune_allocator  # noqa: E402

DATA = Path(__file__).resolve().parents[3] / 'shared' / 'data'


def _times(fn: object, repeat: int) -> np.ndarray:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()  # type: ignore[operator]
        out.append(time.perf_counter() - t0)
    return np.array(out) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--repeat', type=int, default=200)
    args = parser.parse_args()
    scan = read_pcd(DATA / 'kitti' / 'pcd' / '000313.pcd')
    print(f'KITTI 000313: {len(scan)} points, float32 (N, 3), one core')
    for label in ('library default allocator', 'tuned allocator (node, replay, demo)'):
        if label.startswith('tuned'):
            tune_allocator()
        for width in (360.0, 60.0):
            cfg = SolidConfig(fov_width_deg=width)
            describe(scan, cfg)  # warm-up
            ms = _times(lambda cfg=cfg: describe(scan, cfg), args.repeat)
            print(f'describe, FOV {width:5.1f} deg, {label}: median {np.median(ms):5.2f} ms, '
                  f'p90 {np.percentile(ms, 90):5.2f} ms')
    a = describe(scan).a_solid
    b = np.roll(a, 7)
    us = _times(lambda: estimate_yaw(a, b), args.repeat * 20) * 1e3
    print(f'heading search + sub-bin refinement: median {np.median(us):6.1f} us '
          f'({np.median(us) / 1e3:.4f} ms), p90 {np.percentile(us, 90):6.1f} us')


if __name__ == '__main__':
    main()
