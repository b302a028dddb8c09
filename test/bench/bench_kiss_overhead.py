"""Where the node's KISS-ICP odometry spends its time beyond plain KISS-ICP, one cloud at a time.

Run: ``nice python test/bench/bench_kiss_overhead.py [--clouds 150] [--kitti 25]
[--report doc/reports/bench_kiss_overhead.md]``.

bench_node_kiss measured the node's odometry at a median 91 ms per hku1 cloud against 64 ms
for plain KISS-ICP, but the node ran describe and verify beside it on 2 cores and dropped a
sixth of the clouds (wider gaps to register), and plain KISS-ICP ran alone afterwards. Here
the same clouds (hku1, the first ``--clouds``, bench_kiss's RECIPE: voxel 0.5 m, max range
50 m, no deskew) go, each in turn and under the same load, through:

1. plain KISS-ICP 1.3 (``register_frame``);
2. :class:`~solid_ros.core.odometry.kiss.KissOdometry` in this process, with its parts timed:
   the input checks (finite rows, range gate), the overlap check's preparation of the cloud
   (``_prepare``: voxelise, normals, kd-tree), the registration (KISS-ICP's deskew, voxelise,
   align, commit) and the overlap check itself;
3. :class:`~solid_ros.core.odometry.kiss_process.KissProcess` (as the node runs it), its round
   trip split with the child's own clock (``last_ms``): to the child (pickling, pipe,
   waking), in ``KissOdometry.pose_for`` there, and back.

It runs twice: alone, then with a pure-Python thread spinning in this process (the node's
describe and verify threads hold the GIL and a core the same way: KISS-ICP in this process
stalls it, the child has to share the 2 cores with it). Then, alone, ``--kitti`` clouds of
KITTI scan 313 turning (bench_node_kiss's, 121k points) at its two settings (voxel 0.5 m, max
range 50 m; voxel 1 m, max range 30 m). The poses of 2 and 3 are compared.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'test'))

from bench.report import PrintedReport, bench_meta  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
NS_STEP = 100_000_000  # 10 Hz stamps


def _load() -> str:
    return f'load {os.getloadavg()[0]:.1f}'


def _ms(values: list[float]) -> str:
    v = np.asarray(values, dtype=np.float64)
    return f'median {np.median(v):6.2f} ms, p95 {np.percentile(v, 95):6.2f} ms'


def _timed(obj: Any, name: str, into: list[float]) -> None:
    """Replace ``obj.name`` by a wrapper that appends its ms per call to ``into``."""
    inner: Callable[..., Any] = getattr(obj, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            into.append((time.perf_counter() - t0) * 1e3)

    setattr(obj, name, wrapper)


def _spin(stop: threading.Event) -> None:
    x = 0
    while not stop.is_set():
        for i in range(10_000):
            x += i


def run(clouds: list[np.ndarray], voxel: float = 0.5,
        max_range: float = 50.0) -> dict[str, list[float]]:
    """Each cloud through plain KISS-ICP, KissOdometry here and KissProcess; ms by part."""
    from solid_ros.core.config import NodeConfig
    from solid_ros.core.odometry.kiss import KissOdometry, load_kiss_icp
    from solid_ros.core.odometry.kiss_process import KissProcess

    cfg = NodeConfig(kiss_max_range=max_range, kiss_voxel_size=voxel, kiss_deskew=False)
    KissICP, KISSConfig, _ = load_kiss_icp()
    kc = KISSConfig()
    kc.data.max_range, kc.data.deskew, kc.mapping.voxel_size = max_range, False, voxel
    plain = KissICP(kc)
    here = KissOdometry(cfg)
    out: dict[str, list[float]] = defaultdict(list)
    for name in ('_prepare', '_register', '_check'):
        _timed(here, name, out[f'here {name}'])
    child = KissProcess(cfg)
    worst = 0.0
    try:
        for i, points in enumerate(clouds):
            stamp = (i + 1) * NS_STEP
            pts = np.asarray(points, dtype=np.float64)
            t0 = time.perf_counter()
            plain.register_frame(pts, np.zeros(len(pts)))
            t1 = time.perf_counter()
            want = here.pose_for(stamp, points)
            t2 = time.perf_counter()
            got = child.pose_for(stamp, points)
            t3 = time.perf_counter()
            out['plain'].append((t1 - t0) * 1e3)
            out['here'].append((t2 - t1) * 1e3)
            out['process'].append((t3 - t2) * 1e3)
            assert child.last_ms is not None and want is not None and got is not None
            for part, ms in zip(('to child', 'in child', 'back'), child.last_ms):
                out[f'process {part}'].append(ms)
            worst = max(worst, float(np.abs(got.pose - want.pose).max()))
    finally:
        child.close()
    out['worst pose difference here / process'] = [worst]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--clouds', type=int, default=150, help='hku1 clouds')
    parser.add_argument('--kitti', type=int, default=25,
                        help='KITTI 313 clouds (121k points) per setting; 0 skips them')
    parser.add_argument('--report', type=Path, help='write the printed figures (.md or JSON)')
    args = parser.parse_args()
    if not (DATA / 'hku1' / 'bag').is_dir():
        print(f'skip: {DATA / "hku1"} is missing')
        return 0
    from hku1_data import hku1_scans

    clouds = [np.asarray(c[:, :3], dtype=np.float32)
              for c in hku1_scans(DATA)[0][:args.clouds]]
    with PrintedReport(args.report, bench_meta('bench_kiss_overhead', vars(args))):
        for busy in (False, True):
            print(f'hku1, {len(clouds)} clouds, voxel 0.5 m, max range 50 m, no deskew, '
                  f'{"a spinning thread beside" if busy else "alone"} ({_load()} before)')
            _print(_run_beside(clouds, busy))
            print(f'  ({_load()} after)')
        _kitti(args.kitti)
    return 0


def _kitti(count: int) -> None:
    """The same, alone, on KITTI scan 313 (121k points) turning (bench_node_kiss's clouds), with
    bench_node_kiss's two settings: the checks grow with the cloud, KISS-ICP less."""
    if count <= 0:
        return
    from bench_node_kiss import there_and_back, turned

    from solid_ros.formats.pointfiles import read_pcd

    base = turned(read_pcd(DATA / 'kitti' / 'pcd' / '000313.pcd'), 40)
    clouds = [base[there_and_back(i, len(base))] for i in range(count)]
    for voxel, max_range in ((0.5, 50.0), (1.0, 30.0)):
        print(f'KITTI 313 turning, {count} clouds of {len(base[0])} points, voxel {voxel:g} m, '
              f'max range {max_range:g} m, alone ({_load()} before)')
        _print(run(clouds, voxel, max_range))
        print(f'  ({_load()} after)')


def _run_beside(clouds: list[np.ndarray], busy: bool) -> dict[str, list[float]]:
    """:func:`run`, with a spinning thread beside when ``busy``."""
    stop = threading.Event()
    if busy:
        threading.Thread(target=_spin, args=(stop,), daemon=True).start()
    try:
        return run(clouds)
    finally:
        stop.set()


def _print(out: dict[str, list[float]]) -> None:
    for name, values in out.items():
        if name.startswith('worst'):
            print(f'  {name}: {values[0]:.2e}')
        else:
            print(f'  {name:22s} {_ms(values)}')


if __name__ == '__main__':
    raise SystemExit(main())
