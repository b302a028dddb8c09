"""The measures of one registered pose, each taken when a judge's rule first reads it.

:class:`PoseMeasures` is what :func:`~solid_ros.core.verification.judge.judge` reads of a pose
the fine stage settled on: the support both ways (overlap, RMS, horizontal constraint), the
free-space conflict, the constraint without the strongest object, the consistency restarts
(:mod:`solid_ros.core.verification.restarts`), the loop covariance and, from a :class:`Place`,
what the detector knows of the place (this session's odometry and the pose graph's guess). A
measure no rule reads is never taken: most refused candidates cost one support.
"""

from __future__ import annotations

import math
from functools import cached_property
from typing import Protocol

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.verification.judge import Measures
from solid_ros.core.verification.prepared import Query, Source
from solid_ros.core.verification.restarts import drift
from solid_ros.core.verification.support import Support

__all__ = ['Place', 'PoseMeasures', 'VerifierLike']

FloatArray = npt.NDArray[np.float64]

_NAN2 = (math.nan, math.nan)


class Place(Protocol):
    """What the detector knows of a candidate's place besides the clouds: this session's
    odometry and the pose graph's guess (poses ``T_mq`` in the levelled frames)."""

    @property
    def graph(self) -> bool:
        """The pose graph proposed the candidate."""

    def known(self, T_mq: FloatArray, coarse_voxel: float) -> bool:
        """The pose puts the query where the graph predicted it (``known_place``)."""

    def odometry(self, T_mq: FloatArray) -> tuple[float, float]:
        """``(odom_error_m, odom_allowed_m)``, NaN where the odometry says nothing."""

    def heading(self, T_mq: FloatArray) -> tuple[float, float]:
        """``(graph_turn_deg, graph_turn_tol_deg)``, NaN without a graph guess."""

    def position(self, T_mq: FloatArray, voxel: float) -> tuple[float, float]:
        """``(graph_stray_m, graph_stray_allowed_m)``, NaN without a graph guess (``voxel``:
        the pair's fine grid)."""


class VerifierLike(Protocol):
    """What the measures read of the verifier that took the pose (so that this module does not
    import it): its settings and its loop covariance."""

    config: SolidConfig

    def covariance(self, sup: Support, query: Query) -> FloatArray | None:
        """The loop covariance of a support (ROS order), None where it is singular."""


