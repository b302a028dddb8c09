"""Can KISS-ICP run beside the describe and verify work: a thread or a process?

The hku1 clouds (real Livox Avia, ../shared/data) are registered by
:class:`~solid_ros.core.odometry.kiss.KissOdometry` (KISS-ICP 1.3, max range 50 m, voxel 0.5 m)
while the loop closure (config/avia.yaml, describe, search, verify, back end) processes the same
clouds with their poses: alone, with KISS-ICP on a second thread of the same process, and with
KISS-ICP in a second process. Printed: the wall time of each run, the loop closure's per-cloud
wall time (what a stall shows as), and the rate a pure-Python thread keeps while KISS-ICP
registers (1.0: KISS-ICP releases the GIL; near 0: it holds it).

Usage: ``python test/bench/bench_kiss_overlap.py [--clouds 150] [--report doc/reports/x.md]``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'test'))

from bench.report import PrintedReport, bench_meta  # noqa: E402
from hku1_data import hku1_scans  # noqa: E402

from solid_ros.core.config import NodeConfig, SolidConfig  # noqa: E402
from solid_ros.core.flow.closure import LoopClosure  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402
from solid_ros.core.odometry.kiss import KissOdometry  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
RECIPE = NodeConfig(kiss_max_range=50.0, kiss_min_range=0.0, kiss_voxel_size=0.5,
                    kiss_deskew=False)


def run_kiss(clouds: list[Any], stamps: list[int]) -> list[Any]:
    """Register every cloud; the samples."""
    kiss = KissOdometry(RECIPE)
    return [kiss.pose_for(s, p) for p, s in zip(clouds, stamps)]


def run_closure(clouds: list[Any], stamps: list[int], odoms: list[Any]) -> list[float]:
    """The loop closure on every cloud; its wall seconds per cloud."""
    # Resolved as solid_node does with odometry_source kiss_icp: registered steps on.
    cfg = SolidConfig.from_yaml(ROOT / 'config' / 'avia.yaml').for_odometry(True)
    closure = LoopClosure(LoopDetector(cfg), backend=True)
    costs = []
    for points, stamp, odom in zip(clouds, stamps, odoms):
        t0 = time.perf_counter()
        closure.process(points, stamp, odom)
        costs.append(time.perf_counter() - t0)
    return costs


def spinner_share(work: Any) -> float:
    """The rate a pure-Python counting thread keeps while ``work()`` runs, over its rate alone."""
    stop = threading.Event()
    count = [0]

    def spin() -> None:
        while not stop.is_set():
            count[0] += 1

    rates = []
    for job in (lambda: time.sleep(2.0), work):
        count[0] = 0
        stop.clear()
        thread = threading.Thread(target=spin)
        t0 = time.perf_counter()
        thread.start()
        job()
        stop.set()
        thread.join()
        rates.append(count[0] / (time.perf_counter() - t0))
    return rates[1] / rates[0]


def _ms(costs: list[float]) -> str:
    v = np.asarray(costs) * 1e3
    return f'median {np.median(v):5.1f} p95 {np.percentile(v, 95):6.1f} max {v.max():6.1f} ms'


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--clouds', type=int, default=150, help='hku1 clouds used')
    parser.add_argument('--report', type=Path, help='write the printed figures (.md or JSON)')
    args = parser.parse_args()
    if not (DATA / 'hku1').is_dir():
        print(f'no hku1 data at {DATA}; nothing to measure', file=sys.stderr)
        return 1
    clouds, stamps = hku1_scans(DATA)
    clouds, stamps = clouds[:args.clouds], stamps[:args.clouds]
    with PrintedReport(args.report, bench_meta('bench_kiss_overlap', vars(args))):
        t0 = time.perf_counter()
        odoms = run_kiss(clouds, stamps)
        t_kiss = time.perf_counter() - t0
        run_closure(clouds[:20], stamps[:20], odoms[:20])  # imports, first-call costs
        t0 = time.perf_counter()
        alone = run_closure(clouds, stamps, odoms)
        t_closure = time.perf_counter() - t0
        print(f'{len(clouds)} hku1 clouds: KISS-ICP alone {t_kiss:.2f} s, loop closure alone '
              f'{t_closure:.2f} s (sum {t_kiss + t_closure:.2f} s)')
        print(f'  loop closure per cloud, alone:           {_ms(alone)}')
        thread = threading.Thread(target=run_kiss, args=(clouds, stamps))
        t0 = time.perf_counter()
        thread.start()
        beside = run_closure(clouds, stamps, odoms)
        thread.join()
        print(f'  ... with KISS-ICP on a thread:           {_ms(beside)}; both done in '
              f'{time.perf_counter() - t0:.2f} s')
        child = multiprocessing.get_context('spawn').Process(target=run_kiss,
                                                             args=(clouds, stamps))
        child.start()
        time.sleep(3.0)  # the child's imports and loading, not KISS-ICP
        t0 = time.perf_counter()
        apart = run_closure(clouds, stamps, odoms)
        child.join()
        print(f'  ... with KISS-ICP in another process:    {_ms(apart)}')
        share = spinner_share(lambda: run_kiss(clouds[:60], stamps[:60]))
        print(f'  a pure-Python thread keeps {share:.2f} of its rate while KISS-ICP registers '
              '(1.0: the GIL is released)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
