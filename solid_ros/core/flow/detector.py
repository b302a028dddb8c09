"""Loop detector: keyframe gating, descriptor, database query, verification, insertion.

One call per scan, :meth:`LoopDetector.process`, levels the scan (sensor mounting), describes
it, queries the database for earlier places (the scan itself is added afterwards, so it never
matches itself), verifies the candidates by registration (``verify``) and returns one
:class:`ScanResult`: whether the scan became a keyframe, the loops to publish, every candidate
looked at, the best descriptor match and the stage times. The detector keeps no per-scan
result of its own, so the node's two threads, the replay and the back end read the same value.
The same work split in two, :meth:`LoopDetector.propose` (descriptor and database) and
:meth:`LoopDetector.verify` (registration), lets a node run verification on another thread;
calling ``verify(propose(...))`` for every kept scan in order gives exactly what ``process``
gives.

Indices: ``query_index`` is the index of the scan among the keyframes this session stored
(0, 1, 2, ...; gated-out scans get none). ``match_index`` is the index of the matched scan in
its own session ``match_session`` (for scans loaded from a file, the index they had there).

Candidates: the ``num_candidates`` nearest stored scans by descriptor distance that are below
``distance_threshold`` and pass the margin test (``min_margin``). The margin of a candidate is
the distance of the nearest scan outside its ``margin_neighbourhood`` minus its own distance
(``math.inf`` when there is none); the search fetches ``num_candidates + 2 *
margin_neighbourhood + 1`` scans so that this next-best distinct place is always among them.

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

Registered steps (``backend_step_registration`` 'on'; 'auto' is resolved by the replay and the
node: on with KISS-ICP run on the same clouds): :meth:`verify` registers the keyframe to this
session's previous one, started from the odometry step, through the same coarse and fine
stages and tests except the single-object test (the place is known); with a hint it does so
before the candidates and the graph predicts the query from that step, not from the odometry's
(a lost scan-only odometry's step can be metres off). It returns it as
:attr:`ScanResult.step` for the pose graph (never published).

Acceptance with ``verify`` (see :mod:`solid_ros.core.verification.verifier`): every candidate goes
through the coarse registration; those that pass are verified in order of coarse overlap,
best first, until ``max_candidates`` distinct places (outside each other's
``margin_neighbourhood``) are verified; then a loaded map's hits, and peers', until as many
of theirs are. Without ``verify``: candidates in distance order, each
a distinct place, at most ``max_candidates``. In both modes nothing is published within
``min_loop_gap`` queries of the last published loop.

Odometry check (:mod:`solid_ros.core.odometry.track`): a loop between two keyframes of this session
that both came with a pose is refused (reason ``'odometry'``) when its translation differs
from the odometry's by more than the judge's allowance over the path driven between them
(``odom_check_slack_m`` plus a drift per metre: ``odom_check_drift`` until the run has measured
its odometry's, :mod:`solid_ros.core.verification.calibration`); with ``verify`` the next
candidate is tried instead.

Unusable clouds: a cloud with no point that is finite and inside the range gate, the FOV clip
and ``max_distance`` (all NaN, all beyond range, empty, ...) would give an all-zero R-SOLiD
that never matches, yet take an index and move the keyframe gate and the exclusion window.
``process`` and ``propose`` refuse it with :class:`CloudError` before anything changes, gated
out or not, as ``process_descriptor`` refuses an all-zero R-SOLiD. Peers' and loaded scans may
still be all zero (the database stores them; they never match).
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.covisibility import StructureIndex, coarse_structure
from solid_ros.core.candidates.hits import (
    hypotheses_kept,
    placed_peer_hits,
    shared_hits,
    view_centre,
    with_graph_hits,
)
from solid_ros.core.candidates.position import GraphHint
from solid_ros.core.candidates.proposal import Hit, Proposal
from solid_ros.core.candidates.views import KeyframeViews, ViewCentres
from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import CloudStore, KeyframeCloud
from solid_ros.core.database.descriptors import PEER_SEQ_BASE, DescriptorDatabase, unit_vector
from solid_ros.core.descriptor.matching import estimate_yaw, heading_hypotheses
from solid_ros.core.descriptor.mount import Mount
from solid_ros.core.descriptor.solid import describe, preprocess, voxel_downsample
from solid_ros.core.errors import CloudError, ConfigError
from solid_ros.core.flow.own_pairs import OwnKeyframes, calibrate
from solid_ros.core.flow.place import HitPlace
from solid_ros.core.geometry import (
    pose_to_vector,
    rot_z,
    rotation_deg,
    vector_to_matrix,
)
from solid_ros.core.odometry.track import OdometryPath, disagreement
from solid_ros.core.reasons import Reason
from solid_ros.core.results import (
    NAN_COV,
    Descriptor,
    LoopCandidate,
    Match,
    ScanResult,
    Source,
    StageTimes,
)
from solid_ros.core.stamps import check_stamp
from solid_ros.core.verification.calibration import Calibration
from solid_ros.core.verification.judge import Bars, Measures, judge
from solid_ros.core.verification.judge import bars as judge_bars
from solid_ros.core.verification.mixed_pixels import drop_mixed_pixels
from solid_ros.core.verification.prepared import Query, coarsened, for_peers
from solid_ros.core.verification.verifier import (
    TIGHT_GRID,
    CoarseResult,
    Verification,
    Verifier,
)

__all__ = ['CloudFetcher', 'LoopCandidate', 'LoopDetector', 'Proposal', 'ScanResult',
           'Source', 'StageTimes']

FloatArray = npt.NDArray[np.float64]
# (robot = its session id, index, stamp_ns) of a peer's keyframe -> its cloud, or the reason
# there is none.
CloudFetcher = Callable[[int, int, int], 'KeyframeCloud | Reason']


class LoopDetector:
    """SOLiD loop-closure detector over a rolling database of keyframes.

    Args:
        config: settings; ``SolidConfig()`` when omitted.
        database: an existing database (e.g. loaded from a file) built with the same
            descriptor settings; a new empty one when omitted.
        clouds: keyframe clouds of ``database`` (e.g. loaded with it); an empty store when
            omitted.
    """

    def __init__(self, config: SolidConfig | None = None,
                 database: DescriptorDatabase | None = None,
                 clouds: CloudStore | None = None) -> None:
        self._config = config if config is not None else SolidConfig()
        cfg = self._config
        self.database = database if database is not None else DescriptorDatabase(cfg)
        self.clouds = clouds if clouds is not None else CloudStore(
            cfg.cloud_capacity, int(cfg.cloud_memory_mb * 1e6))
        self.verifier = Verifier(cfg) if cfg.verify else None
        self._mount = Mount(cfg)
        # The descriptor's gate without the voxel grid (replace() costs about 0.5 ms).
        self._gate_cfg = cfg.replace(voxel_size=0.0)
        self.reasons: Counter[str] = Counter()  # verification outcomes so far
        self._kf_stamp: int | None = None
        self._kf_pose: FloatArray | None = None
        self._kf_segment: int | None = None  # the odometry's segment of the last keyframe
        self._last_loop_query: int | None = None
        # Path driven up to each own keyframe; a jump (reset) starts a new segment.
        self._path = OdometryPath(cfg.capacity, cfg.backend_segment_jump_m)
        # What right alignments and the odometry's drift look like on this run.
        self.calibration = Calibration()
        # Database sequence number of each own keyframe, by index: written by propose, read
        # by verify (on another thread in the node, where the database's own map may move).
        self._own_seqs: dict[int, int] = {}
        # View centre (keyframe cloud centroid, sensor frame) of each own keyframe, by index,
        # for candidates by what they saw (solid_ros.core.candidates.position); written by
        # propose, read by verify, as the sequence numbers.
        self._views = KeyframeViews(cfg.capacity)
        # Coarse structure of each own keyframe, for candidates by what they share
        # (solid_ros.core.candidates.covisibility): kept only with the back end, for as many
        # keyframes as
        # clouds (a keyframe without its cloud cannot be verified), a tenth of their size.
        self._structures = StructureIndex(self._config.cloud_capacity)
        # Where clouds of other robots' keyframes come from (the node asks the owner); it
        # returns the cloud or the reason there is none. None: such candidates stay unverified.
        self.fetch_cloud: CloudFetcher | None = None
        self._loaded = self.database.sessions() - {cfg.session_id}
        # A loaded map's keyframes by (session, index), for candidates by position in it.
        self._map_seqs = _loaded_seqs(self.database, self._loaded)
        # Their view centres (from the clouds saved with them), for candidates by view in it.
        self._map_views = ViewCentres.of({
            key: view_centre(cloud.points, self._mount) for key, seq in self._map_seqs.items()
            if (cloud := self.clouds.get(seq)) is not None and len(cloud.points)})
        # The step registered before the keyframe's candidates, by query index (with_step
        # hands it on instead of registering it again).
        self._step: tuple[int, LoopCandidate | None, float] | None = None
        # Peers' keyframes' odometry poses as sent, by robot and index, while stored: where
        # their keyframes are placed once aligned (solid_ros.core.candidates.peers).
        self._peer_odom: dict[int, dict[int, FloatArray]] = {}

    @property
    def config(self) -> SolidConfig:
        """Current settings."""
        return self._config

    @property
    def bars(self) -> Bars:
        """The judge's thresholds now: the settings and what the run learned."""
        if self.verifier is not None:
            return self.verifier.bars
        return judge_bars(self._config, self.calibration.learned)

    @property
    def num_keyframes(self) -> int:
        """Keyframes stored by this session so far (the next ``query_index``)."""
        return self.database.session_count

    def reconfigure(self, config: SolidConfig) -> None:
        """Switch to new settings; only runtime-tunable ones may differ.

        Raises:
            ConfigError: a read-only setting differs (the message names it).
        """
        for spec in SolidConfig.specs():
            old, new = getattr(self._config, spec.name), getattr(config, spec.name)
            if spec.read_only and old != new:
                raise ConfigError(f'{spec.name} is read-only while running '
                                  f'({old!r} -> {new!r})')
        self._config = config
        self._gate_cfg = config.replace(voxel_size=0.0)
        if self.verifier is not None:
            self.verifier.reconfigure(config)

    def is_keyframe(self, stamp_ns: int, pose: FloatArray | None = None) -> bool:
        """Whether a scan at ``stamp_ns`` (and ``pose`` as from :func:`pose_to_vector`)
        would be kept.

        The first scan is always kept, and so is every scan when all criteria are off. A scan
        is kept when ``keyframe_min_sec`` passed since the last keyframe, or, with poses for
        both, when it moved ``keyframe_min_distance`` or turned ``keyframe_min_rotation_deg``.
        When no enabled criterion can be evaluated (pose criteria only, but no poses), the
        scan is kept rather than silently dropping everything. A stamp earlier than the last
        keyframe's (time jumped back) keeps the scan.
        """
        cfg = self._config
        if self._kf_stamp is None:
            return True
        use_time = cfg.keyframe_min_sec > 0.0
        use_pose = cfg.keyframe_min_distance > 0.0 or cfg.keyframe_min_rotation_deg > 0.0
        if not use_time and not use_pose:
            return True
        dt = (stamp_ns - self._kf_stamp) * 1e-9
        if dt < 0.0 or (use_time and dt >= cfg.keyframe_min_sec):
            return True
        have_pose = pose is not None and self._kf_pose is not None
        if use_pose and have_pose:
            assert pose is not None and self._kf_pose is not None
            moved = float(np.linalg.norm(pose[:3] - self._kf_pose[:3]))
            if cfg.keyframe_min_distance > 0.0 and moved >= cfg.keyframe_min_distance:
                return True
            turned = rotation_deg(pose[3:], self._kf_pose[3:])
            return (cfg.keyframe_min_rotation_deg > 0.0
                    and turned >= cfg.keyframe_min_rotation_deg)
        return not use_time and not have_pose

    # ------------------------------------------------------------------------------ per scan

    def process(self, points: npt.ArrayLike, stamp_ns: int, pose: Any = None,
                hint: GraphHint | None = None) -> ScanResult:
        """Handle one scan: gate, describe, query, store, verify.

        Args:
            points: (N, 3+) array in the sensor frame.
            stamp_ns: scan stamp, integer nanoseconds.
            pose: optional sensor pose (see :func:`pose_to_vector`), used for keyframe gating
                and stored with the scan.
            hint: the pose graph's estimate, for candidates by position (see :meth:`verify`).

        Returns:
            The scan's result; ``loops`` are the loops to publish, best first (empty for a
            gated-out scan).

        Raises:
            CloudError: no usable point (see the module docstring); nothing changed.
            SolidError: malformed points or pose.
        """
        proposal = self.propose(points, stamp_ns, pose)
        if proposal is None:
            vec = pose_to_vector(pose) if pose is not None else None
            return ScanResult(check_stamp(stamp_ns), pose=vec)
        return self.verify(proposal, hint)

    def propose(self, points: npt.ArrayLike, stamp_ns: int,
                pose: Any = None, segment: int | None = None) -> Proposal | None:
        """Descriptor stage: gate, level, describe, query, store the descriptor (``segment``:
        the odometry's segment of the pose, which a reset changes).

        Returns:
            The proposal to hand to :meth:`verify`, or None for a gated-out scan.

        Raises:
            CloudError: no usable point (see the module docstring); nothing changed.
            SolidError: malformed points, pose or stamp (outside int64).
        """
        stamp = check_stamp(stamp_ns)
        vec = pose_to_vector(pose) if pose is not None else None
        if not self.is_keyframe(stamp, vec):
            self._check_usable(self._mount.level(points))  # refused alike, kept or not
            return None
        t0 = time.perf_counter()
        pts = self._mount.level(points)
        desc = describe(pts, self._config)
        if desc.num_points == 0:  # every point dropped: the R-SOLiD is all zero
            raise CloudError(_unusable(np.shape(pts), self._config))
        cloud = self._keyframe_points(pts) if self.verifier is not None else None
        tight = cloud is not None and self.verifier is not None and self.verifier.is_tight(cloud)
        if tight:
            cloud = self._keyframe_points(pts, tight=True, up=self._mount.upright(vec))
        t1 = time.perf_counter()
        proposal = self._propose_descriptor(desc, stamp, vec, cloud, segment)
        proposal.descriptor, proposal.tight = desc, tight
        proposal.describe_ms = (t1 - t0) * 1e3
        proposal.search_ms = (time.perf_counter() - t1) * 1e3
        return proposal

    def process_descriptor(self, desc: Descriptor, stamp_ns: int,
                           pose: Any = None) -> ScanResult:
        """Like :meth:`process` for an already computed descriptor, without gating.

        No keyframe cloud is stored, so with ``verify`` no loop can be verified.

        Raises:
            CloudError: the R-SOLiD is all zero (or not finite); nothing changed.
            SolidError: bad stamp or pose.
        """
        stamp = check_stamp(stamp_ns)
        vec = pose_to_vector(pose) if pose is not None else None
        if not unit_vector(desc.r_solid)[1]:
            raise CloudError('no usable point: the R-SOLiD is all zero or not finite')
        return self.verify(self._propose_descriptor(desc, stamp, vec, None))

    def _check_usable(self, points: npt.ArrayLike) -> None:
        """Raise CloudError unless a point survives the range gate, FOV and max_distance.

        The descriptor's own gate without its voxel grid. Every 64th point first: a real
        cloud almost always has a usable one among them (0.13 ms instead of 3.8 ms for 121k
        points on a gated-out scan); only when none does is the whole cloud checked.
        """
        arr = np.asarray(points)
        if arr.ndim == 2 and len(arr) > 64 and self._any_usable(arr[::64]):
            return
        if not self._any_usable(arr):
            raise CloudError(_unusable(np.shape(arr), self._gate_cfg))

    def _any_usable(self, points: npt.ArrayLike) -> bool:
        cfg = self._gate_cfg
        kept = preprocess(points, cfg)
        return bool(np.any(np.hypot(kept[:, 0], kept[:, 1]) < cfg.max_distance))

    def _keyframe_points(self, points: npt.ArrayLike, tight: bool = False,
                         up: FloatArray | None = None) -> FloatArray:
        """Range gate and FOV clip as for the descriptor, then the verification voxel grid
        (``tight``: the tight-space one, see ``verify_tight_range``, after dropping the scan's
        mixed pixels, see :mod:`solid_ros.core.verification.mixed_pixels`), laid out upright when
        ``up``
        (see :meth:`Mount.upright`; tight keyframes only)."""
        gated = preprocess(points, self._gate_cfg)
        if tight:  # near edges are everywhere in a tight space: their mixed pixels go
            gated = drop_mixed_pixels(gated)
        voxel = (TIGHT_GRID if tight else 1.0) * self._config.verify_voxel_size
        if up is None:
            return voxel_downsample(gated, voxel)
        out: FloatArray = voxel_downsample(gated[:, :3] @ up.T, voxel) @ up
        return out

    def _propose_descriptor(self, desc: Descriptor, stamp: int, vec: FloatArray | None,
                            cloud: FloatArray | None, segment: int | None = None) -> Proposal:
        cfg = self._config
        db = self.database
        q_index = db.session_count
        hood = cfg.margin_neighbourhood
        hits = db.search(desc.r_solid, stamp, cfg.num_candidates + 2 * hood + 1,
                         exclude_frames=cfg.exclude_recent_frames,
                         exclude_sec=cfg.exclude_recent_sec)

        def margin_of(hit: Match) -> float:
            return min((o.distance for o in hits if not _same_place(o, hit, hood)),
                       default=math.inf) - hit.distance

        best = None
        if hits:
            top = hits[0]
            best = LoopCandidate(
                query_index=q_index, match_index=top.index, query_stamp_ns=stamp,
                match_stamp_ns=top.stamp_ns, match_session=top.session, distance=top.distance,
                yaw=estimate_yaw(desc.heading, db.heading(top.seq), cfg.heading_match),
                margin=margin_of(top),
                reason='best')
        chosen = []
        for hit in hits[:cfg.num_candidates]:
            if hit.distance >= cfg.distance_threshold:
                break
            margin = margin_of(hit)
            if cfg.min_margin > 0.0 and margin < cfg.min_margin:
                continue
            chosen.append(Hit(hit, margin, db.heading(hit.seq).copy()))
        seq = db.next_seq
        db.add(desc.r_solid, desc.heading, stamp, vec)
        self._own_seqs[q_index] = seq
        while len(self._own_seqs) > cfg.capacity:
            del self._own_seqs[next(iter(self._own_seqs))]
        if cloud is not None and len(cloud):
            self._views.put(q_index, view_centre(cloud, self._mount))
        # A reset the odometry announces (KISS-ICP restarts where the last pose was) is no
        # jump, but its new segment is another frame all the same: no path runs across it.
        reset = (segment is not None and self._kf_segment is not None
                 and segment != self._kf_segment)
        self._path.add(q_index, vec, reset)
        self._kf_stamp, self._kf_pose = stamp, vec
        self._kf_segment = segment if segment is not None else self._kf_segment
        return Proposal(q_index, stamp, seq, np.asarray(desc.heading, dtype=np.float64), cloud,
                        np.asarray(desc.r_solid, dtype=np.float64), vec, chosen, best)

    def verify(self, proposal: Proposal, hint: GraphHint | None = None, *,
               step: bool = True) -> ScanResult:
        """Verification stage for one :meth:`propose` result; call in keyframe order.

        Stores the keyframe's cloud, verifies the candidates and applies ``max_candidates``
        and ``min_loop_gap``; the result's ``attempts`` lists every candidate looked at.
        With ``step`` (and ``backend_step_registration`` 'on') it also registers the step
        from the previous keyframe (:meth:`with_step`).

        With a ``hint`` (the pose graph after the previous keyframe), ``graph_candidates`` on,
        verification on and an odometry pose for the keyframe, the keyframes near it in the
        graph's estimate, or that saw its place, or that share its structure, join the
        descriptor's candidates (:mod:`solid_ros.core.candidates.position`,
        :mod:`solid_ros.core.candidates.covisibility`; appended to ``proposal.hits``, source
        ``'graph'``), and every candidate the graph places within
        ``graph_candidate_max_radius_m`` or proposes by view or structure is registered from
        the graph's relative pose first. They pass the same tests.
        """
        t0 = time.perf_counter()
        cfg = self._config
        structure = None
        if self.verifier is not None and proposal.query is None:
            proposal.query = self.verifier.prepare(
                proposal.cloud_points if proposal.cloud_points is not None
                else np.zeros((0, 3)), proposal.tight)
            if cfg.backend and cfg.graph_candidates > 0:  # only the back end's hint uses it
                structure = self._structure_of(proposal.query)
        more: Callable[[], list[Hit]] | None = None
        placed: Callable[[], list[Hit]] | None = None
        if hint is not None and cfg.graph_candidates > 0 and self.verifier is not None:
            hint = self._registered_hint(proposal, hint)
            proposal.hits = with_graph_hits(proposal, hint, cfg, self.database, self._own_seqs,
                                            self._views, self._mount, self._map_seqs,
                                            self._map_views)
            if structure is not None:
                more = partial(shared_hits, proposal, hint, cfg, self.database,
                               self._own_seqs, self._mount, self._structures, structure)
            placed = partial(placed_peer_hits, proposal, hint, cfg, self.database, self._mount)
        gap_blocked = bool(cfg.min_loop_gap and self._last_loop_query is not None
                           and proposal.query_index - self._last_loop_query < cfg.min_loop_gap)
        if self.verifier is None:
            attempts = self._accept_by_descriptor(proposal, gap_blocked)
        else:
            attempts = self._accept_by_registration(proposal, gap_blocked, more, placed)
        if structure is not None:  # after its own search: it shares all with itself
            self._structures.add(proposal.query_index, structure)
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
        if taken:
            self._last_loop_query = proposal.query_index
        self._calibrate(proposal)
        # The step registered before the candidates is the step stage's time, not theirs.
        early = (self._step[2] if self._step is not None
                 and self._step[0] == proposal.query_index else 0.0)
        times = StageTimes(proposal.describe_ms, proposal.search_ms,
                           (time.perf_counter() - t0) * 1e3 - early)
        result = ScanResult(proposal.stamp_ns, True, proposal.query_index, proposal.pose,
                            tuple(taken), tuple(attempts), proposal.best, times,
                            proposal.descriptor)
        return self.with_step(result, proposal) if step else result

    @property
    def _own(self) -> OwnKeyframes:
        """This session's stored keyframes for the registrations to them (a view: the
        database is replaced on reset and load)."""
        return OwnKeyframes(self.database, self.clouds, self._own_seqs, self._path,
                            self._mount, self._config.session_id)

    def _calibrate(self, proposal: Proposal) -> None:
        """Register the keyframe to a partner a few metres back along the odometry and teach
        the calibration what a right alignment and the odometry's drift look like here (see
        :mod:`solid_ros.core.verification.calibration`)."""
        if self.verifier is not None:
            calibrate(self._own, self.verifier, self.calibration, proposal,
                      self._config.verify_min_overlap)

    def _registered_hint(self, proposal: Proposal, hint: GraphHint) -> GraphHint:
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
        if (self._config.backend_step_registration != 'on' or proposal.pose is None
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
        before the candidates (:meth:`_registered_hint`)."""
        if self._config.backend_step_registration != 'on':
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
        got = None if self.verifier is None else self._own.step(self.verifier, proposal)
        if got is None:
            return None
        fine, seq = got
        _, _, stamp = self.database.match_info(seq)
        hit = Hit(Match(seq, proposal.query_index - 1, self._config.session_id, stamp,
                        math.nan), math.nan, np.zeros(0, dtype=np.float32), 'step')
        return self._candidate(proposal, hit, 0.0, fine)

    def _candidate(self, proposal: Proposal, hit: Hit, yaw: float,
                   result: Verification | None) -> LoopCandidate:
        m = hit.match
        if result is None:
            T = np.eye(4)
            T[:3, :3] = rot_z(yaw)
            return LoopCandidate(proposal.query_index, m.index, proposal.stamp_ns, m.stamp_ns,
                                 m.session, m.distance, yaw, hit.margin,
                                 pose=self._mount.unlevel_pose(T), source=hit.source)
        cov: tuple[float, ...] = NAN_COV
        if result.covariance is not None:
            cov = tuple(float(v) for v in self._mount.unlevel_cov(result.covariance).ravel())
        return LoopCandidate(
            proposal.query_index, m.index, proposal.stamp_ns, m.stamp_ns, m.session,
            m.distance, result.yaw if result.verified else yaw, hit.margin,
            verified=result.verified, pose=self._mount.unlevel_pose(result.T),
            fitness=result.fitness, covariance=cov, reason=result.reason,
            evidence=result.evidence, source=hit.source, detail=result.detail)

    def _odometry(self, proposal: Proposal, match: Match, T_mq: FloatArray
                  ) -> tuple[float, float]:
        """The odometry check of a loop ``T_mq`` (sensor frames, not levelled) from the query
        to ``match``: how far its translation is from this session's odometry, and what the
        judge's bars allow over the path driven between them; NaN where the odometry says
        nothing (check off, another session, no pose, a jump of the odometry between)."""
        cfg = self._config
        if (cfg.odom_check_drift <= 0.0 or match.session != cfg.session_id
                or proposal.pose is None):
            return math.nan, math.nan
        pose_m = self.database.pose(match.seq)
        path = self._path.between(match.index, proposal.query_index)
        if pose_m is None or path is None:
            return math.nan, math.nan
        return disagreement(T_mq, proposal.pose, pose_m), self.bars.odom_allowed(path)

    def _place(self, proposal: Proposal, hit: Hit, centre: FloatArray) -> HitPlace:
        """What the judge's context rules ask of a hit's place (levelled poses)."""
        def odom(T_mq: FloatArray) -> tuple[float, float]:
            return self._odometry(proposal, hit.match, self._mount.unlevel(T_mq))

        return HitPlace(hit, centre, self._config, odom)

    def _accept_by_descriptor(self, proposal: Proposal, gap_blocked: bool) -> list[LoopCandidate]:
        """Without verification only the context rules judge (the odometry: no pose to place
        in a graph)."""
        mode = self._config.heading_match
        bars = self.bars
        out = []
        for h in proposal.hits:
            c = self._candidate(proposal, h, estimate_yaw(proposal.heading, h.heading, mode), None)
            error, allowed = self._odometry(proposal, h.match, c.matrix())
            verdict = judge(Measures(odom_error_m=error, odom_allowed_m=allowed), bars,
                            'context')
            if not verdict.verified:
                c = replace(c, reason=verdict.reason, evidence=verdict.evidence,
                            detail=verdict.detail)
                self.reasons[verdict.reason] += 1
            out.append(c)
        return out

    def _accept_by_registration(self, proposal: Proposal, gap_blocked: bool,
                                more: Callable[[], list[Hit]] | None = None,
                                placed: Callable[[], list[Hit]] | None = None
                                ) -> list[LoopCandidate]:
        """Verify the proposal's hits group by group until ``max_candidates`` places are
        verified; ``more``: hits to try last, asked only if it comes to them; ``placed``:
        aligned peers' keyframes by position, asked only when the peers' hits verified
        nothing."""
        verifier = self.verifier
        assert verifier is not None
        clouds, fetched = self._candidate_clouds(proposal, gap_blocked)
        query = proposal.query
        if query is None:
            query = verifier.prepare(proposal.cloud_points if proposal.cloud_points is not None
                                     else np.zeros((0, 3)), proposal.tight)
            proposal.query = query
        if query.usable:
            self.clouds.put(proposal.seq, query.keyframe_cloud())
        self.clouds.drop_before(self.database.oldest_seq)
        results: dict[int, Verification] = dict(fetched)
        yaws: dict[int, float] = {}
        verified: list[Match] = []
        passed: dict[int, CoarseResult] = {}  # coarse results kept for the map's budget
        # The graph's near keyframes first: registered from its pose they mostly verify at
        # once, and the rest are then not needed (max_candidates); then those that saw the
        # query's place from elsewhere, then the descriptor's others, and last, asked only
        # now, those that share the query's structure.
        hits = proposal.hits
        peer = [h.match.seq >= PEER_SEQ_BASE for h in hits]
        for group in ([i for i, h in enumerate(hits) if h.near],
                      [i for i, h in enumerate(hits) if h.view and not h.near],
                      [i for i, h in enumerate(hits) if not (h.near or h.view or peer[i])]):
            if gap_blocked or len(verified) >= self._config.max_candidates:
                break
            self._register(proposal, query, group, clouds, results, yaws, verified, passed)
        # A loaded map's places have a budget of their own: a loop into the map is what
        # places this session in it, and an own keyframe near the query that verified first
        # left none to it (hku1's second half in its first half's map: 8 of the 15 revisits
        # without a loop into the map had one that verifies at the reference pose).
        own = self._config.session_id
        mapped = [i for i, h in enumerate(hits) if not peer[i] and h.match.session != own]
        if (not gap_blocked and mapped and len(verified) >= self._config.max_candidates
                and not any(m.session != own for m in verified)):
            self._register(proposal, query, [i for i in mapped if i not in results], clouds,
                           results, yaws, [], passed)
        # Peers' places have a budget of their own: the graph's near keyframes verify first
        # and would otherwise leave none to the inter-robot loops a fleet is placed by.
        found: list[Match] = []
        if not gap_blocked and any(peer):
            self._register(proposal, query, [i for i in range(len(hits)) if peer[i]], clouds,
                           results, yaws, found)
        if placed is not None and not gap_blocked and not found:
            start = len(hits)
            hits = self._append_hits(proposal, placed(), clouds, results)
            self._register(proposal, query, list(range(start, len(hits))), clouds, results,
                           yaws, found)
        if more is not None and not gap_blocked and len(verified) < self._config.max_candidates:
            extra = more()
            start = len(hits)
            hits = proposal.hits = hits + extra
            clouds += [self.clouds.get(h.match.seq) for h in extra]
            self._register(proposal, query, list(range(start, len(hits))), clouds, results,
                           yaws, verified)
        out = []
        for i, hit in enumerate(hits):
            res = results.get(i)
            if res is not None:
                self.reasons[res.reason] += 1
                out.append(self._candidate(proposal, hit, yaws.get(i, 0.0), res))
        out.sort(key=lambda c: (not c.verified, -_nan_to(c.overlap, -1.0)))
        return out

    def _budget(self, c: LoopCandidate) -> str:
        """Whose places a loop counts against ``max_candidates``: this session's, a loaded
        map's or a peer robot's."""
        if c.match_session == self._config.session_id:
            return 'own'
        return 'peer' if self._is_peer(c) else 'map'

    def _is_peer(self, c: LoopCandidate) -> bool:
        """A loop to another robot's keyframe (not this session's, not a loaded map's)."""
        return (c.match_session != self._config.session_id
                and (c.match_session, c.match_index) not in self._map_seqs)

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
        cloud = self.clouds.get(hit.match.seq)
        if (cloud is None and self.fetch_cloud is not None and not gap_blocked
                and hit.match.session != self._config.session_id
                and hit.match.session not in self._loaded_sessions()):
            got = self.fetch_cloud(hit.match.session, hit.match.index, hit.match.stamp_ns)
            if not isinstance(got, KeyframeCloud):
                return None, Verification(False, got, np.eye(4))
            self.clouds.put(hit.match.seq, got)
            cloud = got
        return cloud, None

    def _append_hits(self, proposal: Proposal, extra: list[Hit],
                     clouds: list[KeyframeCloud | None],
                     results: dict[int, Verification]) -> list[Hit]:
        """``extra`` appended to the proposal's hits, their clouds (fetched) to ``clouds``
        and the verdicts of those that did not come to ``results``; the hits."""
        for h in extra:
            cloud, missing = self._cloud_of(h, False)
            if missing is not None:
                results[len(clouds)] = missing
            clouds.append(cloud)
        proposal.hits = proposal.hits + extra
        return proposal.hits

    def _register(self, proposal: Proposal, query: Query, group: list[int],
                  clouds: list[KeyframeCloud | None], results: dict[int, Verification],
                  yaws: dict[int, float], verified: list[Match],
                  passed: dict[int, CoarseResult] | None = None) -> None:
        """Coarse stage of the hits ``group``, then the fine stage in order of coarse overlap
        until ``max_candidates`` distinct places are verified (``verified`` grows); ``passed``
        keeps the coarse results that passed for a later call (the map's own budget)."""
        verifier = self.verifier
        assert verifier is not None
        cfg = self._config
        coarse = []
        for i in group:
            hit = proposal.hits[i]
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
            hit = proposal.hits[i]
            if len(verified) >= cfg.max_candidates:
                break  # enough distinct places: the rest stay unverified ('skipped')
            if any(_same_place(hit.match, v, cfg.margin_neighbourhood) for v in verified):
                continue
            fine = verifier.fine(query, c, place=self._place(proposal, hit, centre))
            results[i] = fine
            if fine.verified:
                verified.append(hit.match)

    def _structure_of(self, query: Query) -> FloatArray:
        """A prepared keyframe's structure on the configuration's coarse grid, sensor frame
        (:func:`~solid_ros.core.candidates.covisibility.coarse_structure`; empty when unusable)."""
        if not query.usable:
            return np.zeros((0, 3))
        out: FloatArray = self._mount.to_sensor(coarse_structure(
            query.points, query.structure, self._config.verify_coarse_voxel_size))
        return out

    def _loaded_sessions(self) -> set[int]:
        """Sessions loaded from a database file (their clouds came with it or not at all)."""
        return self._loaded

    # -------------------------------------------------------------------------- peer robots

    def add_peer_keyframe(self, robot: int, index: int, stamp_ns: int,
                          r_solid: npt.ArrayLike, heading: npt.ArrayLike,
                          pose: Any = None) -> int:
        """Store another robot's keyframe descriptor so that this robot's queries find it;
        its cloud is fetched through :attr:`fetch_cloud` only when a query's candidate needs
        it. A robot's id is its session id in the database (``match_session`` of its loops).

        Returns:
            Its database sequence number.

        Raises:
            SolidError: bad stamp, shape or pose, or ``robot`` is this robot's own id.
        """
        vec = pose_to_vector(pose) if pose is not None else None
        seq = self.database.add_foreign(int(robot), int(index), r_solid, heading,
                                        check_stamp(stamp_ns), vec)
        if vec is not None:
            self._peer_odom.setdefault(int(robot), {})[int(index)] = vector_to_matrix(vec)
            if sum(map(len, self._peer_odom.values())) > self.database.peer_size + 256:
                for rb, poses in self._peer_odom.items():  # evicted from the peers' ring
                    self._peer_odom[rb] = {i: T for i, T in poses.items()
                                           if self.database.has_foreign(rb, i)}
        return seq

    def peer_odometry(self, robot: int) -> dict[int, FloatArray]:
        """A peer's stored keyframes' odometry poses as sent (4x4), by index."""
        return dict(self._peer_odom.get(int(robot), {}))

    def own_keyframes(self, limit: int) -> list[tuple[int, int, FloatArray, FloatArray,
                                                      FloatArray | None]]:
        """The newest ``limit`` stored keyframes of this session as ``(index, stamp_ns,
        R-SOLiD, heading, pose or None)``, oldest first (unit vectors, as stored)."""
        db = self.database
        out = []
        for index in range(max(db.session_count - limit, 0), db.session_count):
            seq = db.own_seq(index)
            if seq is None:
                continue
            _, _, stamp = db.match_info(seq)
            pose = db.pose(seq)
            out.append((index, stamp, np.asarray(db.r_solid(seq), dtype=np.float64),
                        np.asarray(db.heading(seq), dtype=np.float64),
                        None if pose is None else np.asarray(pose, dtype=np.float64)))
        return out

    def own_cloud(self, index: int) -> KeyframeCloud | None:
        """The stored cloud of this session's keyframe ``index`` (None: evicted or none)."""
        seq = self.database.own_seq(index)
        cloud = None if seq is None else self.clouds.get(seq)
        # Peers keep the configuration's grid: a tight-space cloud goes out on it.
        return None if cloud is None else coarsened(cloud, self._config.verify_voxel_size)

    def peer_cloud(self, index: int) -> KeyframeCloud | None:
        """:meth:`own_cloud` as a peer gets it: the ground thinned (:func:`for_peers`)."""
        cloud = self.own_cloud(index)
        return None if cloud is None else for_peers(cloud, self._config.verify_voxel_size)

    # --------------------------------------------------------------------------- persistence

    def reset(self) -> None:
        """Forget every stored scan and cloud (the configuration stays)."""
        self.database = DescriptorDatabase(self._config)
        self._map_seqs = {}
        self._map_views = ViewCentres.of({})
        self._peer_odom = {}
        self.clouds.clear()
        if self.verifier is not None:
            self.verifier.clear_cache()
        self._kf_stamp = self._kf_pose = self._kf_segment = None
        self._last_loop_query = None
        self._step = None
        self._path.clear()
        self._own_seqs.clear()
        self._views.clear()
        self._structures.clear()
        self.calibration.clear()
        if self.verifier is not None:
            self.verifier.learn(self.calibration.learned)

    def save(self, path: str | Path,
             map_poses: Mapping[tuple[int, int], Any] | None = None) -> Path:
        """Save the database (all sessions) and its keyframe clouds atomically, with the
        back end's map-frame poses by ``(session, index)`` when given; see
        :mod:`solid_ros.core.database.persistence`."""
        from solid_ros.core.database.persistence import save_database

        return save_database(self.database, path, self.clouds, map_poses)

    @classmethod
    def load(cls, path: str | Path, config: SolidConfig | None = None) -> LoopDetector:
        """Start a session that also queries (and verifies against) the scans saved in
        ``path``.

        Raises:
            DatabaseError: unreadable file, different descriptor settings, or the file
                already holds ``config.session_id``.
        """
        from solid_ros.core.database.persistence import load_database

        cfg = config if config is not None else SolidConfig()
        clouds = CloudStore(cfg.cloud_capacity, int(cfg.cloud_memory_mb * 1e6))
        return cls(cfg, database=load_database(path, cfg, clouds), clouds=clouds)


def _unusable(shape: tuple[int, ...], cfg: SolidConfig) -> str:
    """The one-line reason a cloud of ``shape`` holds no usable point."""
    n = shape[0] if len(shape) == 2 and shape[1] > 0 else 0
    if n == 0:
        return 'no usable point: the cloud is empty'
    return (f'no usable point: 0 of {n} points are finite and inside the range gate '
            f'({cfg.min_range:g} to {cfg.max_range:g} m), the FOV ({cfg.fov_width_deg:g} deg) '
            f'and max_distance ({cfg.max_distance:g} m)')


def _loaded_seqs(db: DescriptorDatabase, sessions: set[int]) -> dict[tuple[int, int], int]:
    """Sequence numbers of the stored scans of ``sessions`` by ``(session, index)``."""
    out = {}
    for seq in db.stored_seqs() if sessions else []:
        index, session, _ = db.match_info(seq)
        if session in sessions:
            out[(session, index)] = seq
    return out


def _same_place(a: Match, b: Match, hood: int) -> bool:
    return a.session == b.session and abs(a.index - b.index) <= hood


def _nan_to(value: float, default: float) -> float:
    return default if math.isnan(value) else value
