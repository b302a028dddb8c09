"""Tests of database save/load: round trip, multi-session, refusals, atomic writes."""

from __future__ import annotations

import fcntl
import io
import json
import os
import pickle
import signal
import stat
import subprocess
import sys
import time
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
from project_paths import CONFIG_DIR

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.archive import FORMAT, is_database, read_database
from solid_ros.core.database.atomic import remove_stale_temporaries
from solid_ros.core.database.descriptors import DescriptorDatabase
from solid_ros.core.database.persistence import (
    backup_if_shrinking,
    check_save_target,
    load_database,
    read_map_poses,
    save_database,
)
from solid_ros.core.errors import DatabaseError
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.geometry import matrix_to_vector, rpy_matrix

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
    from random_places import place

    cfg = SolidConfig().replace(search='brute', distance_threshold=0.02, verify=False)
    first = LoopDetector(cfg)
    for i in range(5):
        first.process(place(i), i * SEC)
    first.save(tmp_path / 'run1.npz')
    second = LoopDetector.load(tmp_path / 'run1.npz', cfg.replace(session_id=7))
    (cand,) = second.process(place(3), 0).loops
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


# -- crafted files: refused from the headers, before any array is read -------------------------


def _npz(path: Path, members: dict[str, bytes], compress: int = zipfile.ZIP_STORED) -> Path:
    with zipfile.ZipFile(path, 'w', compression=compress) as zf:
        for name, blob in members.items():
            zf.writestr(name, blob)
    return path


def _npy(arr: np.ndarray | None = None, *, header: dict[str, object] | None = None,
         data: bytes = b'') -> bytes:
    bio = io.BytesIO()
    if arr is not None:
        np.lib.format.write_array(bio, arr, allow_pickle=False)
    else:
        np.lib.format.write_array_header_1_0(bio, header)
        bio.write(data)
    return bio.getvalue()


def _members(db_path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(db_path) as zf:
        return {n: zf.read(n) for n in zf.namelist()}


def _meta(**changes: object) -> bytes:
    meta = {'format': FORMAT, 'version': 1, 'count': 6, 'num_range': 40,
            'num_angle': 60, 'shape_params': SolidConfig().shape_params(), 'sessions': [0]}
    meta.update(changes)
    return _npy(np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8))


def test_crafted_metadata_is_refused(tmp_path: Path) -> None:
    good = _members(save_database(_filled(6), tmp_path / 'db.npz'))
    cases = {
        'infinity': (good | {'meta.npy': _npy(np.frombuffer(
            json.dumps({'format': FORMAT, 'version': 1,
                        'count': float('inf')}).encode(), np.uint8))}, 'Infinity'),
        'nested': (good | {'meta.npy': _npy(np.frombuffer(b'[' * 100_000 + b']' * 100_000,
                                                          np.uint8))}, 'not valid JSON'),
        'float count': (good | {'meta.npy': _meta(count=6.0)}, 'valid count'),
        'negative': (good | {'meta.npy': _meta(num_range=-40)}, 'valid num_range'),
        'meta not bytes': (good | {'meta.npy': _npy(np.zeros(3))}, 'not a solid_ros database'),
        'other format': (good | {'meta.npy': _meta(format='x' * 10_000)}, 'format'),
        'version': (good | {'meta.npy': _meta(version=99)}, 'version 99'),
    }
    for name, (members, words) in cases.items():
        p = _npz(tmp_path / f'{name}.npz', members)
        with pytest.raises(DatabaseError, match=words) as info:
            load_database(p, SolidConfig())
        assert str(p) in str(info.value) and len(str(info.value)) < 400, name


