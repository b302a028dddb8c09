"""Do the published loop covariances match the loops' errors? NEES per data set.

Each data set is replayed through :class:`LoopDetector` with its shipped preset (verification
on), fed its reference poses as odometry (keyframe gating only; the odometry check is off on
the simulated drives, whose odometry is perfect, as in ``bench_generalisation.py``). For
every published loop the error against the reference relative pose ``T_ref = inv(P_match) @
P_query`` is ``delta = Log(inv(T) @ T_ref)`` (ROS order, right perturbation in the query sensor
frame, the convention of doc/conventions.md) and its NEES ``delta^T inv(C) delta``
(:func:`solid_ros.tools.uncertainty.nees`): mean 6 for a covariance that matches the error, 3
for the translation alone. Printed per data set: published loops, mean / median 6-DoF NEES,
mean / median translation NEES, the largest NEES (and the mean without it: one loop in a
second minimum dominates a mean), the share above the chi-square 95 %
bound (12.59), the median published sigmas (x, y, z in cm; roll, pitch, yaw in deg), the
median absolute errors and, where there are such pairs, how much of the translation error
neighbouring loops share (queries and matches at most 3 keyframes apart): an error of the
reference, a smooth deformation, is common to neighbours; the loops' own errors are not.

Data sets: ``hku1`` (real Livox Avia, ``avia.yaml``, reference ``optimized_poses.txt``: a
loop-closed SLAM result, itself uncertain by about 0.1 m at the loops, which adds to the NEES;
with ``--fine-ref`` also against an independent re-registration of the full clouds at 0.1 m
GICP started from the reference; and always against ``odom_poses.txt``, the same FAST-LIO2
run's odometry before its loop closure: over a 64 m walk it drifts little, and it is not
deformed by that loop closure, which moved the reference by 20-35 cm at the revisit), and the
simulator's demo drives (50 m blocks, a scan every 2 m, seed 0 unless ``--seed``, the
``revisits`` route; exact reference): ``hdl64`` (``hdl64.yaml``), ``avia_like``
(``avia.yaml``), ``ouster_like`` (``ouster.yaml``), ``vlp16_like`` (``vlp16.yaml``),
``hdl64_lookalike``, ``avia_lookalike``, and ``indoor`` (the handheld Avia-like walk
through the simulator's cluttered room, as in ``bench_generalisation.py``).

Usage: ``python test/bench/bench_nees.py [--sets hku1,hdl64,avia_like] [--jobs 2]
[--fine-ref] [--scans N] [--seed N] [--set KEY=VALUE]``; ``--seed`` picks another drive and
walk of the simulated sets (a check on data the calibration did not see).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import numpy as np  # noqa: E402
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'test'))
sys.path.insert(0, str(ROOT / 'test' / 'bench'))

from bench_generalisation import Case, case_config, case_scans, indoor_case  # noqa: E402
from report import PrintedReport, bench_meta  # noqa: E402

from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402
from solid_ros.core.results import LoopCandidate  # noqa: E402
from solid_ros.tools.loops import pose_error  # noqa: E402
from solid_ros.tools.uncertainty import Nees, nees, summarise  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
CHI2_6_95 = 12.59

SIM_SETS: dict[str, Case] = {
    'hdl64': Case('hdl64', 'hdl64', 'revisits', 'varied', 'hdl64.yaml'),
    'avia_like': Case('avia_like', 'avia_like', 'revisits', 'varied', 'avia.yaml'),
    'ouster_like': Case('ouster_like', 'ouster_like', 'revisits', 'varied', 'ouster.yaml'),
    'vlp16_like': Case('vlp16_like', 'vlp16_like', 'revisits', 'varied', 'vlp16.yaml'),
    'hdl64_lookalike': Case('hdl64_lookalike', 'hdl64', 'revisits', 'lookalike', 'hdl64.yaml'),
    'avia_lookalike': Case('avia_lookalike', 'avia_like', 'revisits', 'lookalike',
                           'avia.yaml'),
    'indoor': indoor_case(),
}
SETS = ('hku1', *SIM_SETS)


@dataclass
class Loop:
    """A published loop with its reference pose."""

    candidate: LoopCandidate
    T_ref: np.ndarray
    fine_ref: np.ndarray | None = None
    odom_ref: np.ndarray | None = None


def _detect(cfg: SolidConfig, scans: Any) -> tuple[list[Loop], list[int]]:
    """Run the detector over ``(points, stamp_ns, pose)`` and pair each published loop with
    its reference relative pose; also the scan index of each keyframe."""
    det = LoopDetector(cfg)
    poses: list[np.ndarray] = []
    kept: list[int] = []
    loops: list[Loop] = []
    for i, (points, stamp, pose) in enumerate(scans):
        res = det.process(points, stamp, pose)
        if res.keyframe:
            poses.append(pose)
            kept.append(i)
        for c in res.loops:
            T_ref = np.linalg.solve(poses[c.match_index], poses[c.query_index])
            loops.append(Loop(c, T_ref))
    return loops, kept


def _fine_reference(loops: list[Loop], clouds: list[np.ndarray], kf_scan: list[int]) -> None:
    """An independent estimate: full clouds, 0.1 m GICP from the reference pose."""
    import small_gicp as sg

    for lp in loops:
        q = clouds[kf_scan[lp.candidate.query_index]].astype(np.float64)
        m = clouds[kf_scan[lp.candidate.match_index]].astype(np.float64)
        res = sg.align(q, m, np.linalg.inv(lp.T_ref), registration_type='GICP',
                       downsampling_resolution=0.1, max_correspondence_distance=0.5,
                       num_threads=1)
        lp.fine_ref = np.linalg.inv(np.asarray(res.T_target_source))


def _override(cfg: SolidConfig, sets: dict[str, Any]) -> SolidConfig:
    return cfg.replace(**sets) if sets else cfg


def run_hku1(scans: int | None, fine_ref: bool, sets: dict[str, Any]) -> dict[str, Any]:
    """hku1 with ``avia.yaml`` and the loop-closed poses as odometry and reference."""
    from hku1_data import hku1_scans

    from solid_ros.formats.poses import read_kitti_poses

    clouds, stamps = hku1_scans(DATA)
    ref = read_kitti_poses(DATA / 'hku1' / 'optimized_poses.txt')
    n = len(clouds) if scans is None else min(scans, len(clouds))
    cfg = _override(SolidConfig.from_yaml(ROOT / 'config' / 'avia.yaml'), sets)
    feed = ((clouds[i], stamps[i], np.vstack([ref[i][:3], [0.0, 0.0, 0.0, 1.0]]))
            for i in range(n))
    loops, kept = _detect(cfg, feed)
    odom = read_kitti_poses(DATA / 'hku1' / 'odom_poses.txt')
    for lp in loops:
        q, m = (np.vstack([odom[kept[i]][:3], [0.0, 0.0, 0.0, 1.0]])
                for i in (lp.candidate.query_index, lp.candidate.match_index))
        lp.odom_ref = np.linalg.solve(m, q)
    if fine_ref:
        _fine_reference(loops, list(clouds), kept)
    return {'name': 'hku1 (real Avia)', 'preset': 'avia.yaml', 'loops': loops,
            'keyframes': len(kept)}


def run_sim(name: str, scans: int | None, sets: dict[str, Any],
            seed: int = 0) -> dict[str, Any]:
    """One simulated drive (or walk) of ``seed`` with the case's preset, odometry check off."""
    case = SIM_SETS[name]
    feed = (scan[:3] for scan in case_scans(case, seed, scans))  # the reference as odometry
    loops, kept = _detect(_override(case_config(case), sets), feed)
    return {'name': f'sim {name} ({case.route}, {case.scene}, seed {seed})',
            'preset': case.preset, 'loops': loops, 'keyframes': len(kept)}


