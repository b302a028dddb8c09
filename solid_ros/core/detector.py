"""Loop detector: keyframe gating, descriptor, database query, acceptance tests, insertion.

One call per scan, :meth:`LoopDetector.process`, describes the scan, queries the database for
earlier places (the scan itself is added afterwards, so it never matches itself) and returns
the accepted loop candidates.

Indices: ``query_index`` is the index of the scan among the keyframes this session stored
(0, 1, 2, ...; gated-out scans get none). ``match_index`` is the index of the matched scan in
its own session ``match_session`` (for scans loaded from a file, the index they had there).

Acceptance, in order: the loop gap (``min_loop_gap`` queries since the last accepted loop),
the distance threshold (strictly below), the margin test (``min_margin``), distinct places (a
further candidate must lie outside ``margin_neighbourhood`` of the ones already taken), and
``max_candidates``. The margin of a candidate is the distance of the nearest scan outside its
neighbourhood minus its own distance; ``math.inf`` when there is no such scan. The search
fetches ``num_candidates + 2 * margin_neighbourhood + 1`` scans so that this next-best
distinct place is always among them; the first ``num_candidates`` may become loops.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.database import DescriptorDatabase, Match
from solid_ros.core.descriptor import Descriptor, describe
from solid_ros.core.errors import ConfigError, SolidError
from solid_ros.core.geometry import pose_to_vector, rotation_deg
from solid_ros.core.matching import estimate_yaw

__all__ = ['LoopCandidate', 'LoopDetector']

_INT64 = (-(2**63), 2**63 - 1)


def _stamp(stamp_ns: Any) -> int:
    """The stamp as an int that the database's int64 arrays hold, else SolidError."""
    try:
        stamp = int(stamp_ns)
    except (TypeError, ValueError, OverflowError) as err:
        raise SolidError(f'stamp {stamp_ns!r} is not an integer number of nanoseconds') from err
    if not _INT64[0] <= stamp <= _INT64[1]:
        raise SolidError(f'stamp {stamp} ns is outside the int64 range')
    return stamp


@dataclass(frozen=True)
class LoopCandidate:
    """One accepted loop closure between the current scan and a stored one.

    Attributes:
        query_index: index of the query scan among this session's keyframes.
        match_index: index of the matched scan within its session.
        query_stamp_ns: stamp of the query scan, integer nanoseconds.
        match_stamp_ns: stamp of the matched scan, integer nanoseconds.
        match_session: session id of the matched scan.
        distance: cosine distance of the R-SOLiD pair, in [0, 2].
        yaw: heading of the query relative to the match, radians in (-pi, pi];
            p_match = Rz(yaw) p_query.
        margin: distance of the next-best distinct place minus ``distance``; ``math.inf``
            when there is none.
    """

    query_index: int
    match_index: int
    query_stamp_ns: int
    match_stamp_ns: int
    match_session: int
    distance: float
    yaw: float
    margin: float

    def to_dict(self) -> dict[str, Any]:
        """Return the fields as a plain dict."""
        return asdict(self)


