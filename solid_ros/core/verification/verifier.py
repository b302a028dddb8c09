"""Geometric verification of loop candidates: the procedure, from the coarse stage to the verdict.

For a query keyframe and a candidate, :meth:`Verifier.coarse` registers the candidate's
coarse structure points (:mod:`solid_ros.core.verification.registration`) from the pose
graph's relative pose when there is one (:mod:`solid_ros.core.candidates.position`), then from
each heading hypothesis (the best A-SOLiD shifts), keeps the best, and the judge's coarse rules
(:mod:`solid_ros.core.verification.judge`) screen it; most false candidates stop here. A
candidate with more than ``verify_coarse_max_points`` coarse points is registered with an even
subsample of that many.

:meth:`Verifier.fine` runs the fine stage (voxelised GICP on all points) from there and judges
the pose with the fine rules, each measure taken when a rule first reads it
(:class:`~solid_ros.core.verification.measures.PoseMeasures`); a pose that passes is restarted
along its least constrained direction to look for a better minimum
(:mod:`solid_ros.core.verification.restarts`), which the fine rules then judge instead. Last,
the context rules judge the pose the fine stage settled on against this session's odometry and
pose graph (a :class:`~solid_ros.core.verification.measures.Place` from the detector). One
:class:`~solid_ros.core.results.Evidence` record holds every measure taken.

A keyframe that shows a tight space (:meth:`Verifier.is_tight`: the 90th percentile of its
horizontal ranges under ``verify_tight_range``) is kept on ``TIGHT_GRID`` of the voxel, and two
such keyframes run both stages on ``TIGHT_GRID`` of both voxels; any other pair runs on the
configuration's grid (:meth:`Verifier.coarse` picks it).

The relative pose is ``T = T_mq``; its covariance (ROS order, right perturbation in the query
frame) is :func:`solid_ros.core.verification.covariance.support_covariance` of the support,
with ``TIGHT_RESIDUAL`` of its residual factor for two tight-space keyframes.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.geometry import yaw_of
from solid_ros.core.reasons import Reason
from solid_ros.core.results import Evidence
from solid_ros.core.verification.calibration import Learned
from solid_ros.core.verification.covariance import (
    RESIDUAL_SCALE,
    TIGHT_RESIDUAL,
    support_covariance,
)
from solid_ros.core.verification.judge import Bars, Measures, Verdict, bars, judge
from solid_ros.core.verification.measures import Place, PoseMeasures
from solid_ros.core.verification.prepared import Query, RegistrationSettings, Source, coarsened
from solid_ros.core.verification.registration import (
    Alignment,
    align_coarse,
    align_fine,
    settled,
)
from solid_ros.core.verification.support import Support

__all__ = ['TIGHT_GRID', 'CoarseResult', 'Verification', 'Verifier', 'registration_settings']

FloatArray = npt.NDArray[np.float64]

# A tight space (a room) registers on this fraction of both voxels: at 3 m a 0.5 m voxel spans
# 10 deg, and the simulator's room gave headings 3-9 deg off that passed every test on it.
TIGHT_GRID = 0.5
_TIGHT_PERCENTILE = 90.0  # of a keyframe's horizontal ranges, against verify_tight_range
_SOURCE_CACHE = 16  # prepared candidate clouds kept: consecutive queries hit the same places


def registration_settings(config: SolidConfig, tight: bool = False) -> RegistrationSettings:
    """The registration settings of a configuration (``tight``: of two tight-space keyframes,
    both voxels halved; see ``verify_tight_range``)."""
    scale = TIGHT_GRID if tight else 1.0
    return RegistrationSettings(voxel=scale * config.verify_voxel_size,
                                coarse_voxel=scale * config.verify_coarse_voxel_size,
                                coarse_distance=2.0 * scale * config.verify_coarse_voxel_size,
                                coarse_max_points=config.verify_coarse_max_points,
                                max_iterations=config.verify_max_iterations,
                                inlier_distance=config.verify_inlier_distance)


@dataclass(frozen=True)
class Verification:
    """Outcome of verifying one candidate.

    Attributes:
        verified: no rule refused it.
        reason: ``'verified'`` or the reason of the rule that refused it.
        T: 4x4 ``T_mq`` (``p_match = T p_query``) in the levelled frames; the best estimate
            even when refused (identity when no registration ran).
        evidence: every measure taken (:class:`~solid_ros.core.results.Evidence`).
        detail: the refusing rule's reading (empty when verified).
        fitness: fraction of all candidate points supporting the alignment.
        covariance: 6x6 in ROS order (x, y, z, roll, pitch, yaw); None when not verified.
        hypothesis: index of the start the coarse stage kept: the guesses first, then the
            heading hypotheses (-1: none).
    """

    verified: bool
    reason: Reason
    T: FloatArray
    evidence: Evidence = Evidence()
    detail: str = ''
    fitness: float = math.nan
    covariance: FloatArray | None = None
    hypothesis: int = -1

    @property
    def yaw(self) -> float:
        """Heading of ``T`` about +z, radians in (-pi, pi]."""
        return yaw_of(self.T[:3, :3])

    @property
    def overlap(self) -> float:
        """Structure overlap (NaN: not measured)."""
        return self.evidence.overlap

    @property
    def conflict(self) -> float:
        """Free-space conflict (NaN: not measured)."""
        return self.evidence.conflict

    @property
    def constraint(self) -> float:
        """Horizontal constraint, 10 m heading lever (NaN: not measured)."""
        return self.evidence.constraint

    @property
    def rmse(self) -> float:
        """RMS point-to-plane distance of the support (NaN: not measured)."""
        return self.evidence.rmse

    @property
    def coarse_overlap(self) -> float:
        """Coarse-stage structure overlap (NaN: not measured)."""
        return self.evidence.coarse_overlap

    @classmethod
    def refused(cls, verdict: Verdict, T_qm: FloatArray | None = None,
                fitness: float = math.nan) -> Verification:
        """A refusal with the judge's verdict at pose ``T_qm`` (identity when None)."""
        T: FloatArray = (np.eye(4) if T_qm is None
                         else np.asarray(np.linalg.inv(T_qm), dtype=np.float64))
        return cls(False, verdict.reason, T, verdict.evidence, verdict.detail, fitness)