def _job(args: tuple[str, int | None, bool, dict[str, Any], int]) -> dict[str, Any]:
    name, scans, fine_ref, sets, seed = args
    t0 = time.perf_counter()
    out = (run_hku1(scans, fine_ref, sets) if name == 'hku1'
           else run_sim(name, scans, sets, seed))
    out['seconds'] = time.perf_counter() - t0
    return out


def _sigmas(loops: Sequence[Loop]) -> tuple[np.ndarray, np.ndarray]:
    """Median published sigmas (cm, deg) and median absolute errors (cm, deg)."""
    sig = np.array([np.sqrt(np.diag(np.reshape(lp.candidate.covariance, (6, 6))))
                    for lp in loops])
    scale = np.array([100.0] * 3 + [math.degrees(1.0)] * 3)
    return np.median(sig, axis=0) * scale, scale


def report(out: dict[str, Any]) -> list[str]:
    """Lines printed for one data set."""
    loops: list[Loop] = out['loops']
    lines = [f'{out["name"]}, {out["preset"]}: {out["keyframes"]} keyframes, {len(loops)} '
             f'published loops ({out["seconds"]:.0f} s)']
    if not loops:
        return lines
    refs = [('reference', [lp.T_ref for lp in loops])]
    if loops[0].odom_ref is not None:
        refs.append(('odom_poses (no loops)', [lp.odom_ref for lp in loops]))
    if loops[0].fine_ref is not None:
        refs.append(('fine re-registration', [lp.fine_ref for lp in loops]))
    sig, scale = _sigmas(loops)
    lines.append('  median sigma     x y z {:.2f} {:.2f} {:.2f} cm   roll pitch yaw {:.3f} {:.3f} '
                 '{:.3f} deg'.format(*sig))
    for label, ref in refs:
        values: list[Nees] = [nees(lp.candidate.matrix(), r, lp.candidate.covariance)
                              for lp, r in zip(loops, ref)]
        s = summarise(values)
        over = np.mean([v.full > CHI2_6_95 for v in values])
        err = np.median(np.abs([v.error for v in values]), axis=0) * scale
        worst = max(pose_error(lp.candidate.matrix(), r)[0] for lp, r in zip(loops, ref))
        full = sorted(v.full for v in values)
        rest = float(np.mean(full[:-1])) if len(full) > 1 else math.nan
        lines.append(f'  vs {label:20s} NEES 6-DoF mean {s["mean"]:8.2f} median '
                     f'{s["median"]:7.2f} largest {full[-1]:8.1f} (mean without it {rest:.2f}; '
                     f'> chi2 95 %: {over:.2f})   translation mean {s["mean_t"]:7.2f} median '
                     f'{s["median_t"]:6.2f}')
        lines.append('     median |error|  x y z {:.2f} {:.2f} {:.2f} cm   roll pitch yaw {:.3f} '
                     '{:.3f} {:.3f} deg'.format(*err) + f'   largest error {worst:.3f} m')
        shared = _shared_error(loops, values)
        if shared is not None:
            lines.append('     neighbouring loops (queries and matches <= 3 keyframes apart, '
                         f'{shared[2]} pairs): median translation error {shared[0]:.2f} cm, '
                         f'median difference of their errors {shared[1]:.2f} cm')
    return lines


