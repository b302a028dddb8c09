"""The pose graph's solver: iSAM2 over factors it records itself, so it can always rebuild.

:class:`GraphSolver` keeps every factor it was given as a :class:`FactorRecord` (plain numpy:
kind, keys, measured pose, ROS-order covariance, robust or not) and the latest value of every
variable. When gtsam fails (an indeterminant system, a factor it refuses), the update is caught
and the graph rebuilt from those records: a batch Levenberg-Marquardt from the last good
values, then a fresh iSAM2 seeded with its solution. If the newest factors cannot be solved
even so, they are dropped and reported (their loops stay published by the detector).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.gtsam_bridge import (
    GTSAM_ERRORS,
    pose3,
    pose_matrix,
    require_gtsam,
    robust,
    to_gtsam,
)
from solid_ros.core.backend.noise import swap_blocks
from solid_ros.core.errors import BackendError

if TYPE_CHECKING:
    import gtsam

__all__ = ['FactorRecord', 'GraphSolver']

FloatArray = npt.NDArray[np.float64]


@dataclass(eq=False)  # compared by identity: it holds arrays
class FactorRecord:
    """One factor as plain data.

    Attributes:
        kind: ``'anchor'`` or ``'prior'`` (unary on ``keys[0]``: the session's anchor, a
            segment's weak prior), ``'odom'`` (between ``keys[0]`` and ``keys[1]``),
            ``'step'`` (the same keyframes registered to each other),
            ``'loop'`` (between match and query) or ``'map_loop'`` (unary on the query, from a
            loop to a fixed keyframe of a loaded map).
        keys: gtsam keys, one or two.
        measured: 4x4 measured pose (unary: the variable's pose; between: ``X0^-1 X1``).
        covariance: 6x6 ROS-order covariance of a right perturbation of ``measured``.
        robust: whether the loop kernel applies.
        dropped: left out of the graph (gtsam could not solve with it).
    """

    kind: str
    keys: tuple[int, ...]
    measured: FloatArray
    covariance: FloatArray
    robust: bool = False
    dropped: bool = False


class GraphSolver:
    """iSAM2 with its own record of factors and values.

    Args:
        kernel: robust kernel of robust records (``'huber'``, ``'cauchy'``, ``'none'``).
        width: kernel width, sigmas.
    """

    def __init__(self, kernel: str = 'huber', width: float = 1.345) -> None:
        require_gtsam()
        self.kernel, self.width = kernel, width
        self.records: list[FactorRecord] = []
        self.values: dict[int, FloatArray] = {}  # latest known pose of every variable
        self.rebuilds = 0
        self._isam = self._new_isam()

    def _new_isam(self) -> gtsam.ISAM2:
        import gtsam

        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.1)
        params.relinearizeSkip = 1
        # QR, not Cholesky: a long loop-free chain whose heading error swings km-long lever
        # arms made Cholesky call the system indeterminant (1,657 keyframes of 1 m, seen
        # here); QR solved 3,000 at 0.85 ms p50 per update instead of 0.62.
        params.setFactorization('QR')
        return gtsam.ISAM2(params)

    def factor(self, rec: FactorRecord) -> gtsam.NoiseModelFactor:
        """The gtsam factor of a record."""
        import gtsam

        measured, noise = to_gtsam(rec.measured, rec.covariance)
        model = robust(noise, self.kernel, self.width) if rec.robust else noise
        if len(rec.keys) == 1:
            return gtsam.PriorFactorPose3(rec.keys[0], measured, model)
        return gtsam.BetweenFactorPose3(rec.keys[0], rec.keys[1], measured, model)

    def _graph(self, records: Iterable[FactorRecord]) -> gtsam.NonlinearFactorGraph:
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for rec in records:
            if not rec.dropped:
                graph.add(self.factor(rec))
        return graph

    def _values(self, poses: dict[int, FloatArray]) -> gtsam.Values:
        import gtsam

        out = gtsam.Values()
        for key, T in poses.items():
            out.insert(key, pose3(T))
        return out

    def isam_update(self, graph: gtsam.NonlinearFactorGraph | None = None,
                    values: gtsam.Values | None = None) -> None:
        """One iSAM2 step (the seam a test uses to make gtsam fail)."""
        if graph is None or values is None:
            self._isam.update()
        else:
            self._isam.update(graph, values)

    def add(self, records: Sequence[FactorRecord], new_values: dict[int, FloatArray],
            iterations: int = 0) -> str | None:
        """Add factors and new variables, then ``iterations`` more iSAM2 steps.

        Returns:
            None, or what went wrong in gtsam when the graph had to be rebuilt.

        Raises:
            BackendError: not even the graph before these factors can be solved again.
        """
        self.records.extend(records)
        self.values.update(new_values)
        try:
            self.isam_update(self._graph(records), self._values(new_values))
            for _ in range(iterations):
                self.isam_update()
            return None
        except GTSAM_ERRORS as err:
            reason = f'{type(err).__name__}: {" ".join(str(err).split())[:200]}'
        self._refresh_values()
        if self._rebuild():
            return reason
        for rec in records:  # the new factors cannot be solved: drop them, keep the variables
            rec.dropped = rec.kind in ('loop', 'map_loop', 'step')
        if self._rebuild():
            return reason + ' (the new loops were dropped)'
        raise BackendError(f'the pose graph cannot be rebuilt after a gtsam failure: {reason}')

    def _refresh_values(self) -> None:
        """Take the current estimate where gtsam can still give it (else keep the cache)."""
        try:
            est = self._isam.calculateEstimate()
        except GTSAM_ERRORS:
            return
        for key in list(self.values):
            if est.exists(key):
                self.values[key] = pose_matrix(est.atPose3(key))

    def _rebuild(self) -> bool:
        """Solve all kept records from the cached values in batch and restart iSAM2 there."""
        import gtsam

        graph = self._graph(self.records)
        try:
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(100)
            params.setLinearSolverType('MULTIFRONTAL_QR')  # as iSAM2: see _new_isam
            solved = gtsam.LevenbergMarquardtOptimizer(graph, self._values(self.values),
                                                       params).optimize()
            isam = self._new_isam()
            isam.update(graph, solved)
        except GTSAM_ERRORS:
            return False
        self._isam = isam
        self.rebuilds += 1
        for key in self.values:
            self.values[key] = pose_matrix(solved.atPose3(key))
        return True

    def reset_to(self, values: dict[int, FloatArray]) -> bool:
        """Rebuild from the records with these values (after records were changed)."""
        self.values = dict(values)
        return self._rebuild()

    def pose(self, key: int) -> FloatArray:
        """Current estimate of one variable (also cached for rebuilds)."""
        T = pose_matrix(self._isam.calculateEstimatePose3(key))
        self.values[key] = T
        return T

    def estimate(self) -> dict[int, FloatArray]:
        """Current estimate of every variable (:meth:`estimate_arrays` by key)."""
        self.estimate_arrays()
        return dict(self.values)

    def estimate_arrays(self) -> tuple[npt.NDArray[np.int64], FloatArray]:
        """:meth:`estimate` as arrays: the sorted keys and their poses ``(N, 4, 4)``,
        converted in one call (``gtsam.utilities.extractPose3``; pose by pose 5,000 took
        20 ms, in one call 2.5 ms); the cache of values is refreshed alike."""
        import gtsam

        est = self._isam.calculateEstimate()
        keys = np.asarray(est.keys(), dtype=np.int64)
        rows = np.asarray(gtsam.utilities.extractPose3(est), dtype=np.float64).reshape(-1, 12)
        if len(rows) != len(keys) or not bool(np.all(keys[1:] > keys[:-1])):
            raise BackendError('the estimate holds variables other than poses')
        poses = np.zeros((len(rows), 4, 4))
        poses[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
        poses[:, :3, 3] = rows[:, 9:]
        poses[:, 3, 3] = 1.0
        self.values.update(zip(keys.tolist(), poses.copy()))
        return keys, poses

    def marginal(self, key: int) -> FloatArray:
        """Marginal covariance of one variable, ROS order (right perturbation)."""
        return swap_blocks(np.asarray(self._isam.marginalCovariance(key), dtype=np.float64))

    def joint_tangent(self, key_a: int, key_b: int) -> tuple[FloatArray, FloatArray,
                                                            FloatArray]:
        """Blocks ``(C_aa, C_ab, C_bb)`` of the joint marginal covariance, gtsam order."""
        jm = self._isam.jointMarginalCovariance([key_a, key_b])
        return (np.asarray(jm.at(key_a, key_a), dtype=np.float64),
                np.asarray(jm.at(key_a, key_b), dtype=np.float64),
                np.asarray(jm.at(key_b, key_b), dtype=np.float64))