def test_huge_array_headers_are_refused_without_allocating(tmp_path: Path) -> None:
    # The 2.1 MB file that made the loader allocate 2.1 GB: headers consistent with a huge
    # count, data absent.
    n = 10**9
    members = {'meta.npy': _meta(count=n)}
    for key, (dtype, cols) in {'r_solid': ('<f4', (40,)), 'a_solid': ('<f4', (60,)),
                               'stamps_ns': ('<i8', ()), 'indices': ('<i8', ()),
                               'sessions': ('<i4', ()), 'poses': ('<f4', (7,))}.items():
        members[key + '.npy'] = _npy(header={'descr': dtype, 'fortran_order': False,
                                             'shape': (n, *cols)}, data=bytes(2_000_000))
    p = _npz(tmp_path / 'huge.npz', members)
    t0 = time.perf_counter()
    with pytest.raises(DatabaseError, match=r'header says float32\[1000000000, 40\]'):
        LoopDetector.load(p)
    assert time.perf_counter() - t0 < 1.0
    # What the load allocated (numpy reports its buffers to tracemalloc, touched or not; the
    # process's peak RSS would hide an allocation below an earlier peak, or one never touched).
    tracemalloc.start()
    try:
        with pytest.raises(DatabaseError):
            LoopDetector.load(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 100e6, f'{peak / 1e6:.0f} MB'


def test_archives_that_are_not_savez_databases(tmp_path: Path) -> None:
    good_path = save_database(_filled(6), tmp_path / 'db.npz')
    good = _members(good_path)
    cases = {
        'compressed': (_npz(tmp_path / 'c.npz', good, zipfile.ZIP_DEFLATED), 'compressed'),
        'object array': (_npz(tmp_path / 'o.npz', good | {'poses.npy': _npy(
            header={'descr': '|O', 'fortran_order': False, 'shape': (6, 7)})}), 'objects'),
        'bad header': (_npz(tmp_path / 'h.npz', good | {'poses.npy': b'\x93NUMPY\x01\x00'
                                                        b'\x10\x00{nonsense}      \n'}),
                       'malformed .npy header'),
        'short data': (_npz(tmp_path / 's.npz', good | {
            'poses.npy': good['poses.npy'][:-4]}), "'poses' header says"),
        'pickle': (tmp_path / 'p.pkl', 'not a solid_ros database'),
        'png': (tmp_path / 'x.png', 'not a solid_ros database'),
        'directory': (tmp_path / 'dir', 'not a readable'),
    }
    (tmp_path / 'p.pkl').write_bytes(pickle.dumps({'r_solid': [1, 2]}))
    (tmp_path / 'x.png').write_bytes(b'\x89PNG\r\n\x1a\n' + bytes(100))
    (tmp_path / 'dir').mkdir()
    np.save(tmp_path / 'pickled.npy', np.array([{'a': 1}], dtype=object), allow_pickle=True)
    for name, (path, words) in cases.items():
        with pytest.raises(DatabaseError, match=words) as info:
            load_database(path, SolidConfig())
        assert 'allow_pickle' not in str(info.value), name
    with pytest.raises(DatabaseError) as info:
        load_database(tmp_path / 'pickled.npy', SolidConfig())
    assert 'allow_pickle' not in str(info.value)
    # A zip with the same member twice (np.load would pick the last one).
    with zipfile.ZipFile(tmp_path / 'twice.npz', 'w') as zf:
        for name, blob in good.items():
            zf.writestr(name, blob)
        with pytest.warns(UserWarning):
            zf.writestr('poses.npy', good['poses.npy'])
    with pytest.raises(DatabaseError, match='twice'):
        load_database(tmp_path / 'twice.npz', SolidConfig())


# -- saving: never through a link, never over a non-database; stale temporaries ---------------


def test_save_refuses_targets_that_are_not_databases(tmp_path: Path) -> None:
    db = _filled(4)
    text = tmp_path / 'notes.txt'
    text.write_text('precious\n')
    real = save_database(db, tmp_path / 'real.npz')
    real_bytes = real.read_bytes()
    link = tmp_path / 'link.npz'
    link.symlink_to(real)
    dangling = tmp_path / 'dangling.npz'
    dangling.symlink_to(tmp_path / 'nowhere.npz')
    fifo = tmp_path / 'fifo'
    os.mkfifo(fifo)
    (tmp_path / 'dir.npz').mkdir()
    cases = {text: 'not a solid_ros database', link: 'symbolic link',
             dangling: 'symbolic link', fifo: 'not a regular file',
             tmp_path / 'dir.npz': 'not a regular file'}
    for target, words in cases.items():
        with pytest.raises(DatabaseError, match=words):
            save_database(db, target)
        with pytest.raises(DatabaseError, match=words):
            check_save_target(target)
    assert text.read_text() == 'precious\n' and real.read_bytes() == real_bytes
    assert link.is_symlink() and dangling.is_symlink() and not (tmp_path / 'nowhere.npz').exists()
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert not list(tmp_path.glob('.*.tmp'))
    # A database is replaced, a new file written.
    save_database(_filled(9), real)
    assert read_database(real)[0]['count'] == 9
    save_database(db, tmp_path / 'new.npz')
    assert is_database(tmp_path / 'new.npz') and not is_database(text)


def test_stale_temporaries_are_removed_unless_a_save_holds_them(tmp_path: Path) -> None:
    target = tmp_path / 'db.npz'
    stale = [tmp_path / '.db.npz.k3j_9a0q.tmp', tmp_path / '.db.npz.00000000.tmp']
    for p in stale:
        p.write_bytes(os.urandom(1000))
    kept = [tmp_path / '.db.npz.toolongname.tmp', tmp_path / '.other.npz.k3j_9a0q.tmp',
            tmp_path / 'db.npz.k3j_9a0q.tmp']
    for p in kept:
        p.write_bytes(b'x')
    busy = tmp_path / '.db.npz.busy_123.tmp'
    busy.write_bytes(b'being written')
    with busy.open('rb+') as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX)
        save_database(_filled(3), target)
        assert busy.exists()
    assert not any(p.exists() for p in stale) and all(p.exists() for p in kept)
    assert remove_stale_temporaries(target) == [busy]  # its writer is gone now


