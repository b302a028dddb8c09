"""Are the run's calibration pairs and registered steps right? Scored against reference poses.

The calibration (:mod:`solid_ros.core.verification.calibration`) counts a pair as a right
alignment when its registration lands near the odometry; the registered steps
(``backend_step_registration``) go into the pose graph when the fine rules pass them. Neither
is scored by ``bench_real``. This replays one recording of ``../shared/data`` like
``bench_real`` and, for every calibration pair (keyframe k and its partner a a few metres
back), registers two more pairs the same way (a to its own partner b, and k to b, each from
the odometry's relative pose) and prints:

- ``pairs``: how many registered, how many the calibration's rule counts as right (within
  AGREE_M / AGREE_DEG of the odometry), and how many are right by the reference;
- ``triangles``: how many of the three registrations k->a->b close on k->b within
  ``--close-m`` / ``--close-deg`` and how many of those have a k->a leg that is wrong by the
  reference (beyond AGREE_M / AGREE_DEG of it): whether a closing triangle could tell right
  alignments without the odometry, and the nearest closure of a wrong leg;
- ``steps``: registered steps verified, and each verified step wrong by the reference
  (beyond AGREE_M / AGREE_DEG) with its readings and the conflict bar in force.

The extra registrations change nothing the detector decides (they go through the verifier's
cache of prepared clouds only). ``--csv FILE`` writes the pairs, one row each.

Usage: ``python test/bench/probe_calibration.py [--set quickshack] [--odometry kiss-icp|bag]
[--close-m 0.1] [--close-deg 1.0] [--csv FILE]``.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from solid_ros.core.flow.state import DetectorState  # noqa: E402
from solid_ros.core.flow.verify_stage import VerifyStage  # noqa: E402
from solid_ros.core.geometry import angle_deg, vector_to_matrix  # noqa: E402
from solid_ros.core.verification.calibration import AGREE_DEG, AGREE_M  # noqa: E402
from solid_ros.tools.replay import load_config, replay  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_real import DATA, PRESETS  # noqa: E402

FloatArray = npt.NDArray[np.float64]
Leg = dict[str, float]


class Reference:
    """The recording's reference poses (KITTI 3x4), by the nearest stamp."""

    def __init__(self, name: str) -> None:
        self.times = np.loadtxt(DATA / name / 'times.txt')
        poses = np.loadtxt(DATA / name / 'optimized_poses.txt').reshape(-1, 3, 4)
        bottom = np.tile([0.0, 0.0, 0.0, 1.0], (len(poses), 1, 1))
        self.poses = np.concatenate([poses, bottom], axis=1)

    def relative(self, stamp_q: int, stamp_m: int) -> FloatArray:
        """``T_mq`` between the sensor frames of two keyframes."""
        def at(stamp: int) -> FloatArray:
            return np.asarray(self.poses[int(np.argmin(abs(self.times - stamp * 1e-9)))])
        return np.asarray(np.linalg.solve(at(stamp_m), at(stamp_q)), dtype=np.float64)


