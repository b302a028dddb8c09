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

:class:`LoopDetector` is the facade over the stages, which share one
:class:`~solid_ros.core.flow.state.DetectorState`: the descriptor stage
(:mod:`solid_ros.core.flow.proposer`: keyframe gate, unusable clouds, indices, candidates and
their margins), the verification stage (:mod:`solid_ros.core.flow.verify_stage`: candidates by
position, registered steps, ``min_loop_gap`` and the budgets) and acceptance
(:mod:`solid_ros.core.flow.acceptance`: registration of the candidates, the odometry check).
It keeps other robots' keyframes (peers) and saves and loads the database.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.position import GraphHint
from solid_ros.core.candidates.proposal import Proposal
from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import CloudStore, KeyframeCloud
from solid_ros.core.database.descriptors import DescriptorDatabase, unit_vector
from solid_ros.core.descriptor.mount import Mount
from solid_ros.core.errors import CloudError, ConfigError
from solid_ros.core.flow.acceptance import Acceptor, CloudFetcher
from solid_ros.core.flow.proposer import Proposer
from solid_ros.core.flow.state import DetectorState
from solid_ros.core.flow.verify_stage import VerifyStage
from solid_ros.core.geometry import pose_to_vector, vector_to_matrix
from solid_ros.core.odometry.track import OdometryPath
from solid_ros.core.results import Descriptor, ScanResult
from solid_ros.core.stamps import check_stamp
from solid_ros.core.verification.calibration import Calibration
from solid_ros.core.verification.judge import Bars
from solid_ros.core.verification.prepared import coarsened, for_peers
from solid_ros.core.verification.verifier import Verifier

__all__ = ['LoopDetector']