@dataclass(frozen=True)
class CoarseResult:
    """A candidate after the coarse stage, before the fine stage and the tests."""

    key: Hashable
    source: Source | None
    alignment: Alignment | None
    rejection: Verification | None
    query: Query | None = None  # on the grid the pair registers on (see Verifier.coarse)

    @property
    def coarse_overlap(self) -> float:
        """Coarse overlap (-1 when the candidate was already rejected)."""
        return -1.0 if self.alignment is None else float(self.alignment.coarse_overlap)


class Verifier:
    """Verifies candidates of a query scan; keeps a small cache of prepared candidates.

    Args:
        config: settings (the ``verify_*`` keys); :meth:`reconfigure` applies runtime changes
            of the thresholds.
    """

    def __init__(self, config: SolidConfig) -> None:
        self.config = config
        self.learned = Learned()
        self.bars: Bars = bars(config)
        self.step_bars: Bars = bars(config, step=True)  # a registered step's (see bars)
        self.settings = registration_settings(config)
        self.tight_settings = registration_settings(config, tight=True)
        self._cache: OrderedDict[Hashable, Source] = OrderedDict()

    def reconfigure(self, config: SolidConfig) -> None:
        """Use new thresholds (registration settings are read-only and unchanged)."""
        self.config = config
        self.bars = bars(config, self.learned)
        self.step_bars = bars(config, self.learned, step=True)

    def learn(self, learned: Learned) -> None:
        """Use what the run learned about itself (:mod:`.calibration`) in the thresholds."""
        self.learned = learned
        self.bars = bars(self.config, learned)
        self.step_bars = bars(self.config, learned, step=True)

    def is_tight(self, points: npt.ArrayLike) -> bool:
        """Whether a keyframe cloud (levelled, on the configuration's grid) shows a tight
        space: the 90th percentile of its horizontal ranges below ``verify_tight_range``."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        limit = self.config.verify_tight_range
        if limit <= 0.0 or len(pts) == 0:
            return False
        far = np.percentile(np.hypot(pts[:, 0], pts[:, 1]), _TIGHT_PERCENTILE)
        return bool(far < limit)

    def prepare(self, points: npt.ArrayLike, tight: bool = False) -> Query:
        """Prepare a keyframe cloud as query (target) of the registrations (``tight``: kept
        on the tight-space grid, see :meth:`is_tight`)."""
        return Query(points, self.tight_settings if tight else self.settings)

    def query_of(self, cloud: KeyframeCloud) -> Query:
        """A stored keyframe cloud prepared as query, on the grid it was kept on."""
        return self.prepare(cloud.points, _same_grid(cloud.voxel, self.tight_settings))

    def _pair(self, query: Query, cloud: KeyframeCloud) -> tuple[Query, KeyframeCloud]:
        """The query and candidate on the grid they register on: the tight one when both were
        kept on it, else the configuration's."""
        if query.settings == self.tight_settings and _same_grid(cloud.voxel, query.settings):
            return query, cloud
        return query.on_grid(self.settings), coarsened(cloud, self.settings.voxel)

    def _source(self, key: Hashable, cloud: KeyframeCloud,
                settings: RegistrationSettings) -> Source:
        key = (key, settings.voxel)
        src = self._cache.get(key)
        if src is None:
            src = Source(cloud, settings)
            self._cache[key] = src
            while len(self._cache) > _SOURCE_CACHE:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
        return src

    def clear_cache(self) -> None:
        """Forget prepared candidates (after a reset)."""
        self._cache.clear()

    def coarse(self, query: Query, key: Hashable, cloud: KeyframeCloud | None,
               yaws: list[float], guesses: Sequence[FloatArray] = ()) -> CoarseResult:
        """Coarse stage of one candidate and the judge's coarse rules, started from each of
        ``guesses`` (4x4 ``T_mq`` in the levelled frames, e.g. the pose graph's) and then each
        heading hypothesis of ``yaws``."""
        if cloud is None:
            return CoarseResult(key, None, None, self._refused(Measures(cloud=0.0)))
        query, cloud = self._pair(query, cloud)
        src = self._source(key, cloud, query.settings) if query.usable else None
        al = (align_coarse(query, src, yaws, query.settings, guesses, settle=False)
              if src is not None and src.usable else None)
        if al is None:
            return CoarseResult(key, None, None,
                                self._refused(Measures(cloud=1.0, usable=0.0)))
        verdict = judge(Measures(cloud=1.0, usable=1.0, coarse_overlap=al.coarse_overlap),
                        self.bars, 'coarse')
        if not verdict.verified:
            return CoarseResult(key, src, None, Verification.refused(verdict, al.T_qm))
        return CoarseResult(key, src, al, None, query)

    def _refused(self, measures: Measures) -> Verification:
        return Verification.refused(judge(measures, self.bars, 'coarse'))

    def fine(self, query: Query, coarse: CoarseResult, step: bool = False,
             place: Place | None = None) -> Verification:
        """Fine stage of a candidate that passed :meth:`coarse`, judged by the fine rules,
        then, on the pose it settled on, by the context rules (``place``: what the detector
        knows of the place; a ``step``, two consecutive keyframes started from the odometry,
        skips the single-object rule)."""
        if coarse.rejection is not None:
            return coarse.rejection
        assert coarse.source is not None and coarse.alignment is not None
        query = query if coarse.query is None else coarse.query
        src, co = coarse.source, coarse.alignment.coarse_overlap
        start = settled(query, src, coarse.alignment, query.settings)
        fine = align_fine(query, src, start.T_qm, query.settings)
        m = PoseMeasures(self, query, src, fine.T_qm, co, fine.converged, step, place)
        limits = self.step_bars if step else self.bars
        verdict = judge(m, limits, 'fine')
        if verdict.verified:
            verdict = judge(m, limits, 'context')
        if not verdict.verified:
            return Verification.refused(verdict, m.T_qm, m.fitness)
        return Verification(True, 'verified', m.T_mq, verdict.evidence, '',
                            m.support.fitness, m.covariance, coarse.alignment.hypothesis)

    def measure(self, query: Query, coarse: CoarseResult, step: bool = False) -> PoseMeasures:
        """The fine stage from a coarse result that passed, unjudged: the measures of the
        pose it converged to (the calibration's pairs; ``step``: judged as a registered
        step)."""
        assert coarse.source is not None and coarse.alignment is not None
        query = query if coarse.query is None else coarse.query
        start = settled(query, coarse.source, coarse.alignment, query.settings)
        fine = align_fine(query, coarse.source, start.T_qm, query.settings)
        return PoseMeasures(self, query, coarse.source, fine.T_qm,
                            coarse.alignment.coarse_overlap, fine.converged, step)

    def covariance(self, sup: Support, query: Query) -> FloatArray | None:
        """The loop covariance of a support (two tight-space keyframes: ``TIGHT_RESIDUAL``)."""
        tight = query.settings == self.tight_settings
        return support_covariance(sup, self.config.verify_covariance_scale,
                                  RESIDUAL_SCALE * (TIGHT_RESIDUAL if tight else 1.0))

def _same_grid(voxel: float, settings: RegistrationSettings) -> bool:
    """Whether a stored cloud's grid (0: the configuration's) is ``settings``' voxel."""
    return abs(voxel - settings.voxel) <= 1e-6 * settings.voxel