def error(T: FloatArray, T_ref: FloatArray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of ``inv(T_ref) T``."""
    off = np.linalg.solve(T_ref, T)
    return float(np.linalg.norm(off[:3, 3])), angle_deg(off)


def within(err: tuple[float, float], max_m: float, max_deg: float) -> bool:
    """An error within both limits."""
    return err[0] < max_m and err[1] < max_deg


class Probe:
    """Wraps a detector's calibration and registered steps; keeps what it scored."""

    def __init__(self, ref: Reference) -> None:
        self.ref = ref
        self.pairs: list[dict[str, Any]] = []
        self.steps: list[dict[str, Any]] = []
        self._stamps: dict[int, int] = {}
        self._queries: dict[int, Any] = {}

    def install(self) -> Callable[[], None]:
        """Wrap the verification stage's calibration and step; returns the undo."""
        calibrate, step = VerifyStage._calibrate, VerifyStage._register_step
        probe = self

        def _calibrate(stage: VerifyStage, proposal: Any, query: Any) -> None:
            det = stage._state
            probe._stamps[proposal.query_index] = proposal.stamp_ns
            probe._queries[proposal.query_index] = query
            if (det.verifier is not None and query.usable and proposal.pose is not None
                    and det.calibration.wants(proposal.query_index)):
                probe.pair(det, proposal)
            calibrate(stage, proposal, query)

        def _register_step(stage: VerifyStage, proposal: Any) -> Any:
            out = step(stage, proposal)
            probe.step(stage._state, proposal, out)
            return out

        VerifyStage._calibrate = _calibrate  # type: ignore[method-assign]
        VerifyStage._register_step = _register_step  # type: ignore[method-assign]

        def undo() -> None:
            VerifyStage._calibrate = calibrate  # type: ignore[method-assign]
            VerifyStage._register_step = step  # type: ignore[method-assign]
        return undo

    def leg(self, det: DetectorState, k: int, a: int) -> Leg | None:
        """Register keyframe k to a from the odometry's relative pose and score it."""
        seq_k, seq_a = det.own_seqs.get(k), det.own_seqs.get(a)
        query = self._queries.get(k)
        if seq_k is None or seq_a is None or query is None or det.verifier is None:
            return None
        pose_k, pose_a = det.database.pose(seq_k), det.database.pose(seq_a)
        cloud = det.clouds.get(seq_a)
        if pose_k is None or pose_a is None or cloud is None:
            return None
        odo = np.linalg.solve(vector_to_matrix(pose_a), vector_to_matrix(pose_k))
        guess = det.mount.level_pose(np.asarray(odo, dtype=np.float64))
        coarse = det.verifier.coarse(query, (det.config.session_id, seq_a), cloud, [], (guess,))
        if coarse.rejection is not None:
            return None
        m = det.verifier.measure(query, coarse)
        truth = det.mount.level_pose(self.ref.relative(self._stamps[k], self._stamps[a]))
        odo_err, ref_err = error(m.T_mq, guess), error(m.T_mq, truth)
        return {'converged': m.converged, 'overlap': m.overlap, 'conflict': m.conflict,
                'odo_m': odo_err[0], 'odo_deg': odo_err[1], 'ref_m': ref_err[0],
                'ref_deg': ref_err[1], 'T': m.T_mq}

    def pair(self, det: DetectorState, proposal: Any) -> None:
        """Score the calibration pair of this keyframe and its triangle."""
        k = proposal.query_index
        partner = det.own.partner(k, proposal.pose)
        if partner is None:
            return
        index = {s: i for i, s in det.own_seqs.items()}
        a = index.get(partner[1])
        pose_a = None if a is None else det.database.pose(partner[1])
        if a is None or pose_a is None:
            return
        further = det.own.partner(a, np.asarray(pose_a, dtype=np.float64))
        b = None if further is None else index.get(further[1])
        legs = {'ka': self.leg(det, k, a)}
        if b is not None and b in self._queries and a in self._queries:
            legs.update(ab=self.leg(det, a, b), kb=self.leg(det, k, b))
        row: dict[str, Any] = {'k': k, 'a': a, 'b': -1 if b is None else b}
        for name, got in legs.items():
            row.update({f'{name}_{key}': v for key, v in (got or {}).items() if key != 'T'})
        if all(legs.get(n) is not None for n in ('ka', 'ab', 'kb')):
            T = {n: legs[n]['T'] for n in ('ka', 'ab', 'kb')}  # type: ignore[index]
            row['close_m'], row['close_deg'] = error(T['ab'] @ T['ka'], T['kb'])
        self.pairs.append(row)

    def step(self, det: DetectorState, proposal: Any, out: Any) -> None:
        """Score a registered step (None: refused)."""
        k = proposal.query_index
        if out is None or k - 1 not in self._stamps or k not in self._stamps:
            self.steps.append({'k': k, 'verified': out is not None})
            return
        truth = self.ref.relative(self._stamps[k], self._stamps[k - 1])
        err = error(vector_to_matrix(out.pose), truth)
        ev = out.evidence
        self.steps.append({'k': k, 'verified': True, 'ref_m': err[0], 'ref_deg': err[1],
                           'conflict': ev.conflict, 'overlap': ev.overlap,
                           'drift_m': ev.drift_m, 'pinned_m': ev.pinned_m,
                           'bar': det.bars.max_conflict})


def _ok(row: dict[str, Any], leg: str, what: str) -> bool:
    """A leg that converged within AGREE_M / AGREE_DEG of ``what`` ('odo' or 'ref')."""
    return (row.get(f'{leg}_converged') == 1.0
            and within((row.get(f'{leg}_{what}_m', math.nan),
                        row.get(f'{leg}_{what}_deg', math.nan)), AGREE_M, AGREE_DEG))


def summary(probe: Probe, close_m: float, close_deg: float) -> list[str]:
    """The printed lines: pairs, triangles, steps."""
    pairs = [r for r in probe.pairs if 'ka_converged' in r]
    agree = sum(_ok(r, 'ka', 'odo') for r in pairs)
    right = sum(_ok(r, 'ka', 'ref') for r in pairs)
    tri = [r for r in pairs if 'close_m' in r]
    closed = [r for r in tri if within((r['close_m'], r['close_deg']), close_m, close_deg)]
    wrong = [r for r in tri if not _ok(r, 'ka', 'ref')]
    nearest = min(wrong, key=lambda r: r['close_m'] / close_m + r['close_deg'] / close_deg,
                  default=None)
    lines = [f'  pairs      {len(probe.pairs)} registered ({len(pairs)} past the coarse stage): '
             f'{agree} right by the odometry, {right} right by the reference',
             f'  triangles  {len(tri)} registered, {len(closed)} close within {close_m:g} m / '
             f'{close_deg:g} deg: {sum(_ok(r, "ka", "ref") for r in closed)} right by the '
             f'reference, {sum(not _ok(r, "ka", "ref") for r in closed)} wrong; '
             f'{sum(_ok(r, "ka", "ref") and not _ok(r, "ka", "odo") for r in closed)} of them '
             'away from the odometry']
    if nearest is not None:
        lines.append(f'             nearest closure of a wrong k->a leg: k{nearest["k"]} '
                     f'{nearest["close_m"]:.3f} m / {nearest["close_deg"]:.2f} deg (the leg '
                     f'{nearest["ka_ref_m"]:.2f} m / {nearest["ka_ref_deg"]:.1f} deg off, '
                     f'conflict {nearest["ka_conflict"]:.3f})')
    verified = [s for s in probe.steps if s['verified']]
    bad = [s for s in verified if 'ref_m' in s
           and not within((s['ref_m'], s['ref_deg']), AGREE_M, AGREE_DEG)]
    lines.append(f'  steps      {len(probe.steps)} registered, {len(verified)} verified, '
                 f'{len(bad)} of them wrong by the reference')
    for s in bad:
        lines.append(f'             k{s["k"]}: {s["ref_m"]:.2f} m / {s["ref_deg"]:.1f} deg off, '
                     f'conflict {s["conflict"]:.3f} (bar {s["bar"]:.3f}), overlap '
                     f'{s["overlap"]:.3f}, restarts {s["drift_m"]:.3f} m, two sigmas '
                     f'{s["pinned_m"]:.2f} m')
    return lines


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--set', default='quickshack', choices=sorted(PRESETS))
    p.add_argument('--odometry', choices=('kiss-icp', 'bag'), default='kiss-icp')
    p.add_argument('--close-m', type=float, default=0.1)
    p.add_argument('--close-deg', type=float, default=1.0)
    p.add_argument('--csv', type=Path, help='write the pairs here')
    args = p.parse_args()
    if not DATA.is_dir():
        print(f'probe_calibration: {DATA} is missing: nothing to run')
        return 0
    probe = Probe(Reference(args.set))
    undo = probe.install()
    try:
        cfg, ncfg = load_config(ROOT / 'config' / PRESETS[args.set])
        rec = DATA / args.set
        replay(rec / 'bag', cfg, node_config=ncfg, odometry=args.odometry,
               poses=rec / 'optimized_poses.txt', times=rec / 'times.txt', progress='quiet',
               out_dir=None, plots=False)
    finally:
        undo()
    print(f'{args.set} (odometry {args.odometry}):')
    print('\n'.join(summary(probe, args.close_m, args.close_deg)))
    if args.csv is not None:
        keys = list(dict.fromkeys(k for r in probe.pairs for k in r))
        with args.csv.open('w', newline='') as f:
            writer = csv.DictWriter(f, keys)
            writer.writeheader()
            writer.writerows(probe.pairs)
    return 0


if __name__ == '__main__':
    sys.exit(main())
