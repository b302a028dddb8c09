"""The pose-graph back end on simulated drives with drifting odometry.

The simulator's poses are the reference; the odometry is made from them with
``test/drifting_odometry.py`` (1 % scale error, 0.055 deg/m heading bias, a heading random walk
and a slight pitch bias: about 5 % KITTI-style drift). The shipped preset of each sensor runs
through :class:`LoopDetector` with that odometry (``odom_check_drift`` 0.2: the preset's 0.1
allows 10 % of the path, which 5 % drift plus the loop's own pose reach on the longest loops),
then :class:`PoseGraph` with its defaults takes every keyframe. The detector's results are
cached (``--cache``), the back end always runs afresh.

Sections (``--sections``, default all):

- ``drift``: revisit drives (``--sensors``): ATE (SE(3)-aligned RMSE) and RPE over 10
  keyframes of the odometry and of the corrected trajectory; goal: ATE reduced >= 5x.
- ``norevisit``: the 2 km serpentine that never returns: no loop, the trajectory unchanged.
- ``kernels``: Huber, Cauchy and least squares, gate off (a plain robust graph over the
  published loops), at 5 % and 7 % drift, with the default odometry model and one ten times
  tighter (loops start hundreds of sigmas away); and gtsam's GNC (TLS, batch, odometry known
  inliers) over the same graph.
- ``false``: a false loop 20 m off with a tight covariance (1 cm, 0.06 deg) injected at
  several keyframes, alone, and as a burst of five consistent ones (the same 20 m shift at five
  consecutive keyframes): what the back end did with them and the ATE change (goal < 10 %).
- ``reloc``: the hdl64 drive's corrected poses saved with its database; 200 scans of the same
  route driven again from scan 150 (a robot started in the middle of the map; new sensor
  noise, another drift, odometry starting at 50 m and 90 deg) with that database loaded: the
  corrected poses after the first loop against the saved map, against the saved map's pose of
  the same place (goal within 0.3 m / 1 deg).
- ``cost``: update time per keyframe on a synthetic 2,000-keyframe drive with loops (p50 /
  p95 / max over all keyframes and over the last 500; goal p50 <= 5 ms, p95 <= 30 ms).

Usage: ``python test/bench/bench_backend.py [--sections drift,false] [--sensors hdl64]
[--cache DIR] [--keyframes 2000]``. Takes about 5 minutes without a cache on an idle machine
(most of it simulating and verifying scans).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import pickle
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'test'))

from drifting_odometry import Drift, drift_percent, drifting_odometry  # noqa: E402

from solid_ros.core.backend.noise import rotation_angle  # noqa: E402
from solid_ros.core.backend.posegraph import PoseGraph  # noqa: E402
from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.core.database.persistence import read_map_poses  # noqa: E402
from solid_ros.core.flow.detector import LoopDetector  # noqa: E402
from solid_ros.core.geometry import matrix_to_vector  # noqa: E402
from solid_ros.core.odometry.track import OdomSample  # noqa: E402
from solid_ros.core.results import LoopCandidate, ScanResult  # noqa: E402
from solid_ros.sim import DEMO_DEFAULTS, DEMO_SENSORS, Drive, DriveConfig, cast_scan  # noqa: E402
from solid_ros.tools.trajectory_metrics import ate_rmse, rpe  # noqa: E402

PRESET = {'hdl64': 'hdl64.yaml', 'avia_like': 'avia.yaml'}
ODOM_CHECK = 0.2
TIGHT = tuple(np.diag([1e-4] * 3 + [1e-6] * 3).ravel())  # 1 cm, 0.06 deg
SECTIONS = ('drift', 'norevisit', 'kernels', 'false', 'reloc', 'cost')


@dataclass
class Run:
    """A drive through the detector: per keyframe its reference pose, scan index, stamp and
    loops; the odometry is recomputed from the reference for each drift."""

    name: str
    reference: np.ndarray
    scans: list[int]
    stamps: list[int]
    loops: list[tuple[LoopCandidate, ...]]
    database: Path

    def odometry(self, drift: Drift | None = None) -> np.ndarray:
        return drifting_odometry(self.reference, drift or Drift())


def preset(sensor: str) -> SolidConfig:
    return SolidConfig.from_yaml(ROOT / 'config' / PRESET[sensor]).replace(
        odom_check_drift=ODOM_CHECK)


def detect(sensor: str, route: str, cache: Path) -> Run:
    """Run the detector over a demo drive with 5 % drifting odometry (cached)."""
    name = f'{sensor}_{route}'
    pkl, db = cache / f'{name}.pkl', cache / f'{name}.npz'
    if pkl.is_file() and db.is_file():
        return Run(**pickle.loads(pkl.read_bytes()))
    drive = Drive(DriveConfig(**{**DEMO_DEFAULTS, 'sensor': DEMO_SENSORS[sensor],
                                 'route': route}))
    ref = drive.poses()
    odo = drifting_odometry(ref, Drift())
    det = LoopDetector(preset(sensor))
    keep: list[int] = []
    stamps: list[int] = []
    loops: list[tuple[LoopCandidate, ...]] = []
    t0 = time.perf_counter()
    for i in range(len(drive)):
        scan = drive.scan(i)
        res = det.process(scan.points, scan.stamp_ns, odo[i])
        if res.keyframe:
            keep.append(i)
            stamps.append(res.stamp_ns)
            loops.append(res.loops)
    print(f'  (detector over {name}: {len(keep)} keyframes, {sum(map(len, loops))} loops, '
          f'{time.perf_counter() - t0:.0f} s)', flush=True)
    cache.mkdir(parents=True, exist_ok=True)
    det.save(db)
    run = Run(name, ref[keep], keep, stamps, loops, db)
    pkl.write_bytes(pickle.dumps(dataclasses.asdict(run)))
    return run


def back_end(run: Run, odo: np.ndarray, cfg: SolidConfig,
             inject: dict[int, tuple[LoopCandidate, ...]] | None = None,
             ) -> tuple[PoseGraph, np.ndarray, list[Any]]:
    """Feed a run to a new back end; returns it, the corrected poses and the outcomes of the
    injected loops."""
    pg = PoseGraph(cfg)
    seen: list[Any] = []
    for k, (stamp, loops) in enumerate(zip(run.stamps, run.loops)):
        extra = (inject or {}).get(k, ())
        st = pg.update(ScanResult(stamp, True, k, matrix_to_vector(odo[k]), loops + extra))
        seen += [o for o in st.loops if o.loop in extra]
    est = np.array([kf.pose for kf in pg.keyframes()])
    return pg, est, seen


def errors(est: np.ndarray, ref: np.ndarray) -> str:
    t, r = rpe(est, ref, 10)
    return f'ATE {ate_rmse(est, ref):7.3f} m  RPE/10 {t:.3f} m {r:.2f} deg'


def section_drift(runs: list[Run]) -> None:
    print('\n== revisit drives, 5 % drifting odometry: odometry vs corrected (goal ATE / 5)')
    for run in runs:
        odo = run.odometry()
        cfg = SolidConfig()
        pg, est, _ = back_end(run, odo, cfg)
        a0, a1 = ate_rmse(odo, run.reference), ate_rmse(est, run.reference)
        print(f'{run.name:22s} {len(run.stamps)} keyframes, drift '
              f'{drift_percent(odo, run.reference):.2f} %, loops {dict(pg.counts)}')
        print(f'  odometry  {errors(odo, run.reference)}')
        print(f'  corrected {errors(est, run.reference)}   ATE reduced {a0 / a1:.1f}x')


def section_norevisit(run: Run) -> None:
    print('\n== drive without revisit (2 km serpentine): unchanged')
    odo = run.odometry()
    pg, est, _ = back_end(run, odo, SolidConfig())
    moved = max(float(np.linalg.norm(e[:3, 3] - o[:3, 3])) for e, o in zip(est, odo))
    print(f'{run.name:22s} {len(run.stamps)} keyframes, loops published '
          f'{sum(map(len, run.loops))}, outcomes {dict(pg.counts)}')
    print(f'  odometry  {errors(odo, run.reference)}')
    print(f'  corrected {errors(est, run.reference)}   largest change {moved:.2e} m')


def batch(pg: PoseGraph, odo: np.ndarray, kernel: str) -> tuple[np.ndarray, int, float]:
    """The back end's factors solved in one batch from the odometry (every loop at once, as
    a plain graph over the published loops would be): Levenberg-Marquardt under ``kernel``,
    or ``'gnc'``: gtsam's GNC with TLS, odometry and priors known inliers. Returns the
    corrected poses, the loops GNC judged outliers and the seconds taken."""
    import gtsam

    from solid_ros.core.backend.solver import FactorRecord, GraphSolver

    solver = GraphSolver('huber' if kernel == 'gnc' else kernel, 1.345)
    graph = gtsam.NonlinearFactorGraph()
    inliers = []
    for rec in pg._solver.records:
        if rec.kind in ('odom', 'anchor', 'prior'):
            inliers.append(graph.size())
        plain = FactorRecord(rec.kind, rec.keys, rec.measured, rec.covariance,
                             robust=rec.robust and kernel != 'gnc')
        graph.add(solver.factor(plain))
    values = gtsam.Values()
    keys = sorted(pg._solver.values)
    for key, T in zip(keys, odo):
        values.insert(key, gtsam.Pose3(T))
    t0 = time.perf_counter()
    outliers = 0
    if kernel == 'gnc':
        params = gtsam.GncLMParams()
        params.setKnownInliers(inliers)
        params.setLossType(gtsam.GncLossType.TLS)
        opt = gtsam.GncLMOptimizer(graph, values, params)
        result = opt.optimize()
        weights = np.asarray(opt.getWeights())
        known = set(inliers)
        outliers = int(sum(weights[i] < 0.5 for i in range(graph.size()) if i not in known))
    else:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    seconds = time.perf_counter() - t0
    return np.array([result.atPose3(k).matrix() for k in keys]), outliers, seconds


def section_kernels(run: Run) -> None:
    print('\n== robust kernels, gate off (every published loop in the graph): ATE, metres; '
          'iSAM2 = the back end keyframe by keyframe, batch = one solve from the odometry')
    tight = {'backend_odom_trans_sigma': 0.005, 'backend_odom_rot_sigma_deg': 0.01,
             'backend_odom_rot_per_rad': 0.005}
    for drift in (Drift(), Drift(scale=0.015, yaw_bias_deg_per_m=0.075)):
        odo = run.odometry(drift)
        pct = drift_percent(odo, run.reference)
        for model, over in (('default model', {}), ('10x tighter model', tight)):
            inc, bat = [], []
            for kernel in ('huber', 'cauchy', 'none'):
                cfg = SolidConfig(backend_loop_kernel=kernel, backend_loop_gate=0.0,
                                  backend_loop_refuse=0.0, **over)
                pg, est, _ = back_end(run, odo, cfg)
                inc.append(f'{kernel} {ate_rmse(est, run.reference):6.3f}')
                est, _, _ = batch(pg, odo, kernel)
                bat.append(f'{kernel} {ate_rmse(est, run.reference):6.3f}')
            est, out, sec = batch(pg, odo, 'gnc')
            bat.append(f'GNC-TLS {ate_rmse(est, run.reference):6.3f} ({out} outliers, '
                       f'{sec:.1f} s)')
            print(f'{run.name} drift {pct:.1f} % {model} (odometry '
                  f'{ate_rmse(odo, run.reference):.2f})\n  iSAM2  ' + ' | '.join(inc)
                  + '\n  batch  ' + ' | '.join(bat))


def _fake(run: Run, q: int, shift: np.ndarray) -> LoopCandidate | None:
    """A false loop from keyframe ``q``: it claims q's place is 20 m (``shift``) from where it
    is, matched to the older keyframe nearest that false place."""
    ref = run.reference
    claimed = shift @ ref[q]
    if q < 60:
        return None
    d = np.linalg.norm(ref[:q - 50, :3, 3] - claimed[:3, 3], axis=1)
    m = int(np.argmin(d))
    if d[m] > 10.0:
        return None
    T = np.linalg.solve(ref[m], claimed)
    return LoopCandidate(q, m, run.stamps[q], run.stamps[m], 0, 0.1, 0.0, 1.0, True,
                         tuple(matrix_to_vector(T)), covariance=TIGHT, reason='verified')


def section_false(run: Run, placements: int = 8) -> None:
    print('\n== false loops 20 m off, tight covariance (1 cm, 0.06 deg): goal ATE change '
          '< 10 %')
    odo = run.odometry()
    cfg = SolidConfig()
    _, base, _ = back_end(run, odo, cfg)
    a0 = ate_rmse(base, run.reference)
    shift = np.eye(4)
    shift[:3, 3] = [20.0 / math.sqrt(2.0), 20.0 / math.sqrt(2.0), 0.0]
    print(f'{run.name}: ATE without them {a0:.3f} m; each row one injection; outcomes are '
          '(what the back end did, sigmas from the estimate)')
    kfs = [q for q in range(len(run.stamps) - 5)
           if all(_fake(run, q + k, shift) is not None for k in range(5))]
    revisit = [q for q in kfs if run.loops[q]]
    fresh = [q for q in kfs if not any(run.loops[q:q + 5])]
    worst = {'single': 0.0, 'burst': 0.0}
    for label, pool in (('at a revisit', revisit), ('on new ground', fresh)):
        for q in pool[::max(1, len(pool) // placements)][:placements]:
            for kind, n in (('single', 1), ('burst', 5)):
                inject = {q + k: (_fake(run, q + k, shift),) for k in range(n)}
                _, est, seen = back_end(run, odo, cfg, inject)  # type: ignore[arg-type]
                change = ate_rmse(est, run.reference) / a0 - 1.0
                worst[kind] = max(worst[kind], abs(change))
                what = ', '.join(f'{o.reason} {o.sigmas:.0f}' for o in seen)
                print(f'  {label:13s} kf {q:4d} {kind:6s} ATE {100 * change:+6.1f} %  [{what}]')
    print(f'  largest |ATE change|: single {100 * worst["single"]:.1f} %, burst of five '
          f'{100 * worst["burst"]:.1f} %')


def section_reloc(run: Run, cache: Path, scans: int, start: int) -> None:
    print('\n== relocalisation in a saved map (odometry offset by 50 m and 90 deg): goal within '
          '0.3 m / 1 deg of the saved map after the first loop')
    sensor = run.name.split('_revisits')[0]
    odo = run.odometry()
    pg0, est0, _ = back_end(run, odo, SolidConfig())
    cfg = preset(sensor)
    saver = LoopDetector.load(run.database, cfg.replace(session_id=1))
    map_path = saver.save(cache / f'{run.name}_map.npz', map_poses=pg0.map_poses())
    prior = read_map_poses(map_path)
    print(f'  saved map: {len(prior.poses)} keyframe poses ({prior.source}), session 0 ATE '
          f'{ate_rmse(est0, run.reference):.3f} m')
    cfg1 = cfg.replace(session_id=1, backend=True)
    det = LoopDetector.load(map_path, cfg1)
    pg = PoseGraph(cfg1, prior_map=prior.poses)
    drive = Drive(DriveConfig(**{**DEMO_DEFAULTS, 'sensor': DEMO_SENSORS[sensor]}))
    picked = list(range(start, min(start + scans, len(drive))))
    ref = drive.poses()[picked]
    offset = np.eye(4)
    offset[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    offset[:3, 3] = [50.0, 0.0, 0.0]
    odo1 = drifting_odometry(ref, Drift(seed=1), start=offset @ ref[0])  # starts mid-map
    map_of = {i: k for k, i in enumerate(run.scans)}  # scan index -> session-0 keyframe
    rows = []
    anchored_at = None
    t = drive.trajectory
    for j, i in enumerate(picked):
        rng = np.random.default_rng([0, i, 1, 0x1D4])  # new sensor noise (a second lap)
        pts = cast_scan(drive.scene, drive.model, float(t.xy[i, 0]), float(t.xy[i, 1]),
                        float(t.yaw[i]), rng)[:, :3]
        res = det.process(pts, drive.stamp_ns(i) + 10**12, odo1[j])
        st = pg.update(res, OdomSample(res.stamp_ns, odo1[j]))
        for e in st.events:
            if e.kind == 'anchor':
                anchored_at = res.query_index
                print(f'  keyframe {res.query_index} (scan {i}): {e.message}')
        if st.added and pg.anchored and i in map_of:
            rows.append((res.query_index, i, j, st.pose))
    if anchored_at is None:
        print('  never relocalised')
        return
    final = pg.poses()
    err_m, err_d, ref_m = [], [], []
    for q, i, j, _ in rows:
        saved = prior.poses[(0, map_of[i])]
        T = final[q]
        err_m.append(float(np.linalg.norm(T[:3, 3] - saved[:3, 3])))
        err_d.append(math.degrees(rotation_angle(np.linalg.solve(saved, T))))
        ref_m.append(float(np.linalg.norm(T[:3, 3] - ref[j][:3, 3])))
    at_once = [(np.linalg.norm(p[:3, 3] - prior.poses[(0, map_of[i])][:3, 3]))
               for _, i, _, p in rows]
    print(f'  {len(rows)} keyframes after the anchor, against the saved map pose of the same '
          f'place: final estimate median {np.median(err_m):.3f} m / {np.median(err_d):.2f} deg,'
          f' max {max(err_m):.3f} m / {max(err_d):.2f} deg; as published at each keyframe '
          f'median {np.median(at_once):.3f} m, max {max(at_once):.3f} m')
    print(f'  against the reference (map frame = reference frame): median {np.median(ref_m):.3f}'
          f' m, max {max(ref_m):.3f} m; loops {dict(pg.counts)}')


def synthetic_drive(n: int, seed: int = 0) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Reference poses of a drive around a 3 x 3 grid of 60 m blocks, 1 m per keyframe, and
    loop pairs (query, match) wherever it comes within 2 m of a keyframe at least 100 older
    (at most one per query)."""
    rng = np.random.default_rng(seed)
    corners = [(0, 0)]
    poses = []
    pos, heading = np.zeros(2), 0.0
    while len(poses) < n:
        cx, cy = corners[-1]
        options = [(cx + dx, cy + dy) for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1))
                   if 0 <= cx + dx <= 3 and 0 <= cy + dy <= 3]
        nxt = options[rng.integers(len(options))]
        corners.append(nxt)
        target = np.array(nxt, dtype=float) * 60.0
        heading = math.atan2(target[1] - pos[1], target[0] - pos[0])
        while np.linalg.norm(target - pos) > 0.5 and len(poses) < n:
            pos = pos + np.array([math.cos(heading), math.sin(heading)])
            T = np.eye(4)
            T[:3, :3] = [[math.cos(heading), -math.sin(heading), 0.0],
                         [math.sin(heading), math.cos(heading), 0.0], [0.0, 0.0, 1.0]]
            T[:2, 3] = pos
            poses.append(T)
    ref = np.array(poses)
    loops = []
    for q in range(101, n):
        d = np.linalg.norm(ref[:q - 100, :2, 3] - ref[q, :2, 3], axis=1)
        m = int(np.argmin(d))
        if d[m] < 2.0 and q % 3 == 0:
            loops.append((q, m))
    return ref, loops