class LoopDetector:
    """SOLiD loop-closure detector over a rolling database of keyframes.

    Args:
        config: settings; ``SolidConfig()`` when omitted.
        database: an existing database (e.g. loaded from a file) built with the same
            descriptor settings; a new empty one when omitted.
    """

    def __init__(self, config: SolidConfig | None = None,
                 database: DescriptorDatabase | None = None) -> None:
        self._config = config if config is not None else SolidConfig()
        self.database = database if database is not None else DescriptorDatabase(self._config)
        self.last_descriptor: Descriptor | None = None
        self.last_was_keyframe = False
        # Best stored match of the last query, accepted or not (offline PR curves need it).
        self.last_best: LoopCandidate | None = None
        self._kf_stamp: int | None = None
        self._kf_pose: npt.NDArray[np.float64] | None = None
        self._last_loop_query: int | None = None

    @property
    def config(self) -> SolidConfig:
        """Current settings."""
        return self._config

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

    def is_keyframe(self, stamp_ns: int, pose: npt.NDArray[np.float64] | None = None) -> bool:
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

    def process(self, points: npt.ArrayLike, stamp_ns: int,
                pose: Any = None) -> list[LoopCandidate]:
        """Handle one scan: gate, describe, query, then store it.

        Args:
            points: (N, 3+) array in the sensor frame.
            stamp_ns: scan stamp, integer nanoseconds.
            pose: optional sensor pose (see :func:`pose_to_vector`), used for keyframe gating
                and stored with the scan.

        Returns:
            Accepted loop candidates, best first (empty for a gated-out scan).

        Raises:
            SolidError: malformed points, pose or stamp (outside int64).
        """
        stamp = _stamp(stamp_ns)
        vec = pose_to_vector(pose) if pose is not None else None
        if not self.is_keyframe(stamp, vec):
            self.last_was_keyframe = False
            self.last_best = None
            return []
        return self.process_descriptor(describe(points, self._config), stamp, vec)

    def process_descriptor(self, desc: Descriptor, stamp_ns: int,
                           pose: Any = None) -> list[LoopCandidate]:
        """Like :meth:`process` for an already computed descriptor, without gating."""
        stamp = _stamp(stamp_ns)
        vec = pose_to_vector(pose) if pose is not None else None
        out = self._query(desc, stamp)
        self.database.add(desc.r_solid, desc.heading, stamp, vec)
        self.last_descriptor = desc
        self.last_was_keyframe = True
        self._kf_stamp, self._kf_pose = stamp, vec
        return out

    def _query(self, desc: Descriptor, stamp: int) -> list[LoopCandidate]:
        cfg = self._config
        q_index = self.database.session_count
        hood = cfg.margin_neighbourhood
        hits = self.database.search(desc.r_solid, stamp, cfg.num_candidates + 2 * hood + 1,
                                    exclude_frames=cfg.exclude_recent_frames,
                                    exclude_sec=cfg.exclude_recent_sec)

        def same_place(a: Match, b: Match) -> bool:
            return a.session == b.session and abs(a.index - b.index) <= hood

        self.last_best = None
        if hits:
            top = hits[0]
            self.last_best = LoopCandidate(
                query_index=q_index, match_index=top.index, query_stamp_ns=stamp,
                match_stamp_ns=top.stamp_ns, match_session=top.session, distance=top.distance,
                yaw=estimate_yaw(desc.heading, self.database.a_solid(top.seq),
                                 cfg.heading_match),
                margin=min((o.distance for o in hits if not same_place(o, top)),
                           default=math.inf) - top.distance)
        if (cfg.min_loop_gap and self._last_loop_query is not None
                and q_index - self._last_loop_query < cfg.min_loop_gap):
            return []

        taken: list[tuple[Match, float]] = []
        for hit in hits[:cfg.num_candidates]:
            if hit.distance >= cfg.distance_threshold or len(taken) >= cfg.max_candidates:
                break
            if any(same_place(hit, t) for t, _ in taken):
                continue
            margin = min((o.distance for o in hits if not same_place(o, hit)),
                         default=math.inf) - hit.distance
            if cfg.min_margin > 0.0 and margin < cfg.min_margin:
                continue
            taken.append((hit, margin))
        if taken:
            self._last_loop_query = q_index
        return [LoopCandidate(query_index=q_index, match_index=h.index, query_stamp_ns=stamp,
                              match_stamp_ns=h.stamp_ns, match_session=h.session,
                              distance=h.distance,
                              yaw=estimate_yaw(desc.heading, self.database.a_solid(h.seq),
                                               cfg.heading_match),
                              margin=margin)
                for h, margin in taken]

    def save(self, path: str | Path) -> Path:
        """Save the database (all sessions) atomically; see :mod:`solid_ros.core.persistence`."""
        from solid_ros.core.persistence import save_database

        return save_database(self.database, path)

    @classmethod
    def load(cls, path: str | Path, config: SolidConfig | None = None) -> LoopDetector:
        """Start a session that also queries the scans saved in ``path``.

        Raises:
            DatabaseError: unreadable file, different descriptor settings, or the file
                already holds ``config.session_id``.
        """
        from solid_ros.core.persistence import load_database

        cfg = config if config is not None else SolidConfig()
        return cls(cfg, database=load_database(path, cfg))