def test_a_killed_save_leaves_a_temporary_the_next_save_removes(tmp_path: Path) -> None:
    target = tmp_path / 'db.npz'
    code = ('import sys, time, numpy as np\n'
            'from solid_ros.core.database import persistence\n'
            'from solid_ros.core.database.descriptors import DescriptorDatabase\n'
            'from solid_ros.core.config import SolidConfig\n'
            'def slow(f, **arrays):\n'
            '    f.write(b"x" * 100000); f.flush(); print("writing", flush=True); time.sleep(60)\n'
            'np.savez = slow\n'
            'db = DescriptorDatabase(SolidConfig(capacity=10))\n'
            'persistence.save_database(db, sys.argv[1])\n')
    proc = subprocess.Popen([sys.executable, '-c', code, str(target)], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline() == 'writing\n'
        (tmp,) = tmp_path.glob('.db.npz.*.tmp')
        assert remove_stale_temporaries(target) == [] and tmp.exists()  # the save is alive
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert tmp.exists() and not target.exists()
    save_database(_filled(3), target)
    assert not tmp.exists() and is_database(target)


def _sim_points(index: int) -> np.ndarray:
    from solid_ros.sim.drive import Drive, DriveConfig

    return Drive(DriveConfig(seed=0, sensor='avia_like')).scan(index).points.copy()


def test_keyframe_clouds_round_trip_and_verify_a_later_session(tmp_path: Path) -> None:
    pytest.importorskip('small_gicp', reason='small-gicp is not installed')
    cfg = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml')
    cfg = cfg.replace(exclude_recent_frames=0, distance_threshold=0.3, num_candidates=3)
    first = LoopDetector(cfg)
    for k, i in enumerate((5, 60, 120)):
        first.process(_sim_points(i), k * 1_000_000_000)
    assert len(first.clouds) == 3
    first.save(tmp_path / 'run1.npz')
    second = LoopDetector.load(tmp_path / 'run1.npz', cfg.replace(session_id=1))
    assert [c.points.tolist() for _, c in second.clouds.items()] == [
        c.points.tolist() for _, c in first.clouds.items()]
    assert [c.n_struct for _, c in second.clouds.items()] == [
        c.n_struct for _, c in first.clouds.items()]
    (loop,) = second.process(_sim_points(273), 10 * 1_000_000_000).loops  # a revisit of scan 5
    assert (loop.match_session, loop.match_index, loop.verified) == (0, 0, True)

    # The same file as format version 1 (no clouds): loads, but nothing can be verified.
    with zipfile.ZipFile(tmp_path / 'run1.npz') as zf:
        members = {n: zf.read(n) for n in zf.namelist() if not n.startswith('cloud_')}
    meta = json.loads(np.load(io.BytesIO(members['meta.npy'])).tobytes())
    meta['version'] = 1
    del meta['cloud_points']
    buf = io.BytesIO()
    np.save(buf, np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8))
    members['meta.npy'] = buf.getvalue()
    _npz(tmp_path / 'v1.npz', members)
    old = LoopDetector.load(tmp_path / 'v1.npz', cfg.replace(session_id=1))
    assert old.database.size == 3 and len(old.clouds) == 0
    res = old.process(_sim_points(273), 10 * 1_000_000_000)
    assert res.loops == ()
    assert [a.reason for a in res.attempts][:1] == ['no_cloud']