def section_cost(n: int) -> None:
    print(f'\n== cost per keyframe, synthetic drive of {n} keyframes with loops '
          f'(shared machine: load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)')
    ref, pairs = synthetic_drive(n)
    odo = drifting_odometry(ref, Drift())
    by_q: dict[int, list[int]] = {}
    for q, m in pairs:
        by_q.setdefault(q, []).append(m)
    cov = tuple(np.diag([4e-4] * 3 + [1e-5] * 3).ravel())
    pg = PoseGraph(SolidConfig())
    ms = []
    for k in range(n):
        loops = tuple(
            LoopCandidate(k, m, k, m, 0, 0.1, 0.0, 1.0, True,
                          tuple(matrix_to_vector(np.linalg.solve(ref[m], ref[k]))),
                          covariance=cov, reason='verified') for m in by_q.get(k, ()))
        st = pg.update(ScanResult(k * 10**8, True, k, matrix_to_vector(odo[k]), loops))
        ms.append(st.update_ms)
    t = np.array(ms)
    est = np.array([kf.pose for kf in pg.keyframes()])
    loop_kf = np.array([bool(by_q.get(k)) for k in range(n)])
    print(f'  {len(pairs)} loops on {int(loop_kf.sum())} keyframes; ATE odometry '
          f'{ate_rmse(odo, ref):.2f} m -> {ate_rmse(est, ref):.3f} m; outcomes {dict(pg.counts)}')
    for label, sel in (('all keyframes', slice(None)), ('last 500', slice(-500, None))):
        s = t[sel]
        print(f'  {label:14s} p50 {np.percentile(s, 50):6.2f} ms  p95 {np.percentile(s, 95):6.2f}'
              f' ms  max {s.max():7.2f} ms')
    s = t[loop_kf]
    print(f'  keyframes with a loop: p50 {np.percentile(s, 50):.2f} ms, p95 '
          f'{np.percentile(s, 95):.2f} ms; without: p50 {np.percentile(t[~loop_kf], 50):.2f} ms')


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--sections', default=','.join(SECTIONS))
    p.add_argument('--sensors', default='hdl64,avia_like')
    p.add_argument('--cache', type=Path, default=Path('/tmp/solid_ros_bench_backend'))
    p.add_argument('--keyframes', type=int, default=2000)
    p.add_argument('--reloc-scans', type=int, default=200)
    p.add_argument('--reloc-start', type=int, default=150,
                   help='scan of the route where the second drive starts')
    args = p.parse_args()
    sections = args.sections.split(',')
    sensors = args.sensors.split(',')
    runs = [detect(s, 'revisits', args.cache) for s in sensors] if set(sections) & {
        'drift', 'kernels', 'false', 'reloc'} else []
    if 'drift' in sections:
        section_drift(runs)
    if 'norevisit' in sections:
        section_norevisit(detect('hdl64', 'no_revisit', args.cache))
    if 'kernels' in sections:
        for run in runs:
            section_kernels(run)
    if 'false' in sections:
        for run in runs:
            section_false(run)
    if 'reloc' in sections:
        section_reloc(runs[0], args.cache, args.reloc_scans, args.reloc_start)
    if 'cost' in sections:
        section_cost(args.keyframes)
    return 0


if __name__ == '__main__':
    sys.exit(main())
