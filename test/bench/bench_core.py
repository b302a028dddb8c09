"""Speed of the core against the SOLiD authors' C++, measured in one run, interleaved.

Run: .venv/bin/python test/bench/bench_core.py [--rounds 5] [--reps 100] [--cpp PATH]

Builds the authors' C++ (../shared/reference/authors_cpp/build.sh: their range gate, PCL voxel
grid and descriptor, -O3 -march=native) into a temporary directory, unless ``--cpp`` names a
built ``bench_solid``. Then, round after round, it runs the C++ timing driver and this
package's Python on the same KITTI scan 313 (C++, Python, C++, Python, ...) and prints per
round and overall (median of the per-round ratios):

- describe, 360 deg: Python ``describe()`` / C++ gate + voxel grid + descriptor;
- describe, 60-degree FOV: Python ``describe()`` of the full scan with ``fov_width_deg=60``
  / the C++ on the full scan (the authors' code has no FOV clip), and / the C++ on the scan
  already clipped to 60 deg (written as a PCD file for it);
- distance + heading for one pair (313 vs 314): Python ``cosine_distance`` +
  ``estimate_yaw`` / C++ ``loop_detection`` + ``pose_estimation``.

Describe times are medians of thread CPU time (the C++ driver's RESULTCPU line), robust to a
shared machine; wall-clock ratios are printed too. The pair is wall-clock on both sides (the
C++ driver times it so). The Python side is a plain process: no allocator or thread tuning.
Without cmake, PCL or the reference sources the C++ part is skipped with the reason, and
only the Python times are printed.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from solid_ros import SolidConfig, cosine_distance, describe, estimate_yaw
from solid_ros.core.descriptor.solid import fov_mask
from solid_ros.formats.pointfiles import read_pcd

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / 'shared' / 'data'
AUTHORS = ROOT.parent / 'shared' / 'reference' / 'authors_cpp'
GOALS = {'describe_360': 0.5, 'describe_60': 0.2, 'pair': 2.0}


def _median_times(fn: Callable[[], object], repeat: int,
                  clock: Callable[[], float]) -> float:
    """Median seconds of ``fn`` over ``repeat`` calls, by ``clock``."""
    out = []
    for _ in range(repeat):
        t0 = clock()
        fn()
        out.append(clock() - t0)
    return float(np.median(out))


def _build_cpp(workdir: Path) -> tuple[Path | None, str]:
    """Build the authors' C++ into ``workdir``; (executable, '') or (None, reason)."""
    script = AUTHORS / 'build.sh'
    if not script.is_file():
        return None, f'{script} not found'
    for tool in ('cmake', 'g++'):
        if shutil.which(tool) is None:
            return None, f'{tool} is not installed (apt-get install -y cmake g++ libpcl-dev)'
    proc = subprocess.run(['bash', str(script), str(workdir / 'build')], capture_output=True,
                          text=True, check=False)
    exe = Path(proc.stdout.strip().splitlines()[-1]) if proc.stdout.strip() else None
    if proc.returncode != 0 or exe is None or not exe.is_file():
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return None, ('build failed (PCL missing? apt-get install -y libpcl-dev '
                      f'libeigen3-dev): {" | ".join(tail)}')
    return exe, ''


def _write_pcd(path: Path, points: np.ndarray) -> None:
    pts = np.ascontiguousarray(points[:, :3], dtype='<f4')
    header = ('VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n'
              f'WIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(pts)}\n'
              'DATA binary\n')
    path.write_bytes(header.encode('ascii') + pts.tobytes())


