"""Rolling store of SOLiD descriptors with exact nearest-neighbour search by cosine distance.

Storage is a ring buffer of arrays: unit-normalised R-SOLiD and A-SOLiD as float32, stamps,
per-session indices, session ids and an optional pose per scan. The arrays start small and
double as scans arrive (amortised O(1) per insert) until they hold ``capacity`` rows; only then
does the ring wrap, so growing never moves a scan to another slot. Every stored scan also has a
sequence number ``seq`` (0, 1, 2, ... in insertion order, loaded scans first); its slot in the
arrays is ``seq % capacity`` and the live scans are the last ``size`` sequence numbers.

Search returns the ``k`` nearest valid scans, re-ranked by exact cosine distance (float64 over
the stored vectors). Brute force is one float32 matrix-vector product. The kd-tree mode indexes
the L2-normalised R-SOLiD (on unit vectors ``|a - b|^2 = 2 * cosine_distance``, so the order is
the same) and searches the scans added since its last rebuild exactly, so nothing is missed.

A scan whose R-SOLiD is all zero (another robot's, or one from a file; the detector refuses
such clouds of its own) is stored, so indices stay contiguous, but it neither matches nor is
matched.

Peer robots' scans (:meth:`DescriptorDatabase.add_foreign`) live in a ring of their own,
``peer_capacity`` scans, so however many a peer sends they never evict this session's scans
(nor loaded ones); their sequence numbers start at ``PEER_SEQ_BASE``. Searches cover both
rings; at equal distance this session's scan ranks first.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import DatabaseError
from solid_ros.core.results import Match

__all__ = ['DescriptorDatabase', 'PEER_SEQ_BASE', 'POSE_FIELDS']

# Stored pose layout: position then unit quaternion (NaN when the scan had no pose).
POSE_FIELDS = ('x', 'y', 'z', 'qx', 'qy', 'qz', 'qw')
# The kd-tree is rebuilt when the unindexed tail reaches max(kdtree_rebuild_every,
# indexed / _TAIL_DIVISOR): a rebuild costs O(n log n), so a tail growing with n keeps the
# amortised insert cost O(log n) while the exact tail search stays a small fraction of n.
_TAIL_DIVISOR = 16
# Rows allocated at first; the arrays double from here up to ``capacity``.
_INITIAL_ROWS = 1024
# Sequence numbers of peers' scans start here (their own ring; see the module docstring).
PEER_SEQ_BASE = 1 << 56
_HAS_R = np.uint8(1)
_HAS_POSE = np.uint8(2)
_MAX_SESSION = 2**31 - 1  # session ids: SolidConfig.session_id's range

Int64Array = npt.NDArray[np.int64]


def unit_vector(v: npt.ArrayLike) -> tuple[npt.NDArray[np.float64], bool]:
    """Return ``v / |v|`` as float64 and whether ``v`` was non-zero and finite."""
    arr = np.asarray(v, dtype=np.float64).ravel()
    norm = float(np.linalg.norm(arr))
    if not math.isfinite(norm) or norm == 0.0:
        return np.zeros_like(arr), False
    return arr / norm, True


class DescriptorDatabase:
    """Ring of at most ``capacity`` descriptors; the oldest scan is evicted when it is full.

    Args:
        config: settings; reads ``capacity``, ``search``, ``kdtree_rebuild_every``,
            ``session_id``, ``num_range`` and ``num_angle``.
    """

    def __init__(self, config: SolidConfig) -> None:
        self.config = config
        cap = config.capacity
        self.capacity = cap
        self.session_id = config.session_id
        self.num_range = config.num_range
        self.num_angle = config.num_angle
        rows = min(cap, _INITIAL_ROWS)
        self._r = np.zeros((rows, self.num_range), dtype=np.float32)
        self._a = np.zeros((rows, self.num_angle), dtype=np.float32)
        self._stamp = np.zeros(rows, dtype=np.int64)
        self._index = np.zeros(rows, dtype=np.int64)
        self._session = np.zeros(rows, dtype=np.int32)
        self._pose = np.zeros((rows, len(POSE_FIELDS)), dtype=np.float32)
        self._flags = np.zeros(rows, dtype=np.uint8)
        # Stored vector for an all-zero R-SOLiD: the farthest possible from every
        # non-negative unit query, so it never crowds the top k.
        self._sentinel = np.full(self.num_range, -1.0 / math.sqrt(self.num_range), np.float32)
        # The stored scans are seqs _oldest .. _next - 1. Stage 2 of solid_node reads
        # oldest_seq while stage 1 adds, so _oldest is a field of its own that never runs
        # ahead of the scans stored (next - size did, for an instant, between the two).
        self._next = 0  # next sequence number
        self._oldest = 0
        self._size = 0
        self._session_count = 0  # scans added in the current session (the next index)
        self._last_stamp: int | None = None
        self._monotone = True  # current-session stamps never decreased
        # Sequence numbers of this session's scans, oldest first (scans of other sessions,
        # e.g. peer robots, may be interleaved with them).
        self._own: deque[int] = deque()
        self._tree: Any = None  # scipy.spatial.cKDTree, imported only in kd-tree mode
        self._tree_seqs: Int64Array = np.zeros(0, dtype=np.int64)
        self._tree_hi = 0  # the tree holds scans with seq < _tree_hi
        self._peers: DescriptorDatabase | None = None  # peers' ring, made on first use
        self._peer_keys: dict[tuple[int, int], int] = {}  # (session, index) -> its seq

    # ----------------------------------------------------------------------------- state
    @property
    def size(self) -> int:
        """Number of stored scans (all sessions, peers' included)."""
        return self._size + (self._peers.size if self._peers is not None else 0)

    @property
    def peer_size(self) -> int:
        """Number of stored peers' scans (in their own ring of ``peer_capacity``)."""
        return self._peers.size if self._peers is not None else 0

    @property
    def session_count(self) -> int:
        """Scans added in the current session; also the index the next one gets."""
        return self._session_count

    @property
    def oldest_seq(self) -> int:
        """Sequence number of the oldest stored scan of this session or a loaded one."""
        return self._oldest

    @property
    def next_seq(self) -> int:
        """Sequence number the next added scan of this session gets."""
        return self._next

    def stored_seqs(self) -> list[int]:
        """Sequence numbers of every stored scan in :meth:`export_arrays` order."""
        out = list(range(self.oldest_seq, self._next))
        if self._peers is not None:
            out += [PEER_SEQ_BASE + s for s in range(self._peers.oldest_seq,
                                                     self._peers.next_seq)]
        return out

    def _arrays(self) -> tuple[npt.NDArray[np.generic], ...]:
        return (self._r, self._a, self._stamp, self._index, self._session, self._pose,
                self._flags)

    @property
    def allocated(self) -> int:
        """Rows allocated now (grows by doubling up to ``capacity``, peers' ring included)."""
        return len(self._flags) + (self._peers.allocated if self._peers is not None else 0)

    @property
    def nbytes(self) -> int:
        """Bytes the allocated arrays hold (the kd-tree's copy excluded)."""
        return (sum(a.nbytes for a in self._arrays())
                + (self._peers.nbytes if self._peers is not None else 0))

    @property
    def bytes_per_scan(self) -> int:
        """Storage bytes of one scan (one row of every array)."""
        return sum(a.itemsize * math.prod(a.shape[1:]) for a in self._arrays())

    @property
    def stored_bytes(self) -> int:
        """Bytes the stored scans use: ``size * bytes_per_scan``."""
        return self.size * self.bytes_per_scan

    def _reserve(self, rows: int) -> None:
        """Grow the arrays to hold at least ``rows`` (<= capacity) rows, doubling."""
        have = self.allocated
        if rows <= have:
            return
        new = min(self.capacity, max(rows, 2 * have))
        grown = []
        for a in self._arrays():
            b = np.zeros((new, *a.shape[1:]), dtype=a.dtype)
            b[:have] = a
            grown.append(b)
        (self._r, self._a, self._stamp, self._index, self._session, self._pose,
         self._flags) = grown

    def slot(self, seq: int) -> int:
        """Array slot of a stored scan."""
        return seq % self.capacity

    def _peer(self, seq: int) -> DescriptorDatabase | None:
        """The peers' ring when ``seq`` is one of its scans."""
        return self._peers if seq >= PEER_SEQ_BASE else None

    def is_stored(self, seq: int) -> bool:
        """Whether scan ``seq`` is still stored (not evicted)."""
        if seq >= PEER_SEQ_BASE:
            return self._peers is not None and self._peers.is_stored(seq - PEER_SEQ_BASE)
        return self.oldest_seq <= seq < self._next

    def heading(self, seq: int) -> npt.NDArray[np.float32]:
        """Heading signature (A-SOLiD unless heading_weight is range), unit-normalised."""
        if (peers := self._peer(seq)) is not None:
            return peers.heading(seq - PEER_SEQ_BASE)
        row: npt.NDArray[np.float32] = self._a[self.slot(seq)]
        return row

    def r_solid(self, seq: int) -> npt.NDArray[np.float32]:
        """R-SOLiD (unit-normalised; zeros for an empty scan) of a stored scan."""
        if (peers := self._peer(seq)) is not None:
            return peers.r_solid(seq - PEER_SEQ_BASE)
        s = self.slot(seq)
        if not self._flags[s] & _HAS_R:
            return np.zeros(self.num_range, dtype=np.float32)
        row: npt.NDArray[np.float32] = self._r[s]
        return row

    def pose(self, seq: int) -> npt.NDArray[np.float32] | None:
        """Stored pose ``(x, y, z, qx, qy, qz, qw)`` of a scan, or None."""
        if (peers := self._peer(seq)) is not None:
            return peers.pose(seq - PEER_SEQ_BASE)
        s = self.slot(seq)
        return self._pose[s] if self._flags[s] & _HAS_POSE else None

    def match_info(self, seq: int) -> tuple[int, int, int]:
        """Return ``(index, session, stamp_ns)`` of a stored scan."""
        if (peers := self._peer(seq)) is not None:
            return peers.match_info(seq - PEER_SEQ_BASE)
        s = self.slot(seq)
        return int(self._index[s]), int(self._session[s]), int(self._stamp[s])

    # ---------------------------------------------------------------------------- insert
    def add(self, r_solid: npt.ArrayLike, heading: npt.ArrayLike, stamp_ns: int,
            pose: Sequence[float] | npt.ArrayLike | None = None) -> int:
        """Store one scan of the current session, evicting the oldest when full.

        Args:
            r_solid: R-SOLiD, shape (N_r,) (need not be normalised).
            heading: heading signature (:attr:`Descriptor.heading`), shape (N_a,).
            stamp_ns: stamp in integer nanoseconds.
            pose: optional ``(x, y, z, qx, qy, qz, qw)``.

        Returns:
            The index of the scan within the current session.
        """
        index = self._session_count
        self._own.append(self._next)
        self._put(r_solid, heading, int(stamp_ns), index, self.session_id, pose)
        self._session_count += 1
        if self._last_stamp is not None and stamp_ns < self._last_stamp:
            self._monotone = False
        self._last_stamp = int(stamp_ns)
        self._maybe_rebuild()
        return index

    def sessions(self) -> set[int]:
        """Session ids of the stored scans."""
        out = {int(v) for v in np.unique(self._session[:self._size])}
        return out | (self._peers.sessions() if self._peers is not None else set())

    def own_seq(self, index: int) -> int | None:
        """Sequence number of this session's scan ``index``, or None when not stored."""
        own = self._own
        while own and own[0] < self.oldest_seq:
            own.popleft()
        k = int(index) - (self._session_count - len(own))
        return own[k] if 0 <= k < len(own) else None

    def add_foreign(self, session: int, index: int, r_solid: npt.ArrayLike,
                    heading: npt.ArrayLike, stamp_ns: int,
                    pose: Sequence[float] | npt.ArrayLike | None = None) -> int:
        """Store a scan of another session (a peer robot's keyframe) while this one runs.

        Such scans are never excluded as recent. They go to the peers' ring
        (``peer_capacity`` scans, the oldest peer scan evicted beyond it), never evicting a
        scan of this session or a loaded one.

        Args:
            session: its session (robot) id; not this database's ``session_id``.
            index: its index within that session.
            r_solid, heading, stamp_ns, pose: as for :meth:`add`.

        Returns:
            Its sequence number (``PEER_SEQ_BASE`` or more).

        Raises:
            DatabaseError: the session is this database's own, the scan is already stored
                (see :meth:`has_foreign`), a shape is wrong, or ``peer_capacity`` is 0.
        """
        session, index = int(session), int(index)
        if session == self.session_id:
            raise DatabaseError(f"session {session} is this database's own session id")
        if (session, index) in self._peer_keys:
            raise DatabaseError(f'scan {index} of session {session} is already stored')
        peers = self._peer_ring()
        if peers.size == peers.capacity:  # its oldest goes
            gone_index, gone_session, _ = peers.match_info(peers.oldest_seq)
            self._peer_keys.pop((gone_session, gone_index), None)
        seq = peers._next
        peers._put(r_solid, heading, int(stamp_ns), index, session, pose)
        peers._maybe_rebuild()
        self._peer_keys[(session, index)] = seq
        return PEER_SEQ_BASE + seq

    def has_foreign(self, session: int, index: int) -> bool:
        """Whether a peer's scan ``index`` of ``session`` is stored (a repeat is refused)."""
        return (int(session), int(index)) in self._peer_keys

    def foreign_seq(self, session: int, index: int) -> int | None:
        """Sequence number of a peer's stored scan ``index`` of ``session`` (None: not
        stored)."""
        seq = self._peer_keys.get((int(session), int(index)))
        return None if seq is None else PEER_SEQ_BASE + seq

    def _peer_ring(self) -> DescriptorDatabase:
        if self._peers is None:
            cap = self.config.peer_capacity
            if cap <= 0:
                raise DatabaseError("peer_capacity is 0: peers' scans are not stored")
            self._peers = DescriptorDatabase(self.config.replace(capacity=cap))
        return self._peers

    def _put(self, r_solid: npt.ArrayLike, heading: npt.ArrayLike, stamp_ns: int, index: int,
             session: int, pose: Sequence[float] | npt.ArrayLike | None) -> None:
        r = np.asarray(r_solid, dtype=np.float64).ravel()
        a = np.asarray(heading, dtype=np.float64).ravel()
        if r.shape != (self.num_range,) or a.shape != (self.num_angle,):
            raise DatabaseError(f'descriptor shape ({r.shape[0]}, {a.shape[0]}) does not match '
                                f'the database ({self.num_range}, {self.num_angle})')
        p = None
        if pose is not None:  # checked before anything changes
            p = np.asarray(pose, dtype=np.float32).ravel()
            if p.shape != (len(POSE_FIELDS),):
                raise DatabaseError(f'pose must have {len(POSE_FIELDS)} values '
                                    f'{POSE_FIELDS}, got shape {p.shape}')
        s = self._next % self.capacity
        self._reserve(s + 1)
        if self._size == self.capacity:
            self._oldest += 1  # the scan in slot s is gone before it is overwritten
        r_unit, has_r = unit_vector(r)
        a_unit, _ = unit_vector(a)
        flags = _HAS_R if has_r else np.uint8(0)
        self._r[s] = r_unit if has_r else self._sentinel
        self._a[s] = a_unit
        self._stamp[s] = stamp_ns
        self._index[s] = index
        self._session[s] = session
        if p is not None:
            self._pose[s] = p
            flags |= _HAS_POSE
        else:
            self._pose[s] = np.nan
        self._flags[s] = flags
        self._next += 1
        self._size = min(self._size + 1, self.capacity)

    def _maybe_rebuild(self, force: bool = False) -> None:
        if self.config.search != 'kdtree':
            return
        tail = self._next - self._tree_hi
        if not force and tail < max(self.config.kdtree_rebuild_every,
                                    len(self._tree_seqs) // _TAIL_DIVISOR):
            return
        seqs = np.arange(self.oldest_seq, self._next, dtype=np.int64)
        slots = seqs % self.capacity
        keep = (self._flags[slots] & _HAS_R) != 0
        seqs, slots = seqs[keep], slots[keep]
        self._tree_seqs = seqs
        self._tree_hi = self._next
        from scipy.spatial import cKDTree  # 0.45 s to import: only when used

        self._tree = (cKDTree(self._r[slots].astype(np.float64), balanced_tree=False,
                              compact_nodes=False) if len(seqs) else None)

    # ---------------------------------------------------------------------------- search
    def search(self, r_solid: npt.ArrayLike, stamp_ns: int, k: int, *,
               exclude_frames: int = 0, exclude_sec: float = 0.0) -> list[Match]:
        """Return the ``k`` nearest stored scans by exact cosine distance, nearest first.

        Args:
            r_solid: R-SOLiD of the query, shape (N_r,).
            stamp_ns: stamp of the query, integer nanoseconds.
            k: number of scans to return (fewer when fewer are eligible).
            exclude_frames: skip the most recent N scans of the current session.
            exclude_sec: skip current-session scans with stamp > query stamp - this
                (0 = off). Both rules apply: whichever excludes more wins. Scans of loaded
                sessions are never excluded.

        Returns:
            Matches sorted by distance; empty when the query R-SOLiD is all zero.
        """
        q, ok = unit_vector(r_solid)
        if q.shape != (self.num_range,):
            raise DatabaseError(f'query R-SOLiD has {q.shape[0]} bins, the database '
                                f'{self.num_range}')
        if not ok or self.size == 0 or k <= 0:
            return []
        found = self._search_own(q, int(stamp_ns), k, exclude_frames, exclude_sec)
        if self._peers is None or self._peers.size == 0:
            return found
        peers = [Match(PEER_SEQ_BASE + m.seq, m.index, m.session, m.stamp_ns, m.distance)
                 for m in self._peers.search(r_solid, stamp_ns, k)]
        return sorted(found + peers, key=lambda m: (m.distance, m.seq))[:k]

    def _search_own(self, q: npt.NDArray[np.float64], stamp_ns: int, k: int,
                    exclude_frames: int, exclude_sec: float) -> list[Match]:
        if self._size == 0:
            return []
        cut, time_limit = self._exclusion(stamp_ns, exclude_frames, exclude_sec)
        if self.config.search == 'kdtree' and self._tree is not None:
            seqs = self._search_tree(q, k, cut, time_limit)
        else:
            seqs = self._search_brute(q, k, cut, time_limit)
        return self._rerank(q, seqs, k)

    def _exclusion(self, stamp_ns: int, frames: int, sec: float) -> tuple[int, int | None]:
        """Return ``cut`` (this session's scans with seq >= cut are excluded) and, when the
        stamps are not monotone, the stamp above which its scans are also excluded."""
        own = self._own
        while own and own[0] < self.oldest_seq:
            own.popleft()
        if not own:
            return self._next, None
        if frames <= 0:
            cut = self._next
        else:
            cut = own[max(len(own) - frames, 0)]
        if sec <= 0.0:
            return cut, None
        limit = stamp_ns - int(round(sec * 1e9))
        if not self._monotone:
            return cut, limit
        lo, hi = 0, len(own)  # first of this session's scans with stamp > limit
        while lo < hi:
            mid = (lo + hi) // 2
            if self._stamp[own[mid] % self.capacity] > limit:
                hi = mid
            else:
                lo = mid + 1
        return min(cut, own[lo] if lo < len(own) else self._next), None

    def _slot_ranges(self, seq_lo: int, seq_hi: int) -> list[tuple[int, int]]:
        """Slot ranges of the stored sequence numbers ``[seq_lo, seq_hi)``."""
        if seq_hi <= seq_lo:
            return []
        a, n = seq_lo % self.capacity, seq_hi - seq_lo
        if a + n <= self.capacity:
            return [(a, a + n)]
        return [(a, self.capacity), (0, a + n - self.capacity)]

    def _time_excluded(self, seqs: Int64Array, limit: int | None) -> npt.NDArray[np.bool_]:
        if limit is None:
            return np.zeros(len(seqs), dtype=bool)
        slots = seqs % self.capacity
        out: npt.NDArray[np.bool_] = ((self._session[slots] == self.session_id)
                                      & (self._stamp[slots] > limit))
        return out

    def _search_brute(self, q: npt.NDArray[np.float64], k: int, cut: int,
                      limit: int | None) -> Int64Array:
        return self._exact(q, k, self.oldest_seq, self._next, cut, limit)

    def _exact(self, q: npt.NDArray[np.float64], k: int, seq_lo: int, seq_hi: int, cut: int,
               limit: int | None) -> Int64Array:
        """Top ``k`` valid seqs in ``[seq_lo, seq_hi)`` by float32 dot product."""
        if seq_hi <= seq_lo:
            return np.zeros(0, dtype=np.int64)
        q32 = q.astype(np.float32)
        everything = seq_hi - seq_lo == self._size
        own = self.session_id
        if everything:  # positions in `dots` are slots: no gather copy
            dots = self._r[:self._size] @ q32
            for a, b in self._slot_ranges(max(cut, seq_lo), seq_hi):
                recent = dots[a:b]  # a view: only this session's recent scans are excluded
                recent[self._session[a:b] == own] = -np.inf
        else:  # positions are seq - seq_lo
            slots = np.concatenate([np.arange(a, b)
                                    for a, b in self._slot_ranges(seq_lo, seq_hi)])
            dots = self._r[slots] @ q32
            first = max(cut - seq_lo, 0)
            recent = dots[first:]
            recent[self._session[slots[first:]] == own] = -np.inf
        if limit is not None:
            seqs = (self._seqs_of_slots(np.arange(self._size)) if everything
                    else np.arange(seq_lo, seq_hi, dtype=np.int64))
            dots[self._time_excluded(seqs, limit)] = -np.inf
        n = len(dots)
        kk = min(k, n)
        top = np.argpartition(dots, n - kk)[n - kk:]
        top = top[dots[top] > -np.inf]
        if everything:
            return self._seqs_of_slots(top)
        return top.astype(np.int64) + seq_lo

    def _seqs_of_slots(self, slots: npt.NDArray[np.integer]) -> Int64Array:
        last = self._next - 1
        return last - ((last - slots.astype(np.int64)) % self.capacity)

    def _search_tree(self, q: npt.NDArray[np.float64], k: int, cut: int,
                     limit: int | None) -> Int64Array:
        assert self._tree is not None
        tree_seqs = self._tree_seqs
        n_tree = len(tree_seqs)
        oldest = self.oldest_seq
        # Tree entries known to be invalid now (evicted or excluded) are asked for on top.
        stale = int(np.searchsorted(tree_seqs, oldest))
        excluded = n_tree - int(np.searchsorted(tree_seqs, cut))
        kq = min(n_tree, k + stale + excluded)
        while True:
            _, idx = self._tree.query(q, k=kq)
            idx = np.atleast_1d(idx)
            idx = idx[idx < n_tree]
            seqs = tree_seqs[idx]
            mine = self._session[seqs % self.capacity] == self.session_id
            valid = ((seqs >= oldest) & ((seqs < cut) | ~mine)
                     & ~self._time_excluded(seqs, limit))
            if int(valid.sum()) >= k or kq >= n_tree:
                break
            kq = min(n_tree, 2 * kq)
        found = seqs[valid][:k]
        tail = self._exact(q, k, max(self._tree_hi, oldest), self._next, cut, limit)
        return np.concatenate([found, tail])

    def _rerank(self, q: npt.NDArray[np.float64], seqs: Int64Array, k: int) -> list[Match]:
        if len(seqs) == 0:
            return []
        slots = seqs % self.capacity
        has_r = (self._flags[slots] & _HAS_R) != 0
        seqs, slots = seqs[has_r], slots[has_r]
        # Row-wise sum, not BLAS: the result must not depend on which rows are gathered.
        dist = np.clip(1.0 - (self._r[slots].astype(np.float64) * q).sum(axis=1), 0.0, 2.0)
        order = np.lexsort((seqs, dist))[:k]
        return [Match(int(seqs[i]), int(self._index[slots[i]]), int(self._session[slots[i]]),
                      int(self._stamp[slots[i]]), float(dist[i])) for i in order]

    # ------------------------------------------------------------------------ persistence
    def export_arrays(self) -> dict[str, npt.NDArray[np.generic]]:
        """Return the stored scans, oldest first, as plain arrays (for saving).

        This session's and loaded scans first, then peers' scans (as :meth:`stored_seqs`).
        Keys: ``r_solid`` (n, N_r) float32 unit (zeros for empty scans), ``a_solid`` (n,
        N_a) float32 (the heading signature; the file key keeps its first name),
        ``stamps_ns`` int64, ``indices`` int64, ``sessions`` int32, ``poses`` (n, 7)
        float32 (NaN rows without pose).
        """
        slots = np.arange(self.oldest_seq, self._next, dtype=np.int64) % self.capacity
        r = self._r[slots].copy()
        r[(self._flags[slots] & _HAS_R) == 0] = 0.0
        poses = self._pose[slots].copy()
        poses[(self._flags[slots] & _HAS_POSE) == 0] = np.nan
        out = {'r_solid': r, 'a_solid': self._a[slots].copy(),
               'stamps_ns': self._stamp[slots].copy(), 'indices': self._index[slots].copy(),
               'sessions': self._session[slots].copy(), 'poses': poses}
        if self._peers is not None and self._peers.size:  # then the peers' scans
            theirs = self._peers.export_arrays()
            out = {k: np.concatenate([v, theirs[k]]) for k, v in out.items()}
        return out

    def import_arrays(self, arrays: dict[str, npt.NDArray[np.generic]]) -> None:
        """Store scans of earlier sessions (as given by :meth:`export_arrays`).

        Only allowed before the current session has added a scan. When there are more scans
        than ``capacity`` the newest ``capacity`` are kept.

        Raises:
            DatabaseError: the current session already started, or a stored session id
                equals this session's ``session_id``.
        """
        if self._session_count:
            raise DatabaseError('scans can only be loaded before the session adds any')
        sessions = np.asarray(arrays['sessions'])
        if np.any((sessions < 0) | (sessions > _MAX_SESSION)):
            bad = int(sessions[(sessions < 0) | (sessions > _MAX_SESSION)][0])
            raise DatabaseError(f'the saved database holds session id {bad}, outside 0 to '
                                f'{_MAX_SESSION}: not a database this version wrote')
        if np.any(sessions == self.session_id):
            raise DatabaseError(f'the saved database already holds session_id '
                                f'{self.session_id}; give this run another session_id '
                                f'(e.g. {_free_session(sessions)}) so its scans stay '
                                'distinguishable')
        n = len(sessions)
        first = max(0, n - self.capacity)
        count = n - first
        slots = np.arange(self._next, self._next + count) % self.capacity
        self._reserve(min(self.capacity, self._next + count))
        # The scans of the slots overwritten are gone first (see ``_oldest``).
        self._oldest = self._next + count - min(self._size + count, self.capacity)
        r_unit, has_r = _unit_rows(np.asarray(arrays['r_solid'])[first:])
        r_unit[~has_r] = self._sentinel
        a_unit, _ = _unit_rows(np.asarray(arrays['a_solid'])[first:])
        poses = np.asarray(arrays['poses'], dtype=np.float32)[first:]
        has_pose = np.all(np.isfinite(poses), axis=1)
        self._r[slots] = r_unit
        self._a[slots] = a_unit
        self._stamp[slots] = np.asarray(arrays['stamps_ns'])[first:]
        self._index[slots] = np.asarray(arrays['indices'])[first:]
        self._session[slots] = sessions[first:]
        self._pose[slots] = poses
        self._flags[slots] = np.where(has_r, _HAS_R, 0) | np.where(has_pose, _HAS_POSE, 0)
        self._next += count
        self._size = min(self._size + count, self.capacity)
        self._maybe_rebuild(force=True)


def _free_session(sessions: npt.NDArray[np.generic]) -> int:
    """The smallest valid session id not in ``sessions``."""
    used = {int(v) for v in np.unique(sessions)}
    return next(i for i in range(len(used) + 1) if i not in used)


def _unit_rows(rows: npt.NDArray[np.generic]) -> tuple[npt.NDArray[np.float32],
                                                        npt.NDArray[np.bool_]]:
    """Rows scaled to unit length as float32, and which rows were non-zero and finite.

    Rows already unit to float32 precision (as saved) are kept bit for bit, so a loaded
    database answers exactly like the one that was saved.
    """
    r64 = rows.astype(np.float64)
    norms = np.linalg.norm(r64, axis=1)
    ok = np.isfinite(norms) & (norms > 0.0)
    rescale = ok & (np.abs(norms - 1.0) > 1e-5)
    out = rows.astype(np.float32)
    out[rescale] = (r64[rescale] / norms[rescale, None]).astype(np.float32)
    out[~ok] = 0.0
    return out, ok
