"""The one judge of a loop candidate: every rule that accepts or refuses it, in one table.

A candidate is measured into one :class:`~solid_ros.core.results.Evidence` record
(registration, support, restarts, covariance, the odometry and the pose graph: see
:mod:`solid_ros.core.verification.verifier`) and judged by :data:`RULES` in their order; the
first rule that fails names the reason, and its reading (``'conflict 0.057 > 0.030'``) goes
with it into ``candidates.csv``, the report and the log. Measures are taken on demand: a rule
reads only what it needs, so a candidate the cheap rules refuse never pays for the costly
ones, and the evidence holds what was read (NaN: never needed).

Every threshold is a :class:`Bars` field, derived in one place (:func:`bars`) from the
configuration and from what the run taught about itself
(:class:`~solid_ros.core.verification.calibration.Learned`): a setting, a named derivation of
one, or the run's own distribution, each documented there.

The rules run in three stages. ``coarse``: is there anything to register, and did the coarse
stage align enough structure (cheap, most false candidates stop here). ``fine``: does the
fine alignment hold as a place and a pose. ``context``: does it agree with what this session
already knows, its odometry and its pose graph (after the fine stage settled on a pose, the
better of two minima; see the verifier).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from solid_ros.core.config import SolidConfig
from solid_ros.core.reasons import RULE_REASONS, Reason
from solid_ros.core.results import EVIDENCE_FIELDS, Evidence
from solid_ros.core.verification.calibration import Learned

__all__ = ['RULES', 'STAGES', 'Bars', 'Measures', 'Rule', 'Verdict', 'bars', 'evidence_of',
           'judge']

Stage = Literal['coarse', 'fine', 'context']
STAGES: tuple[Stage, ...] = ('coarse', 'fine', 'context')

# Where the pose graph says the place is known, this share of verify_min_overlap suffices:
# that bar asks whether two views show one place, which the graph answered (views of a place
# from another heading share less).
KNOWN_PLACE_SHARE = 0.7
# There, too, this many times the conflict bar: what changed since the last visit (a car
# parked or gone, a door, furniture) puts a whole object into space the other scan saw
# through, and whether the place is right the graph answered.
KNOWN_PLACE_CONFLICT = 2.0
# A loop is right within 1 m and 3 degrees: one whose own covariance puts two sigmas beyond
# that in some direction is not pinned there (a sensor facing one wall leaves a roll free).
PINNED_M = 1.0
PINNED_DEG = 3.0
# The consistency restarts turn by at most this much; the rotation they may drift is
# verify_max_drift_deg per this turn (a restart that did not move must still fail).
PROBE_DEG = 2.0
# The conflict bar sits this far above the upper quartile of the run's right alignments'
# conflict, so the single-object bar (half of it) sits at that quartile.
CONFLICT_OVER_RIGHT = 2.0
# The odometry may drift this many times what the run measured over a few metres (its 90th
# percentile per metre, registration noise included): a heading error grows the drift faster
# than the path.
DRIFT_OVER_MEASURED = 2.0


@dataclass(frozen=True)
class Bars:
    """The thresholds the rules compare the evidence with (see :func:`bars`)."""

    min_coarse_overlap: float
    min_overlap: float
    known_place_overlap: float
    max_rmse: float
    max_conflict: float
    known_place_conflict: float
    min_constraint: float
    min_spread: float
    single_object_overlap: float
    single_object_conflict: float
    max_drift_m: float
    max_drift_deg_per_probe: float
    pinned_m: float
    pinned_deg: float
    odom_slack_m: float = math.inf
    odom_drift_per_m: float = 0.0

    def odom_allowed(self, path_m: float) -> float:
        """How far a loop may disagree with the odometry over ``path_m`` of path, metres."""
        return self.odom_slack_m + self.odom_drift_per_m * path_m


def bars(config: SolidConfig, learned: Learned | None = None, step: bool = False) -> Bars:
    """The thresholds of a configuration, and of what the run learned about itself (``step``:
    for a registered step).

    - ``known_place_overlap``: ``KNOWN_PLACE_SHARE`` of ``verify_min_overlap``, where the pose
      graph predicted the place.
    - ``known_place_conflict``: ``KNOWN_PLACE_CONFLICT`` times ``max_conflict``, there.
    - ``single_object_conflict``: half of ``max_conflict``: a pose that rests on one object
      the graph did not predict must show clearly less conflict than the bar.
    - ``max_drift_deg_per_probe``: ``verify_max_drift_deg`` per ``PROBE_DEG`` of restart turn.
    - ``pinned_m``, ``pinned_deg``: what a right loop is (``PINNED_M``, ``PINNED_DEG``).
    - ``max_conflict``: ``verify_max_conflict``, or ``CONFLICT_OVER_RIGHT`` times the upper
      quartile of the conflict of the run's right alignments where that is more (a sensor or
      scene whose right poses show more conflict than the setting allows: mixed pixels,
      porous vegetation, moving people). A registered step skips the single-object rule,
      so its bar rests on the pairs the odometry agreed with only, not on those a triangle
      of registrations showed right: quickshack with KISS-ICP, whose triangles set the bar
      from its 21st keyframe, put two steps 2.6-3 m off into the graph (the sensor moved
      5 cm; conflict 0.052 and 0.083) and a false loop followed.
    - ``odom_slack_m``, ``odom_drift_per_m``: the odometry check allows a floor plus a drift
      per metre of path: ``odom_check_drift`` until the run measured its odometry, then
      ``DRIFT_OVER_MEASURED`` times what it measured. The floor is ``odom_check_slack_m``
      (an odometry of unknown quality, a sensor offset from its frame) until most of the run's
      pairs agreed with the odometry (:attr:`Learned.odometry_agrees`), and then, for verified
      loops, ``PINNED_M``: what a right loop is.
    """
    c = config
    drift, slack = c.odom_check_drift, c.odom_check_slack_m
    max_conflict = c.verify_max_conflict
    if learned is not None:
        if math.isfinite(learned.drift_per_m):
            drift = DRIFT_OVER_MEASURED * learned.drift_per_m
        if learned.odometry_agrees and c.verify:
            slack = min(slack, PINNED_M)
        right_q75 = learned.agreed_conflict_q75 if step else learned.conflict_q75
        if math.isfinite(right_q75):
            max_conflict = max(max_conflict, CONFLICT_OVER_RIGHT * right_q75)
    return Bars(
        min_coarse_overlap=c.verify_min_coarse_overlap,
        min_overlap=c.verify_min_overlap,
        known_place_overlap=KNOWN_PLACE_SHARE * c.verify_min_overlap,
        max_rmse=c.verify_max_rmse,
        max_conflict=max_conflict,
        known_place_conflict=KNOWN_PLACE_CONFLICT * max_conflict,
        min_constraint=c.verify_min_constraint,
        min_spread=c.verify_min_spread,
        single_object_overlap=c.verify_single_object_overlap,
        single_object_conflict=max_conflict / 2.0,
        max_drift_m=c.verify_max_drift,
        max_drift_deg_per_probe=c.verify_max_drift_deg,
        pinned_m=PINNED_M,
        pinned_deg=PINNED_DEG,
        odom_slack_m=slack if c.odom_check_drift > 0.0 else math.inf,
        odom_drift_per_m=drift,
    )


Test = Callable[[Any, Bars], bool]
Explain = Callable[[Any, Bars], str]


@dataclass(frozen=True)
class Rule:
    """One rule: its reason, stage, what it reads, the test and its reading.

    Attributes:
        reason: the reason a refusal carries (its own: no two rules share one).
        stage: ``'coarse'``, ``'fine'`` or ``'context'`` (see the module docstring).
        reads: the evidence fields the test may read.
        passes: ``passes(measures, bars)``: the candidate passes this rule.
        explain: the refusal's reading, with the values and the bar.
        doc: what the rule asks, one line.
    """

    reason: Reason
    stage: Stage
    reads: tuple[str, ...]
    passes: Test
    explain: Explain
    doc: str


def _flag(value: float) -> bool:
    return value == 1.0


def _within(value: float, allowed: float) -> bool:
    """NaN (not applicable) passes."""
    return math.isnan(value) or value <= allowed


RULES: tuple[Rule, ...] = (
    Rule('no_cloud', 'coarse', ('cloud',), lambda m, b: _flag(m.cloud),
         lambda m, b: 'the candidate has no stored keyframe cloud',
         'the candidate has a keyframe cloud to register (evicted or never saved: none)'),
    Rule('too_sparse', 'coarse', ('usable',), lambda m, b: _flag(m.usable),
         lambda m, b: 'fewer than 10 points or coarse structure points in a cloud',
         'both clouds hold at least 10 points and 10 coarse structure points'),
    Rule('coarse_overlap', 'coarse', ('coarse_overlap',),
         lambda m, b: m.coarse_overlap >= b.min_coarse_overlap,
         lambda m, b: f'coarse_overlap {m.coarse_overlap:.3f} < {b.min_coarse_overlap:.3f}',
         'the coarse stage aligned at least verify_min_coarse_overlap of the structure'),
    Rule('not_converged', 'fine', ('converged',), lambda m, b: _flag(m.converged),
         lambda m, b: 'the fine registration did not converge',
         'the fine registration converged (or stood still when resumed)'),
    Rule('overlap', 'fine', ('overlap', 'known_place'),
         lambda m, b: (m.overlap >= b.min_overlap
                       or (m.overlap >= b.known_place_overlap and _flag(m.known_place))),
         lambda m, b: f'overlap {m.overlap:.3f} < {b.min_overlap:.3f}',
         'at least verify_min_overlap of the structure supports the pose both ways '
         '(KNOWN_PLACE_SHARE of it where the pose graph predicted the place)'),
    Rule('rmse', 'fine', ('rmse',), lambda m, b: m.rmse <= b.max_rmse,
         lambda m, b: f'rmse {m.rmse:.3f} > {b.max_rmse:.3f} m',
         'the supporting points lie within verify_max_rmse of their planes (RMS)'),
    Rule('conflict', 'fine', ('conflict', 'known_place'),
         lambda m, b: (m.conflict <= b.max_conflict
                       or (m.conflict <= b.known_place_conflict and _flag(m.known_place))),
         lambda m, b: (f'conflict {m.conflict:.3f} > {b.max_conflict:.3f}'
                       + (f' (at the place the graph predicted {b.known_place_conflict:.3f})'
                          if _flag(m.known_place) else '')),
         'at most verify_max_conflict of either scan lies in space the other saw through '
         '(KNOWN_PLACE_CONFLICT times it where the pose graph predicted the place)'),
    Rule('constraint', 'fine', ('constraint', 'known_place', 'constraint_near'),
         lambda m, b: (m.constraint >= b.min_constraint
                       or (_flag(m.known_place) and m.constraint_near >= b.min_constraint)),
         lambda m, b: f'constraint {m.constraint:.4f} < {b.min_constraint:.4f}',
         'the structure pins the horizontal position and heading (at a known place with '
         'its own range as the heading lever)'),
    Rule('single_object', 'fine', ('step', 'spread', 'known_place', 'overlap', 'conflict'),
         lambda m, b: (_flag(m.step) or m.spread >= b.min_spread or _flag(m.known_place)
                       or (m.overlap >= b.single_object_overlap
                           and m.conflict <= b.single_object_conflict)),
         lambda m, b: f'spread {m.spread:.4f} < {b.min_spread:.4f}',
         'the pose rests on more than one object, or on one the pose graph predicted, or on '
         'one with more overlap and half the conflict; a registered step skips it'),
    Rule('unstable', 'fine', ('drift_m', 'drift_deg', 'drift_turn_deg'),
         lambda m, b: (m.drift_m <= b.max_drift_m and m.drift_deg
                       <= b.max_drift_deg_per_probe * m.drift_turn_deg / PROBE_DEG),
         lambda m, b: (f'restarts drifted {m.drift_m:.2f} m / {m.drift_deg:.2f} deg '
                       f'(at most {b.max_drift_m:.2f} m / '
                       f'{b.max_drift_deg_per_probe * m.drift_turn_deg / PROBE_DEG:.2f} deg)'),
         'restarts one voxel and a little turn off return to the pose'),
    Rule('pinned', 'fine', ('pinned_m', 'pinned_deg'),
         lambda m, b: m.pinned_m <= b.pinned_m and m.pinned_deg <= b.pinned_deg,
         lambda m, b: (f'two sigmas {m.pinned_m:.2f} m / {m.pinned_deg:.2f} deg beyond '
                       f'{b.pinned_m:g} m / {b.pinned_deg:g} deg'),
         "the loop's own covariance pins every direction within what a right loop is"),
    Rule('odometry', 'context', ('odom_error_m', 'odom_allowed_m'),
         lambda m, b: _within(m.odom_error_m, m.odom_allowed_m),
         lambda m, b: f'{m.odom_error_m:.2f} m from the odometry (allowed '
                      f'{m.odom_allowed_m:.2f} m)',
         "this session's odometry between the two keyframes allows the loop"),
    Rule('graph_heading', 'context', ('graph_turn_deg', 'graph_turn_tol_deg'),
         lambda m, b: _within(m.graph_turn_deg, m.graph_turn_tol_deg),
         lambda m, b: f'turns {m.graph_turn_deg:.1f} deg from the pose graph (tolerance '
                      f'{m.graph_turn_tol_deg:.1f} deg)',
         "the loop keeps the pose graph's relative heading within its tolerance"),
    Rule('graph_position', 'context', ('graph_stray_m', 'graph_stray_allowed_m'),
         lambda m, b: _within(m.graph_stray_m, m.graph_stray_allowed_m),
         lambda m, b: f'moves the view {m.graph_stray_m:.2f} m from the pose graph (allowed '
                      f'{m.graph_stray_allowed_m:.2f} m)',
         "the loop puts the query's view where the pose graph predicted it"),
)
assert tuple(r.reason for r in RULES) == RULE_REASONS[1:], 'RULES and reasons.Reason differ'


class Measures:
    """Evidence fields read by attribute: those given (or, in a subclass, measured on first
    read and then kept in ``__dict__``, as ``functools.cached_property`` does); a field nobody
    measured or gave reads NaN (the rules reading it pass or fail as they define)."""

    def __init__(self, **given: float) -> None:
        for name, value in given.items():
            if name not in EVIDENCE_FIELDS:
                raise TypeError(f'{name!r} is no evidence field')
            setattr(self, name, float(value))

    def __getattr__(self, name: str) -> float:
        if name in EVIDENCE_FIELDS:
            return math.nan
        raise AttributeError(name)


@dataclass(frozen=True)
class Verdict:
    """What the judge concluded.

    Attributes:
        reason: ``'verified'`` or the reason of the first rule that failed.
        evidence: what was measured.
        detail: the failed rule's reading (empty when verified).
    """

    reason: Reason
    evidence: Evidence
    detail: str = ''

    @property
    def verified(self) -> bool:
        """No rule refused the candidate."""
        return self.reason == 'verified'


def evidence_of(measures: Measures) -> Evidence:
    """The evidence fields ``measures`` holds so far (measured or given; NaN otherwise)."""
    held = vars(measures)
    return Evidence(**{k: float(held[k]) for k in EVIDENCE_FIELDS if k in held})


def judge(measures: Measures, limits: Bars, stage: Stage) -> Verdict:
    """Run the rules of ``stage`` on ``measures`` in order; the first that fails refuses.

    Args:
        measures: the candidate's measures, read by attribute (see :func:`evidence_of`).
        limits: the thresholds (:func:`bars`).
        stage: which rules to run.
    """
    for rule in RULES:
        if rule.stage == stage and not rule.passes(measures, limits):
            return Verdict(rule.reason, evidence_of(measures), rule.explain(measures, limits))
    return Verdict('verified', evidence_of(measures))