def _run_cpp(exe: Path, query: Path, candidate: Path, reps: int,
             desc_out: Path | None = None) -> dict[str, float]:
    """Run the C++ driver once; its medians in ms, keys 'cpu_total', 'wall_total', 'pair'."""
    cmd = [str(exe), str(query), str(candidate), str(reps), '1000']
    if desc_out is not None:
        cmd.append(str(desc_out))
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout

    def fields(tag: str) -> dict[str, float]:
        line = re.search(rf'^{tag} (.*)$', out, re.M)
        if line is None:
            raise RuntimeError(f'no {tag} line in the C++ output:\n{out}')
        return {k: float(v) for k, v in re.findall(r'(\w+)=([\d.eE+-]+)', line.group(1))}

    wall, cpu = fields('RESULT'), fields('RESULTCPU')
    return {'cpu_total': cpu['total'], 'wall_total': wall['total'], 'pair': wall['pair'],
            'cpu_gate': cpu['gate'], 'cpu_voxel': cpu['voxel'], 'cpu_desc': cpu['desc']}


def _run_python(scan: np.ndarray, other: np.ndarray, reps: int) -> dict[str, float]:
    """Python medians in ms: describe at 360 and 60 deg (CPU and wall) and the pair (wall)."""
    out: dict[str, float] = {}
    for key, cfg in (('360', SolidConfig()), ('60', SolidConfig(fov_width_deg=60.0))):
        describe(scan, cfg)  # warm-up
        out[f'cpu_{key}'] = _median_times(lambda c=cfg: describe(scan, c), reps,
                                          time.thread_time) * 1e3
        out[f'wall_{key}'] = _median_times(lambda c=cfg: describe(scan, c), reps,
                                           time.perf_counter) * 1e3
    d, e = describe(scan), describe(other)

    def pair() -> None:
        cosine_distance(d.r_solid, e.r_solid)
        estimate_yaw(d.a_solid, e.a_solid)

    out['pair'] = _median_times(pair, 20 * reps, time.perf_counter) * 1e3
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rounds', type=int, default=5, help='C++ / Python alternations')
    parser.add_argument('--reps', type=int, default=100, help='describe calls per round')
    parser.add_argument('--cpp', type=Path, help='an already built bench_solid executable')
    parser.add_argument('--no-cpp', action='store_true', help='Python times only')
    args = parser.parse_args()
    pcd313 = DATA / 'kitti' / 'pcd' / '000313.pcd'
    pcd314 = DATA / 'kitti' / 'pcd' / '000314.pcd'
    if not pcd313.is_file():
        print(f'KITTI scans not found at {pcd313.parent}; nothing to measure', file=sys.stderr)
        return 1
    scan, other = read_pcd(pcd313), read_pcd(pcd314)
    print(f'KITTI 000313: {len(scan)} points, float32 (N, 3); Python {sys.version.split()[0]}, '
          f'numpy {np.__version__}, plain process (no tuning)')
    with tempfile.TemporaryDirectory(prefix='solid_bench_') as tmp:
        work = Path(tmp)
        exe: Path | None = None
        if args.cpp is not None:
            exe = args.cpp
        elif not args.no_cpp:
            print("building the authors' C++ (build.sh, -O3 -march=native) ...", flush=True)
            exe, reason = _build_cpp(work)
            if exe is None:
                print(f'C++ part skipped: {reason}')
        clipped = work / 'kitti313_fov60.pcd'
        _write_pcd(clipped, scan[fov_mask(scan[:, 0], scan[:, 1], 60.0)])
        if exe is not None:
            desc_file = work / 'cpp_desc.txt'
            _run_cpp(exe, pcd313, pcd314, 5, desc_file)
            theirs = np.loadtxt(desc_file)
            ours = describe(scan)
            ref = np.concatenate([ours.r_solid, ours.a_solid])
            err = float(np.max(np.abs(theirs - ref) / np.maximum(np.abs(ref), 1e-300)))
            print(f'C++ {exe}: descriptor of 313 matches Python to max relative error '
                  f'{err:.1e}')
        return _rounds(args, exe, scan, other, pcd313, pcd314, clipped)