FloatArray = npt.NDArray[np.float64]


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
        cfg = config if config is not None else SolidConfig()
        self._state = DetectorState(
            cfg, database if database is not None else DescriptorDatabase(cfg),
            clouds if clouds is not None else CloudStore(
                cfg.cloud_capacity, int(cfg.cloud_memory_mb * 1e6)),
            Verifier(cfg) if cfg.verify else None, Mount(cfg),
            OdometryPath(cfg.capacity, cfg.backend_segment_jump_m))
        self._proposer = Proposer(self._state)
        loaded = self._state.database.sessions() - {cfg.session_id}
        self._acceptor = Acceptor(self._state, loaded)
        self._stage = VerifyStage(self._state, self._acceptor, loaded)
        # Peers' keyframes' odometry poses as sent, by robot and index, while stored: where
        # their keyframes are placed once aligned (solid_ros.core.candidates.peers).
        self._peer_odom: dict[int, dict[int, FloatArray]] = {}

    @property
    def config(self) -> SolidConfig:
        """Current settings."""
        return self._state.config

    @property
    def database(self) -> DescriptorDatabase:
        """The descriptor database (all sessions; a new one after :meth:`reset`)."""
        return self._state.database

    @property
    def clouds(self) -> CloudStore:
        """Keyframe clouds by database sequence number."""
        return self._state.clouds

    @property
    def verifier(self) -> Verifier | None:
        """The registration procedure; None without ``verify``."""
        return self._state.verifier

    @property
    def calibration(self) -> Calibration:
        """What right alignments and the odometry's drift look like on this run."""
        return self._state.calibration

    @property
    def reasons(self) -> Counter[str]:
        """Verification outcomes so far."""
        return self._acceptor.reasons

    @property
    def fetch_cloud(self) -> CloudFetcher | None:
        """Where clouds of other robots' keyframes come from (the node asks the owner); it
        returns the cloud or the reason there is none. None: such candidates stay
        unverified."""
        return self._acceptor.fetch_cloud

    @fetch_cloud.setter
    def fetch_cloud(self, fetch: CloudFetcher | None) -> None:
        self._acceptor.fetch_cloud = fetch

    @property
    def bars(self) -> Bars:
        """The judge's thresholds now: the settings and what the run learned."""
        return self._state.bars

    @property
    def num_keyframes(self) -> int:
        """Keyframes stored by this session so far (the next ``query_index``)."""
        return self._state.database.session_count

    def reconfigure(self, config: SolidConfig) -> None:
        """Switch to new settings; only runtime-tunable ones may differ.

        Raises:
            ConfigError: a read-only setting differs (the message names it).
        """
        for spec in SolidConfig.specs():
            old, new = getattr(self._state.config, spec.name), getattr(config, spec.name)
            if spec.read_only and old != new:
                raise ConfigError(f'{spec.name} is read-only while running '
                                  f'({old!r} -> {new!r})')
        self._state.config = config
        self._proposer.reconfigure(config)
        if self._state.verifier is not None:
            self._state.verifier.reconfigure(config)

    def resolve_odometry(self, scan_only: bool) -> None:
        """Resolve the 'auto' settings for the odometry in use
        (:meth:`SolidConfig.for_odometry`; ``scan_only``: KISS-ICP run on the same clouds).

        Raises:
            ConfigError: an 'auto' setting would change after the first keyframe.
        """
        config = self._state.config.for_odometry(scan_only)
        if config == self._state.config:
            return
        if self.num_keyframes:
            raise ConfigError("backend_step_registration: resolve 'auto' for the odometry "
                              'before the first keyframe')
        self._state.config = config
        self._proposer.reconfigure(config)
        if self._state.verifier is not None:
            self._state.verifier.reconfigure(config)

    def is_keyframe(self, stamp_ns: int, pose: FloatArray | None = None) -> bool:
        """Whether a scan at ``stamp_ns`` (and ``pose`` as from :func:`pose_to_vector`)
        would be kept (see :meth:`Proposer.is_keyframe
        <solid_ros.core.flow.proposer.Proposer.is_keyframe>`)."""
        return self._proposer.is_keyframe(stamp_ns, pose)

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
            CloudError: no usable point (see :mod:`solid_ros.core.flow.proposer`); nothing
                changed.
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
            CloudError: no usable point (see :mod:`solid_ros.core.flow.proposer`); nothing
                changed.
            SolidError: malformed points, pose or stamp (outside int64).
        """
        stamp = check_stamp(stamp_ns)
        vec = pose_to_vector(pose) if pose is not None else None
        return self._proposer.propose(points, stamp, vec, segment)

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
        return self.verify(self._proposer.propose_descriptor(desc, stamp, vec, None))

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
        :mod:`solid_ros.core.candidates.covisibility`; after the proposal's hits, source
        ``'graph'``), and every candidate the graph places within
        ``graph_candidate_max_radius_m`` or proposes by view or structure is registered from
        the graph's relative pose first. They pass the same tests (see
        :mod:`solid_ros.core.flow.verify_stage`). ``proposal`` is not changed.
        """
        return self._stage.verify(proposal, hint, step=step)

    def with_step(self, result: ScanResult, proposal: Proposal) -> ScanResult:
        """``result`` (of :meth:`verify` with ``step=False``) with its registered step, when
        ``backend_step_registration`` is 'on' (else unchanged): registered here, or already
        before the candidates (:meth:`VerifyStage.registered_hint
        <solid_ros.core.flow.verify_stage.VerifyStage.registered_hint>`)."""
        return self._stage.with_step(result, proposal)

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
        return None if cloud is None else coarsened(cloud, self._state.config.verify_voxel_size)

    def seq_of(self, session: int, index: int) -> int | None:
        """Database sequence number of scan ``index`` of ``session`` (this one's, a loaded
        map's or a peer's), or None when it is not stored."""
        if session == self._state.config.session_id:
            return self.database.own_seq(index)
        seq = self._stage.map_seqs.get((session, index))
        return seq if seq is not None else self.database.foreign_seq(session, index)

    def peer_cloud(self, index: int) -> KeyframeCloud | None:
        """:meth:`own_cloud` as a peer gets it: the ground thinned (:func:`for_peers`)."""
        cloud = self.own_cloud(index)
        return None if cloud is None else for_peers(cloud, self._state.config.verify_voxel_size)

    # --------------------------------------------------------------------------- persistence

    def reset(self) -> None:
        """Forget every stored scan and cloud (the configuration stays)."""
        state = self._state
        state.database = DescriptorDatabase(state.config)
        self._stage.reset()
        self._peer_odom = {}
        state.clouds.clear()
        if state.verifier is not None:
            state.verifier.clear_cache()
        self._proposer.reset()
        state.path.clear()
        state.own_seqs.clear()
        state.views.clear()
        state.calibration.clear()
        if state.verifier is not None:
            state.verifier.learn(state.calibration.learned)

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
