"""Verification stage: graph candidates, the registered step, loop gap and budgets, calibration.

:meth:`VerifyStage.verify` takes one proposal of the descriptor stage
(:mod:`solid_ros.core.flow.proposer`), adds the pose graph's candidates, has them judged
(:mod:`solid_ros.core.flow.acceptance`) and keeps the loops to publish: at most
``max_candidates`` distinct places each of this session's, a loaded map's and peers', and
nothing within ``min_loop_gap`` queries of the last published loop.

Candidates by position (:mod:`solid_ros.core.candidates.position`): given the pose graph's estimate
(a :class:`~solid_ros.core.candidates.position.GraphHint`, from
:class:`~solid_ros.core.flow.closure.LoopClosure`
or the node's graph snapshot) with ``verify`` and ``graph_candidates`` on, :meth:`verify` adds
the earlier keyframes of this session near the query in the corrected estimate (source
``'graph'``), and, when none of those saw the query's place and the query's view is
one-sided, the keyframes whose view centre (their cloud's centroid) lies near the query's: a
narrow field of view sees the place ahead, so a street driven the other way is seen from
keyframes tens of metres off. Every candidate
the graph knows is registered from the graph's relative pose first, then from the heading
hypotheses that turn no farther from it than the graph's heading tolerance (a loop beyond it is
refused: :func:`~solid_ros.core.candidates.hits.hypotheses_kept`). Those near keyframes (the
graph's, and the descriptor's among them) are verified first, then those by view; the
descriptor's other candidates only when they leave fewer than ``max_candidates`` places
verified. Without a hint nothing changes.

Registered steps (``backend_step_registration`` 'on'; 'auto' is resolved by the replay, the
node and a :class:`~solid_ros.core.flow.closure.LoopClosure` given its odometry: on with
KISS-ICP run on the same clouds): :meth:`verify` registers the keyframe to this
session's previous one, started from the odometry step, through the same coarse and fine
stages and tests except the single-object test (the place is known); with a hint it does so
before the candidates and the graph predicts the query from that step, not from the odometry's
(a lost scan-only odometry's step can be metres off). It returns it as
:attr:`ScanResult.step` for the pose graph (never published).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.covisibility import StructureIndex, coarse_structure
from solid_ros.core.candidates.hits import (
    placed_peer_hits,
    shared_hits,
    view_centre,
    with_graph_hits,
)
from solid_ros.core.candidates.position import GraphHint
from solid_ros.core.candidates.proposal import Hit, Proposal
from solid_ros.core.candidates.views import ViewCentres
from solid_ros.core.database.descriptors import DescriptorDatabase
from solid_ros.core.flow.acceptance import Acceptor
from solid_ros.core.flow.own_pairs import calibrate
from solid_ros.core.flow.state import DetectorState
from solid_ros.core.geometry import vector_to_matrix
from solid_ros.core.results import LoopCandidate, Match, ScanResult, StageTimes
from solid_ros.core.verification.prepared import Query

__all__ = ['VerifyStage']

FloatArray = npt.NDArray[np.float64]


class VerifyStage:
    """The verification stage of a detector.

    Args:
        state: the detector's shared state.
        acceptor: judges the candidates.
        loaded: sessions loaded from a database file (a map to find this session in).

    Attributes:
        map_seqs: the loaded map's keyframes by (session, index), for candidates by
            position in it.
        map_views: their view centres (from the clouds saved with them), for candidates by
            view in it.
    """

    def __init__(self, state: DetectorState, acceptor: Acceptor, loaded: set[int]) -> None:
        self._state = state
        self._acceptor = acceptor
        self.map_seqs = _loaded_seqs(state.database, loaded)
        self.map_views = ViewCentres.of({
            key: view_centre(cloud.points, state.mount) for key, seq in self.map_seqs.items()
            if (cloud := state.clouds.get(seq)) is not None and len(cloud.points)})
        self._last_loop_query: int | None = None
        # Coarse structure of each own keyframe, for candidates by what they share
        # (solid_ros.core.candidates.covisibility): kept only with the back end, for as many
        # keyframes as clouds (a keyframe without its cloud cannot be verified), a tenth of
        # their size.
        self._structures = StructureIndex(state.config.cloud_capacity)
        # The step registered before the keyframe's candidates, by query index (with_step
        # hands it on instead of registering it again).
        self._step: tuple[int, LoopCandidate | None, float] | None = None
        # The last keyframe's prepared cloud, by query index (its step registers from it).
        self._query: tuple[int, Query] | None = None

    def reset(self) -> None:
        """Forget the loaded map, the last loop, the pending step, the prepared cloud and
        the structures."""
        self.map_seqs = {}
        self.map_views = ViewCentres.of({})
        self._last_loop_query = None
        self._step = None
        self._query = None
        self._structures.clear()

    def verify(self, proposal: Proposal, hint: GraphHint | None = None, *,
               step: bool = True) -> ScanResult:
        """:meth:`~solid_ros.core.flow.detector.LoopDetector.verify`."""
        t0 = time.perf_counter()
        state = self._state
        cfg = state.config
        query = self._prepared(proposal)
        structure = None
        if query is not None and cfg.backend and cfg.graph_candidates > 0:
            structure = self._structure_of(query)  # only the back end's hint uses it
        more: Callable[[], list[Hit]] | None = None
        placed: Callable[[], list[Hit]] | None = None
        if hint is not None and cfg.graph_candidates > 0 and query is not None:
            hint = self.registered_hint(proposal, hint)
            # The graph's candidates join a copy: the caller's proposal stays as proposed.
            proposal = replace(proposal, hits=tuple(with_graph_hits(
                proposal, hint, cfg, state.database, state.own_seqs, state.views, state.mount,
                self.map_seqs, self.map_views)))
            if structure is not None:
                more = partial(shared_hits, proposal, hint, cfg, state.database,
                               state.own_seqs, state.mount, self._structures, structure)
            placed = partial(placed_peer_hits, proposal, hint, cfg, state.database, state.mount)
        gap_blocked = bool(cfg.min_loop_gap and self._last_loop_query is not None
                           and proposal.query_index - self._last_loop_query < cfg.min_loop_gap)
        if query is None:
            attempts = self._acceptor.by_descriptor(proposal)
        else:
            attempts = self._acceptor.by_registration(proposal, query, gap_blocked, more, placed)
        if structure is not None:  # after its own search: it shares all with itself
            self._structures.add(proposal.query_index, structure)
        taken = self._taken(attempts, gap_blocked)
        if taken:
            self._last_loop_query = proposal.query_index
        if query is not None:
            self._calibrate(proposal, query)
        # The step registered before the candidates is the step stage's time, not theirs.
        early = (self._step[2] if self._step is not None
                 and self._step[0] == proposal.query_index else 0.0)
        times = StageTimes(proposal.describe_ms, proposal.search_ms,
                           (time.perf_counter() - t0) * 1e3 - early)
        result = ScanResult(proposal.stamp_ns, True, proposal.query_index, proposal.pose,
                            tuple(taken), tuple(attempts), proposal.best, times,
                            proposal.descriptor)
        return self.with_step(result, proposal) if step else result

    def _calibrate(self, proposal: Proposal, query: Query) -> None:
        """Register the keyframe to a partner a few metres back along the odometry and teach
        the calibration what a right alignment and the odometry's drift look like here (see
        :mod:`solid_ros.core.verification.calibration`)."""
        state = self._state
        assert state.verifier is not None
        calibrate(state.own, state.verifier, state.calibration, proposal, query,
                  state.config.verify_min_overlap)

    def _prepared(self, proposal: Proposal) -> Query | None:
        """The keyframe's cloud prepared for registration (None without verification), kept
        for the keyframe's registered step (:meth:`with_step`) until the next keyframe."""
        verifier = self._state.verifier
        if verifier is None:
            return None
        if self._query is None or self._query[0] != proposal.query_index:
            points = (proposal.cloud_points if proposal.cloud_points is not None
                      else np.zeros((0, 3)))
            self._query = (proposal.query_index, verifier.prepare(points, proposal.tight))
        return self._query[1]

    def _taken(self, attempts: list[LoopCandidate], gap_blocked: bool) -> list[LoopCandidate]:
        """The accepted ``attempts`` to publish: none while ``gap_blocked``, each a distinct
        place, at most ``max_candidates`` per budget."""
        cfg = self._state.config
        taken: list[LoopCandidate] = []
        for c in attempts:
            if c.reason not in ('verified', 'descriptor'):
                continue
            if gap_blocked:
                break
            if sum(self._budget(t) == self._budget(c) for t in taken) >= cfg.max_candidates:
                continue  # this robot's places, its maps' and peers', each up to the cap
            if any(c.match_session == t.match_session
                   and abs(c.match_index - t.match_index) <= cfg.margin_neighbourhood
                   for t in taken):
                continue
            taken.append(c)
        return taken

    def registered_hint(self, proposal: Proposal, hint: GraphHint) -> GraphHint:
        """``hint`` predicting the query from its registered step instead of the odometry's,
        when a scan-only odometry's steps are registered (``backend_step_registration`` 'on')
        and the step verified; else ``hint`` itself.

        The graph places the previous keyframe well, but a lost KISS-ICP's step from it can
        be far off: on quickshack it put queries 1.5-2.9 m and 23-36 deg from where they
        were (the sensor had moved 2-10 cm), the graph's relative pose of the previous
        keyframe and the match being within 0.05-0.13 m of the reference, and ten right loops
        were refused as too far from the graph's guess. The registration was right within
        0.1 m. The step is registered here, before the candidates, and handed on by
        :meth:`with_step`."""
        if (self._state.config.backend_step_registration != 'on' or proposal.pose is None
                or not len(hint.indices) or int(hint.indices[-1]) != proposal.query_index - 1):
            return hint
        t0 = time.perf_counter()
        step = self._register_step(proposal)
        self._step = (proposal.query_index, step, (time.perf_counter() - t0) * 1e3)
        if step is None:
            return hint
        correction = np.asarray(hint.poses[-1] @ step.matrix()
                                @ np.linalg.inv(vector_to_matrix(proposal.pose)), dtype=np.float64)
        correction.setflags(write=False)  # as the hint's own arrays
        return replace(hint, correction=correction)

    def with_step(self, result: ScanResult, proposal: Proposal) -> ScanResult:
        """``result`` (of :meth:`verify` with ``step=False``) with its registered step, when
        ``backend_step_registration`` is 'on' (else unchanged): registered here, or already
        before the candidates (:meth:`registered_hint`)."""
        if self._state.config.backend_step_registration != 'on':
            return result
        early, self._step = self._step, None
        if early is not None and early[0] == proposal.query_index:
            return replace(result, times=replace(result.times, step=early[2]), step=early[1])
        t0 = time.perf_counter()
        step = self._register_step(proposal)
        # Timed whenever tried: a step that fails a test cost as much as one that passes.
        times = replace(result.times, step=(time.perf_counter() - t0) * 1e3)
        return replace(result, times=times, step=step)

    def _register_step(self, proposal: Proposal) -> LoopCandidate | None:
        """The keyframe registered to this session's previous one from the odometry step
        (the loops' coarse and fine stages and tests); None without a pose, a cloud or a
        verified alignment. It corrects an odometry that ran away between two keyframes."""
        state = self._state
        query = self._prepared(proposal)
        got = (None if state.verifier is None or query is None
               else state.own.step(state.verifier, proposal, query))
        if got is None:
            return None
        fine, seq = got
        _, _, stamp = state.database.match_info(seq)
        hit = Hit(Match(seq, proposal.query_index - 1, state.config.session_id, stamp,
                        math.nan), math.nan, np.zeros(0, dtype=np.float32), 'step')
        return self._acceptor.candidate(proposal, hit, 0.0, fine)

    def _budget(self, c: LoopCandidate) -> str:
        """Whose places a loop counts against ``max_candidates``: this session's, a loaded
        map's or a peer robot's."""
        if c.match_session == self._state.config.session_id:
            return 'own'
        return 'peer' if self._is_peer(c) else 'map'

    def _is_peer(self, c: LoopCandidate) -> bool:
        """A loop to another robot's keyframe (not this session's, not a loaded map's)."""
        return (c.match_session != self._state.config.session_id
                and (c.match_session, c.match_index) not in self.map_seqs)

    def _structure_of(self, query: Query) -> FloatArray:
        """A prepared keyframe's structure on the configuration's coarse grid, sensor frame
        (:func:`~solid_ros.core.candidates.covisibility.coarse_structure`; empty when unusable)."""
        if not query.usable:
            return np.zeros((0, 3))
        out: FloatArray = self._state.mount.to_sensor(coarse_structure(
            query.points, query.structure, self._state.config.verify_coarse_voxel_size))
        return out


def _loaded_seqs(db: DescriptorDatabase, sessions: set[int]) -> dict[tuple[int, int], int]:
    """Sequence numbers of the stored scans of ``sessions`` by ``(session, index)``."""
    out = {}
    for seq in db.stored_seqs() if sessions else []:
        index, session, _ = db.match_info(seq)
        if session in sessions:
            out[(session, index)] = seq
    return out
