"""Geometric verification of loop candidates: the measures the judge reads, and the procedure.

For a query keyframe and a candidate, :meth:`Verifier.coarse` registers the candidate's
coarse structure points (:mod:`solid_ros.core.verification.registration`) from the pose
graph's relative pose when there is one (:mod:`solid_ros.core.candidates.position`), then from
each heading hypothesis (the best A-SOLiD shifts), keeps the best, and the judge's coarse rules
(:mod:`solid_ros.core.verification.judge`) screen it; most false candidates stop here. A
candidate with more than ``verify_coarse_max_points`` coarse points is registered with an even
subsample of that many.

:meth:`Verifier.fine` runs the fine stage (voxelised GICP on all points) from there and judges
the pose with the fine rules, each measure taken when a rule first reads it
(:class:`PoseMeasures`): the support both ways (overlap, RMS, horizontal constraint), the
free-space conflict, the constraint without the strongest object, the consistency restarts and
the loop covariance. A pose that passes is then restarted from two of the configuration's
voxels either way along its least constrained horizontal direction (four of the tight grid's):
a second minimum along a street seen head-on holds its one-voxel basin as well as the right
pose does. A restart that ends beyond ``verify_max_drift`` at a pose with no more conflict,
and more structure overlap with neither direction's lower or at least ``verify_min_overlap``
of it with an RMS below ``_FITS_BETTER`` of the loop's, found a better minimum, and the fine rules
judge that pose instead (the right pose 0.7-1.2 m along such a street has a basin narrower
than a voxel, so this mostly refuses an ambiguous place). Last, the context rules judge the
pose the fine stage settled on against this session's odometry and pose graph (a
:class:`Place` from the detector). One :class:`~solid_ros.core.results.Evidence` record holds
every measure taken.

Consistency restarts (``unstable``): the fine stage restarts from the pose moved one fine
voxel along the least constrained horizontal direction and turned, both ways, by 2 degrees or,
if less, the angle that moves the candidate's far points (the 90th percentile of their
horizontal range) by one fine voxel: together within the fine stage's reach of two voxels. A
true alignment sits in a basin and is found again, a spurious one slides away.

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
from functools import cached_property
from typing import Protocol

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.geometry import rot_z, yaw_of
from solid_ros.core.reasons import Reason
from solid_ros.core.results import Evidence
from solid_ros.core.verification.calibration import Learned
from solid_ros.core.verification.covariance import (
    RESIDUAL_SCALE,
    TIGHT_RESIDUAL,
    support_covariance,
)
from solid_ros.core.verification.judge import PROBE_DEG, Bars, Measures, Verdict, bars, judge
from solid_ros.core.verification.prepared import Query, RegistrationSettings, Source, coarsened
from solid_ros.core.verification.registration import (
    Alignment,
    align_coarse,
    align_fine,
    settled,
)
from solid_ros.core.verification.support import Support

__all__ = ['TIGHT_GRID', 'CoarseResult', 'Place', 'PoseMeasures', 'Verification', 'Verifier',
           'registration_settings']

FloatArray = npt.NDArray[np.float64]

_PROBE_VOXELS = 1.0  # restart offset, in fine voxels (half the correspondence distance)
_FAR_VOXELS = 2.0  # far restarts that look for a second minimum along the street
_FITS_BETTER = 0.8  # a far restart's RMS below this share of the loop's fits clearly better
_FAR_PERCENTILE = 90.0  # the far points' range that bounds the turn
# A tight space (a room) registers on this fraction of both voxels: at 3 m a 0.5 m voxel spans
# 10 deg, and the simulator's room gave headings 3-9 deg off that passed every test on it.
TIGHT_GRID = 0.5
_TIGHT_PERCENTILE = 90.0  # of a keyframe's horizontal ranges, against verify_tight_range
_SOURCE_CACHE = 16  # prepared candidate clouds kept: consecutive queries hit the same places
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
        T: FloatArray = np.eye(4) if T_qm is None else _inv(T_qm)
        return cls(False, verdict.reason, T, verdict.evidence, verdict.detail, fitness)


@dataclass
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


class PoseMeasures(Measures):
    """The measures of one registered pose ``T_qm``, each taken when a rule first reads it
    (and then kept: :func:`~solid_ros.core.verification.judge.evidence_of`).

    Args:
        verifier: the verifier (its settings and its restarts).
        query: the query on the pair's grid.
        src: the prepared candidate.
        T_qm: the pose (``p_query = T_qm p_match``, levelled frames).
        coarse_overlap: the coarse stage's.
        converged: whether the fine stage converged.
        step: a registered step to the previous keyframe, not a loop.
        place: what the detector knows of the place (None: nothing).
        second_minimum: the pose is a far restart's better minimum.
    """

    def __init__(self, verifier: Verifier, query: Query, src: Source, T_qm: FloatArray,
                 coarse_overlap: float, converged: bool, step: bool = False,
                 place: Place | None = None, second_minimum: bool = False) -> None:
        self._verifier, self._query, self._src, self.T_qm = verifier, query, src, T_qm
        self._place = place
        self.cloud = self.usable = 1.0
        self.coarse_overlap = coarse_overlap
        self.converged = 1.0 if converged else 0.0
        self.step = 1.0 if step else 0.0
        self.graph = 1.0 if place is not None and place.graph else 0.0
        if second_minimum:
            self.second_minimum = 1.0

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
        out = self._verifier.drift(self._query, self._src, self.T_qm, self.support.information)
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
        skips the single-object rule and the search for a second minimum)."""
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
        if verdict.verified and not step:  # a step starts from the odometry: no street
            other = self._second_minimum(query, src, fine.T_qm, m.support)
            if other is not None:
                m = PoseMeasures(self, query, src, other, co, True, step, place, True)
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

    def _second_minimum(self, query: Query, src: Source, T_qm: FloatArray,
                        sup: Support) -> FloatArray | None:
        """A better pose the fine stage finds from ``T_qm`` moved ``_FAR_VOXELS`` of the
        configuration's voxels either way along the least constrained horizontal direction, if
        any: one beyond ``verify_max_drift`` that fits better (:func:`_better_minimum`); the
        one with more overlap where both restarts find one."""
        weak = _weak_direction(sup.information)
        best: tuple[float, FloatArray] | None = None
        for sign in (1.0, -1.0):
            shift = np.eye(4)
            shift[:2, 3] = sign * _FAR_VOXELS * self.settings.voxel * weak
            again = align_fine(query, src, shift @ T_qm, query.settings)
            diff = np.linalg.inv(T_qm) @ again.T_qm
            if not (again.converged
                    and float(np.linalg.norm(diff[:3, 3])) > self.config.verify_max_drift):
                continue
            there = Support(query, src, again.T_qm, query.settings)
            if (_better_minimum(there, sup, self.config.verify_min_overlap)
                    and (best is None or there.overlap > best[0])):
                best = (there.overlap, again.T_qm)
        return None if best is None else best[1]

    def drift(self, query: Query, src: Source, T_qm: FloatArray,
              info: FloatArray) -> tuple[float, float, float]:
        """Largest distance and angle between ``T_qm`` and two perturbed restarts, and the
        turn of the restarts in degrees: ``PROBE_DEG``, less where it would move the
        candidate's far points (90th percentile of their horizontal range from the query
        sensor) by more than ``_PROBE_VOXELS`` fine voxels: with the shift, no point moves
        beyond the fine stage's reach (two voxels); 2 degrees pushed the far structure of a
        narrow view that sees 30 m and more out of it, and right poses did not return."""
        weak = _weak_direction(info)
        shift = _PROBE_VOXELS * query.settings.voxel
        xy = src.points[:, :2] @ T_qm[:2, :2].T + T_qm[:2, 3]
        far = float(np.percentile(np.linalg.norm(xy, axis=1), _FAR_PERCENTILE))
        turn = min(math.radians(PROBE_DEG), shift / max(far, 1e-6))
        worst_m = worst_deg = 0.0
        for sign in (1.0, -1.0):
            shake = np.eye(4)
            shake[:3, :3] = rot_z(sign * turn)
            shake[:2, 3] = sign * shift * weak
            again = align_fine(query, src, shake @ T_qm, query.settings)
            diff = np.linalg.inv(T_qm) @ again.T_qm
            worst_m = max(worst_m, float(np.linalg.norm(diff[:3, 3])))
            worst_deg = max(worst_deg, _angle_deg(diff[:3, :3]))
        return worst_m, worst_deg, math.degrees(turn)


