"""Benchmark of the descriptor database: median query time and amortised insert time.

Run: ``.venv/bin/python test/bench/bench_database.py [--sizes 1000 10000 100000]``

Stores N synthetic descriptors (N_r = 40, N_a = 60) in each search mode, then times
``search`` with the detector's defaults (k = num_candidates + 2 * margin_neighbourhood + 1 =
31, the 50 most recent scans excluded) and reports the median over the queries. ``random``
descriptors are uniform in [0, 1)^40 (worst case for a kd-tree); ``walk`` descriptors follow a
smooth random trajectory in a 6-D latent space, closer to a real drive. One core only.
"""

from __future__ import annotations

import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import numpy.typing as npt  # noqa: E402

from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.core.database.descriptors import DescriptorDatabase  # noqa: E402

SEC = 1_000_000_000


def descriptors(kind: str, n: int, seed: int = 0) -> npt.NDArray[np.float64]:
    """Synthetic R-SOLiD-like vectors, shape (n, 40), non-negative."""
    rng = np.random.default_rng(seed)
    if kind == 'random':
        return rng.random((n, 40))
    latent = np.cumsum(rng.normal(scale=0.05, size=(n, 6)), axis=0)
    return np.sin(latent @ rng.normal(size=(6, 40))) + 1.2


def bench(kind: str, mode: str, n: int, queries: int) -> tuple[float, float, float]:
    """Return (median query ms, amortised insert ms, bytes per scan incl. kd-tree copy)."""
    cfg = SolidConfig().replace(search=mode, capacity=max(n, 1))
    db = DescriptorDatabase(cfg)
    r = descriptors(kind, n)
    a = np.ones(60)
    t0 = time.perf_counter()
    for i in range(n):
        db.add(r[i], a, i * SEC // 10)
    insert_ms = (time.perf_counter() - t0) * 1e3 / n
    k = cfg.num_candidates + 2 * cfg.margin_neighbourhood + 1
    rng = np.random.default_rng(1)
    picks = rng.integers(0, n, queries)
    qs = r[picks] + rng.normal(scale=0.01, size=(queries, 40))
    times = []
    for q in qs:
        t = time.perf_counter()
        db.search(q, n * SEC // 10, k, exclude_frames=cfg.exclude_recent_frames)
        times.append(time.perf_counter() - t)
    tree_bytes = 0
    if db._tree is not None:  # the tree's float64 copy, its index array and our seq map
        tree_bytes = db._tree.data.nbytes + db._tree.indices.nbytes + db._tree_seqs.nbytes
    return statistics.median(times) * 1e3, insert_ms, (db.nbytes + tree_bytes) / cfg.capacity


def main() -> None:
    """Print one table row per (data, mode, size)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--sizes', type=int, nargs='+', default=[1000, 10_000, 100_000])
    ap.add_argument('--queries', type=int, default=200)
    ap.add_argument('--data', nargs='+', default=['random', 'walk'], choices=['random', 'walk'])
    args = ap.parse_args()
    print(f'{"data":7} {"mode":7} {"stored":>8} {"query median ms":>16} '
          f'{"insert ms (amortised)":>22} {"bytes/scan":>11}')
    for kind in args.data:
        for mode in ('brute', 'kdtree'):
            for n in args.sizes:
                q_ms, i_ms, bps = bench(kind, mode, n, args.queries)
                print(f'{kind:7} {mode:7} {n:8d} {q_ms:16.3f} {i_ms:22.4f} {bps:11.0f}',
                      flush=True)


if __name__ == '__main__':
    main()
