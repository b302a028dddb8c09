"""Descriptor stage: keyframe gate, usable clouds, keyframe points, database query, margins.

:meth:`Proposer.propose` gates a scan, levels it (sensor mounting), describes it, queries the
database for earlier places and stores the descriptor afterwards (so the scan never matches
itself). The :class:`~solid_ros.core.candidates.proposal.Proposal` it returns is what the
verification stage (:mod:`solid_ros.core.flow.verify_stage`) works on.

Indices: ``query_index`` is the index of the scan among the keyframes this session stored
(0, 1, 2, ...; gated-out scans get none). ``match_index`` is the index of the matched scan in
its own session ``match_session`` (for scans loaded from a file, the index they had there).

Candidates: the ``num_candidates`` nearest stored scans by descriptor distance that are below
``distance_threshold`` and pass the margin test (``min_margin``). The margin of a candidate is
the distance of the nearest scan outside its ``margin_neighbourhood`` minus its own distance
(``math.inf`` when there is none); the search fetches ``num_candidates + 2 *
margin_neighbourhood + 1`` scans so that this next-best distinct place is always among them.

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
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.hits import view_centre
from solid_ros.core.candidates.proposal import Hit, Proposal
from solid_ros.core.config import SolidConfig
from solid_ros.core.descriptor.matching import estimate_yaw
from solid_ros.core.descriptor.solid import describe, preprocess, voxel_downsample
from solid_ros.core.errors import CloudError
from solid_ros.core.flow.place import same_place
from solid_ros.core.flow.state import DetectorState
from solid_ros.core.geometry import rotation_deg
from solid_ros.core.results import Descriptor, LoopCandidate, Match
from solid_ros.core.verification.mixed_pixels import drop_mixed_pixels
from solid_ros.core.verification.verifier import TIGHT_GRID

__all__ = ['Proposer']

FloatArray = npt.NDArray[np.float64]


class Proposer:
    """The descriptor stage of a detector.

    Args:
        state: the detector's shared state (this stage writes the keyframes' sequence
            numbers, view centres and path into it).
    """

    def __init__(self, state: DetectorState) -> None:
        self._state = state
        # The descriptor's gate without the voxel grid (replace() costs about 0.5 ms).
        self.gate_cfg = state.config.replace(voxel_size=0.0)
        self._kf_stamp: int | None = None
        self._kf_pose: FloatArray | None = None
        self._kf_segment: int | None = None  # the odometry's segment of the last keyframe

    def reconfigure(self, config: SolidConfig) -> None:
        """Follow new settings (the state's are already replaced)."""
        self.gate_cfg = config.replace(voxel_size=0.0)

    def reset(self) -> None:
        """Forget the last keyframe (the gate keeps the next scan)."""
        self._kf_stamp = self._kf_pose = self._kf_segment = None

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
        cfg = self._state.config
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

    def propose(self, points: npt.ArrayLike, stamp: int, vec: FloatArray | None,
                segment: int | None = None) -> Proposal | None:
        """Gate, level, describe, query, store the descriptor of a scan with a checked
        ``stamp`` and pose ``vec`` (``segment``: the odometry's segment of the pose).

        Returns:
            The proposal, or None for a gated-out scan.

        Raises:
            CloudError: no usable point (see the module docstring); nothing changed.
        """
        state = self._state
        if not self.is_keyframe(stamp, vec):
            self._check_usable(state.mount.level(points))  # refused alike, kept or not
            return None
        t0 = time.perf_counter()
        pts = state.mount.level(points)
        desc = describe(pts, state.config)
        if desc.num_points == 0:  # every point dropped: the R-SOLiD is all zero
            raise CloudError(_unusable(np.shape(pts), state.config))
        verifier = state.verifier
        cloud = self.keyframe_points(pts) if verifier is not None else None
        tight = cloud is not None and verifier is not None and verifier.is_tight(cloud)
        if tight:
            cloud = self.keyframe_points(pts, tight=True, up=state.mount.upright(vec))
        t1 = time.perf_counter()
        proposal = self.propose_descriptor(desc, stamp, vec, cloud, segment)
        return replace(proposal, descriptor=desc, tight=tight, describe_ms=(t1 - t0) * 1e3,
                       search_ms=(time.perf_counter() - t1) * 1e3)

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
            raise CloudError(_unusable(np.shape(arr), self.gate_cfg))

    def _any_usable(self, points: npt.ArrayLike) -> bool:
        cfg = self.gate_cfg
        kept = preprocess(points, cfg)
        return bool(np.any(np.hypot(kept[:, 0], kept[:, 1]) < cfg.max_distance))

    def keyframe_points(self, points: npt.ArrayLike, tight: bool = False,
                        up: FloatArray | None = None) -> FloatArray:
        """Range gate and FOV clip as for the descriptor, then the verification voxel grid
        (``tight``: the tight-space one, see ``verify_tight_range``, after dropping the scan's
        mixed pixels, see :mod:`solid_ros.core.verification.mixed_pixels`), laid out upright when
        ``up``
        (see :meth:`Mount.upright`; tight keyframes only)."""
        gated = preprocess(points, self.gate_cfg)
        if tight:  # near edges are everywhere in a tight space: their mixed pixels go
            gated = drop_mixed_pixels(gated)
        voxel = (TIGHT_GRID if tight else 1.0) * self._state.config.verify_voxel_size
        if up is None:
            return voxel_downsample(gated, voxel)
        out: FloatArray = voxel_downsample(gated[:, :3] @ up.T, voxel) @ up
        return out

    def propose_descriptor(self, desc: Descriptor, stamp: int, vec: FloatArray | None,
                           cloud: FloatArray | None, segment: int | None = None) -> Proposal:
        """Query the database with ``desc``, then store it as this session's next keyframe
        (with its cloud's view centre and the odometry path); the proposal."""
        state = self._state
        cfg = state.config
        db = state.database
        q_index = db.session_count
        hood = cfg.margin_neighbourhood
        hits = db.search(desc.r_solid, stamp, cfg.num_candidates + 2 * hood + 1,
                         exclude_frames=cfg.exclude_recent_frames,
                         exclude_sec=cfg.exclude_recent_sec)

        def margin_of(hit: Match) -> float:
            return min((o.distance for o in hits if not same_place(o, hit, hood)),
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
        state.own_seqs[q_index] = seq
        while len(state.own_seqs) > cfg.capacity:
            del state.own_seqs[next(iter(state.own_seqs))]
        if cloud is not None and len(cloud):
            state.views.put(q_index, view_centre(cloud, state.mount))
        # A reset the odometry announces (KISS-ICP restarts where the last pose was) is no
        # jump, but its new segment is another frame all the same: no path runs across it.
        reset = (segment is not None and self._kf_segment is not None
                 and segment != self._kf_segment)
        state.path.add(q_index, vec, reset)
        self._kf_stamp, self._kf_pose = stamp, vec
        self._kf_segment = segment if segment is not None else self._kf_segment
        return Proposal(q_index, stamp, seq, np.asarray(desc.heading, dtype=np.float64), cloud,
                        np.asarray(desc.r_solid, dtype=np.float64), vec, tuple(chosen), best)


def _unusable(shape: tuple[int, ...], cfg: SolidConfig) -> str:
    """The one-line reason a cloud of ``shape`` holds no usable point."""
    n = shape[0] if len(shape) == 2 and shape[1] > 0 else 0
    if n == 0:
        return 'no usable point: the cloud is empty'
    return (f'no usable point: 0 of {n} points are finite and inside the range gate '
            f'({cfg.min_range:g} to {cfg.max_range:g} m), the FOV ({cfg.fov_width_deg:g} deg) '
            f'and max_distance ({cfg.max_distance:g} m)')