def _better_minimum(there: Support, here: Support, min_overlap: float) -> bool:
    """Whether a far restart's pose (``there``) fits better than the loop's (``here``): no
    more conflict, and more overlap with neither direction's lower, or ``min_overlap`` of it
    with a clearly better fit (RMS below ``_FITS_BETTER`` of the loop's).

    Both directions are compared, not only the smaller: on a street lined with porous foliage
    the smaller (the query's) rose 0.48 -> 0.52 at a pose 1.5 m along the street while the
    candidate's own fell 0.88 -> 0.67, and that pose replaced the right one. The clearly
    better fit stands alone: held to both directions too, it no longer found out the room
    slides and the street's second minimum of test_verifier.
    """
    more = (there.overlap > here.overlap and there.overlap_match >= here.overlap_match
            and there.overlap_query >= here.overlap_query)
    fits = more or (there.rmse < _FITS_BETTER * here.rmse and there.overlap >= min_overlap)
    return fits and there.conflict <= here.conflict  # the conflict last: it costs most


def _angle_deg(R: FloatArray) -> float:
    return math.degrees(math.acos(min(max((float(np.trace(R)) - 1.0) / 2.0, -1.0), 1.0)))


def _same_grid(voxel: float, settings: RegistrationSettings) -> bool:
    """Whether a stored cloud's grid (0: the configuration's) is ``settings``' voxel."""
    return abs(voxel - settings.voxel) <= 1e-6 * settings.voxel


def _weak_direction(info: FloatArray) -> FloatArray:
    """The least constrained horizontal direction (unit x, y) of a rotation-first 6x6
    information: where both the consistency restarts and the far restarts push."""
    out: FloatArray = np.linalg.eigh(info[3:5, 3:5])[1][:, 0]
    return out


def _inv(m: FloatArray) -> FloatArray:
    return np.asarray(np.linalg.inv(m), dtype=np.float64)
