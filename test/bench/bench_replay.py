"""Replay throughput: scans/s end to end (read + decode + detect) and growth with length.

Usage: ``python test/bench/bench_replay.py [--params config/avia.yaml] [--repeats 3]``

1. Replays ../shared/data/hku1/bag (314 keyframes) through :func:`solid_ros.tools.replay.replay`
   and prints scans/s (best of ``--repeats`` runs).
2. Writes MCAP bags holding the hku1 clouds 1x, 2x and 4x (stamps shifted, every copy a new
   scan) in a temporary directory and prints the replay time of each, the time per scan and
   the ratio to the 1x time: linear growth keeps time per scan flat.
Evaluation and plots are off, so only reading, decoding and the detector are timed.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.formats.bags import Bag, write_cloud_bag  # noqa: E402
from solid_ros.tools.replay import replay  # noqa: E402

HKU1 = ROOT.parent / 'shared' / 'data' / 'hku1' / 'bag'


def _best(bag: Path, cfg: SolidConfig, repeats: int) -> tuple[float, int]:
    best = float('inf')
    n = 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = replay(bag, cfg, progress='quiet', plots=False)
        best = min(best, time.perf_counter() - t0)
        n = r.messages - r.skipped
    return best, n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--params', default=str(ROOT / 'config' / 'avia.yaml'))
    ap.add_argument('--repeats', type=int, default=3)
    args = ap.parse_args()
    if not HKU1.is_dir():
        print(f'hku1 bag not found at {HKU1}; nothing to measure')
        return 1
    cfg = SolidConfig.from_yaml(args.params)
    print(f'params: {args.params}')
    sec, n = _best(HKU1, cfg, args.repeats)
    print(f'hku1: {n} scans in {sec:.3f} s -> {n / sec:.0f} scans/s end to end '
          f'(best of {args.repeats})')

    with Bag(HKU1) as bag:
        scans = [(np.array(c.points), c.stamp_ns) for c in bag.clouds('/points')
                 if c.points is not None]
    span = scans[-1][1] - scans[0][1] + 1_000_000_000
    base = None
    print(f'{"copies":>6} {"scans":>6} {"time s":>8} {"ms/scan":>8} {"scans/s":>8} '
          f'{"time / 1x":>9}')
    with tempfile.TemporaryDirectory() as tmp:
        for k in (1, 2, 4):
            path = write_cloud_bag(Path(tmp) / f'x{k}', ((p, s + i * span)
                                                         for i in range(k) for p, s in scans))
            sec, n = _best(path, cfg, args.repeats)
            base = base or sec
            print(f'{k:>6} {n:>6} {sec:>8.3f} {1e3 * sec / n:>8.3f} {n / sec:>8.0f} '
                  f'{sec / base:>9.2f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
