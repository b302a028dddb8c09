"""The one judge: its rule table, its thresholds and the evidence it keeps."""

from __future__ import annotations

import math
from functools import cached_property

import pytest

from solid_ros.core.config import SolidConfig
from solid_ros.core.reasons import RULE_REASONS
from solid_ros.core.results import EVIDENCE_FIELDS
from solid_ros.core.verification.calibration import Learned
from solid_ros.core.verification.judge import (
    DRIFT_OVER_MEASURED,
    KNOWN_PLACE_CONFLICT,
    KNOWN_PLACE_SHARE,
    PINNED_M,
    RULES,
    STAGES,
    Measures,
    bars,
    evidence_of,
    judge,
)

CFG = SolidConfig()
BARS = bars(CFG)
# A pose that passes every fine rule with the default settings.
GOOD = dict(converged=1.0, overlap=0.6, rmse=0.05, conflict=0.01, constraint=0.02,
            spread=0.01, drift_m=0.01, drift_deg=0.1, drift_turn_deg=2.0, pinned_m=0.1,
            pinned_deg=0.5)


def test_every_rule_has_its_own_reason_in_the_vocabulary_order() -> None:
    reasons = [r.reason for r in RULES]
    assert len(set(reasons)) == len(reasons)
    assert tuple(reasons) == RULE_REASONS[1:]  # 'verified' first, then the rules
    assert [STAGES.index(r.stage) for r in RULES] == sorted(STAGES.index(r.stage) for r in RULES)
    for rule in RULES:
        assert set(rule.reads) <= set(EVIDENCE_FIELDS), rule.reason
        assert rule.doc


def test_a_pose_that_passes_every_rule_is_verified_and_keeps_what_was_read() -> None:
    verdict = judge(Measures(**GOOD), BARS, 'fine')
    assert verdict.verified and verdict.detail == ''
    assert verdict.evidence.overlap == 0.6 and verdict.evidence.pinned_deg == 0.5
    assert math.isnan(verdict.evidence.odom_error_m)  # never given: not measured


@pytest.mark.parametrize(('field', 'value', 'reason'), [
    ('converged', 0.0, 'not_converged'), ('overlap', 0.2, 'overlap'), ('rmse', 0.5, 'rmse'),
    ('conflict', 0.2, 'conflict'), ('constraint', 0.001, 'constraint'),
    ('drift_m', 1.0, 'unstable'), ('pinned_deg', 5.0, 'pinned')])
def test_the_first_failing_rule_names_the_refusal_with_its_reading(
        field: str, value: float, reason: str) -> None:
    verdict = judge(Measures(**{**GOOD, field: value}), BARS, 'fine')
    assert verdict.reason == reason and not verdict.verified
    assert verdict.detail  # the rule's reading, with the value and the bar


def test_a_rule_reads_what_it_needs_and_no_more() -> None:
    class Counting(Measures):
        read: list[str] = []

        @cached_property
        def overlap(self) -> float:
            self.read.append('overlap')
            return 0.1

        @cached_property
        def conflict(self) -> float:  # never reached: the overlap rule refuses first
            self.read.append('conflict')
            return 0.0

    m = Counting(converged=1.0)
    verdict = judge(m, BARS, 'fine')
    assert verdict.reason == 'overlap' and m.read == ['overlap']
    assert math.isnan(verdict.evidence.conflict) and verdict.evidence.overlap == 0.1
    assert evidence_of(m).overlap == 0.1


def test_a_known_place_asks_less_overlap_and_no_spread() -> None:
    low = KNOWN_PLACE_SHARE * CFG.verify_min_overlap + 0.01
    assert judge(Measures(**{**GOOD, 'overlap': low}), BARS, 'fine').reason == 'overlap'
    known = {**GOOD, 'overlap': low, 'known_place': 1.0, 'spread': 0.0}
    assert judge(Measures(**known), BARS, 'fine').verified
    one_object = {**GOOD, 'spread': 0.0, 'overlap': 0.4}
    assert judge(Measures(**one_object), BARS, 'fine').reason == 'single_object'


def test_a_known_place_tolerates_more_conflict_but_not_any() -> None:
    # A car parked or gone since the last visit: more conflict than the bar, at the place the
    # graph predicted.
    changed = {**GOOD, 'conflict': 1.5 * BARS.max_conflict}
    refused = judge(Measures(**{**changed, 'known_place': 0.0}), BARS, 'fine')
    assert refused.reason == 'conflict' and 'graph' not in refused.detail
    assert judge(Measures(**{**changed, 'known_place': 1.0}), BARS, 'fine').verified
    beyond = {**GOOD, 'conflict': 1.01 * KNOWN_PLACE_CONFLICT * BARS.max_conflict,
              'known_place': 1.0}
    verdict = judge(Measures(**beyond), BARS, 'fine')
    assert verdict.reason == 'conflict'
    assert f'{BARS.known_place_conflict:.3f}' in verdict.detail


def test_context_rules_pass_where_nothing_was_measured_and_refuse_what_disagrees() -> None:
    assert judge(Measures(), BARS, 'context').verified
    far = Measures(odom_error_m=12.0, odom_allowed_m=10.0)
    assert judge(far, BARS, 'context').reason == 'odometry'
    turned = Measures(graph_turn_deg=20.0, graph_turn_tol_deg=5.0)
    assert judge(turned, BARS, 'context').reason == 'graph_heading'
    strayed = Measures(graph_stray_m=3.0, graph_stray_allowed_m=2.0)
    assert judge(strayed, BARS, 'context').reason == 'graph_position'


def test_what_the_run_learned_sets_the_conflict_bar_and_the_odometry_allowance() -> None:
    assert bars(CFG, Learned()) == BARS  # nothing learned yet: the settings
    # Right alignments with more conflict than the setting allows raise the bar (and the
    # single-object bar, half of it, to their upper quartile).
    noisy = bars(CFG, Learned(30, 20, 0.04, 20, 0.05, agreed=20, agreed_conflict_q75=0.02))
    assert noisy.max_conflict == pytest.approx(0.08) and noisy.single_object_conflict == 0.04
    # A registered step's bar rests on the pairs the odometry agreed with only.
    assert bars(CFG, Learned(30, 20, 0.04, 20, 0.05, agreed=20, agreed_conflict_q75=0.02),
                step=True).max_conflict == pytest.approx(0.04)
    assert bars(CFG, Learned(30, 20, 0.04, 20, 0.05), step=True).max_conflict == \
        CFG.verify_max_conflict  # none agreed: the setting
    # Most pairs agreed with the odometry: the floor is what a right loop is, and the drift
    # per metre twice what was measured.
    assert noisy.odom_allowed(100.0) == pytest.approx(PINNED_M + DRIFT_OVER_MEASURED * 5.0)
    # Clean right alignments never lower the conflict bar below the setting.
    assert bars(CFG, Learned(30, 20, 0.001, 20, 0.01)).max_conflict == CFG.verify_max_conflict
    # An odometry that mostly disagreed keeps the setting's floor, however many pairs a
    # triangle showed right.
    lost = bars(CFG, Learned(80, 60, 0.03, 5, math.nan, agreed=12))
    assert lost.odom_allowed(100.0) == pytest.approx(CFG.odom_check_slack_m
                                                     + CFG.odom_check_drift * 100.0)
    assert bars(CFG.replace(odom_check_drift=0.0)).odom_allowed(1.0) == math.inf
