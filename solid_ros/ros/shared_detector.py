"""The loop detector that solid_node's two threads share, each stage under its own lock.

Stage 1 (describe, search, store) and stage 2 (verify) each hold their lock while they use the
detector, so one keyframe is described while the one before it is verified; saving, resetting
and reconfiguring take both. Peer robots' keyframes are stored under the stage-1 lock, like
this robot's descriptors. No ROS import: the node and its tests hand it plain values.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.detector import CloudFetcher, LoopCandidate, LoopDetector, Proposal, ScanResult
from solid_ros.core.keyframes import KeyframeCloud
from solid_ros.core.mapping import keyframe_clouds
from solid_ros.core.proposals import GraphHint
from solid_ros.formats.peers import DescriptorMessage

__all__ = ['SharedDetector']

FloatArray = npt.NDArray[np.float64]


class SharedDetector:
    """A :class:`LoopDetector` behind the two stage locks.

    Args:
        detector: the detector to start with.
    """

    def __init__(self, detector: LoopDetector) -> None:
        self._detector = detector
        self._fetch_cloud: CloudFetcher | None = None
        self._describe_lock = threading.Lock()
        self._verify_lock = threading.Lock()

    @property
    def detector(self) -> LoopDetector:
        """The detector now (another one after :meth:`replace`)."""
        return self._detector

    @property
    def size(self) -> int:
        """Scans in its database."""
        return int(self._detector.database.size)

    def set_fetch_cloud(self, fetch: CloudFetcher | None) -> None:
        """Where clouds of other robots' keyframes come from, for this and later detectors."""
        self._fetch_cloud = self._detector.fetch_cloud = fetch

    # -- the two stages ----------------------------------------------------------------------

    def propose(self, points: npt.ArrayLike, stamp_ns: int, pose: Any) -> Proposal | None:
        """Stage 1: :meth:`LoopDetector.propose` under the stage-1 lock."""
        with self._describe_lock:
            return self._detector.propose(points, stamp_ns, pose=pose)

    def verify(self, proposal: Proposal,
               hint: GraphHint | None = None) -> tuple[ScanResult, LoopDetector]:
        """Stage 2: :meth:`LoopDetector.verify` (with the pose graph's ``hint``) under the
        stage-2 lock; also returns the detector that verified (a reset may replace it right
        after)."""
        with self._verify_lock:
            detector = self._detector
            return detector.verify(proposal, hint), detector

    def match_position(self, cand: LoopCandidate, proposal: Proposal,
                       detector: LoopDetector) -> FloatArray | None:
        """Position stored with the matched scan (any session), or None when unknown (or
        ``detector`` was replaced since it verified)."""
        seq = next((h.match.seq for h in proposal.hits
                    if (h.match.session, h.match.index) == (cand.match_session,
                                                            cand.match_index)), None)
        if seq is None:
            return None
        # Under the stage-1 lock: it stores scans, and may evict this one meanwhile.
        with self._describe_lock:
            db = detector.database
            if (detector is not self._detector or not db.is_stored(seq)
                    or db.match_info(seq)[:2] != (cand.match_index, cand.match_session)):
                return None
            stored = db.pose(seq)
            return None if stored is None else np.asarray(stored[:3], dtype=np.float64)

    # -- both locks --------------------------------------------------------------------------

    def reconfigure(self, config: SolidConfig) -> None:
        """Apply tunable settings (raises ConfigError if a read-only one differs)."""
        with self._describe_lock, self._verify_lock:
            self._detector.reconfigure(config)

    def replace(self, detector: LoopDetector) -> None:
        """Continue with ``detector`` (``~/reset``); it fetches peer clouds as before."""
        with self._describe_lock, self._verify_lock:
            if self._fetch_cloud is not None:
                detector.fetch_cloud = self._fetch_cloud
            self._detector = detector

    def save(self, path: str,
             map_poses: dict[tuple[int, int], FloatArray] | None = None) -> int:
        """Save the database to ``path`` (its folder made; the core writes a temporary file
        and renames it over ``path``), with the back end's map-frame poses when given; return
        the scans saved.

        Raises:
            SolidError, OSError: nothing was saved.
        """
        target = Path(path).expanduser()
        with self._describe_lock, self._verify_lock:
            size = self.size
            target.parent.mkdir(parents=True, exist_ok=True)
            self._detector.save(target, map_poses or None)
        return size

    # -- peer robots (see solid_ros.ros.peers) -----------------------------------------------

    def add_peer_keyframe(self, d: DescriptorMessage) -> None:
        """Store another robot's keyframe descriptor (raises SolidError if refused)."""
        with self._describe_lock:
            self._detector.add_peer_keyframe(d.robot, d.index, d.stamp_ns, d.r_solid,
                                             d.heading, d.pose)

    def own_cloud(self, index: int) -> KeyframeCloud | None:
        """This robot's stored cloud of keyframe ``index``, or None."""
        # Not under the stage-2 lock: the verify thread may hold it while it waits for a
        # peer's reply, and this runs on the executor that delivers that reply.
        with self._describe_lock:
            seq = self._detector.database.own_seq(index)
        return None if seq is None else self._detector.clouds.get(seq)

    def own_keyframes(self, limit: int) -> list[tuple[int, int, FloatArray, FloatArray,
                                                      FloatArray | None]]:
        """This robot's newest stored keyframes (for a peer's catch-up)."""
        with self._describe_lock:
            return self._detector.own_keyframes(limit)

    def keyframe_clouds(self, poses: dict[int, FloatArray],
                        ) -> list[tuple[FloatArray, npt.NDArray[np.float32]]]:
        """``(pose, levelled points)`` of this session's kept keyframe clouds that have a pose
        in ``poses`` (by index), for the map; under the stage-2 lock, which stores clouds."""
        with self._verify_lock:
            return keyframe_clouds(self._detector, poses)

    def values(self) -> dict[str, object]:
        """The detector's /diagnostics values: keyframe clouds and verification outcomes."""
        det = self._detector
        out: dict[str, object] = {
            'keyframe_clouds': len(det.clouds),
            'keyframe_clouds_mb': f'{det.clouds.nbytes / 1e6:.2f}',
            'keyframe_clouds_dropped': det.clouds.dropped}
        for reason, count in sorted(dict(det.reasons).items()):
            out[f'verify_{reason}'] = count
        return out
