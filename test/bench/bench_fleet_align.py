"""Inter-robot alignment: maximum-clique PCM (the back end's) against gtsam's GNC, same inputs.

Run: .venv/bin/python test/bench/bench_fleet_align.py [--seeds 5]

Two synthetic robots (``test/fleet_scenes.py``): robot 1's map is a random rigid transform of
the world and drifts (1 %, 0.055 deg/m); robot 0's map is the world. True loops (5 cm, 0.3
deg noise) join robot 1's first keyframes to robot 0's; false ones claim a 20 m offset with a
tight covariance (1 cm, 0.05 deg). For each case, both estimators get the same loops and
poses:

- PCM: :class:`solid_ros.core.backend.alignment.FleetAlignment` (maximum set of pairwise
  consistent loops, at least 4, then their weighted mean);
- GNC: one ``Pose3`` variable, a ``PriorFactorPose3`` per loop at the alignment it implies
  with that implied alignment's covariance (the same as PCM's mean uses),
  ``GncLMOptimizer`` with the truncated-least-squares loss, inlier threshold at chi-square
  0.99 (6 dof).

Printed per case: the placement error of robot 1's keyframes of every loop (true and false)
in robot 0's map (mean, metres; 'unaligned' when the estimator declines; robot 1's drift
counts in it), over seeds; and the time per solve.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent)]

from fleet_scenes import TwoRobots  # noqa: E402

from solid_ros.core.backend.alignment import AlignmentSettings, FleetAlignment  # noqa: E402
from solid_ros.core.backend.consistency import implied  # noqa: E402
from solid_ros.core.config import SolidConfig  # noqa: E402
from solid_ros.core.results import LoopCandidate  # noqa: E402

Case = Callable[[TwoRobots], list[LoopCandidate]]


def _true(scene: TwoRobots, first: int, count: int, step: int = 2) -> list[LoopCandidate]:
    return [scene.loop(q, scene.matching(q)) for q in range(first, first + step * count, step)]


def _false(scene: TwoRobots, qs: range | list[int], offset: float = 20.0) -> list[LoopCandidate]:
    return [scene.loop(q, scene.matching(q), offset=offset) for q in qs]


def _random(scene: TwoRobots, count: int) -> list[LoopCandidate]:
    rng = np.random.default_rng(scene.seed + 100)
    out = []
    for q in rng.integers(30, 190, count):
        out += _false(scene, [int(q)], float(rng.uniform(5.0, 30.0) * rng.choice([-1, 1])))
    return out


CASES: dict[str, Case] = {
    '12 true': lambda s: _true(s, 12, 12),
    '12 true + 1 false': lambda s: _true(s, 12, 12) + _false(s, [60]),
    '12 true + burst of 3 false': lambda s: _true(s, 12, 12) + _false(s, range(60, 63)),
    'burst of 3 false alone': lambda s: _false(s, range(60, 63)),
    'burst of 3 false + 4 true': lambda s: _false(s, range(60, 63)) + _true(s, 12, 4),
    '12 true + 8 random false': lambda s: _true(s, 12, 12) + _random(s, 8),
    '2 revisits 100 m apart (drift)': lambda s: _true(s, 12, 6) + _true(s, 110, 6),
}


def _arrays(scene: TwoRobots, fa: FleetAlignment) -> tuple[np.ndarray, np.ndarray]:
    """Implied alignments and covariances of the loops PCM holds (the GNC's inputs)."""
    links = fa._peers[1].links  # the same normalised loops for both estimators
    X = np.array([scene.own[k.own] for k in links])
    Y = np.array([scene.peer[k.theirs] for k in links])
    return implied(X, np.array([k.Z for k in links]), Y, np.array([k.cov for k in links]))


def gnc(A: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """GNC (TLS) over one Pose3 with a prior per loop's implied alignment."""
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    for T, c in zip(A, cov):
        pose = gtsam.Pose3(gtsam.Rot3(T[:3, :3]), T[:3, 3])
        graph.add(gtsam.PriorFactorPose3(0, pose, gtsam.noiseModel.Gaussian.Covariance(c)))
    init = gtsam.Values()
    init.insert(0, gtsam.Pose3(gtsam.Rot3(A[0][:3, :3]), A[0][:3, 3]))
    params = gtsam.GncLMParams()
    params.setLossType(gtsam.GncLossType.TLS)
    opt = gtsam.GncLMOptimizer(graph, init, params)
    opt.setInlierCostThresholdsAtProbability(0.99)
    return np.asarray(opt.optimize().atPose3(0).matrix())


def _run(case: Case, seed: int) -> tuple[float, float, float, float]:
    scene = TwoRobots(seed=seed, lead=10)
    fa = FleetAlignment(0, AlignmentSettings.from_config(SolidConfig()))
    loops = case(scene)
    for loop in loops:
        fa.add(loop)
    idx = sorted({loop.match_index for loop in loops})
    t0 = time.perf_counter()
    fa.solve(scene.own_poses(), {1: scene.peer_poses()})
    t1 = time.perf_counter()
    st = fa.state(1)
    pcm = scene.placement_error(st.transform, idx) if st.transform is not None else np.nan
    A, cov = _arrays(scene, fa)
    t2 = time.perf_counter()
    g = gnc(A, cov)
    t3 = time.perf_counter()
    return pcm, scene.placement_error(g, idx), (t1 - t0) * 1e3, (t3 - t2) * 1e3


def _fmt(errors: list[float]) -> str:
    ok = [e for e in errors if np.isfinite(e)]
    un = len(errors) - len(ok)
    text = f'median {statistics.median(ok):6.2f} m, max {max(ok):6.2f} m' if ok else 'n/a'
    return text + (f', unaligned {un}/{len(errors)}' if un else '')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, default=5)
    args = parser.parse_args()
    print(f'placement error of robot 1 at its loop keyframes, {args.seeds} seeds '
          '(PCM: unaligned = declined)')
    for name, case in CASES.items():
        runs = [_run(case, seed) for seed in range(args.seeds)]
        pcm, g = [r[0] for r in runs], [r[1] for r in runs]
        ms = statistics.median(r[2] for r in runs), statistics.median(r[3] for r in runs)
        print(f'  {name:<32} PCM {_fmt(pcm):<44} GNC {_fmt(g):<32} '
              f'({ms[0]:.1f} / {ms[1]:.1f} ms)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