def _map_pose(i: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(0.01 * i, -0.02 * i, 0.3 * i)
    T[:3, 3] = [1000.0 + i, -2000.0 + 0.5 * i, 3.25]  # far from the origin: float64 kept
    return T


def test_map_poses_round_trip_and_older_files_serve_odometry(tmp_path: Path) -> None:
    db = _filled(12)
    poses = {(0, i): _map_pose(i) for i in range(12) if i != 4}
    path = save_database(db, tmp_path / 'map.npz', map_poses=poses)
    meta, arrays = read_database(path)
    assert meta['version'] == 3 and arrays['map_poses'].dtype == np.float64
    prior = read_map_poses(path)
    assert prior.source == 'map' and set(prior.poses) == set(poses)
    for key, T in poses.items():
        np.testing.assert_allclose(prior.poses[key], T, atol=1e-9)
    assert load_database(path, SolidConfig(session_id=1)).size == 12  # loads as before
    # A version-2 file (saved before the back end): loads, its odometry poses stand in.
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist() if n != 'map_poses.npy'}
    meta['version'] = 2
    buf = io.BytesIO()
    np.save(buf, np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8))
    members['meta.npy'] = buf.getvalue()
    old = read_map_poses(_npz(tmp_path / 'v2.npz', members))
    assert old.source == 'odometry'
    assert sorted(old.poses) == [(0, i) for i in range(0, 12, 3)]  # the scans with a pose
    np.testing.assert_allclose(old.poses[(0, 3)][:3, 3], [3.0, 0.0, 0.0])
    assert load_database(tmp_path / 'v2.npz', SolidConfig(session_id=1)).size == 12


def test_bad_map_poses_are_refused(tmp_path: Path) -> None:
    path = save_database(_filled(6), tmp_path / 'db.npz', map_poses={(0, 1): _map_pose(1)})
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    half = arrays['map_poses'].copy()
    half[1, 2] = np.nan  # a row partly NaN
    np.savez(tmp_path / 'half.npz', **dict(arrays, map_poses=half))
    with pytest.raises(DatabaseError, match='map_poses'):
        read_map_poses(tmp_path / 'half.npz')
    with pytest.raises(DatabaseError, match='session 0 keyframe 2'):
        save_database(_filled(6), tmp_path / 'x.npz', map_poses={(0, 2): np.full((4, 4), 1.0)})


def test_detector_saves_the_map_poses_it_is_given(tmp_path: Path) -> None:
    det = LoopDetector(SolidConfig(verify=False))
    rng = np.random.default_rng(1)
    for i in range(3):
        det.process(rng.uniform(-30.0, 30.0, (2000, 3)), i * SEC)
    det.save(tmp_path / 'db.npz', map_poses={(0, 2): matrix_to_vector(_map_pose(2))})
    prior = read_map_poses(tmp_path / 'db.npz')
    assert list(prior.poses) == [(0, 2)]
    np.testing.assert_allclose(prior.poses[(0, 2)], _map_pose(2), atol=1e-9)
