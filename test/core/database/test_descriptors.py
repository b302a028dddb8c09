"""Tests of the rolling descriptor database: eviction, exclusion, search modes, empty scans."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.descriptors import DescriptorDatabase
from solid_ros.core.descriptor.solid import describe
from solid_ros.core.errors import DatabaseError

SEC = 1_000_000_000


def _db(**kw: object) -> DescriptorDatabase:
    return DescriptorDatabase(SolidConfig().replace(**kw))


def _random(n: int, seed: int = 0, dim: int = 40) -> npt.NDArray[np.float64]:
    return np.random.default_rng(seed).random((n, dim))


def _fill(db: DescriptorDatabase, r: npt.NDArray[np.float64], t0: int = 0) -> None:
    a = np.ones(db.num_angle)
    for i, row in enumerate(r):
        db.add(row, a, t0 + i * SEC // 10)


def test_eviction_is_oldest_first() -> None:
    db = _db(capacity=5, search='brute')
    _fill(db, _random(8))
    assert db.size == 5
    out = db.export_arrays()
    assert out['indices'].tolist() == [3, 4, 5, 6, 7]
    assert out['stamps_ns'].tolist() == [i * SEC // 10 for i in range(3, 8)]
    assert not db.is_stored(2) and db.is_stored(3)


class _Watched(DescriptorDatabase):
    """Records which scans the database says it stores after every field it sets, and which
    slot's scan an array write replaces: what another thread may read in between."""

    def __init__(self, config: SolidConfig) -> None:
        self.seen: list[tuple[int, int]] = []
        self.overwritten: list[tuple[int, int, int]] = []  # (slot, oldest, next) at a write
        super().__init__(config)

    def __setattr__(self, name: str, value: object) -> None:
        if isinstance(value, np.ndarray) and name in ('_r', '_a', '_stamp', '_pose'):
            value = value.view(_WriteWatch)
            value.db = self
        super().__setattr__(name, value)
        if hasattr(self, '_size'):
            self.seen.append((self.oldest_seq, self.next_seq))


class _WriteWatch(np.ndarray):
    db: _Watched

    def __setitem__(self, key: object, value: object) -> None:
        db = getattr(self, 'db', None)
        if db is not None and isinstance(key, (int, np.integer)):
            db.overwritten.append((int(key), db.oldest_seq, db.next_seq))
        super().__setitem__(key, value)


def test_stored_range_never_claims_a_scan_gone_or_one_being_overwritten() -> None:
    # solid_node's verify thread reads oldest_seq while its describe thread adds: it once
    # read oldest_seq 1 for an instant while scan 0 was still stored, dropped scan 0's cloud,
    # and a loop to it was lost (test_node's bag replay, about one run in nine under load).
    db = _Watched(SolidConfig().replace(capacity=3, search='brute'))
    a = np.ones(db.num_angle)
    for i, row in enumerate(_random(7)):
        db.seen.clear()
        db.add(row, a, i * SEC)
        first = max(0, i - 2)  # the oldest scan stored after this add
        assert all(oldest in (max(0, i - 3), first) for oldest, _ in db.seen), (i, db.seen)
        assert [o for o, _ in db.seen] == sorted(o for o, _ in db.seen), (i, db.seen)
    for slot, oldest, nxt in db.overwritten:
        assert not any(seq % 3 == slot for seq in range(oldest, nxt)), (slot, oldest, nxt)
    assert (db.oldest_seq, db.next_seq, db.size) == (4, 7, 3)


def test_evicted_scan_is_never_returned() -> None:
    r = _random(12, seed=1)
    for mode in ('brute', 'kdtree'):
        db = _db(capacity=6, search=mode, kdtree_rebuild_every=2)
        _fill(db, r)
        hits = db.search(r[2], 10 * SEC, k=6)
        assert {h.index for h in hits} == set(range(6, 12)), mode


