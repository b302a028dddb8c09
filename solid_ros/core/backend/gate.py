"""The loop gate: how far a loop lies from the pose graph's estimate, in sigmas.

A loop factor predicts ``X_m^-1 X_q = T`` (or ``X_q = P_m T`` to a loaded map). Its distance
from the estimate is the Mahalanobis distance of ``r = Logmap(T^-1 X_m^-1 X_q)`` under the
loop's covariance plus the relative marginal covariance of ``X_m^-1 X_q`` (iSAM2's joint
marginal of the two keyframes, propagated through the between function): a chi-square test
with 6 degrees of freedom, given as ``sqrt(r^T S^-1 r)``.

Two loops agree with each other when the cycle they close with the estimate's own motion
between their queries and between their matches, ``T_a^-1 (X_ma^-1 X_mb) T_b (X_qa^-1
X_qb)^-1``, is the identity within its covariance (both loops', both relative motions'; the
Jacobians are taken numerically). Loops of one true revisit agree; a lone false loop agrees
with none.

:class:`LoopJudge` decides with both. A loop within ``backend_loop_gate`` sigmas of the
estimate is taken; beyond ``backend_loop_refuse`` it is refused; in between it waits
(``'pending'``) for a loop of another keyframe that agrees with it, and both are taken (a true
revisit after a drift the model underrates gives a run of such loops; a lone false loop gets
no partner). Loops taken together must agree with each other: of two that do not, the one
farther from the estimate waits. Pending and refused loops are taken later if the graph moves
so that they agree with the estimate, and dropped after :data:`PENDING_KEYFRAMES` keyframes.
A loop taken is never retracted: a false loop within the gate stays (its kernel bounds its
pull).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.gtsam_bridge import GTSAM_ERRORS, pose3, pose_matrix
from solid_ros.core.backend.noise import swap_blocks
from solid_ros.core.backend.solver import FactorRecord, GraphSolver
from solid_ros.core.config import SolidConfig
from solid_ros.core.results import BackendEvent, LoopCandidate, loop_name

__all__ = ['PENDING_KEYFRAMES', 'Candidate', 'LoopJudge', 'loop_sigmas', 'pair_sigmas',
           'relative']

FloatArray = npt.NDArray[np.float64]
_EPS = 1e-6
PENDING_KEYFRAMES = 30  # a pending loop waits this many keyframes for a loop that agrees
_POOL_MAX = 16


def _log(T: FloatArray) -> FloatArray:
    import gtsam

    return np.asarray(gtsam.Pose3.Logmap(pose3(T)), dtype=np.float64)


def _exp(xi: FloatArray) -> FloatArray:
    import gtsam

    return pose_matrix(gtsam.Pose3.Expmap(xi))


def relative(solver: GraphSolver, key_a: int, key_b: int) -> tuple[FloatArray, FloatArray]:
    """Estimated ``X_a^-1 X_b`` and its covariance (gtsam tangent order, right perturbation).

    Raises:
        RuntimeError: gtsam cannot give the joint marginal.
    """
    if key_a == key_b:
        return np.eye(4), np.zeros((6, 6))
    pred = np.asarray(np.linalg.solve(solver.pose(key_a), solver.pose(key_b)), dtype=np.float64)
    c_aa, c_ab, c_bb = solver.joint_tangent(key_a, key_b)
    a = -np.asarray(pose3(np.linalg.inv(pred)).AdjointMap(), dtype=np.float64)
    cov = a @ c_aa @ a.T + a @ c_ab + c_ab.T @ a.T + c_bb
    out: FloatArray = 0.5 * (cov + cov.T)
    return pred, out


def _mahalanobis(r: FloatArray, cov: FloatArray) -> float:
    try:
        return math.sqrt(max(float(r @ np.linalg.solve(cov, r)), 0.0))
    except np.linalg.LinAlgError:
        return math.nan


def loop_sigmas(solver: GraphSolver, rec: FactorRecord) -> float:
    """Distance of a ``'loop'`` or ``'map_loop'`` record from the estimate, sigmas (NaN when
    gtsam cannot give the marginals)."""
    try:
        if rec.kind == 'loop':
            pred, rel = relative(solver, rec.keys[0], rec.keys[1])
        else:
            pred = solver.pose(rec.keys[0])
            rel = swap_blocks(solver.marginal(rec.keys[0]))
    except GTSAM_ERRORS:
        return math.nan
    r = _log(np.asarray(np.linalg.solve(rec.measured, pred), dtype=np.float64))
    return _mahalanobis(r, rel + swap_blocks(rec.covariance))


def _cycle(parts: Sequence[FloatArray]) -> FloatArray:
    t_a, d_m, t_b, d_q = parts
    return np.asarray(np.linalg.solve(t_a, d_m @ t_b @ np.linalg.inv(d_q)), dtype=np.float64)


def pair_sigmas(solver: GraphSolver, a: FactorRecord, b: FactorRecord) -> float:
    """How far two loop records of one kind disagree with each other, sigmas (NaN: of two
    kinds, or gtsam cannot give the marginals)."""
    try:
        if a.kind == b.kind == 'loop':
            d_m, c_m = relative(solver, a.keys[0], b.keys[0])
            t_a, t_b = a.measured, b.measured
        elif a.kind == b.kind == 'map_loop':  # fixed matches: their poses are in measured
            d_m = np.asarray(np.linalg.solve(a.measured, b.measured), dtype=np.float64)
            c_m = np.zeros((6, 6))
            t_a = t_b = np.eye(4)
        else:
            return math.nan
        d_q, c_q = relative(solver, a.keys[-1], b.keys[-1])
    except GTSAM_ERRORS:
        return math.nan
    return _propagated([t_a, d_m, t_b, d_q],
                       [swap_blocks(a.covariance), c_m, swap_blocks(b.covariance), c_q])


def _propagated(parts: list[FloatArray], covs: list[FloatArray]) -> float:
    """Mahalanobis distance of ``Logmap(cycle(parts))`` with each part's covariance propagated
    by a numerical Jacobian (right perturbations)."""
    r0 = _log(_cycle(parts))
    total = np.zeros((6, 6))
    for i, cov in enumerate(covs):
        if not np.any(cov):
            continue
        jac = np.empty((6, 6))
        for j in range(6):
            xi = np.zeros(6)
            xi[j] = _EPS
            moved = list(parts)
            moved[i] = parts[i] @ _exp(xi)
            jac[:, j] = (_log(_cycle(moved)) - r0) / _EPS
        total += jac @ cov @ jac.T
    return _mahalanobis(r0, total)


@dataclass(frozen=True, eq=False)  # compared by identity
class Candidate:
    """A loop's factor on its way into the graph.

    Attributes:
        rec: its factor record.
        loop: the published loop.
        sigmas: its distance from the estimate when judged (NaN: not measured).
        index: its query keyframe.
        refused: it lay beyond ``backend_loop_refuse`` (no other loop can confirm it).
    """

    rec: FactorRecord
    loop: LoopCandidate
    sigmas: float
    index: int
    refused: bool = False


class LoopJudge:
    """Takes, holds back or refuses loops (see the module docstring)."""

    def __init__(self) -> None:
        self.pool: list[Candidate] = []  # pending and refused loops, oldest first

    def judge(self, solver: GraphSolver, config: SolidConfig, c: Candidate,
              taken: list[Candidate], events: list[BackendEvent]) -> str:
        """``'added'`` (appended to ``taken`` with the pending loops that agree with it),
        ``'pending'`` or ``'gate'`` (refused) for a new loop."""
        gate, refuse = config.backend_loop_gate, config.backend_loop_refuse
        if math.isnan(c.sigmas) or gate <= 0.0 or c.sigmas <= gate:
            taken.append(c)
            return 'added'
        if 0.0 < refuse < c.sigmas:
            self._keep(replace(c, refused=True))
            events.append(BackendEvent('gate', f'loop {loop_name(c.loop)} refused: '
                                       f'{c.sigmas:.0f} sigmas from the estimate (refused '
                                       f'beyond {refuse:g})'))
            return 'gate'
        agree = [p for p in self.pool if not p.refused and p.index != c.index
                 and pair_sigmas(solver, p.rec, c.rec) <= gate]
        if not agree:
            self._keep(c)
            return 'pending'
        for p in agree:
            self.pool.remove(p)
            events.append(BackendEvent('confirmed', f'loop {loop_name(p.loop)} ({p.sigmas:.0f} '
                                       f'sigmas) confirmed by loop {loop_name(c.loop)} '
                                       f'({c.sigmas:.0f} sigmas)'))
        taken.extend(agree + [c])
        return 'added'

    def _keep(self, c: Candidate) -> None:
        self.pool.append(c)
        del self.pool[:-_POOL_MAX]

    def untangle(self, solver: GraphSolver, config: SolidConfig,
                 taken: list[Candidate]) -> list[Candidate]:
        """Loops about to be taken together must agree with each other: of two that do not,
        the one farther from the estimate goes back to the pool. Returns those sent back."""
        back: list[Candidate] = []
        for a, b in itertools.combinations(sorted(taken, key=_order), 2):
            if a in back or b in back:
                continue
            if pair_sigmas(solver, a.rec, b.rec) > config.backend_loop_gate:
                back.append(b)
        for b in back:
            taken.remove(b)
            self.pool.append(b)
        return back

    def regate(self, solver: GraphSolver, config: SolidConfig,
               events: list[BackendEvent]) -> list[Candidate]:
        """Pooled loops that agree with the estimate now that the graph moved (removed from
        the pool: the caller takes them)."""
        out = []
        for p in list(self.pool):
            sigmas = loop_sigmas(solver, p.rec)
            if sigmas <= config.backend_loop_gate:
                self.pool.remove(p)
                out.append(p)
                events.append(BackendEvent('confirmed', f'loop {loop_name(p.loop)} now agrees '
                                           f'with the estimate ({sigmas:.1f} sigmas)'))
        return out

    def expire(self, index: int, events: list[BackendEvent]) -> int:
        """Drop pooled loops older than :data:`PENDING_KEYFRAMES` keyframes; returns how many
        pending (not refused) ones were dropped."""
        old = [p for p in self.pool if index - p.index > PENDING_KEYFRAMES]
        for p in old:
            self.pool.remove(p)
            if not p.refused:
                events.append(BackendEvent('unconfirmed', f'loop {loop_name(p.loop)} '
                                           f'({p.sigmas:.0f} sigmas) dropped: no other loop '
                                           f'agreed with it within {PENDING_KEYFRAMES} '
                                           'keyframes'))
        return sum(not p.refused for p in old)


def _order(c: Candidate) -> float:
    return -math.inf if math.isnan(c.sigmas) else c.sigmas
