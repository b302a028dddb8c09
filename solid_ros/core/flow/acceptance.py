"""Acceptance: a proposal's hits judged, by registration or by the descriptor alone.

Acceptance with ``verify`` (see :mod:`solid_ros.core.verification.verifier`): every candidate goes
through the coarse registration; those that pass are verified in order of coarse overlap,
best first, until ``max_candidates`` distinct places (outside each other's
``margin_neighbourhood``) are verified; then a loaded map's hits, and peers', until as many
of theirs are. Without ``verify``: candidates in distance order, each
a distinct place, at most ``max_candidates``. A peer's cloud is fetched (:data:`CloudFetcher`)
only when its hit is to be registered. Nothing is registered while ``gap_blocked`` (the
verification stage's ``min_loop_gap``, :mod:`solid_ros.core.flow.verify_stage`).

Odometry check (:mod:`solid_ros.core.odometry.track`): a loop between two keyframes of this session
that both came with a pose is refused (reason ``'odometry'``) when its translation differs
from the odometry's by more than the judge's allowance over the path driven between them
(``odom_check_slack_m`` plus a drift per metre: ``odom_check_drift`` until the run has measured
its odometry's, :mod:`solid_ros.core.verification.calibration`); with ``verify`` the next
candidate is tried instead.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.hits import hypotheses_kept
from solid_ros.core.candidates.proposal import Hit, Proposal
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.database.descriptors import PEER_SEQ_BASE
from solid_ros.core.descriptor.matching import estimate_yaw, heading_hypotheses
from solid_ros.core.flow.place import HitPlace, same_place
from solid_ros.core.flow.state import DetectorState
from solid_ros.core.geometry import rot_z
from solid_ros.core.odometry.track import disagreement
from solid_ros.core.reasons import Reason
from solid_ros.core.results import NAN_COV, LoopCandidate, Match
from solid_ros.core.verification.judge import Measures, judge
from solid_ros.core.verification.prepared import Query
from solid_ros.core.verification.verifier import CoarseResult, Verification

__all__ = ['Acceptor', 'CloudFetcher']

FloatArray = npt.NDArray[np.float64]
# (robot = its session id, index, stamp_ns) of a peer's keyframe -> its cloud, or the reason
# there is none.
CloudFetcher = Callable[[int, int, int], 'KeyframeCloud | Reason']


class Acceptor:
    """Judges a proposal's hits into loop candidates.

    Args:
        state: the detector's shared state.
        loaded: sessions loaded from a database file (their clouds came with it or not at
            all: never fetched).

    Attributes:
        reasons: verification outcomes so far.
        fetch_cloud: where clouds of other robots' keyframes come from (the node asks the
            owner); it returns the cloud or the reason there is none. None: such candidates
            stay unverified.
    """

    def __init__(self, state: DetectorState, loaded: set[int]) -> None:
        self._state = state
        self._loaded = loaded
        self.reasons: Counter[str] = Counter()
        self.fetch_cloud: CloudFetcher | None = None

    def candidate(self, proposal: Proposal, hit: Hit, yaw: float,
                  result: Verification | None) -> LoopCandidate:
        """The loop candidate of ``hit`` (sensor frames): unverified at ``yaw`` without a
        ``result``."""
        mount = self._state.mount
        m = hit.match
        if result is None:
            T = np.eye(4)
            T[:3, :3] = rot_z(yaw)
            return LoopCandidate(proposal.query_index, m.index, proposal.stamp_ns, m.stamp_ns,
                                 m.session, m.distance, yaw, hit.margin,
                                 pose=mount.unlevel_pose(T), source=hit.source)
        cov: tuple[float, ...] = NAN_COV
        if result.covariance is not None:
            cov = tuple(float(v) for v in mount.unlevel_cov(result.covariance).ravel())
        return LoopCandidate(
            proposal.query_index, m.index, proposal.stamp_ns, m.stamp_ns, m.session,
            m.distance, result.yaw if result.verified else yaw, hit.margin,
            verified=result.verified, pose=mount.unlevel_pose(result.T),
            fitness=result.fitness, covariance=cov, reason=result.reason,
            evidence=result.evidence, source=hit.source, detail=result.detail)

    def _odometry(self, proposal: Proposal, match: Match, T_mq: FloatArray
                  ) -> tuple[float, float]:
        """The odometry check of a loop ``T_mq`` (sensor frames, not levelled) from the query
        to ``match``: how far its translation is from this session's odometry, and what the
        judge's bars allow over the path driven between them; NaN where the odometry says
        nothing (check off, another session, no pose, a jump of the odometry between)."""
        state = self._state
        cfg = state.config
        if (cfg.odom_check_drift <= 0.0 or match.session != cfg.session_id
                or proposal.pose is None):
            return math.nan, math.nan
        pose_m = state.database.pose(match.seq)
        path = state.path.between(match.index, proposal.query_index)
        if pose_m is None or path is None:
            return math.nan, math.nan
        return disagreement(T_mq, proposal.pose, pose_m), state.bars.odom_allowed(path)

    def _place(self, proposal: Proposal, hit: Hit, centre: FloatArray) -> HitPlace:
        """What the judge's context rules ask of a hit's place (levelled poses)."""
        def odom(T_mq: FloatArray) -> tuple[float, float]:
            return self._odometry(proposal, hit.match, self._state.mount.unlevel(T_mq))

        return HitPlace(hit, centre, self._state.config, odom)

    def by_descriptor(self, proposal: Proposal) -> list[LoopCandidate]:
        """Without verification only the context rules judge (the odometry: no pose to place
        in a graph)."""
        mode = self._state.config.heading_match
        bars = self._state.bars
        out = []
        for h in proposal.hits:
            c = self.candidate(proposal, h, estimate_yaw(proposal.heading, h.heading, mode), None)
            error, allowed = self._odometry(proposal, h.match, c.matrix())
            verdict = judge(Measures(odom_error_m=error, odom_allowed_m=allowed), bars,
                            'context')
            if not verdict.verified:
                c = replace(c, reason=verdict.reason, evidence=verdict.evidence,
                            detail=verdict.detail)
                self.reasons[verdict.reason] += 1
            out.append(c)
        return out

    def by_registration(self, proposal: Proposal, query: Query, gap_blocked: bool,
                        more: Callable[[], list[Hit]] | None = None,
                        placed: Callable[[], list[Hit]] | None = None
                        ) -> list[LoopCandidate]:
        """Verify the proposal's hits group by group until ``max_candidates`` places are
        verified; ``query``: its cloud prepared; ``more``: hits to try last, asked only if it
        comes to them; ``placed``: aligned peers' keyframes by position, asked only when the
        peers' hits verified nothing."""
        state = self._state
        clouds, fetched = self._candidate_clouds(proposal, gap_blocked)
        if query.usable:
            state.clouds.put(proposal.seq, query.keyframe_cloud())
        state.clouds.drop_before(state.database.oldest_seq)
        results: dict[int, Verification] = dict(fetched)
        yaws: dict[int, float] = {}
        verified: list[Match] = []
        passed: dict[int, CoarseResult] = {}  # coarse results kept for the map's budget
        # The graph's near keyframes first: registered from its pose they mostly verify at
        # once, and the rest are then not needed (max_candidates); then those that saw the
        # query's place from elsewhere, then the descriptor's others, and last, asked only
        # now, those that share the query's structure.
        hits = list(proposal.hits)
        peer = [h.match.seq >= PEER_SEQ_BASE for h in hits]
        for group in ([i for i, h in enumerate(hits) if h.near],
                      [i for i, h in enumerate(hits) if h.view and not h.near],
                      [i for i, h in enumerate(hits) if not (h.near or h.view or peer[i])]):
            if gap_blocked or len(verified) >= state.config.max_candidates:
                break
            self._register(proposal, query, hits, group, clouds, results, yaws, verified,
                           passed)
        # A loaded map's places have a budget of their own: a loop into the map is what
        # places this session in it, and an own keyframe near the query that verified first
        # left none to it (hku1's second half in its first half's map: 8 of the 15 revisits
        # without a loop into the map had one that verifies at the reference pose).
        own = state.config.session_id
        mapped = [i for i, h in enumerate(hits) if not peer[i] and h.match.session != own]
        if (not gap_blocked and mapped and len(verified) >= state.config.max_candidates
                and not any(m.session != own for m in verified)):
            self._register(proposal, query, hits, [i for i in mapped if i not in results],
                           clouds, results, yaws, [], passed)
        # Peers' places have a budget of their own: the graph's near keyframes verify first
        # and would otherwise leave none to the inter-robot loops a fleet is placed by.
        found: list[Match] = []
        if not gap_blocked and any(peer):
            self._register(proposal, query, hits, [i for i in range(len(hits)) if peer[i]],
                           clouds, results, yaws, found)
        if placed is not None and not gap_blocked and not found:
            start = len(hits)
            self._append_hits(hits, placed(), clouds, results)
            self._register(proposal, query, hits, list(range(start, len(hits))), clouds,
                           results, yaws, found)
        if more is not None and not gap_blocked and len(verified) < state.config.max_candidates:
            extra = more()
            start = len(hits)
            hits += extra
            clouds += [state.clouds.get(h.match.seq) for h in extra]
            self._register(proposal, query, hits, list(range(start, len(hits))), clouds,
                           results, yaws, verified)
        out = []
        for i, hit in enumerate(hits):
            res = results.get(i)
            if res is not None:
                self.reasons[res.reason] += 1
                out.append(self.candidate(proposal, hit, yaws.get(i, 0.0), res))
        out.sort(key=lambda c: (not c.verified, -_nan_to(c.overlap, -1.0)))
        return out

    def _candidate_clouds(self, proposal: Proposal, gap_blocked: bool
                          ) -> tuple[list[KeyframeCloud | None], dict[int, Verification]]:
        """Each hit's stored cloud (a peer's fetched when needed), and the verdicts of peer
        clouds that did not come."""
        clouds: list[KeyframeCloud | None] = []
        fetched: dict[int, Verification] = {}
        for i, h in enumerate(proposal.hits):
            cloud, missing = self._cloud_of(h, gap_blocked)
            if missing is not None:
                fetched[i] = missing
            clouds.append(cloud)
        if proposal.cloud_points is None:  # process_descriptor: nothing to register
            clouds = [None] * len(clouds)
        return clouds, fetched

    def _cloud_of(self, hit: Hit, gap_blocked: bool
                  ) -> tuple[KeyframeCloud | None, Verification | None]:
        """A hit's stored cloud (a peer's fetched when needed), or the verdict of a peer
        cloud that did not come."""
        clouds = self._state.clouds
        cloud = clouds.get(hit.match.seq)
        if (cloud is None and self.fetch_cloud is not None and not gap_blocked
                and hit.match.session != self._state.config.session_id
                and hit.match.session not in self._loaded):
            got = self.fetch_cloud(hit.match.session, hit.match.index, hit.match.stamp_ns)
            if not isinstance(got, KeyframeCloud):
                return None, Verification(False, got, np.eye(4))
            clouds.put(hit.match.seq, got)
            cloud = got
        return cloud, None

    def _append_hits(self, hits: list[Hit], extra: list[Hit],
                     clouds: list[KeyframeCloud | None],
                     results: dict[int, Verification]) -> None:
        """``extra`` appended to ``hits``, their clouds (fetched) to ``clouds`` and the
        verdicts of those that did not come to ``results``."""
        for h in extra:
            cloud, missing = self._cloud_of(h, False)
            if missing is not None:
                results[len(clouds)] = missing
            clouds.append(cloud)
        hits += extra

    def _register(self, proposal: Proposal, query: Query, hits: list[Hit], group: list[int],
                  clouds: list[KeyframeCloud | None], results: dict[int, Verification],
                  yaws: dict[int, float], verified: list[Match],
                  passed: dict[int, CoarseResult] | None = None) -> None:
        """Coarse stage of the hits ``group``, then the fine stage in order of coarse overlap
        until ``max_candidates`` distinct places are verified (``verified`` grows); ``hits``: the
        proposal's and those joined since, by index; ``passed``
        keeps the coarse results that passed for a later call (the map's own budget)."""
        verifier = self._state.verifier
        assert verifier is not None
        cfg = self._state.config
        coarse = []
        for i in group:
            hit = hits[i]
            hyps = heading_hypotheses(proposal.heading, hit.heading, cfg.verify_hypotheses,
                                      cfg.heading_match)
            yaws[i] = hyps[0][0] if hyps else 0.0
            if i in results:  # a peer's cloud that did not come
                continue
            # The graph's guess first; the heading hypotheses when drift put it too far off
            # (those a loop could keep: within the graph's heading tolerance of its guess).
            c = None if passed is None else passed.get(i)
            if c is None:
                starts = hypotheses_kept(hit, [y for y, _ in hyps])
                c = verifier.coarse(query, (hit.match.session, hit.match.seq), clouds[i],
                                    starts, () if hit.guess is None else (hit.guess,))
            if c.rejection is not None:
                results[i] = c.rejection
            else:
                coarse.append((i, c))
                if passed is not None:
                    passed[i] = c
        coarse.sort(key=lambda ic: -ic[1].coarse_overlap)
        centre = query.points[:, :3].mean(axis=0) if len(query.points) else np.zeros(3)
        for i, c in coarse:
            hit = hits[i]
            if len(verified) >= cfg.max_candidates:
                break  # enough distinct places: the rest stay unverified ('skipped')
            if any(same_place(hit.match, v, cfg.margin_neighbourhood) for v in verified):
                continue
            fine = verifier.fine(query, c, place=self._place(proposal, hit, centre))
            results[i] = fine
            if fine.verified:
                verified.append(hit.match)


def _nan_to(value: float, default: float) -> float:
    return default if math.isnan(value) else value