class PoseMeasures(Measures):
    """The measures of one registered pose ``T_qm``, each taken when a rule first reads it
    (and then kept: :func:`~solid_ros.core.verification.judge.evidence_of`).

    Args:
        verifier: the verifier that took the pose (its settings and its covariance).
        query: the query on the pair's grid.
        src: the prepared candidate.
        T_qm: the pose (``p_query = T_qm p_match``, levelled frames).
        coarse_overlap: the coarse stage's.
        converged: whether the fine stage converged.
        step: a registered step to the previous keyframe, not a loop.
        place: what the detector knows of the place (None: nothing).
    """

    def __init__(self, verifier: VerifierLike, query: Query, src: Source, T_qm: FloatArray,
                 coarse_overlap: float, converged: bool, step: bool = False,
                 place: Place | None = None) -> None:
        self._verifier, self._query, self._src, self.T_qm = verifier, query, src, T_qm
        self._place = place
        self.cloud = self.usable = 1.0
        self.coarse_overlap = coarse_overlap
        self.converged = 1.0 if converged else 0.0
        self.step = 1.0 if step else 0.0
        self.graph = 1.0 if place is not None and place.graph else 0.0

    @cached_property
    def T_mq(self) -> FloatArray:
        """The pose the other way round, as the detector and the graph give it."""
        return _inv(self.T_qm)

    @cached_property
    def support(self) -> Support:
        """The support both ways; its cheap measures join the evidence at once."""
        sup = Support(self._query, self._src, self.T_qm, self._query.settings)
        self.__dict__.update(overlap=sup.overlap, rmse=sup.rmse, constraint=sup.constraint)
        return sup

    @property
    def fitness(self) -> float:
        """Fraction of all candidate points supporting the pose (NaN: support not measured);
        not a rule's: the registration's score."""
        return float(self.support.fitness) if 'support' in vars(self) else math.nan

    @cached_property
    def overlap(self) -> float:
        return float(self.support.overlap)

    @cached_property
    def rmse(self) -> float:
        return float(self.support.rmse)

    @cached_property
    def constraint(self) -> float:
        return float(self.support.constraint)

    @cached_property
    def conflict(self) -> float:
        return float(self.support.conflict)

    @cached_property
    def conflict_points(self) -> float:
        return float(self.support.conflict_points)

    @cached_property
    def constraint_near(self) -> float:
        return float(self.support.constraint_near)

    @cached_property
    def spread(self) -> float:
        return float(self.support.spread)

    @cached_property
    def known_place(self) -> float:
        if self._place is None:
            return math.nan
        return 1.0 if self._place.known(self.T_mq, self._query.settings.coarse_voxel) else 0.0

    @cached_property
    def drift(self) -> tuple[float, float, float]:
        """(drift_m, drift_deg, drift_turn_deg) of the consistency restarts."""
        out = drift(self._query, self._src, self.T_qm, self.support.information)
        self.__dict__.update(drift_m=out[0], drift_deg=out[1], drift_turn_deg=out[2])
        return out

    @cached_property
    def drift_m(self) -> float:
        return self.drift[0]

    @cached_property
    def drift_deg(self) -> float:
        return self.drift[1]

    @cached_property
    def drift_turn_deg(self) -> float:
        return self.drift[2]

    @cached_property
    def covariance(self) -> FloatArray | None:
        """The loop covariance (ROS order), None where the information is singular."""
        return self._verifier.covariance(self.support, self._query)

    @cached_property
    def pinned(self) -> tuple[float, float]:
        """Two sigmas of the least pinned translation (m) and rotation (deg) of the
        calibrated covariance: a user's caution (``verify_covariance_scale``) changes no
        verdict."""
        cov = self.covariance
        if cov is None:
            out = (math.inf, math.inf)
        else:
            cov = cov / self._verifier.config.verify_covariance_scale
            t = float(np.linalg.eigvalsh(cov[:3, :3])[-1])
            r = float(np.linalg.eigvalsh(cov[3:, 3:])[-1])
            out = (2.0 * math.sqrt(max(t, 0.0)), 2.0 * math.degrees(math.sqrt(max(r, 0.0))))
        self.__dict__.update(pinned_m=out[0], pinned_deg=out[1])
        return out

    @cached_property
    def pinned_m(self) -> float:
        return self.pinned[0]

    @cached_property
    def pinned_deg(self) -> float:
        return self.pinned[1]

    @cached_property
    def odom(self) -> tuple[float, float]:
        out = _NAN2 if self._place is None else self._place.odometry(self.T_mq)
        self.__dict__.update(odom_error_m=out[0], odom_allowed_m=out[1])
        return out

    @cached_property
    def odom_error_m(self) -> float:
        return self.odom[0]

    @cached_property
    def odom_allowed_m(self) -> float:
        return self.odom[1]

    @cached_property
    def graph_turn(self) -> tuple[float, float]:
        out = _NAN2 if self._place is None else self._place.heading(self.T_mq)
        self.__dict__.update(graph_turn_deg=out[0], graph_turn_tol_deg=out[1])
        return out

    @cached_property
    def graph_turn_deg(self) -> float:
        return self.graph_turn[0]

    @cached_property
    def graph_turn_tol_deg(self) -> float:
        return self.graph_turn[1]

    @cached_property
    def graph_stray(self) -> tuple[float, float]:
        out = (_NAN2 if self._place is None
               else self._place.position(self.T_mq, self._query.settings.voxel))
        self.__dict__.update(graph_stray_m=out[0], graph_stray_allowed_m=out[1])
        return out

    @cached_property
    def graph_stray_m(self) -> float:
        return self.graph_stray[0]

    @cached_property
    def graph_stray_allowed_m(self) -> float:
        return self.graph_stray[1]


def _inv(m: FloatArray) -> FloatArray:
    return np.asarray(np.linalg.inv(m), dtype=np.float64)
