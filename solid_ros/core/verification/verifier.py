"""Geometric verification of loop candidates: registration plus acceptance tests.

For a query scan and a descriptor candidate, in this order (the first failing test names the
rejection ``reason``):

1. ``no_cloud``: the candidate has no stored keyframe cloud (evicted, or loaded from a
   database saved without clouds): it cannot be verified and is never accepted.
2. ``too_sparse``: either cloud has fewer than 10 points, or fewer than 10 structure points
   after the coarse voxel grid.
3. ``coarse_overlap``: the coarse stage registers the candidate's structure points (see
   :mod:`solid_ros.core.verification.registration`) from the pose graph's relative pose when there
   is one
   (:mod:`solid_ros.core.candidates.position`), then from each heading hypothesis (the best A-SOLiD
   shifts), and keeps the best; fewer than ``verify_min_coarse_overlap`` of its coarse
   structure points land within half a coarse voxel of the query's. This is the cheap screen
   most false candidates stop at. A candidate with more than ``verify_coarse_max_points``
   coarse points is registered with an even subsample of that many (the cost grows with
   them).
4. ``not_converged``: the fine stage (voxelised GICP on all points) did not converge within
   ``verify_max_iterations``, and its pose did not stand still when resumed (a stationary
   pose counts as converged; see :func:`solid_ros.core.verification.registration.align_fine`).
5. ``overlap``: fewer than ``verify_min_overlap`` of the structure points support the
   alignment, in either direction (candidate into query, query into candidate); where the
   place is known (see test 9) ``KNOWN_PLACE_OVERLAP`` of it: whether two views show one
   place is what the bar asks, and the graph answered it.
6. ``rmse``: the supporting points' RMS point-to-plane distance exceeds ``verify_max_rmse``.
7. ``conflict``: more than ``verify_max_conflict`` of one scan's points, or of its structure
   points alone, lie in space the other sensor saw through (in front of the surface it
   measured in their direction, by more than two voxels and 5 % of the range); directions it
   saw nothing in do not count, nor do points within a quarter voxel of one of that sensor's
   own points (it saw a surface there: near objects' voxel centroids sit degrees away from
   the directions their surfaces cover, which is occlusion, not contradiction). Structure
   alone because the ground aligns anywhere and would
   dilute the evidence: on look-alike streets seen through a narrow field of view, false
   alignments put about 2-3 % of all points but 5-15 % of the structure points (trees,
   poles, building ends) where the other sensor saw through; all points because a wrong
   tilt shows on the ground.
8. ``constraint``: the supporting structure leaves a horizontal direction or the heading
   nearly free (a corridor, a single wall, a plane): the smallest eigenvalue of its
   information on (x, y, 10 m x yaw) per query structure point is below
   ``verify_min_constraint``. Where the place is known (test 9) the heading's lever is the
   supporting structure's RMS horizontal range when under 10 m: a room's walls 2-4 m away
   cannot pin the heading to what a 10 m lever asks, right poses there scored alike wrong
   ones (0.0009-0.0077 against 0.0004-0.008), and the graph's prediction, not this test,
   holds the loop to the right place (everywhere on the simulator's room walks, seeds 0-7,
   0 false loops; without a known place the same lever published 3 false loops on seed 0).
9. ``single_object``: the pose rests on one object: without the object that contributes most
   (structure clustered in a top-view grid of the coarse voxel), the constraint falls below
   ``verify_min_spread``. One generic object (a building corner, a wall end) matches any other
   like it, so such a loop must also clear a stricter bar: structure overlap at least
   ``verify_single_object_overlap`` and conflict at most half of ``verify_max_conflict``.
   Skipped for a registered step; and where the place is known (a loop that puts the query's
   view where the pose graph predicted it within one coarse voxel,
   :mod:`solid_ros.core.candidates.position`) only the stricter conflict bar stays: the graph says
   which object it is, not that the pose on it is right (in the simulator's room two loops
   at the right place but 3.4-3.8 deg off passed with conflict 0.019-0.025 otherwise).
10. ``unstable``: consistency check. The fine stage is restarted from the solution moved one
   fine voxel along the least constrained horizontal direction and turned, both ways, by
   2 degrees or, if less, the angle that moves the candidate's far points (the 90th
   percentile of their horizontal range) by one fine voxel: together within the fine stage's
   reach of two voxels. A true alignment sits in a basin and is found again, a spurious one
   slides away. The restarts must end within ``verify_max_drift`` metres and
   ``verify_max_drift_deg`` degrees per 2 degrees of turn (a restart that does not move
   fails either way). A fixed 2 degrees moved the far points of a narrow view that sees
   30 m and more out of reach, and right poses did not return. Then a loop that passed is
   restarted from two of the configuration's voxels either way along that direction
   (without a turn; on the tight grid too, four of its voxels): a second minimum along a
   street seen head-on holds its one-voxel basin as well as the right pose does. A restart
   that ends beyond ``verify_max_drift`` at a pose with no more conflict and more structure
   overlap, or at least ``verify_min_overlap`` of it with an RMS below ``_FITS_BETTER`` of
   the loop's, found a better minimum: tests 5-10 run again on it, and their verdict is the
   loop's (the right pose 0.7-1.2 m along the street from such a minimum has a basin
   narrower than a voxel, so this mostly refuses an ambiguous place as ``unstable``). On the
   tight grid a slide of 0.7-1.2 m along a room's shelves and walls kept more structure
   within reach than the right pose (0.65 against 0.60, 0.75 against 0.71) but fitted it
   worse (RMS 0.040 and 0.045 against 0.028), with conflict where the right pose had none.
   Right poses' far restarts land in worse places (less overlap or a worse fit, more
   conflict) and change nothing. Steps skip it: they start from the odometry.

Passing all of them gives ``verified``, unless the loop's covariance (below, without
``verify_covariance_scale``) puts two sigmas beyond what a right loop is in some direction
(``PINNED_M``, ``PINNED_DEG``): then ``constraint``, the structure did not pin that direction
(a hand-held sensor facing one wall, the ground out of view, leaves the roll about the wall's
normal free). The detector may still refuse a verified loop that
this session's odometry contradicts (``odometry``, see :mod:`solid_ros.core.flow.detector`). A
rejected candidate carries the scores of the tests it reached (the rest are NaN): the later
measures cost the most and most candidates never need them.

A keyframe that shows a tight space (:meth:`Verifier.is_tight`: the 90th percentile of its
horizontal ranges under ``verify_tight_range``) is kept on ``TIGHT_GRID`` of the voxel, and two
such keyframes run stages and tests on ``TIGHT_GRID`` of both voxels; any other pair runs on the
configuration's grid (:meth:`Verifier.coarse` picks it).

The relative pose is ``T = T_mq``; its covariance (ROS order, right perturbation in the query
frame) is :func:`solid_ros.core.verification.covariance.support_covariance` of the support the
tests
measured, with ``TIGHT_RESIDUAL`` of its residual factor for two tight-space keyframes.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.geometry import rot_z, yaw_of
from solid_ros.core.reasons import VERIFY_REASONS, Reason
from solid_ros.core.verification.covariance import (
    RESIDUAL_SCALE,
    TIGHT_RESIDUAL,
    support_covariance,
)
from solid_ros.core.verification.registration import (
    Alignment,
    Query,
    RegistrationSettings,
    Source,
    Support,
    align_coarse,
    align_fine,
    coarsened,
)

__all__ = ['KNOWN_PLACE_OVERLAP', 'REASONS', 'TIGHT_GRID', 'CoarseResult', 'Verification',
           'Verifier', 'registration_settings']

FloatArray = npt.NDArray[np.float64]

# Kept under this name for callers that list the verdicts a verification can give.
REASONS = VERIFY_REASONS
_PROBE_VOXELS = 1.0  # restart offset, in fine voxels (half the correspondence distance)
_PROBE_DEG = 2.0  # largest restart turn
_FAR_VOXELS = 2.0  # far restarts that look for a second minimum along the street
_FITS_BETTER = 0.8  # a far restart's RMS below this share of the loop's fits clearly better
_FAR_PERCENTILE = 90.0  # the far points' range that bounds the turn
# Where the place is known (the pose graph predicted it), this fraction of verify_min_overlap
# suffices: that bar asks whether two views show the same place, which the graph answered;
# whether the pose is right is for the tests after it. Views of a place from another
# heading share less (right poses at 0.31-0.35 on the simulator's tilted look-alike streets).
KNOWN_PLACE_OVERLAP = 0.7
# A tight space (a room) registers on this fraction of both voxels: at 3 m a 0.5 m voxel spans
# 10 deg, and the simulator's room gave headings 3-9 deg off that passed every test on it.
TIGHT_GRID = 0.5
_TIGHT_PERCENTILE = 90.0  # of a keyframe's horizontal ranges, against verify_tight_range
# A loop is right within 1 m and 3 degrees (the bar); one whose own covariance puts
# two sigmas beyond it in some direction is not pinned there (a tilted hand-held sensor facing
# one wall: nothing holds the roll about the wall's normal; the ground is out of view).
PINNED_M = 1.0
PINNED_DEG = 3.0
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
        verified: every test passed.
        reason: ``'verified'`` or the first failed test (see the module docstring).
        T: 4x4 ``T_mq`` (``p_match = T p_query``) in the levelled frames; the best estimate
            even when rejected (identity when no registration ran).
        fitness: fraction of all candidate points supporting the alignment.
        rmse: RMS point-to-plane distance of the supporting points, metres.
        overlap: structure overlap, the smaller of the two directions.
        constraint: horizontal constraint per query structure point.
        coarse_overlap: coarse-stage structure overlap.
        drift_m: largest translation between the solution and the restarts, metres.
        drift_deg: largest rotation between the solution and the restarts, degrees.
        covariance: 6x6 in ROS order (x, y, z, roll, pitch, yaw); NaN when not verified.
        hypothesis: index of the start the coarse stage kept: the guesses first, then the
            heading hypotheses (-1: none).
    """

    verified: bool
    reason: Reason
    T: FloatArray
    fitness: float = math.nan
    rmse: float = math.nan
    overlap: float = math.nan
    constraint: float = math.nan
    coarse_overlap: float = math.nan
    conflict: float = math.nan
    spread: float = math.nan
    drift_m: float = math.nan
    drift_deg: float = math.nan
    covariance: FloatArray | None = None
    hypothesis: int = -1

    @property
    def yaw(self) -> float:
        """Heading of ``T`` about +z, radians in (-pi, pi]."""
        return yaw_of(self.T[:3, :3])


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