def test_exclusion_by_frames() -> None:
    r = _random(30, seed=2)
    db = _db(search='brute')
    _fill(db, r)
    hits = db.search(r[27], 3 * SEC, k=30, exclude_frames=5)
    assert max(h.index for h in hits) == 24
    assert len(hits) == 25
    assert db.search(r[27], 3 * SEC, k=1, exclude_frames=0)[0].index == 27


def test_exclusion_by_seconds_and_stricter_wins() -> None:
    r = _random(30, seed=3)  # stamps 0.0, 0.1, ..., 2.9 s
    db = _db(search='brute')
    _fill(db, r)
    query = 3 * SEC
    by_time = db.search(r[0], query, k=30, exclude_sec=1.05)  # keeps stamps <= 1.95 s
    assert max(h.index for h in by_time) == 19
    both = db.search(r[0], query, k=30, exclude_frames=3, exclude_sec=1.05)
    assert max(h.index for h in both) == 19  # seconds stricter
    both = db.search(r[0], query, k=30, exclude_frames=15, exclude_sec=1.05)
    assert max(h.index for h in both) == 14  # frames stricter


def test_exclusion_by_seconds_with_stamps_out_of_order() -> None:
    r = _random(10, seed=4)
    stamps = [0, 5, 1, 6, 2, 7, 3, 8, 4, 9]
    for mode in ('brute', 'kdtree'):
        db = _db(search=mode, kdtree_rebuild_every=3)
        for row, t in zip(r, stamps):
            db.add(row, np.ones(60), t * SEC)
        hits = db.search(r[0], 10 * SEC, k=10, exclude_sec=4.5)  # keeps stamps <= 5.5 s
        assert sorted(h.stamp_ns // SEC for h in hits) == [0, 1, 2, 3, 4, 5], mode


def _same_best(r: npt.NDArray[np.float64], queries: npt.NDArray[np.float64], *,
               capacity: int, exclude: int) -> None:
    dbs = {m: _db(search=m, capacity=capacity, kdtree_rebuild_every=97) for m in
           ('brute', 'kdtree')}
    for db in dbs.values():
        _fill(db, r)
    assert dbs['kdtree']._tree is not None
    for i, q in enumerate(queries):
        best = {m: db.search(q, i, k=5, exclude_frames=exclude) for m, db in dbs.items()}
        assert [h.seq for h in best['brute']] == [h.seq for h in best['kdtree']]
        assert best['brute'][0].distance == pytest.approx(best['kdtree'][0].distance)


def test_kdtree_and_brute_agree_on_10000_random() -> None:
    r = _random(10_000, seed=5)
    queries = _random(60, seed=6)
    _same_best(r, queries, capacity=100_000, exclude=50)
    _same_best(r, queries, capacity=7_000, exclude=500)  # wrapped ring, stale tree entries


def test_kdtree_and_brute_agree_on_real_descriptors(shared_data: Path) -> None:
    from hku1_data import HKU1_CONFIG, hku1_scans

    clouds, _ = hku1_scans(shared_data)
    cfg = SolidConfig().replace(**HKU1_CONFIG)
    r = np.array([describe(c, cfg).r_solid for c in clouds])
    # The queries are the stored scans themselves: exclusion must hide the exact copies.
    _same_best(r, r[::7], capacity=1000, exclude=20)
    _same_best(r, r[::7], capacity=150, exclude=20)


def test_search_returns_exact_cosine_distances() -> None:
    r = _random(50, seed=7)
    db = _db(search='brute')
    _fill(db, r)
    q = _random(1, seed=8)[0]
    hits = db.search(q, 0, k=3)
    for h in hits:
        ref = 1.0 - r[h.index] @ q / (np.linalg.norm(r[h.index]) * np.linalg.norm(q))
        assert h.distance == pytest.approx(ref, abs=1e-6)
    assert [h.distance for h in hits] == sorted(h.distance for h in hits)


@pytest.mark.parametrize('mode', ['brute', 'kdtree'])
def test_zero_descriptor_neither_matches_nor_is_matched(mode: str) -> None:
    db = _db(search=mode, kdtree_rebuild_every=2)
    empty = describe(np.zeros((0, 3)))
    assert not np.any(empty.r_solid)
    db.add(empty.r_solid, empty.a_solid, 0)
    r = _random(5, seed=9)
    _fill(db, r, t0=SEC)
    db.add(np.zeros(40), np.zeros(60), 2 * SEC)
    assert db.search(np.zeros(40), 3 * SEC, k=5) == []
    hits = db.search(r[0], 3 * SEC, k=10)
    assert sorted(h.index for h in hits) == [1, 2, 3, 4, 5]
    assert all(np.isfinite(h.distance) for h in hits)
    assert not np.any(np.isnan(db.export_arrays()['r_solid']))


def test_wrong_shape_is_refused() -> None:
    db = _db()
    with pytest.raises(DatabaseError, match='shape'):
        db.add(np.ones(39), np.ones(60), 0)
    with pytest.raises(DatabaseError, match='bins'):
        db.search(np.ones(41), 0, k=1)


def test_memory_per_scan_is_under_1_kib() -> None:
    db = _db(capacity=100_000)
    assert db.bytes_per_scan <= 1024
    assert db.nbytes == db.bytes_per_scan * db.allocated
    assert db.allocated < 100_000 and db.stored_bytes == 0  # not allocated up front
    db.add(np.ones(40), np.ones(60), 0)
    assert db.stored_bytes == db.bytes_per_scan


def test_store_grows_by_doubling_and_keeps_every_scan() -> None:
    r = _random(3000, seed=4)
    grown = _db(capacity=2500, search='brute')
    sizes = []
    for i, row in enumerate(r):
        grown.add(row, np.ones(60), i * SEC, [i, 0, 0, 0, 0, 0, 1])
        sizes.append(grown.allocated)
    assert sorted(set(sizes)) == [1024, 2048, 2500]  # doubled, capped at capacity
    out = grown.export_arrays()
    unit = r[500:] / np.linalg.norm(r[500:], axis=1, keepdims=True)
    np.testing.assert_allclose(out['r_solid'], unit, rtol=1e-6)
    assert out['stamps_ns'].tolist() == [i * SEC for i in range(500, 3000)]
    assert out['poses'][:, 0].tolist() == list(range(500, 3000))
    # Queries before and after growth and wrap find the exact nearest stored scan.
    for q in range(600, 3000, 97):
        (best,) = grown.search(r[q], 10**13, k=1)
        assert best.index == q
    loaded = _db(capacity=5000, search='kdtree', session_id=1)
    loaded.import_arrays(out)
    assert loaded.allocated == 2500 and loaded.size == 2500


def test_loaded_session_is_not_excluded() -> None:
    r = _random(20, seed=10)
    old = _db(session_id=0, search='brute')
    _fill(old, r[:10])
    new = _db(session_id=1, search='brute')
    new.import_arrays(old.export_arrays())
    _fill(new, r[10:], t0=0)
    hits = new.search(r[3], SEC, k=20, exclude_frames=100, exclude_sec=100.0)
    assert {(h.session, h.index) for h in hits} == {(0, i) for i in range(10)}
    assert hits[0].session == 0 and hits[0].index == 3


def test_import_refuses_same_session_id() -> None:
    old = _db(session_id=4)
    _fill(old, _random(3))
    new = _db(session_id=4)
    with pytest.raises(DatabaseError, match='session_id 4.*e.g. 0'):
        new.import_arrays(old.export_arrays())


def test_import_suggests_a_valid_free_session_id_and_refuses_ids_out_of_range() -> None:
    top = 2**31 - 1
    old = _db(session_id=top)
    _fill(old, _random(3))
    arrays = old.export_arrays()
    with pytest.raises(DatabaseError, match=f'session_id {top}.*e.g. 0\\)') as err:
        _db(session_id=top).import_arrays(arrays)
    assert str(2**31) not in str(err.value)
    arrays['sessions'] = np.array([0, 1, 2], dtype=np.int32)
    with pytest.raises(DatabaseError, match=r'e\.g\. 3\)'):
        _db(session_id=1).import_arrays(arrays)
    arrays['sessions'] = np.array([0, -7, 2], dtype=np.int32)
    with pytest.raises(DatabaseError, match='session id -7, outside 0 to 2147483647'):
        _db(session_id=5).import_arrays(arrays)


@pytest.mark.parametrize('search', ['brute', 'kdtree'])
def test_peer_scans_never_evict_this_sessions_scans(search: str) -> None:
    """A flood of peer keyframes fills the peers' own ring only; repeats are refused."""
    cfg = SolidConfig().replace(search=search, kdtree_rebuild_every=4, session_id=0,
                                capacity=50, peer_capacity=20)
    db = DescriptorDatabase(cfg)
    rng = np.random.default_rng(8)
    mine = rng.random((10, 40))
    for i in range(10):
        db.add(mine[i], np.ones(60), i * SEC)
    flood = rng.random((500, 40))
    for i in range(500):
        db.add_foreign(1 + i % 7, i, flood[i], np.ones(60), i * SEC)
    assert db.size == 30 and db.peer_size == 20 and db.session_count == 10
    for i in range(10):  # every own scan is still found, at distance 0
        best = db.search(mine[i], 100 * SEC, k=1)[0]
        assert (best.session, best.index, best.distance) == (0, i, pytest.approx(0.0, abs=1e-6))
    assert db.has_foreign(1 + 499 % 7, 499) and not db.has_foreign(1, 0)
    with pytest.raises(DatabaseError, match='already stored'):
        db.add_foreign(1 + 499 % 7, 499, flood[499], np.ones(60), 0)
    # An evicted peer scan may come again (a catch-up after it left the ring).
    seq = db.add_foreign(1, 0, flood[0], np.ones(60), 0)
    assert db.is_stored(seq) and db.match_info(seq) == (0, 1, 0)
    # A peer sending this robot's own descriptor ties at distance 0: this robot's ranks first.
    db.add_foreign(3, 10**6, mine[4], np.ones(60), 0)
    hits = db.search(mine[4], 100 * SEC, k=2)
    assert [(h.session, h.index) for h in hits] == [(0, 4), (3, 10**6)]
    # Saved rows: own scans first, then the peers'.
    arrays = db.export_arrays()
    assert list(arrays['sessions'][:10]) == [0] * 10 and len(arrays['sessions']) == 30
    assert db.stored_seqs()[:10] == list(range(10))
    with pytest.raises(DatabaseError, match='peer_capacity is 0'):
        DescriptorDatabase(cfg.replace(peer_capacity=0)).add_foreign(1, 0, mine[0],
                                                                     np.ones(60), 0)


@pytest.mark.parametrize('search', ['brute', 'kdtree'])
def test_peer_scans_interleave_without_shrinking_the_exclusion(search: str) -> None:
    cfg = SolidConfig().replace(search=search, kdtree_rebuild_every=1, session_id=4)
    db = DescriptorDatabase(cfg)
    rng = np.random.default_rng(5)
    mine = rng.random((12, 40))
    peers = rng.random((12, 40))
    for i in range(12):
        db.add(mine[i], np.ones(60), i * SEC)
        db.add_foreign(9, 100 + i, peers[i], np.ones(60), i * SEC)
    assert db.session_count == 12 and db.size == 24
    # The newest 5 of this session are excluded; every peer scan stays eligible.
    got = db.search(mine[11], 12 * SEC, k=30, exclude_frames=5)
    own = sorted(m.index for m in got if m.session == 4)
    assert own == list(range(7)) and len([m for m in got if m.session == 9]) == 12
    # The time rule also applies to this session only.
    got = db.search(peers[11], 12 * SEC, k=30, exclude_sec=3.5)
    assert max(m.index for m in got if m.session == 4) == 8
    assert {m.index for m in got if m.session == 9} == set(range(100, 112))
    assert db.search(peers[11], 12 * SEC, k=1)[0].session == 9
    with pytest.raises(DatabaseError, match='own session'):
        db.add_foreign(4, 0, mine[0], np.ones(60), 0)
