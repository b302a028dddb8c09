"""Fuzz: malformed clouds, parameter files, database files and bags from one fixed seed.

Every input must end as documented: a cloud decodes or raises CloudError, and the detector
stores it exactly when some point is finite and inside the range gate (else CloudError 'no
usable point', nothing changed); a parameter file is accepted or refused by solid_node (exit
2, one line) and solid_replay (exit 1, the same line) alike; a database file loads or raises
DatabaseError quickly, is never modified, and is never replaced by a save unless it is a
solid_ros database; a bag replays (exit 0) or stops with one line (exit 1), its files
unchanged, and a damaged MCAP file written here always stops. In-process calls do the bulk
(the executables run the same functions); a handful of real executable runs check the wiring.
The counts tried and survived are printed.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import random
import subprocess
import sys
import time
import tracemalloc
import zipfile
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from project_paths import CONFIG_DIR

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.archive import FORMAT
from solid_ros.core.database.persistence import check_save_target, save_database
from solid_ros.core.errors import CloudError, ConfigError, DatabaseError
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.formats.bags import write_cloud_bag
from solid_ros.formats.pointcloud2 import FLOAT32, FLOAT64, cloud_to_xyz
from solid_ros.ros.cli import check_parameter_files, scan_arguments
from solid_ros.tools import replay

pytestmark = pytest.mark.slow  # hundreds of malformed files, bags and processes

SEED = 20261122
BIN = Path(sys.executable).parent
CFG = SolidConfig(exclude_recent_frames=2, capacity=64)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else ''


def _tree_sha(path: Path) -> dict[str, str]:
    """Hash of every file of a bag (a file or a directory): nothing changed, added or gone."""
    files = sorted(p for p in path.rglob('*') if p.is_file()) if path.is_dir() else [path]
    return {str(p.relative_to(path.parent)): _sha(p) for p in files if p.exists()}


def _flip(blob: bytes, rng: random.Random, n: int = 1) -> bytes:
    out = bytearray(blob)
    for _ in range(n):
        pos = rng.randrange(len(out))
        out[pos] ^= 1 << rng.randrange(8)
    return bytes(out)


def _overwrite(blob: bytes, rng: random.Random, size: int = 32) -> bytes:
    pos = rng.randrange(max(1, len(blob) - size))
    return blob[:pos] + rng.randbytes(size) + blob[pos + size:]


class Tally:
    """Counts per family; failures keep their description for the assertion message."""

    def __init__(self) -> None:
        self.tried: Counter[str] = Counter()
        self.survived: Counter[str] = Counter()
        self.failures: list[str] = []

    def check(self, family: str, name: str, fn: Callable[[], None]) -> None:
        self.tried[family] += 1
        try:
            fn()
        except Exception as err:  # noqa: BLE001 - any escape is a finding to report
            self.failures.append(f'{family}/{name}: {type(err).__name__}: {err}'[:400])
        else:
            self.survived[family] += 1


# -- clouds -------------------------------------------------------------------------------------


def _cloud(rng: random.Random) -> tuple[str, SimpleNamespace]:
    n = rng.choice([0, 1, 7, 300])
    pts = np.random.default_rng(rng.randrange(2**32)).normal(scale=20.0, size=(n, 4))
    ftype = rng.choice([FLOAT32, FLOAT64])
    size = 4 if ftype == FLOAT32 else 8
    step = 4 * size
    fields = [SimpleNamespace(name=k, offset=i * size, datatype=ftype, count=1)
              for i, k in enumerate(['x', 'y', 'z', 'intensity'])]
    data = pts.astype('<f4' if ftype == FLOAT32 else '<f8').tobytes()
    msg = SimpleNamespace(height=1, width=n, point_step=step, row_step=step * n,
                          is_bigendian=False, fields=fields, data=data)
    kind = rng.choice(['count', 'duplicate', 'datatype', 'offset', 'missing', 'step', 'size',
                       'data', 'garbage', 'values', 'endian', 'overlap'])
    f = rng.choice(fields[:3])
    if kind == 'count':
        f.count = rng.choice([0, 2, 3, -1])
    elif kind == 'duplicate':
        fields.append(SimpleNamespace(name=f.name, offset=rng.randrange(step), datatype=ftype,
                                      count=1))
    elif kind == 'datatype':
        f.datatype = rng.choice([0, 1, 2, 5, 6, 9, 255])
    elif kind == 'offset':
        f.offset = rng.choice([-4, step - 1, step, 10**9, rng.randrange(step)])
    elif kind == 'missing':
        fields.remove(f)
    elif kind == 'step':
        msg.point_step = rng.choice([0, -step, 1, step - 1, step + 3, 10**12])
    elif kind == 'size':
        msg.width, msg.height = rng.choice([(-1, 1), (n, 0), (n + 5, 1), (10**9, 10**9),
                                            (n, 2)])
        msg.row_step = rng.choice([0, msg.row_step, -1])
    elif kind == 'data':
        msg.data = data[:rng.randrange(len(data) + 1)] if data else b'\x00'
    elif kind == 'garbage':
        msg.data = rng.randbytes(len(data))
    elif kind == 'values':
        arr = np.frombuffer(data, '<f4' if ftype == FLOAT32 else '<f8').copy()
        arr[rng.randrange(len(arr) + 1) - 1:] = rng.choice([np.nan, np.inf, -np.inf, 1e38, 0.0])
        msg.data = arr.tobytes()
    elif kind == 'endian':
        msg.is_bigendian = True
    else:
        fields[1].offset = fields[0].offset + 1
    return kind, msg


def _unusable_cloud(rng: random.Random) -> tuple[str, SimpleNamespace]:
    """A well-formed cloud whose every point is non-finite, huge, zero or out of range."""
    n = rng.choice([1, 7, 300])
    kind = rng.choice(['nan', 'inf', '-inf', '1e38', 'zeros', 'mixed', 'far', 'near'])
    nprng = np.random.default_rng(rng.randrange(2**32))
    pts = nprng.normal(size=(n, 4))
    xyz = pts[:, :3]
    if kind == 'mixed':
        xyz[:] = nprng.choice([np.nan, np.inf, -np.inf, 1e38], size=(n, 3))
        xyz[:, rng.randrange(3)] = np.nan  # not a finite point left
    elif kind in ('far', 'near'):
        want = CFG.max_range * rng.uniform(1.0, 1e3) if kind == 'far' else \
            CFG.min_range * rng.uniform(0.0, 0.99)
        xyz *= want / np.linalg.norm(xyz, axis=1, keepdims=True)
    else:
        xyz[:] = {'nan': np.nan, 'inf': np.inf, '-inf': -np.inf, '1e38': 1e38, 'zeros': 0.0}[kind]
    ftype = rng.choice([FLOAT32, FLOAT64])
    size = 4 if ftype == FLOAT32 else 8
    fields = [SimpleNamespace(name=k, offset=i * size, datatype=ftype, count=1)
              for i, k in enumerate(['x', 'y', 'z', 'intensity'])]
    with np.errstate(over='ignore'):
        data = pts.astype('<f4' if ftype == FLOAT32 else '<f8').tobytes()
    return 'unusable ' + kind, SimpleNamespace(
        height=1, width=n, point_step=4 * size, row_step=4 * size * n, is_bigendian=False,
        fields=fields, data=data)


def _usable(pts: np.ndarray, cfg: SolidConfig) -> bool:
    """Whether a point is finite, inside the range gate and within max_distance (360 deg)."""
    with np.errstate(invalid='ignore', over='ignore'):
        xyz = pts.astype(np.float64)
        d = np.linalg.norm(xyz, axis=1)
        keep = (d > cfg.min_range) & (d < cfg.max_range)
        keep &= np.hypot(xyz[:, 0], xyz[:, 1]) < cfg.max_distance
    return bool(keep.any())


def _check_cloud(msg: SimpleNamespace, det: LoopDetector, stamp: int) -> str:
    """Decode and process; returns the outcome, raises AssertionError when it is wrong."""
    try:
        pts = cloud_to_xyz(msg)
    except CloudError:
        return 'undecodable'  # rejected and counted by the node and the replay
    assert pts.ndim == 2 and pts.shape[1] == 3, pts.shape
    assert CFG.fov_width_deg == 360.0 and CFG.keyframe_min_sec == 0.0  # what _usable knows
    before = (det.num_keyframes, det.database.next_seq)
    try:
        det.process(pts, stamp)
    except CloudError as err:
        # No usable point: refused before anything is stored (no empty keyframe).
        assert not _usable(pts, det.config), f'usable cloud refused: {err}'
        assert str(err).startswith('no usable point: ') and '\n' not in str(err), str(err)
        assert (det.num_keyframes, det.database.next_seq) == before
        return 'no usable point'
    assert _usable(pts, det.config), 'a cloud without a usable point was stored'
    assert (det.num_keyframes, det.database.next_seq) == (before[0] + 1, before[1] + 1)
    return 'stored'


# -- parameter files ------------------------------------------------------------------------------


def _param_file(rng: random.Random, base: str) -> tuple[str, bytes]:
    lines = base.splitlines(keepends=True)
    values = [i for i, ln in enumerate(lines) if ln.startswith('    ') and ':' in ln
              and not ln.strip().startswith('#')]
    kind = rng.choice(['flip', 'truncate', 'value', 'key', 'indent', 'node', 'binary', 'empty',
                       'list', 'nested', 'insert'])
    blob = base.encode()
    if kind == 'flip':
        blob = _flip(blob, rng, rng.randint(1, 3))
    elif kind == 'truncate':
        blob = blob[:rng.randrange(len(blob))]
    elif kind == 'value':
        i = rng.choice(values)
        key = lines[i].split(':')[0]
        token = rng.choice(['90', '1e400', '.nan', '-.inf', 'abc', '[1, 2]', '{a: 1}', 'true',
                            '~', '99999999999999999999', '-1', '0', '1.5', "'x'", '2001-13-45',
                            '!!python/object:os.system', '"\\x00"', '&a [*a]'])
        lines[i] = f'{key}: {token}\n'
        blob = ''.join(lines).encode()
    elif kind == 'key':
        i = rng.choice(values)
        lines[i] = lines[i].replace(lines[i].strip()[:3], lines[i].strip()[:3][::-1], 1)
        blob = ''.join(lines).encode()
    elif kind == 'indent':
        i = rng.choice(values)
        lines[i] = lines[i].lstrip() if rng.random() < 0.5 else '\t' + lines[i]
        blob = ''.join(lines).encode()
    elif kind == 'node':
        blob = base.replace('solid_node:', rng.choice(['other:', '/ns/solid_node:', '/*/x:',
                                                       'solid_node_2:', '"":']), 1).encode()
    elif kind == 'binary':
        blob = rng.randbytes(rng.randrange(1, 2000))
    elif kind == 'empty':
        blob = rng.choice([b'', b'\n', b'# comment\n', b'---\n', b'...\n'])
    elif kind == 'list':
        blob = b'- solid_node:\n    ros__parameters: {}\n'
    elif kind == 'nested':
        depth = rng.choice([50, 2000, 20000])
        blob = b'solid_node: ' + b'[' * depth + b']' * depth + b'\n'
    else:
        pos = rng.randrange(len(blob))
        blob = blob[:pos] + rng.choice([b'\x00', b'\xff\xfe', b':', b'\n  - ', b'{', b'"']) \
            + blob[pos:]
    return kind, blob


def _check_param_file(path: Path, capsys: pytest.CaptureFixture[str]) -> bool:
    """Node and replay agree; a refusal is one line (node exit 2, replay exit 1)."""
    from solid_ros.ros.node import main as node_main

    before = _sha(path)
    try:
        check_parameter_files(scan_arguments(['solid_node', '--ros-args', '--params-file',
                                              str(path)]))
        node_error = None
    except ConfigError as err:
        node_error = str(err)
    try:
        replay.load_config(path)
        replay_error = None
    except ConfigError as err:
        replay_error = str(err)
    if node_error is None:
        # The node applies the rules between settings after rclpy.init (same ConfigError).
        assert replay_error is None or 'must be greater than' in replay_error, replay_error
        return False
    assert replay_error == node_error, (node_error, replay_error)
    assert '\n' not in node_error
    capsys.readouterr()
    assert node_main(['solid_node', '--ros-args', '--params-file', str(path)]) == 2
    assert replay.main([str(path.parent / 'no_bag'), '--params', str(path), '-q']) == 1
    out, err = capsys.readouterr()
    assert err == (f'solid_node: error: {node_error}\n'
                   f'solid_replay: error: {node_error}\n') and out == '', err
    assert _sha(path) == before
    return True


# -- database files -----------------------------------------------------------------------------


def _members(blob: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(blob)) as zf:
        return {n: zf.read(n) for n in zf.namelist()}


def _zip(members: dict[str, bytes], compress: int = zipfile.ZIP_STORED) -> bytes:
    bio = io.BytesIO()
    with zipfile.ZipFile(bio, 'w', compression=compress) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return bio.getvalue()


def _npy_header(shape: tuple[int, ...], descr: str) -> bytes:
    bio = io.BytesIO()
    np.lib.format.write_array_header_1_0(bio, {'descr': descr, 'fortran_order': False,
                                               'shape': shape})
    return bio.getvalue()


def _database_file(rng: random.Random, good: bytes) -> tuple[str, bytes]:
    kind = rng.choice(['flip', 'flips', 'overwrite', 'truncate', 'meta', 'header', 'drop',
                       'compress', 'garbage', 'npy', 'text'])
    members = _members(good)
    if kind == 'flip':
        return kind, _flip(good, rng)
    if kind == 'flips':
        return kind, _flip(good, rng, rng.randint(2, 50))
    if kind == 'overwrite':
        return kind, _overwrite(good, rng, rng.choice([4, 64, 4096]))
    if kind == 'truncate':
        return kind, good[:rng.randrange(len(good))]
    if kind == 'meta':
        meta: Any = json.loads(np.lib.format.read_array(io.BytesIO(members['meta.npy'])).tobytes())
        key = rng.choice(['count', 'num_range', 'num_angle', 'format', 'version',
                          'shape_params'])
        meta[key] = rng.choice([float('inf'), -1, 10**12, 1.5, None, 'x', [1] * 3, {'a': 1},
                                2**64, True])
        text = json.dumps(meta)
        if rng.random() < 0.2:
            text = '[' * 100_000 + ']' * 100_000
        members['meta.npy'] = _npy_blob(np.frombuffer(text.encode(), np.uint8))
        return kind, _zip(members)
    if kind == 'header':
        key = rng.choice([k for k in members if k != 'meta.npy'])
        shape = rng.choice([(10**9, 40), (2**40,), (50, 41), (0,), (50, 7, 2), (-1, 40)])
        descr = rng.choice(['<f4', '<f8', '<i8', '|O', '>f4', '<U8'])
        members[key] = _npy_header(shape, descr) + rng.randbytes(rng.choice([0, 16, 4096]))
        return kind, _zip(members)
    if kind == 'drop':
        del members[rng.choice(list(members))]
        return kind, _zip(members)
    if kind == 'compress':
        return kind, _zip(members, zipfile.ZIP_DEFLATED)
    if kind == 'garbage':
        return kind, rng.randbytes(rng.randrange(1, 100_000))
    if kind == 'npy':
        return kind, _npy_blob(np.zeros(rng.randrange(1, 100)))
    return kind, b'not a database\n' * rng.randrange(1, 100)


def _npy_blob(arr: np.ndarray) -> bytes:
    bio = io.BytesIO()
    np.lib.format.write_array(bio, arr, allow_pickle=False)
    return bio.getvalue()


def _check_database(path: Path, db: Any) -> bool:
    """Load fast or refuse; the file is never modified; never replaced unless a database."""
    before = _sha(path)
    t0 = time.perf_counter()
    try:
        LoopDetector.load(path, CFG.replace(session_id=9))
        loaded = True
    except DatabaseError as err:
        assert '\n' not in str(err) and 'allow_pickle' not in str(err), str(err)
        loaded = False
    assert time.perf_counter() - t0 < 2.0
    assert _sha(path) == before
    try:
        check_save_target(path)
    except DatabaseError:
        with pytest.raises(DatabaseError):
            save_database(db, path)
        assert _sha(path) == before
    return not loaded


# -- bags ---------------------------------------------------------------------------------------


def _storage(bag: Path) -> Path:
    return bag if bag.is_file() else next(p for p in bag.iterdir() if p.name != 'metadata.yaml')


def _bag_variant(rng: random.Random, sources: dict[str, Path], dest: Path) -> tuple[str, Path]:
    fmt = rng.choice(['mcap', 'mcap', 'mcap', 'sqlite3', 'ros1'])
    src = sources[fmt]
    if src.is_dir():
        dest.mkdir()
        for p in src.iterdir():
            (dest / p.name).write_bytes(p.read_bytes())
        target = dest
    else:
        target = dest.with_suffix('.bag')
        target.write_bytes(src.read_bytes())
    kind = rng.choice(['flip', 'flips', 'overwrite', 'truncate', 'metadata'] if fmt != 'ros1'
                      else ['flip', 'flips', 'overwrite', 'truncate'])
    storage = _storage(target)
    blob = storage.read_bytes()
    if kind == 'flip':
        storage.write_bytes(_flip(blob, rng))
    elif kind == 'flips':
        storage.write_bytes(_flip(blob, rng, rng.randint(2, 20)))
    elif kind == 'overwrite':
        storage.write_bytes(_overwrite(blob, rng, rng.choice([8, 256, 8192])))
    elif kind == 'truncate':
        storage.write_bytes(blob[:rng.randrange(len(blob))])
    else:
        meta = target / 'metadata.yaml'
        meta.write_bytes(rng.choice([rng.randbytes(200), _flip(meta.read_bytes(), rng, 3),
                                     b'', b'[1, 2\n']))
    return f'{fmt}/{kind}', target


def _check_bag(name: str, bag: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    capsys.readouterr()
    before = _tree_sha(bag)
    code = replay.main([str(bag), '--out', str(out), '--no-plots', '-q'])
    stdout, err = capsys.readouterr()
    assert _tree_sha(bag) == before, 'the replay changed the bag'
    assert stdout == ''
    if code == 1:
        assert err.count('\n') == 1 and err.startswith('solid_replay: error: '), err
        return 'stopped'
    assert code == 0 and err == '', (code, err)
    # Damage to a sealed MCAP file is always caught; the other formats carry no checksums.
    assert not name.startswith('mcap/') or name == 'mcap/metadata', 'damaged MCAP replayed'
    report = json.loads((out / 'report.json').read_text())
    scans = report['scans']
    assert scans['messages'] == scans['decoded'] + scans['skipped'], scans
    return 'replayed'


# -- the test -----------------------------------------------------------------------------------


@pytest.fixture(scope='module')
def sources(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Path]]:
    base = tmp_path_factory.mktemp('fuzz_sources')
    rng = np.random.default_rng(SEED)
    scans = []
    for i in range(8):
        pose = np.eye(4)
        pose[0, 3] = 3.0 * (i % 5)
        scans.append((rng.normal(scale=15.0, size=(400, 3)), (i + 1) * 100_000_000, pose))
    yield {fmt: write_cloud_bag(base / fmt, scans, fmt) for fmt in ('mcap', 'sqlite3', 'ros1')}


# numpy's warnings are findings too: a damaged message must not make the core warn about
# signalling NaNs (ros1/overwrite did, from the sensor check's sum over raw points).
@pytest.mark.filterwarnings('error::RuntimeWarning')
def test_fuzz_malformed_inputs(tmp_path: Path, sources: dict[str, Path],
                               capsys: pytest.CaptureFixture[str]) -> None:
    rng = random.Random(SEED)
    tally = Tally()
    outcomes: Counter[str] = Counter()
    # What the inputs made it allocate: numpy reports its buffers to tracemalloc, touched or
    # not (the process's peak RSS would hide one below an earlier peak, or one never touched).
    tracemalloc.start()

    det = LoopDetector(CFG)

    def cloud(msg: SimpleNamespace, stamp: int) -> None:
        outcomes['clouds ' + _check_cloud(msg, det, stamp)] += 1
    for i in range(140):
        kind, msg = _cloud(rng)
        tally.check('clouds', kind, lambda m=msg, s=i: cloud(m, s * 10**8))
    urng = random.Random(SEED + 2)  # its own generator: the other families stay as they were
    for i in range(40):
        kind, msg = _unusable_cloud(urng)
        tally.check('clouds', kind, lambda m=msg, s=140 + i: cloud(m, s * 10**8))

    base = (CONFIG_DIR / 'avia.yaml').read_text()
    pdir = tmp_path / 'params'
    pdir.mkdir()
    for i in range(110):
        kind, blob = _param_file(rng, base)
        path = pdir / f'{i:03d}_{kind}.yaml'
        path.write_bytes(blob)

        def params(p: Path = path, k: str = kind) -> None:
            outcomes[f'params {k} ' + ('refused' if _check_param_file(p, capsys)
                                       else 'accepted')] += 1
        tally.check('parameter files', kind, params)

    db = LoopDetector(CFG)
    for i in range(50):
        db.process(np.random.default_rng(i).normal(scale=15.0, size=(300, 3)), i * 10**8)
    good_path = db.save(tmp_path / 'good.npz')
    good = good_path.read_bytes()
    ddir = tmp_path / 'db'
    ddir.mkdir()
    for i in range(110):
        kind, blob = _database_file(rng, good)
        path = ddir / f'{i:03d}_{kind}.npz'
        path.write_bytes(blob)

        def database(p: Path = path, k: str = kind) -> None:
            outcomes[f'db {k} ' + ('refused' if _check_database(p, db.database)
                                   else 'loaded')] += 1
        tally.check('database files', kind, database)

    bdir = tmp_path / 'bags'
    bdir.mkdir()
    for i in range(45):
        name, bag = _bag_variant(rng, sources, bdir / f'{i:03d}')

        def bags(n: str = name, b: Path = bag, k: int = i) -> None:
            outcomes['bag ' + _check_bag(n, b, tmp_path / 'out' / f'{k:03d}', capsys)] += 1
        tally.check('bags', name, bags)

    grew_mb = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    total, ok = sum(tally.tried.values()), sum(tally.survived.values())
    with capsys.disabled():
        print(f'\nfuzz (seed {SEED}): {total} tried, {ok} survived; '
              + ', '.join(f'{k} {tally.survived[k]}/{n}' for k, n in tally.tried.items())
              + '; ' + ', '.join(f'{k} {n}' for k, n in sorted(outcomes.items()))
              + f'; peak allocation {grew_mb:.0f} MB')
    assert total >= 300
    assert not tally.failures, '\n'.join(tally.failures[:20])
    assert outcomes['clouds no usable point'] >= 40 and outcomes['clouds stored'] > 0
    # What can never be a parameter file or a database is refused, every time it came up.
    for family, kinds, ok in (('params', ('binary', 'empty', 'list', 'nested', 'node'),
                               'accepted'),
                              ('db', ('garbage', 'npy', 'text', 'truncate', 'drop', 'header'),
                               'loaded')):
        for k in kinds:
            assert outcomes[f'{family} {k} refused'] > 0 and not outcomes[f'{family} {k} {ok}'], k
    assert grew_mb < 500


def test_fuzz_through_the_executables(tmp_path: Path, sources: dict[str, Path]) -> None:
    """A handful of real runs: the installed entry points give the same one line."""
    node, replay_exe = BIN / 'solid_node', BIN / 'solid_replay'
    if not node.is_file() or not replay_exe.is_file():
        pytest.skip(f'solid_node / solid_replay not installed next to {sys.executable}')
    rng = random.Random(SEED + 1)
    env = dict(os.environ, ROS_DOMAIN_ID=str(rng.randint(150, 230)))
    params = tmp_path / 'garbage.yaml'
    params.write_bytes(rng.randbytes(500) + b'\xff')
    crafted = tmp_path / 'crafted.npz'
    meta = json.dumps({'format': FORMAT, 'version': 1})[:-1] + ', "count": Infinity}'
    crafted.write_bytes(_zip({'meta.npy': _npy_blob(np.frombuffer(meta.encode(), np.uint8))}))
    damaged = tmp_path / 'damaged'
    damaged.mkdir()
    for p in sources['mcap'].iterdir():
        (damaged / p.name).write_bytes(p.read_bytes())
    storage = _storage(damaged)
    storage.write_bytes(_overwrite(storage.read_bytes(), rng, 64))
    runs = [
        ([str(node), '--ros-args', '--params-file', str(params)], 2, 'not a parameter file'),
        ([str(node), '--ros-args', '-p', f'database_load_path:={crafted}'], 1,
         'Infinity is not allowed'),
        ([str(replay_exe), str(sources['mcap']), '--params', str(params)], 1,
         'not a parameter file'),
        ([str(replay_exe), str(sources['mcap']), '--load-db', str(crafted)], 1,
         'Infinity is not allowed'),
        ([str(replay_exe), str(damaged), '-q'], 1, 'fails its CRC check'),
    ]
    before = {p: _sha(p) for p in (params, crafted, storage)}
    bags_before = {p: _tree_sha(p) for p in (sources['mcap'], damaged)}
    for argv, code, words in runs:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=60, env=env)
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert proc.returncode == code, (argv, proc.stderr)
        assert len(lines) == 1 and words in lines[0], (argv, proc.stderr)
        assert 'Traceback' not in proc.stderr
    assert before == {p: _sha(p) for p in before}
    assert bags_before == {p: _tree_sha(p) for p in bags_before}


# -- peer messages ------------------------------------------------------------------------------


def test_fuzz_peer_messages(capsys: pytest.CaptureFixture[str]) -> None:
    """Damaged peer messages, plain or sealed: decoding refuses them with PeerMessageError
    (or reads a valid message); with a fleet key not one damaged envelope opens."""
    from solid_ros.core.database.clouds import KeyframeCloud
    from solid_ros.formats.peers import (
        CatchUpRequest,
        CloudReply,
        CloudRequest,
        DescriptorMessage,
        PeerMessageError,
        decode,
        encode,
    )
    from solid_ros.ros.peer_guard import PeerGuard, Refused

    rng = random.Random(SEED + 3)
    nrng = np.random.default_rng(SEED)
    key = b'fuzzing fleet key, 32 bytes long'
    cloud = KeyframeCloud(nrng.normal(size=(200, 3)).astype(np.float32), 50)
    msgs = [encode(DescriptorMessage(3, 7, 11, '0123456789abcdef',
                                     nrng.random(40).astype(np.float32),
                                     nrng.random(60).astype(np.float32), (0.0,) * 6 + (1.0,))),
            encode(CloudRequest(3, 4, 5, 6, 7)), encode(CatchUpRequest(3, 100)),
            encode(CloudReply(4, 3, 5, 6, 7, cloud)), encode(CloudReply(4, 3, 5, 6, 7, None))]
    sender = PeerGuard(3, key)
    receiver = PeerGuard(9, key)
    tally = Tally()
    opened = Counter[str]()

    def plain(blob: bytes) -> None:
        try:
            decode(blob, max_cloud_points=1000)
            opened['plain decoded'] += 1
        except PeerMessageError:
            opened['plain refused'] += 1

    def sealed(blob: bytes, intact: bool) -> None:
        try:
            _, inner = receiver.open('/t', blob)
        except Refused as r:
            assert not intact, r
            opened[f'sealed {r.kind}'] += 1
            return
        assert intact, 'a damaged envelope opened'
        decode(inner)
        opened['sealed opened'] += 1

    for _ in range(600):
        base = rng.choice(msgs)
        kind = rng.choice(['flip', 'overwrite', 'truncate', 'extend'])
        if kind == 'flip':
            blob = _flip(base, rng, rng.randint(1, 4))
        elif kind == 'overwrite':
            blob = _overwrite(base, rng, rng.choice([4, 8, 32]))
        elif kind == 'truncate':
            blob = base[:rng.randrange(len(base))]
        else:
            blob = base + rng.randbytes(rng.randint(1, 64))
        tally.check('peer messages', kind, lambda b=blob: plain(b))
        env = sender.seal('/t', base)
        tally.check('sealed peer messages', 'intact', lambda e=env: sealed(e, True))
        bad = _flip(env, rng, rng.randint(1, 3)) if kind != 'truncate' else env[:-1]
        if bad != env:
            tally.check('sealed peer messages', kind, lambda b=bad: sealed(b, False))
    with capsys.disabled():
        print(f'\npeer fuzz: {sum(tally.tried.values())} tried; '
              + ', '.join(f'{k} {n}' for k, n in sorted(opened.items())))
    assert not tally.failures, '\n'.join(tally.failures[:20])
    assert opened['plain refused'] > 300 and opened['sealed opened'] == 600
