"""Two robots on one synthetic drive, for the inter-robot alignment's tests and bench.

Robot 0 drives laps of a square (``drifting_odometry.square``); its map is the world, or its
drifting odometry. Robot 1 drives the same square on a lane 3 m aside, started ``lead``
metres further on; its map is its own odometry (drifting unless ``drift`` is None) placed by
a random rigid transform ``G``: ``T_world_map1``, so the true alignment ``T_map0<-map1`` is
``G`` where robot 1's map has not drifted yet (at its start). Loops carry the true relative
pose (with noise) or a false one that places robot 1's map ``offset`` metres off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from drifting_odometry import Drift, drifting_odometry, square

from solid_ros.core.geometry import matrix_to_vector, rpy_matrix
from solid_ros.core.results import LoopCandidate

FloatArray = np.ndarray
LOOP_SIGMAS = (0.05, math.radians(0.3))  # metres, radians: a verified loop's covariance
TIGHT = (0.01, math.radians(0.05))  # a false loop claiming to be very sure


def _cov(sigmas: tuple[float, float]) -> tuple[float, ...]:
    return tuple(np.diag([sigmas[0] ** 2] * 3 + [sigmas[1] ** 2] * 3).ravel())


@dataclass
class TwoRobots:
    """The two robots' true poses, their maps and the true alignment (module docstring)."""

    n: int = 200
    lead: int = 0
    seed: int = 0
    drift: Drift | None = field(default_factory=Drift)
    own_drift: Drift | None = None

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        path = square(self.n + self.lead)
        self.truth0 = path[:self.n]
        self.truth1 = path[self.lead:self.lead + self.n].copy()
        self.truth1[:, :3, 3] += self.truth1[:, :3, 1] * 3.0  # a lane to the left
        G = np.eye(4)
        G[:3, :3] = rpy_matrix(*rng.uniform(-0.05, 0.05, 2), rng.uniform(-math.pi, math.pi))
        G[:3, 3] = rng.uniform(-100.0, 100.0, 3) * [1.0, 1.0, 0.05]
        self.G = G
        self.own = (self.truth0 if self.own_drift is None
                    else drifting_odometry(self.truth0, self.own_drift))
        odo1 = (self.truth1 if self.drift is None
                else drifting_odometry(self.truth1, self.drift))
        self.peer = np.linalg.inv(G) @ odo1
        self._rng = rng

    def own_poses(self) -> dict[int, FloatArray]:
        return dict(enumerate(self.own))

    def peer_poses(self) -> dict[int, FloatArray]:
        return dict(enumerate(self.peer))

    def matching(self, q: int) -> int:
        """Robot 1's keyframe at robot 0's keyframe ``q`` (the same place)."""
        return q - self.lead

    def loop(self, q: int, m: int, offset: float = 0.0, noise: bool = True,
             sigmas: tuple[float, float] = LOOP_SIGMAS, by_peer: bool = False
             ) -> LoopCandidate:
        """A loop of robot 0's keyframe ``q`` to robot 1's ``m`` (``by_peer``: as robot 1
        publishes it, from its ``m`` to robot 0's ``q``). ``offset`` places robot 1's map that
        many metres off along x of robot 0's map (a false loop; the same offset at every
        keyframe makes a consistent burst)."""
        Z = np.linalg.solve(self.truth1[m], self.truth0[q])
        if offset:
            shift = np.eye(4)
            shift[0, 3] = offset
            # implies shift @ G where the maps are true: Y^-1 (shift G)^-1 X
            Z = np.linalg.solve(self.truth1[m], np.linalg.solve(shift, self.truth0[q]))
        if noise and not offset:
            e = np.eye(4)
            e[:3, :3] = rpy_matrix(*self._rng.normal(0.0, sigmas[1], 3))
            e[:3, 3] = self._rng.normal(0.0, sigmas[0], 3)
            Z = Z @ e
        cov = _cov(TIGHT if offset else sigmas)
        if by_peer:
            return LoopCandidate(m, q, m, q, 0, 0.1, 0.0, 1.0, True,
                                 tuple(matrix_to_vector(np.linalg.inv(Z))),
                                 covariance=cov, reason='verified')
        return LoopCandidate(q, m, q, m, 1, 0.1, 0.0, 1.0, True, tuple(matrix_to_vector(Z)),
                             covariance=cov, reason='verified')

    def placement_error(self, A: FloatArray, peer_indices: list[int]) -> float:
        """Mean distance between where ``A`` puts robot 1's keyframes in robot 0's map and
        where they truly are (robot 0's map being the world where it has not drifted)."""
        pos = (A @ self.peer[peer_indices])[:, :3, 3]
        return float(np.mean(np.linalg.norm(pos - self.truth1[peer_indices, :3, 3], axis=1)))