def _rejected(reason: Reason, T_qm: FloatArray | None = None, **scores: float) -> Verification:
    T: FloatArray = np.eye(4) if T_qm is None else _inv(T_qm)
    return Verification(False, reason, T, **scores)  # type: ignore[arg-type]


def _angle_deg(R: FloatArray) -> float:
    return math.degrees(math.acos(min(max((float(np.trace(R)) - 1.0) / 2.0, -1.0), 1.0)))


class Verifier:
    """Verifies candidates of a query scan; keeps a small cache of prepared candidates.

    Args:
        config: settings (the ``verify_*`` keys); :meth:`reconfigure` applies runtime changes
            of the acceptance thresholds.
    """

    def __init__(self, config: SolidConfig) -> None:
        self._config = config
        self.settings = registration_settings(config)
        self.tight_settings = registration_settings(config, tight=True)
        self._cache: OrderedDict[Hashable, Source] = OrderedDict()

    def reconfigure(self, config: SolidConfig) -> None:
        """Use new thresholds (registration settings are read-only and unchanged)."""
        self._config = config

    def is_tight(self, points: npt.ArrayLike) -> bool:
        """Whether a keyframe cloud (levelled, on the configuration's grid) shows a tight
        space: the 90th percentile of its horizontal ranges below ``verify_tight_range``."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        limit = self._config.verify_tight_range
        if limit <= 0.0 or len(pts) == 0:
            return False
        far = np.percentile(np.hypot(pts[:, 0], pts[:, 1]), _TIGHT_PERCENTILE)
        return bool(far < limit)

    def prepare(self, points: npt.ArrayLike, tight: bool = False) -> Query:
        """Prepare a keyframe cloud as query (target) of the registrations (``tight``: kept
        on the tight-space grid, see :meth:`is_tight`)."""
        return Query(points, self.tight_settings if tight else self.settings)

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
        """Coarse stage of one candidate (tests 1-3), started from each of ``guesses``
        (4x4 ``T_mq`` in the levelled frames, e.g. the pose graph's) and then each heading
        hypothesis of ``yaws``."""
        if cloud is None:
            return CoarseResult(key, None, None, _rejected('no_cloud'))
        query, cloud = self._pair(query, cloud)
        if not query.usable:
            return CoarseResult(key, None, None, _rejected('too_sparse'))
        src = self._source(key, cloud, query.settings)
        if not src.usable:
            return CoarseResult(key, None, None, _rejected('too_sparse'))
        al = align_coarse(query, src, yaws, query.settings, guesses)
        if al is None:
            return CoarseResult(key, None, None, _rejected('too_sparse'))
        if not al.coarse_overlap >= self._config.verify_min_coarse_overlap:
            return CoarseResult(key, src, None, _rejected(
                'coarse_overlap', al.T_qm, coarse_overlap=al.coarse_overlap))
        return CoarseResult(key, src, al, None, query)

    def fine(self, query: Query, coarse: CoarseResult, step: bool = False,
             place: Callable[[FloatArray, float], bool] | None = None) -> Verification:
        """Fine stage and tests 4-10 of a candidate that passed :meth:`coarse`; a ``step``
        (two consecutive keyframes, started from the odometry) skips test 9: whether one
        object matched another like it is a question of place, and the place is known. So
        does a pose ``T_mq`` for which ``place`` holds (the pose graph predicted that object,
        :func:`solid_ros.core.candidates.position.knows_place`)."""
        if coarse.rejection is not None:
            return coarse.rejection
        assert coarse.source is not None and coarse.alignment is not None
        query = query if coarse.query is None else coarse.query
        src, co = coarse.source, coarse.alignment.coarse_overlap
        hyp = coarse.alignment.hypothesis
        fine = align_fine(query, src, coarse.alignment.T_qm, query.settings)
        if not fine.converged:
            return _rejected('not_converged', fine.T_qm, coarse_overlap=co)
        result, sup = self._tests(query, src, fine.T_qm, co, hyp, step, place)
        if step or not result.verified:  # a step starts from the odometry: no street to slide
            return result
        # A better minimum along the street: the loop is right there or nowhere.
        other = self._second_minimum(query, src, fine.T_qm, sup)
        if other is None:
            return result
        return self._tests(query, src, other, co, hyp, step, place)[0]

    def _tests(self, query: Query, src: Source, T_qm: FloatArray, co: float, hyp: int,
               step: bool, place: Callable[[FloatArray, float], bool] | None,
               ) -> tuple[Verification, Support]:
        """Tests 5-10 of a converged pose ``T_qm``, and its support."""
        cfg = self._config
        sup = Support(query, src, T_qm, query.settings)
        # Scores as far as the tests got: the later ones cost more and a rejection skips them.
        scores = {'fitness': sup.fitness, 'rmse': sup.rmse, 'overlap': sup.overlap,
                  'constraint': sup.constraint, 'coarse_overlap': co}
        known = cache(lambda: place is not None
                      and place(_inv(T_qm), query.settings.coarse_voxel))
        if not (sup.overlap >= cfg.verify_min_overlap
                or (sup.overlap >= KNOWN_PLACE_OVERLAP * cfg.verify_min_overlap and known())):
            return _rejected('overlap', T_qm, **scores), sup
        if not sup.rmse <= cfg.verify_max_rmse:
            return _rejected('rmse', T_qm, **scores), sup
        scores['conflict'] = sup.conflict
        if not sup.conflict <= cfg.verify_max_conflict:
            return _rejected('conflict', T_qm, **scores), sup
        if not sup.constraint >= cfg.verify_min_constraint:
            if not (known() and sup.constraint_near >= cfg.verify_min_constraint):
                return _rejected('constraint', T_qm, **scores), sup
            scores['constraint'] = sup.constraint_near  # the measure that passed
        scores['spread'] = sup.spread
        if not (step or sup.spread >= cfg.verify_min_spread
                or (sup.overlap >= cfg.verify_single_object_overlap
                    and sup.conflict <= cfg.verify_max_conflict / 2.0)
                or (known() and sup.conflict <= cfg.verify_max_conflict / 2.0)):
            return _rejected('single_object', T_qm, **scores), sup
        drift_m, drift_deg, turn_deg = self._drift(query, src, T_qm, sup.information)
        scores.update(drift_m=drift_m, drift_deg=drift_deg)
        # The angle bound shrinks with the turn: a restart that did not move must still fail.
        if not (drift_m <= cfg.verify_max_drift
                and drift_deg <= cfg.verify_max_drift_deg * turn_deg / _PROBE_DEG):
            return _rejected('unstable', T_qm, **scores), sup
        tight = query.settings == self.tight_settings
        cov = support_covariance(sup, cfg.verify_covariance_scale,
                                 RESIDUAL_SCALE * (TIGHT_RESIDUAL if tight else 1.0))
        # Pinned by the calibrated covariance: a user's caution (the scale) changes no verdict.
        if cov is None or not _pinned(cov / cfg.verify_covariance_scale):
            return _rejected('constraint', T_qm, **scores), sup
        return Verification(True, 'verified', _inv(T_qm), covariance=cov,
                            hypothesis=hyp, **scores), sup

    def _second_minimum(self, query: Query, src: Source, T_qm: FloatArray,
                        sup: Support) -> FloatArray | None:
        """A better pose the fine stage finds from ``T_qm`` moved ``_FAR_VOXELS`` of the
        configuration's voxels either way along the least constrained horizontal direction, if
        any: one beyond ``verify_max_drift`` with at most the conflict of ``T_qm`` and more
        structure overlap, or ``verify_min_overlap`` of it and a clearly better fit (RMS below
        ``_FITS_BETTER`` of ``T_qm``'s); the one with more overlap where both restarts find
        one."""
        weak = _weak_direction(sup.information)
        best: tuple[float, FloatArray] | None = None
        for sign in (1.0, -1.0):
            shift = np.eye(4)
            shift[:2, 3] = sign * _FAR_VOXELS * self.settings.voxel * weak
            again = align_fine(query, src, shift @ T_qm, query.settings)
            diff = np.linalg.inv(T_qm) @ again.T_qm
            if not (again.converged
                    and float(np.linalg.norm(diff[:3, 3])) > self._config.verify_max_drift):
                continue
            there = Support(query, src, again.T_qm, query.settings)
            better = (there.overlap > sup.overlap
                      or (there.rmse < _FITS_BETTER * sup.rmse
                          and there.overlap >= self._config.verify_min_overlap))
            if (better and there.conflict <= sup.conflict
                    and (best is None or there.overlap > best[0])):
                best = (there.overlap, again.T_qm)
        return None if best is None else best[1]

    def _drift(self, query: Query, src: Source, T_qm: FloatArray,
               info: FloatArray) -> tuple[float, float, float]:
        """Largest distance and angle between ``T_qm`` and two perturbed restarts, and the
        turn of the restarts in degrees: ``_PROBE_DEG``, less where it would move the
        candidate's far points (90th percentile of their horizontal range from the query
        sensor) by more than ``_PROBE_VOXELS`` fine voxels: with the shift, no point moves
        beyond the fine stage's reach (two voxels); 2 degrees pushed the far structure of a
        narrow view that sees 30 m and more out of it, and right poses did not return."""
        weak = _weak_direction(info)
        shift = _PROBE_VOXELS * query.settings.voxel
        xy = src.points[:, :2] @ T_qm[:2, :2].T + T_qm[:2, 3]
        far = float(np.percentile(np.linalg.norm(xy, axis=1), _FAR_PERCENTILE))
        turn = min(math.radians(_PROBE_DEG), shift / max(far, 1e-6))
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


def _same_grid(voxel: float, settings: RegistrationSettings) -> bool:
    """Whether a stored cloud's grid (0: the configuration's) is ``settings``' voxel."""
    return abs(voxel - settings.voxel) <= 1e-6 * settings.voxel


def _pinned(cov: FloatArray) -> bool:
    """Whether a loop's covariance (ROS order) keeps two sigmas inside what a right loop is
    (``PINNED_M``, ``PINNED_DEG``) in every direction."""
    t = float(np.linalg.eigvalsh(cov[:3, :3])[-1])
    r = float(np.linalg.eigvalsh(cov[3:, 3:])[-1])
    return (2.0 * math.sqrt(max(t, 0.0)) <= PINNED_M
            and 2.0 * math.degrees(math.sqrt(max(r, 0.0))) <= PINNED_DEG)


def _weak_direction(info: FloatArray) -> FloatArray:
    """The least constrained horizontal direction (unit x, y) of a rotation-first 6x6
    information: where both the consistency restarts and the far restarts push."""
    out: FloatArray = np.linalg.eigh(info[3:5, 3:5])[1][:, 0]
    return out


def _inv(m: FloatArray) -> FloatArray:
    return np.asarray(np.linalg.inv(m), dtype=np.float64)
