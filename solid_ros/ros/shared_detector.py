"""The loop closure that solid_node's two threads share, each stage under its own lock.

The node runs the product's per-scan flow, :class:`~solid_ros.core.flow.closure.LoopClosure`,
on two threads: stage 1 (:meth:`SharedDetector.propose`: describe, search, store) and stage 2
(:meth:`SharedDetector.verify`, then :meth:`SharedDetector.commit`: the registered step and
the pose graph) each hold their lock while they use it, so one keyframe is described while the
one before it is verified; saving, resetting and reconfiguring take both. The pose graph and
its hint are stage 2's. Peer robots' keyframes are stored under the stage-1 lock, like this
robot's descriptors. No ROS import: the node and its tests hand it plain values.

No lock is ever held across a network wait: the clouds of peers' keyframes a proposal needs
are fetched before stage 2 takes its lock (:meth:`SharedDetector.fetch_clouds`); the detector
then reads them from what was fetched, so saving, resetting and peers' requests never wait
for another robot.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.mapping import keyframe_clouds
from solid_ros.core.candidates.proposal import Proposal
from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.database.persistence import backup_if_shrinking
from solid_ros.core.flow.closure import LoopClosure, Step
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.odometry.track import OdomSample
from solid_ros.core.reasons import Reason
from solid_ros.core.results import BackendEvent, LoopCandidate, PeerAlignment, ScanResult
from solid_ros.formats.peers import DescriptorMessage

__all__ = ['CloudSource', 'IN_FLIGHT', 'SharedDetector']

FloatArray = npt.NDArray[np.float64]
IN_FLIGHT = 8  # cloud requests out at once (the reply topic keeps 10)


class CloudSource(Protocol):
    """Where peers' keyframe clouds come from (:class:`~solid_ros.ros.peers.PeerLink`)."""

    def request(self, robot: int, index: int, stamp_ns: int) -> Any:
        """Send a request now; what it returns goes to :meth:`collect`."""

    def collect(self, ticket: Any) -> KeyframeCloud | Reason:
        """Wait for a request's cloud (or the reason there is none)."""