def _shared_error(loops: Sequence[Loop],
                  values: Sequence[Nees]) -> tuple[float, float, int] | None:
    """How much of the translation error neighbouring loops share: an error of the reference
    (a smooth deformation) is common to them, the loops' own errors are not."""
    own, diff = [], []
    for i, (a, ea) in enumerate(zip(loops, values)):
        for b, eb in zip(loops[i + 1:], values[i + 1:]):
            ca, cb = a.candidate, b.candidate
            if (0 < abs(ca.query_index - cb.query_index) <= 3
                    and abs(ca.match_index - cb.match_index) <= 3):
                own.append(float(np.linalg.norm(ea.error[:3])))
                diff.append(float(np.linalg.norm(ea.error[:3] - eb.error[:3])))
    if not own:
        return None
    return 100.0 * float(np.median(own)), 100.0 * float(np.median(diff)), len(own)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the chosen data sets and print their NEES."""
    p = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    p.add_argument('--sets', default='hku1,hdl64,avia_like,ouster_like,indoor',
                   help=f'comma-separated, of: {",".join(SETS)}')
    p.add_argument('--scans', type=int, default=None, help='at most this many scans per set')
    p.add_argument('--seed', type=int, default=0,
                   help='seed of the simulated sets (hku1 is one recording)')
    p.add_argument('--jobs', type=int, default=1, help='data sets run in parallel processes')
    p.add_argument('--fine-ref', action='store_true',
                   help='hku1: also against an independent 0.1 m re-registration')
    p.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='override a setting of every preset, e.g. verify_covariance_scale=2')
    p.add_argument('--report', type=Path,
                   help='also write what is printed, with date and commit (.md: doc/reports)')
    args = p.parse_args(argv)
    with PrintedReport(args.report, bench_meta('bench_nees', vars(args))):
        return _run(p, args)


def _run(p: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    sets: dict[str, Any] = {}
    for item in args.set:
        key, _, value = item.partition('=')
        sets[key] = yaml.safe_load(value)
    names = [n for n in args.sets.split(',') if n]
    bad = [n for n in names if n not in SETS]
    if bad:
        p.error(f'unknown set: {", ".join(bad)} (allowed: {", ".join(SETS)})')
    if 'hku1' in names and not (DATA / 'hku1' / 'bag').is_dir():
        print(f'hku1 skipped: {DATA / "hku1" / "bag"} is missing')
        names.remove('hku1')
    print('NEES = delta^T inv(C) delta, delta = Log(inv(T) T_ref), ROS order, right '
          'perturbation; consistent: mean 6 (translation 3)', flush=True)
    jobs = [(n, args.scans, args.fine_ref, sets, args.seed) for n in names]
    if args.jobs > 1:
        from multiprocessing import Pool

        with Pool(args.jobs) as pool:
            for out in pool.imap(_job, jobs):
                print('\n'.join(report(out)), flush=True)
    else:
        for job in jobs:
            print('\n'.join(report(_job(job))), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