def test_a_shrinking_save_keeps_the_larger_database_as_a_backup(tmp_path: Path) -> None:
    """~/reset then ~/save_database must not wear a saved map away: the node calls
    backup_if_shrinking before each save."""
    target = tmp_path / 'map.npz'
    big = _filled(40)
    save_database(big, target)
    assert backup_if_shrinking(target, 30) is None  # not much smaller: no backup
    assert backup_if_shrinking(tmp_path / 'absent.npz', 0) is None
    backup = backup_if_shrinking(target, 0)
    assert backup == tmp_path / 'map.npz.bak'
    save_database(DescriptorDatabase(SolidConfig()), target)  # the empty one replaces it
    assert read_database(target)[0]['count'] == 0
    assert read_database(backup)[0]['count'] == 40
    # The next shrink (10 scans -> 0) keeps the 40-scan backup, as does a save of nothing.
    save_database(_filled(10), target)
    assert backup_if_shrinking(target, 0) == backup
    assert read_database(backup)[0]['count'] == 40
    assert backup_if_shrinking(tmp_path / 'map.npz', 0) == backup
    # A backup slot taken by something else is never replaced: the save is refused.
    other = tmp_path / 'other.npz'
    save_database(_filled(10), other)
    (tmp_path / 'other.npz.bak').write_text('not a database')
    with pytest.raises(DatabaseError, match='not a solid_ros database'):
        backup_if_shrinking(other, 0)


def test_peer_scans_are_saved_after_this_sessions_with_their_clouds(tmp_path: Path) -> None:
    from solid_ros.core.database.clouds import CloudStore, KeyframeCloud

    db = _filled(5, peer_capacity=10)
    clouds = CloudStore(100, 10**9)
    rng = np.random.default_rng(3)
    seq = db.add_foreign(7, 42, rng.random(40), rng.random(60), 3 * SEC)
    clouds.put(seq, KeyframeCloud(np.ones((4, 3), np.float32), 2))
    clouds.put(db.oldest_seq, KeyframeCloud(np.zeros((3, 3), np.float32), 1))
    path = save_database(db, tmp_path / 'db.npz', clouds)
    meta, arrays = read_database(path)
    assert meta['sessions'] == [0, 7] and list(arrays['indices'][-1:]) == [42]
    assert list(np.diff(arrays['cloud_offsets'])) == [3, 0, 0, 0, 0, 4]
    loaded = CloudStore(100, 10**9)
    again = load_database(path, db.config.replace(session_id=1), loaded)
    assert again.size == 6 and len(loaded) == 2


def test_the_grid_of_each_cloud_round_trips_and_older_files_mean_the_configurations(
        tmp_path: Path) -> None:
    from solid_ros.core.database.clouds import CloudStore, KeyframeCloud

    db = _filled(3)
    clouds = CloudStore(100, 10**9)
    clouds.put(db.oldest_seq, KeyframeCloud(np.zeros((3, 3), np.float32), 1, 0.25))
    clouds.put(db.oldest_seq + 2, KeyframeCloud(np.ones((4, 3), np.float32), 2, 0.5))
    path = save_database(db, tmp_path / 'db.npz', clouds)
    loaded = CloudStore(100, 10**9)
    load_database(path, db.config.replace(session_id=1), loaded)
    assert [c.voxel for _, c in loaded.items()] == [0.25, 0.5]
    # A file from before the tight-space grid has no cloud_voxel: its clouds are on the
    # configuration's grid (0).
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist() if n != 'cloud_voxel.npy'}
    _npz(tmp_path / 'old.npz', members)
    old = CloudStore(100, 10**9)
    load_database(tmp_path / 'old.npz', db.config.replace(session_id=1), old)
    assert [c.voxel for _, c in old.items()] == [0.0, 0.0]
    # A crafted grid is refused.
    buf = io.BytesIO()
    np.save(buf, np.array([-1.0, 0.0, 0.0]))
    _npz(tmp_path / 'bad.npz', {**members, 'cloud_voxel.npy': buf.getvalue()})
    with pytest.raises(DatabaseError, match='cloud_voxel'):
        load_database(tmp_path / 'bad.npz', db.config.replace(session_id=1), CloudStore(9, 10**9))


def test_stored_session_ids_out_of_range_are_refused_in_one_line(tmp_path: Path) -> None:
    path = save_database(_filled(3), tmp_path / 'db.npz')
    meta, arrays = read_database(path)
    arrays['sessions'][1] = -2
    bad = tmp_path / 'bad.npz'
    meta['sessions'] = [-2, 0]
    arrays['meta'] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(bad, **arrays)
    with pytest.raises(DatabaseError) as err:
        load_database(bad, SolidConfig().replace(session_id=1))
    assert str(err.value) == (f'{bad}: the saved database holds session id -2, outside 0 to '
                              '2147483647: not a database this version wrote')
