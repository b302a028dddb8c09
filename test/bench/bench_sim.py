"""Benchmark of the simulator and of the detector over a long simulated drive.

Run: ``.venv/bin/python test/bench/bench_sim.py [--gen-scans 200] [--scale-scans 10000]``

1. Generation: ms per scan for each sensor preset, ray casting alone and with MCAP bag
   writing (into a temporary directory), and bag megabytes per scan. ``--gen-scans 2000``
   times the issue's 2,000-scan 64-beam run in full.
2. Scaling: ``--scale-scans`` scans of the 64-beam drive (the route repeats with fresh noise
   beyond its length) through ``LoopDetector`` with default settings. Prints, for the first
   and the last 500 scans, the mean ms per scan of describing and of query + insert
   (``process_descriptor``), then the stored count, the database size and the peak RSS.
   ``--scale-scans 0`` skips it.

One core (BLAS threads pinned to 1). Timings on a shared machine are noisy.
"""

from __future__ import annotations

import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'

import argparse  # noqa: E402
import resource  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.core.descriptor.solid import describe  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402
from solid_ros.sim import simulate, write_bag  # noqa: E402

WINDOW = 500


def bench_generation(sensor: str, n: int) -> None:
    """Print ms/scan of ray casting alone and with bag writing for ``n`` scans."""
    t0 = time.perf_counter()
    points = 0
    for scan in simulate(seed=0, sensor=sensor, num_scans=n):
        points += len(scan.cloud)
    cast_ms = (time.perf_counter() - t0) * 1e3 / n
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / 'bag'
        t0 = time.perf_counter()
        write_bag(bag, simulate(seed=0, sensor=sensor, num_scans=n))
        total = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in bag.iterdir())
    print(f'{sensor:10} {n:6d} scans  {points / n:8.0f} points/scan  cast {cast_ms:6.1f} ms/scan'
          f'  cast+bag {total * 1e3 / n:6.1f} ms/scan  ({total:6.1f} s total)'
          f'  bag {size / n / 1e6:5.2f} MB/scan')


def bench_scaling(n: int) -> None:
    """Run ``n`` simulated scans through the detector; print start/end per-scan costs."""
    det = LoopDetector(SolidConfig())
    desc_ms = np.zeros(n)
    query_ms = np.zeros(n)
    loops = 0
    t_start = time.perf_counter()
    for k, scan in enumerate(simulate(seed=0, sensor='hdl64', num_scans=n)):
        t0 = time.perf_counter()
        desc = describe(scan.points, det.config)
        t1 = time.perf_counter()
        loops += bool(det.process_descriptor(desc, scan.stamp_ns, scan.pose).loops)
        t2 = time.perf_counter()
        desc_ms[k], query_ms[k] = (t1 - t0) * 1e3, (t2 - t1) * 1e3
        if (k + 1) % 1000 == 0:
            print(f'  {k + 1:6d} scans, {time.perf_counter() - t_start:6.0f} s elapsed, '
                  f'query+insert {np.mean(query_ms[k + 1 - 1000:k + 1]):.3f} ms/scan', flush=True)
    w = min(WINDOW, n)
    print(f'scaling run: {n} scans, {loops} accepted loops, '
          f'{time.perf_counter() - t_start:.0f} s including simulation')
    for name, part in (('first', slice(0, w)), ('last', slice(n - w, n))):
        print(f'  {name:5} {w} scans: describe {np.mean(desc_ms[part]):6.2f} ms/scan, '
              f'query+insert mean {np.mean(query_ms[part]):6.3f} ms, '
              f'median {np.median(query_ms[part]):6.3f} ms, '
              f'p99 {np.percentile(query_ms[part], 99):6.3f} ms')
    db = det.database
    nbytes = getattr(db, 'nbytes', None)
    db_text = f'{nbytes / 1e6:.1f} MB' if nbytes is not None else 'n/a'
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux
    print(f'  stored {det.num_keyframes} scans, database {db_text}, peak RSS {peak:.0f} MB')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--gen-scans', type=int, default=200)
    parser.add_argument('--scale-scans', type=int, default=10_000)
    args = parser.parse_args()
    if args.gen_scans > 0:
        for sensor in ('hdl64', 'avia_like'):
            bench_generation(sensor, args.gen_scans)
    if args.scale_scans > 0:
        bench_scaling(args.scale_scans)


if __name__ == '__main__':
    main()