def _rounds(args: argparse.Namespace, exe: Path | None, scan: np.ndarray, other: np.ndarray,
            pcd313: Path, pcd314: Path, clipped: Path) -> int:
    ratios: dict[str, list[float]] = {k: [] for k in (
        'describe_360', 'describe_360_wall', 'describe_60', 'describe_60_clipped', 'pair')}
    py_all: list[dict[str, float]] = []
    cpp_all: list[dict[str, float]] = []
    for r in range(args.rounds):
        line = f'round {r + 1}:'
        if exe is not None:
            cpp = _run_cpp(exe, pcd313, pcd314, args.reps)
            cpp60 = _run_cpp(exe, clipped, pcd314, args.reps)
            cpp['cpu_total_60'] = cpp60['cpu_total']
            cpp_all.append(cpp)
            line += (f' C++ {cpp["cpu_total"]:.2f} ms (60-deg clip {cpp60["cpu_total"]:.2f}), '
                     f'pair {cpp["pair"] * 1e3:.1f} us;')
        py = _run_python(scan, other, args.reps)
        py_all.append(py)
        line += (f' Python {py["cpu_360"]:.2f} ms, 60 deg {py["cpu_60"]:.2f} ms, '
                 f'pair {py["pair"] * 1e3:.1f} us')
        if exe is not None:
            ratios['describe_360'].append(py['cpu_360'] / cpp['cpu_total'])
            ratios['describe_360_wall'].append(py['wall_360'] / cpp['wall_total'])
            ratios['describe_60'].append(py['cpu_60'] / cpp['cpu_total'])
            ratios['describe_60_clipped'].append(py['cpu_60'] / cpp['cpu_total_60'])
            ratios['pair'].append(py['pair'] / cpp['pair'])
            line += (f' -> ratios {ratios["describe_360"][-1]:.2f} / '
                     f'{ratios["describe_60"][-1]:.2f} / {ratios["pair"][-1]:.2f}')
        print(line, flush=True)

    def med(rows: list[dict[str, float]], key: str) -> float:
        return float(np.median([row[key] for row in rows]))

    print(f'\nPython medians over {args.rounds} rounds: describe 360 deg '
          f'{med(py_all, "cpu_360"):.2f} ms CPU, 60 deg {med(py_all, "cpu_60"):.2f} ms, '
          f'distance + heading {med(py_all, "pair") * 1e3:.1f} us')
    if exe is None:
        return 0
    print(f'C++ medians: gate {med(cpp_all, "cpu_gate"):.2f} + voxel '
          f'{med(cpp_all, "cpu_voxel"):.2f} + descriptor {med(cpp_all, "cpu_desc"):.2f} = '
          f'{med(cpp_all, "cpu_total"):.2f} ms CPU; on the 60-degree clip '
          f'{med(cpp_all, "cpu_total_60"):.2f} ms; distance + heading '
          f'{med(cpp_all, "pair") * 1e3:.1f} us')
    print("\nRatio Python / authors' C++ (median of the per-round ratios; lower is faster):")
    rows = [
        ('describe, KITTI 313, 360 deg (CPU time)', 'describe_360', GOALS['describe_360']),
        ('describe, KITTI 313, 360 deg (wall clock)', 'describe_360_wall', None),
        ('describe, 60-degree FOV, vs C++ on the full scan', 'describe_60',
         GOALS['describe_60']),
        ('describe, 60-degree FOV, vs C++ on the pre-clipped scan', 'describe_60_clipped',
         None),
        ('distance + heading, one pair (wall clock)', 'pair', GOALS['pair']),
    ]
    for label, key, goal in rows:
        value = float(np.median(ratios[key]))
        spread = f'{min(ratios[key]):.2f}-{max(ratios[key]):.2f}'
        verdict = '' if goal is None else (
            f'  goal <= {goal}: {"met" if value <= goal else "NOT met"}')
        print(f'  {label:58s} {value:5.2f}x  (rounds {spread}){verdict}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