class SharedDetector:
    """A :class:`~solid_ros.core.flow.closure.LoopClosure` behind the two stage locks.

    Args:
        closure: the loop closure (its detector and, with the back end, its pose graph).
    """

    def __init__(self, closure: LoopClosure) -> None:
        self._closure = closure
        self._detector = closure.detector
        self._loaded = self._loaded_sessions(self._detector)
        self._source: CloudSource | None = None
        self._fetched: dict[tuple[int, int, int], KeyframeCloud | Reason] = {}
        self._describe_lock = threading.Lock()
        self._verify_lock = threading.Lock()

    @property
    def closure(self) -> LoopClosure:
        """The loop closure (read its graph only under the stage-2 lock, or for counters)."""
        return self._closure

    @property
    def detector(self) -> LoopDetector:
        """The detector now (another one after :meth:`reset`)."""
        return self._detector

    @property
    def size(self) -> int:
        """Scans in its database."""
        return int(self._detector.database.size)

    def set_cloud_source(self, source: CloudSource | None) -> None:
        """Where clouds of other robots' keyframes come from, for this and later detectors."""
        self._source = source
        self._detector.fetch_cloud = self._collected if source is not None else None

    @staticmethod
    def _loaded_sessions(detector: LoopDetector) -> set[int]:
        # As the detector decides: sessions stored before any peer's (their clouds came
        # with the file or not at all; they are never asked for).
        return detector.database.sessions() - {detector.config.session_id}

    # -- the two stages ----------------------------------------------------------------------

    def propose(self, points: npt.ArrayLike, stamp_ns: int,
                odom: OdomSample | None) -> Proposal | None:
        """Stage 1: :meth:`LoopClosure.propose` under the stage-1 lock."""
        with self._describe_lock:
            return self._closure.propose(points, stamp_ns, odom)

    def fetch_clouds(self, proposal: Proposal) -> dict[tuple[int, int, int],
                                                        KeyframeCloud | Reason]:
        """The clouds of peers' keyframes among the proposal's candidates that are not stored
        here, fetched without holding a lock: requests go out ``IN_FLIGHT`` at a time (all
        fit in the reply topic's history) and are collected together, so a keyframe waits at
        most one time-out per batch, however many candidates it has."""
        source, det = self._source, self._detector
        if source is None or det.verifier is None:
            return {}
        own = det.config.session_id
        wanted: list[tuple[int, int, int]] = []
        for hit in proposal.hits:
            m = hit.match
            key = (m.session, m.index, m.stamp_ns)
            if not (m.session == own or m.session in self._loaded or key in wanted
                    or m.seq in det.clouds):
                wanted.append(key)
        out: dict[tuple[int, int, int], KeyframeCloud | Reason] = {}
        for i in range(0, len(wanted), IN_FLIGHT):
            batch = [(key, source.request(*key)) for key in wanted[i:i + IN_FLIGHT]]
            out.update((key, source.collect(ticket)) for key, ticket in batch)
        return out

    def verify(self, proposal: Proposal) -> tuple[ScanResult, LoopDetector]:
        """Stage 2: fetch the proposal's peer clouds (:meth:`fetch_clouds`) without a lock,
        then :meth:`LoopClosure.verify` (with the pose graph's hint) under the stage-2 lock;
        also returns the detector that verified (a reset may replace it right after)."""
        fetched = self.fetch_clouds(proposal)
        with self._verify_lock:
            detector = self._detector
            self._fetched = fetched
            try:
                return self._closure.verify(proposal), detector
            finally:
                self._fetched = {}

    def commit(self, proposal: Proposal, result: ScanResult, odom: OdomSample | None,
               detector: LoopDetector) -> Step | None:
        """The rest of stage 2 after the loops of :meth:`verify` went out:
        :meth:`LoopClosure.commit` (registered step, pose graph) under the stage-2 lock; None
        when a reset replaced ``detector`` since it verified (nothing changed).

        Raises:
            BackendError: see :meth:`LoopClosure.commit`.
        """
        with self._verify_lock:
            if detector is not self._detector:
                return None
            return self._closure.commit(proposal, result, odom)

    def _collected(self, robot: int, index: int, stamp_ns: int) -> KeyframeCloud | Reason:
        """The detector's ``fetch_cloud``: only what was fetched before the lock (a cloud
        stored then and dropped since counts as timed out; that takes a reset between)."""
        return self._fetched.get((robot, index, stamp_ns), 'peer_timeout')

    def match_position(self, cand: LoopCandidate, detector: LoopDetector) -> FloatArray | None:
        """Position stored with the matched scan (any session), or None when unknown (or
        ``detector`` was replaced since it verified)."""
        # Under the stage-1 lock: it stores scans, and may evict this one meanwhile.
        with self._describe_lock:
            db = detector.database
            seq = detector.seq_of(cand.match_session, cand.match_index)
            if (detector is not self._detector or seq is None or not db.is_stored(seq)
                    or db.match_info(seq)[:2] != (cand.match_index, cand.match_session)):
                return None
            stored = db.pose(seq)
            return None if stored is None else np.asarray(stored[:3], dtype=np.float64)

    # -- both locks --------------------------------------------------------------------------

    def reconfigure(self, config: SolidConfig) -> None:
        """Apply tunable settings (raises ConfigError if a read-only one differs)."""
        with self._describe_lock, self._verify_lock:
            self._detector.reconfigure(config)

    def reset(self, detector: LoopDetector) -> None:
        """Continue with ``detector`` and an empty pose graph (``~/reset``;
        :meth:`LoopClosure.reset`); it fetches peer clouds as before."""
        with self._describe_lock, self._verify_lock:
            if self._source is not None:
                detector.fetch_cloud = self._collected
            self._loaded = self._loaded_sessions(detector)
            self._closure.reset(detector)
            self._detector = detector

    def save(self, path: str) -> tuple[int, Path | None]:
        """Save the database to ``path`` (its folder made; the core writes a temporary file
        and renames it over ``path``) with the back end's map-frame poses
        (:meth:`LoopClosure.save`); return the scans saved and, when the save would have
        replaced a database with an empty or much smaller one, the backup kept of it
        (:func:`~solid_ros.core.database.persistence.backup_if_shrinking`).

        Raises:
            SolidError, OSError: nothing was saved.
        """
        target = Path(path).expanduser()
        with self._describe_lock, self._verify_lock:
            size = self.size
            target.parent.mkdir(parents=True, exist_ok=True)
            backup = backup_if_shrinking(target, size)
            self._closure.save(target)
        return size, backup

    # -- peer robots (see solid_ros.ros.peers) -----------------------------------------------

    def add_peer_keyframe(self, d: DescriptorMessage) -> bool:
        """Store another robot's keyframe descriptor; False when it is already stored
        (raises SolidError if refused)."""
        with self._describe_lock:
            if self._detector.database.has_foreign(d.robot, d.index):
                return False
            self._detector.add_peer_keyframe(d.robot, d.index, d.stamp_ns, d.r_solid,
                                             d.heading, d.pose)
            return True

    def own_cloud(self, index: int, stamp_ns: int) -> KeyframeCloud | None:
        """This robot's stored cloud of keyframe ``index`` as a peer gets it
        (:meth:`LoopDetector.peer_cloud`) if it is stamped ``stamp_ns``, else None (a request
        naming another stamp is not for this keyframe)."""
        with self._describe_lock:  # stage 1 adds to what own_seq reads
            db = self._detector.database
            seq = db.own_seq(index)
            if seq is None or db.match_info(seq)[2] != stamp_ns:
                return None
            return self._detector.peer_cloud(index)

    def own_keyframes(self, limit: int) -> list[tuple[int, int, FloatArray, FloatArray,
                                                      FloatArray | None]]:
        """This robot's newest stored keyframes (for a peer's catch-up)."""
        with self._describe_lock:
            return self._detector.own_keyframes(limit)

    def add_peer_loop(self, loop: LoopCandidate, robot: int) -> bool:
        """A loop ``robot`` published against this robot (:meth:`LoopClosure.add_peer_loop`,
        under the stage-2 lock, where the graph holds this robot's own)."""
        with self._verify_lock:
            return self._closure.add_peer_loop(loop, robot)

    def align(self, peers: Mapping[int, Mapping[int, FloatArray]],
              paths: Mapping[int, Mapping[int, float]]) -> list[BackendEvent]:
        """:meth:`LoopClosure.align` under the stage-2 lock (the graph's poses are read)."""
        with self._verify_lock:
            return self._closure.align(peers, paths)

    def alignments(self) -> list[PeerAlignment]:
        """Every peer's alignment as decided last (empty without the back end)."""
        with self._verify_lock:
            fleet = self._closure.fleet
            return [] if fleet is None else fleet.states()

    def forget_peer(self, robot: int) -> None:
        """Drop a peer's loops and alignment (it is no longer tracked)."""
        with self._verify_lock:
            if self._closure.fleet is not None:
                self._closure.fleet.forget(robot)

    def keyframe_clouds(self, poses: dict[int, FloatArray],
                        ) -> list[tuple[FloatArray, npt.NDArray[np.float32]]]:
        """``(pose, levelled points)`` of this session's kept keyframe clouds that have a pose
        in ``poses`` (by index), for the map; under the stage-2 lock, which stores clouds."""
        with self._verify_lock:
            return keyframe_clouds(self._detector, poses)

    def values(self) -> dict[str, object]:
        """The detector's /diagnostics values: keyframe clouds, verification outcomes and
        what the calibration learned."""
        det = self._detector
        out: dict[str, object] = {
            'keyframe_clouds': len(det.clouds),
            'keyframe_clouds_mb': f'{det.clouds.nbytes / 1e6:.2f}',
            'keyframe_clouds_dropped': det.clouds.dropped}
        for reason, count in sorted(dict(det.reasons).items()):
            out[f'verify_{reason}'] = count
        # What the run learned about itself, and the bars it sets (core/verification).
        for key, value in det.calibration.learned.as_dict().items():
            out[f'calibration_{key}'] = value
        bars = det.bars
        out['verify_max_conflict_in_force'] = f'{bars.max_conflict:.4f}'
        out['odom_check_drift_in_force'] = f'{bars.odom_drift_per_m:.4f}'
        return out
