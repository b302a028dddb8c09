"""Tests of database save/load: round trip, multi-session, refusals, atomic writes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from solid_ros.core.config import SolidConfig
from solid_ros.core.database import DescriptorDatabase
from solid_ros.core.detector import LoopDetector
from solid_ros.core.errors import DatabaseError
from solid_ros.core.persistence import load_database, read_database, save_database

SEC = 1_000_000_000


def _filled(n: int = 40, seed: int = 0, **kw: object) -> DescriptorDatabase:
    db = DescriptorDatabase(SolidConfig().replace(**kw))
    rng = np.random.default_rng(seed)
    for i in range(n):
        pose = None if i % 3 else [i, 0, 0, 0, 0, 0, 1]
        r = np.zeros(40) if i == 5 else rng.random(40)
        db.add(r, rng.random(60), i * SEC, pose)
    return db


def test_round_trip_gives_identical_queries(tmp_path: Path) -> None:
    db = _filled()
    path = save_database(db, tmp_path / 'db.npz')
    loaded = load_database(path, db.config.replace(session_id=1))
    assert loaded.size == db.size and loaded.session_count == 0
    saved = db.export_arrays()
    again = loaded.export_arrays()
    for key, arr in saved.items():
        np.testing.assert_array_equal(arr, again[key], err_msg=key)
    rng = np.random.default_rng(9)
    for q in rng.random((20, 40)):
        a = db.search(q, 100 * SEC, k=5)
        b = loaded.search(q, 100 * SEC, k=5)
        assert [(m.index, m.session, m.stamp_ns, m.distance) for m in a] == [
            (m.index, m.session, m.stamp_ns, m.distance) for m in b]
    assert loaded.pose(loaded.oldest_seq) is not None and loaded.pose(1) is None


def test_new_session_queries_the_saved_one(tmp_path: Path) -> None:
    from test_detector import place

    cfg = SolidConfig().replace(search='brute', distance_threshold=0.02)
    first = LoopDetector(cfg)
    for i in range(5):
        first.process(place(i), i * SEC)
    first.save(tmp_path / 'run1.npz')
    second = LoopDetector.load(tmp_path / 'run1.npz', cfg.replace(session_id=7))
    (cand,) = second.process(place(3), 0)
    assert (cand.query_index, cand.match_index, cand.match_session) == (0, 3, 0)
    second.process(place(9), SEC)
    second.save(tmp_path / 'run2.npz')
    meta, arrays = read_database(tmp_path / 'run2.npz')
    assert meta['sessions'] == [0, 7] and meta['count'] == 7
    assert arrays['indices'].tolist() == [0, 1, 2, 3, 4, 0, 1]
    with pytest.raises(DatabaseError, match='session_id 7'):
        LoopDetector.load(tmp_path / 'run2.npz', cfg.replace(session_id=7))


def test_incompatible_parameters_are_named(tmp_path: Path) -> None:
    save_database(_filled(5), tmp_path / 'db.npz')
    cfg = SolidConfig().replace(voxel_size=0.3, fov_up_deg=10.0)
    with pytest.raises(DatabaseError) as err:
        load_database(tmp_path / 'db.npz', cfg)
    text = str(err.value)
    assert 'voxel_size (file 0.4, config 0.3)' in text
    assert 'fov_up_deg (file 2.0, config 10.0)' in text
    assert 'num_range' not in text
    # Settings that do not change descriptor values may differ.
    assert load_database(tmp_path / 'db.npz', SolidConfig().replace(
        distance_threshold=0.5, session_id=3, capacity=4)).size == 4


def test_truncated_garbage_and_missing_files_are_refused(tmp_path: Path) -> None:
    good = save_database(_filled(30), tmp_path / 'db.npz').read_bytes()
    cases = {'truncated': good[:len(good) // 2], 'garbage': os.urandom(5000), 'empty': b'',
             'tail_cut': good[:-10], 'text': b'hello world\n'}
    for name, blob in cases.items():
        p = tmp_path / f'{name}.npz'
        p.write_bytes(blob)
        with pytest.raises(DatabaseError, match=str(p)):
            load_database(p, SolidConfig())
    with pytest.raises(DatabaseError, match='does not exist'):
        load_database(tmp_path / 'nope.npz', SolidConfig())
    np.save(tmp_path / 'single.npy', np.zeros(3))
    with pytest.raises(DatabaseError, match='single .npy'):
        load_database(tmp_path / 'single.npy', SolidConfig())
    np.savez(tmp_path / 'other.npz', x=np.zeros(3))
    with pytest.raises(DatabaseError, match='no "meta"'):
        load_database(tmp_path / 'other.npz', SolidConfig())


def test_wrong_arrays_are_refused(tmp_path: Path) -> None:
    path = save_database(_filled(6), tmp_path / 'db.npz')
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    bad = dict(arrays, stamps_ns=arrays['stamps_ns'].astype(np.float64))
    np.savez(tmp_path / 'dtype.npz', **bad)
    with pytest.raises(DatabaseError, match="'stamps_ns' is float64"):
        load_database(tmp_path / 'dtype.npz', SolidConfig())
    bad = dict(arrays, r_solid=arrays['r_solid'][:3])
    np.savez(tmp_path / 'shape.npz', **bad)
    with pytest.raises(DatabaseError, match="'r_solid'"):
        load_database(tmp_path / 'shape.npz', SolidConfig())
    nan = arrays['a_solid'].copy()
    nan[0, 0] = np.nan
    np.savez(tmp_path / 'nan.npz', **dict(arrays, a_solid=nan))
    with pytest.raises(DatabaseError, match='NaN'):
        load_database(tmp_path / 'nan.npz', SolidConfig())
    del arrays['poses']
    np.savez(tmp_path / 'missing.npz', **arrays)
    with pytest.raises(DatabaseError, match="missing array 'poses'"):
        load_database(tmp_path / 'missing.npz', SolidConfig())


def test_save_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = save_database(_filled(10), tmp_path / 'db.npz')
    before = path.read_bytes()

    def crash(*_: object, **__: object) -> None:
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(np, 'savez', crash)
    with pytest.raises(DatabaseError, match='No space left'):
        save_database(_filled(20), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ['db.npz']  # no temp file left
    with pytest.raises(DatabaseError, match='cannot write'):
        save_database(_filled(2), tmp_path / 'no_dir' / 'db.npz')
