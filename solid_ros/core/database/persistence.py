"""Saving and loading a descriptor database as one ``.npz`` file, atomically and safely.

File layout (``numpy.savez``, no pickled objects; loaded with ``allow_pickle=False``):

- ``meta``: UTF-8 JSON as a uint8 array: ``format`` (``'solid_ros.database'``), ``version``,
  ``count``, ``shape_params`` (every setting that changes descriptor values), ``fingerprint``,
  ``sessions`` (the session ids held).
- ``r_solid`` (n, N_r) float32, unit-normalised (all-zero rows for empty scans);
  ``a_solid`` (n, N_a) float32, unit-normalised; ``stamps_ns`` (n,) int64; ``indices`` (n,)
  int64 (index of the scan within its session); ``sessions`` (n,) int32; ``poses`` (n, 7)
  float32 ``x y z qx qy qz qw`` (NaN rows where the scan had no pose). Rows are oldest first.
- Keyframe clouds (version 2): ``cloud_points`` (P, 3) float32, all clouds one after another
  (each structure points first); ``cloud_offsets`` (n + 1,) int64, scan ``i`` owns rows
  ``offsets[i]:offsets[i + 1]`` (empty: no cloud); ``cloud_struct`` (n,) int32, its structure
  points (-1: no cloud); ``cloud_voxel`` (n,) float64, the grid each cloud was kept on (0:
  the configuration's; optional, files from before the tight-space grid lack it).
  ``meta['cloud_points']`` is P. Version 1 files (no clouds) still load; their scans cannot be
  verified.

Reading checks every array's dtype and shape in its ``.npy`` header, and the header against the
archive member's size, before any array is read (:func:`read_npz_headers`), so a crafted file is
refused before it can make the loader allocate memory; a file that is not such an archive is
named as not a solid_ros database.

Writing goes to a temporary file in the target directory, which is flushed, fsynced and then
renamed over the target, so a crash leaves either the old file or the new one, never a torn one.
The target must be absent or a regular file holding a solid_ros database: a symbolic link, a
device, a directory or any other file is never replaced (:func:`check_save_target`). The
temporary file is locked while it is written; one left by a killed save is removed by the next
save of the same target (:func:`remove_stale_temporaries`).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import re
import shutil
import stat
import tempfile
import zipfile
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import CloudStore, KeyframeCloud
from solid_ros.core.database.descriptors import POSE_FIELDS, DescriptorDatabase
from solid_ros.core.errors import DatabaseError, SolidError
from solid_ros.core.geometry import pose_to_vector, vector_to_matrix

__all__ = ['FORMAT', 'VERSION', 'NpyHeader', 'PriorMap', 'backup_if_shrinking',
           'check_save_target', 'is_database', 'load_database', 'read_database',
           'read_map_poses', 'read_npz_headers', 'remove_stale_temporaries', 'save_database',
           'write_atomic']

FORMAT = 'solid_ros.database'
VERSION = 3
_READABLE = (1, 2, 3)

_READ_ERRORS = (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile,
                zlib.error, UnicodeDecodeError, RecursionError, OverflowError, MemoryError,
                NotImplementedError)  # zipfile: unknown compression or 'zip file version'
# The metadata is a few settings and session ids; an .npy header is a short dict literal.
_MAX_META_BYTES = 1 << 20
_MAX_NPY_HEADER = 10_000
_NPY_MAGIC = b'\x93NUMPY'
_ZIP_MAGICS = (b'PK\x03\x04', b'PK\x05\x06')


def save_database(db: DescriptorDatabase, path: str | Path,
                  clouds: CloudStore | None = None,
                  map_poses: Mapping[tuple[int, int], Any] | None = None) -> Path:
    """Write every stored scan of ``db`` (all sessions) to ``path`` atomically.

    Args:
        db: the database.
        path: target file; written exactly as named (no ``.npz`` is appended).
        clouds: keyframe clouds of ``db``'s scans, saved with them (None: no clouds).
        map_poses: map-frame pose of scans by ``(session, index)`` (4x4 or ``x y z qx qy qz
            qw``), e.g. the back end's corrected poses; scans without one get a NaN row.

    Returns:
        The path written.

    Raises:
        DatabaseError: the file cannot be written (the message names it and the reason).
    """
    target = Path(path)
    check_save_target(target)
    remove_stale_temporaries(target)
    arrays: dict[str, Any] = db.export_arrays()
    arrays.update(_export_clouds(db, clouds))
    arrays['map_poses'] = _export_map_poses(arrays, map_poses or {})
    meta = {'format': FORMAT, 'version': VERSION, 'count': int(len(arrays['indices'])),
            'num_range': db.num_range, 'num_angle': db.num_angle,
            'cloud_points': int(len(arrays['cloud_points'])),
            'shape_params': db.config.shape_params(), 'fingerprint': db.config.fingerprint(),
            'sessions': sorted({int(s) for s in arrays['sessions']})}
    arrays['meta'] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    write_atomic(target, lambda f: np.savez(f, **arrays), check=check_save_target,
                 what='database', error=DatabaseError)
    return target


def _export_clouds(db: DescriptorDatabase,
                   clouds: CloudStore | None) -> dict[str, npt.NDArray[Any]]:
    """The clouds of the stored scans, oldest first, as the three cloud arrays."""
    seqs = db.stored_seqs()
    parts: list[npt.NDArray[np.float32]] = []
    offsets = np.zeros(len(seqs) + 1, dtype=np.int64)
    struct = np.full(len(seqs), -1, dtype=np.int32)
    voxel = np.zeros(len(seqs), dtype=np.float64)
    for i, seq in enumerate(seqs):
        cloud = clouds.get(seq) if clouds is not None else None
        offsets[i + 1] = offsets[i]
        if cloud is not None:
            parts.append(cloud.points)
            offsets[i + 1] += len(cloud.points)
            struct[i] = cloud.n_struct
            voxel[i] = cloud.voxel
    points = (np.concatenate(parts).astype(np.float32, copy=False) if parts
              else np.zeros((0, 3), dtype=np.float32))
    return {'cloud_points': points, 'cloud_offsets': offsets, 'cloud_struct': struct,
            'cloud_voxel': voxel}


def _export_map_poses(arrays: dict[str, Any],
                      map_poses: Mapping[tuple[int, int], Any]) -> npt.NDArray[np.float64]:
    """(n, 7) map poses in the order of the exported rows (NaN rows: none)."""
    out = np.full((len(arrays['indices']), len(POSE_FIELDS)), np.nan)
    for row, key in enumerate(zip(arrays['sessions'].tolist(), arrays['indices'].tolist())):
        pose = map_poses.get(key)
        if pose is not None:
            try:
                out[row] = pose_to_vector(pose)
            except SolidError as err:
                raise DatabaseError(f'map pose of session {key[0]} keyframe {key[1]}: '
                                    f'{err}') from err
    return out


def write_atomic(target: str | Path, write: Callable[[IO[bytes]], object], *,
                 check: Callable[[Path], None] | None = None, what: str = 'file',
                 error: type[SolidError] = SolidError) -> Path:
    """Write through ``write(file)`` to a locked temporary file beside ``target``, then rename
    it over ``target``: a crash leaves the old file or the new one, never a torn one.

    The lock tells :func:`remove_stale_temporaries` that the file is in use; it is held until
    the rename is done.

    Args:
        target: the file to write.
        write: writes the content into the open temporary file.
        check: called with ``target`` just before the rename (may raise to keep the old file).
        what: the kind of file, for the error message.
        error: the error class raised.

    Raises:
        SolidError: (``error``) the file cannot be written.
    """
    path = Path(target)
    tmp_name = ''
    try:
        directory = path.parent.resolve()  # not path.resolve(): never follow a link
        fd, tmp_name = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp',
                                        dir=directory)
        with os.fdopen(fd, 'wb') as f:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX)
            write(f)
            f.flush()
            os.fsync(f.fileno())
            if check is not None:
                check(path)  # again, just before replacing it
            os.replace(tmp_name, path)
            tmp_name = ''
        _fsync_dir(directory)
    except OSError as err:
        raise error(f'cannot write {what} {path}: {err.strerror or err}') from err
    finally:
        if tmp_name:
            with contextlib.suppress(OSError):
                os.unlink(tmp_name)
    return path


def check_save_target(path: str | Path) -> None:
    """Refuse a save target that is not absent or a regular solid_ros database file.

    Raises:
        DatabaseError: ``path`` is a symbolic link, a device, a directory or another
            non-regular file, or a regular file that is not a solid_ros database.
    """
    target = Path(path)
    try:
        st = os.lstat(target)
    except FileNotFoundError:
        return
    except OSError as err:
        raise DatabaseError(f'cannot check database target {target}: '
                            f'{err.strerror or err}') from err
    if stat.S_ISLNK(st.st_mode):
        raise DatabaseError(f'{target} is a symbolic link; a database is never written through '
                            'a link: give the real path')
    if not stat.S_ISREG(st.st_mode):
        raise DatabaseError(f'{target} exists and is not a regular file; it is not replaced by '
                            'a database')
    if not is_database(target):
        raise DatabaseError(f'{target} exists and is not a solid_ros database; it is not '
                            'replaced (remove it or save elsewhere)')


def is_database(path: str | Path) -> bool:
    """Whether ``path`` is a regular file holding a solid_ros database (any version)."""
    try:
        with _open_archive(Path(path)) as zf:
            meta = _read_meta(zf, read_npz_headers(zf, Path(path)), Path(path))
    except (DatabaseError, *_READ_ERRORS):
        return False
    return meta.get('format') == FORMAT


def _scan_count(path: Path) -> int | None:
    """Scans held by the database at ``path`` (None: not a readable database)."""
    try:
        with _open_archive(path) as zf:
            meta = _read_meta(zf, read_npz_headers(zf, path), path)
    except (DatabaseError, *_READ_ERRORS):
        return None
    count = meta.get('count')
    return count if isinstance(count, int) and meta.get('format') == FORMAT else None


def backup_if_shrinking(path: str | Path, new_count: int, ratio: float = 0.5) -> Path | None:
    """Keep the database at ``path`` as ``<path>.bak`` before a save of ``new_count`` scans
    that would replace it with an empty one or one under ``ratio`` of its size.

    The backup is a hard link (a copy where links are impossible) taken before the save, so
    the saved scans survive a ``~/reset`` followed by ``~/save_database``. An existing backup
    is replaced only by a database at least as large: repeated resets and saves never wear
    the largest one away.

    Returns:
        The backup written, or None (no database at ``path``, or the save does not shrink it).

    Raises:
        DatabaseError: the backup could not be written (the save should not go ahead).
    """
    target = Path(path)
    old = _scan_count(target) if target.is_file() and not target.is_symlink() else None
    if old is None or old == 0 or (new_count > 0 and new_count >= ratio * old):
        return None
    backup = target.with_name(target.name + '.bak')
    check_save_target(backup)
    kept = _scan_count(backup) if backup.exists() else None
    if kept is not None and kept > old:
        return backup  # a larger backup is kept as it is
    tmp = backup.with_name(f'.{backup.name}.{os.getpid()}.link')
    try:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        try:
            os.link(target, tmp)
        except OSError:
            shutil.copyfile(target, tmp, follow_symlinks=False)
        os.replace(tmp, backup)
        _fsync_dir(backup.parent)
    except OSError as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise DatabaseError(f'cannot keep a backup of {target} as {backup}: '
                            f'{err.strerror or err}') from err
    return backup


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove temporary files that killed saves of ``path`` left behind.

    Only files named like this module's temporaries of ``path`` are considered, and only
    those no live save holds locked.

    Returns:
        The files removed.
    """
    target = Path(path)
    pattern = re.compile(re.escape(f'.{target.name}.') + r'[a-z0-9_]{8}\.tmp')
    removed: list[Path] = []
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return removed
    for entry in entries:
        if not pattern.fullmatch(entry.name) or not entry.is_file(follow_symlinks=False):
            continue
        try:
            fd = os.open(entry.path, os.O_RDWR | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.unlink(entry.path)
            removed.append(Path(entry.path))
        except OSError:
            continue  # a save in progress holds the lock
        finally:
            os.close(fd)
    return removed


def _fsync_dir(directory: Path) -> None:
    """Make the rename durable (POSIX); not possible everywhere, so best effort."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def read_database(path: str | Path) -> tuple[dict[str, Any], dict[str, npt.NDArray[Any]]]:
    """Read and validate a saved database without checking it against a configuration.

    Every array's header is checked against the metadata and the archive before any array is
    read (see the module docstring).

    Returns:
        ``(meta, arrays)`` with the keys described in the module docstring.

    Raises:
        DatabaseError: the file is missing, unreadable, truncated, not a database, of another
            format version, or its arrays have wrong keys, types or shapes.
    """
    p = Path(path)
    try:
        with _open_archive(p) as zf:
            headers = read_npz_headers(zf, p)
            meta = _read_meta(zf, headers, p)
            expected = _expected(meta, p)
            if 'cloud_voxel' in headers and 'cloud_struct' in expected:  # optional: newer files
                expected['cloud_voxel'] = (np.dtype(np.float64), expected['cloud_struct'][1])
            check_headers(p, headers, expected)
            arrays = {k: _read_array(zf, headers[k]) for k in expected}
    except DatabaseError:
        raise
    except FileNotFoundError as err:
        raise DatabaseError(f'database file {p} does not exist') from err
    except _READ_ERRORS as err:
        raise DatabaseError(f'{p} is not a readable solid_ros database (truncated, corrupt or '
                            f'another kind of file): {type(err).__name__}: '
                            f'{_short(str(err))}') from err
    _check_arrays(p, meta, arrays)
    return meta, arrays


@dataclass(frozen=True)
class NpyHeader:
    """The header of one ``.npy`` member of an ``.npz`` archive.

    Attributes:
        member: archive member name (``key + '.npy'``).
        dtype: array dtype.
        shape: array shape.
        fortran_order: whether the data is in Fortran order.
        data_offset: where the data starts within the member.
    """

    member: str
    dtype: np.dtype[Any]
    shape: tuple[int, ...]
    fortran_order: bool
    data_offset: int

    @property
    def nbytes(self) -> int:
        """Bytes the array data takes (exact Python integer, no overflow)."""
        return math.prod(self.shape) * self.dtype.itemsize


def _open_archive(p: Path) -> zipfile.ZipFile:
    """Open ``p`` as a zip archive, or say what else it is."""
    with p.open('rb') as f:
        head = f.read(8)
    if head.startswith(_NPY_MAGIC):
        raise DatabaseError(f'{p} is a single .npy array, not a solid_ros database')
    if not head.startswith(_ZIP_MAGICS):
        raise DatabaseError(f'{p} is not a solid_ros database (not a numpy .npz archive)')
    try:
        return zipfile.ZipFile(p)
    except zipfile.BadZipFile as err:
        raise DatabaseError(f'{p} is not a solid_ros database (damaged or not a numpy .npz '
                            f'archive: {_short(str(err))})') from err


def read_npz_headers(zf: zipfile.ZipFile, path: str | Path) -> dict[str, NpyHeader]:
    """Read the ``.npy`` header of every array of an archive, and no array data.

    Each header must describe exactly the bytes its member holds, members must be stored
    uncompressed (as ``numpy.savez`` writes them) and fit in the file, so that reading an
    array afterwards allocates no more than the file's size.

    Returns:
        Headers by array name (the member name without ``.npy``).

    Raises:
        DatabaseError: a member is duplicated, compressed, bigger than the file, or its
            header is malformed, holds Python objects or disagrees with the member's size.
    """
    p = Path(path)
    size = os.stat(p).st_size
    out: dict[str, NpyHeader] = {}
    stored = 0
    for info in zf.infolist():
        if not info.filename.endswith('.npy'):
            continue
        key = info.filename[:-4]
        if key in out:
            raise DatabaseError(f'{p}: archive holds {info.filename!r} twice')
        if info.compress_type != zipfile.ZIP_STORED or info.compress_size != info.file_size:
            raise DatabaseError(f'{p}: array {key!r} is compressed; solid_ros databases are '
                                'stored uncompressed (numpy.savez)')
        stored += info.file_size
        if stored > size:
            raise DatabaseError(f'{p}: archive members claim {stored} bytes, more than the '
                                f'file holds ({size})')
        with zf.open(info) as fp:
            header = _npy_header(fp, info.filename, p)
        if header.data_offset + header.nbytes != info.file_size:
            raise DatabaseError(f'{p}: array {key!r} header says {header.dtype}'
                                f'{list(header.shape)} ({header.nbytes} bytes) but the archive '
                                f'holds {info.file_size - header.data_offset} bytes of data')
        out[key] = header
    return out


def _npy_header(fp: IO[bytes], member: str, p: Path) -> NpyHeader:
    try:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(
                fp, max_header_size=_MAX_NPY_HEADER)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(
                fp, max_header_size=_MAX_NPY_HEADER)
        else:
            raise DatabaseError(f'{p}: {member} has .npy version {version}; expected 1.0 '
                                'or 2.0')
    except DatabaseError:
        raise
    except (ValueError, TypeError, SyntaxError, EOFError) as err:
        raise DatabaseError(f'{p}: {member} has a malformed .npy header: '
                            f'{_short(str(err))}') from err
    if dtype.hasobject:
        raise DatabaseError(f'{p}: {member} holds Python objects; solid_ros databases never do')
    return NpyHeader(member, dtype, tuple(int(n) for n in shape), bool(fortran), fp.tell())


def check_headers(p: Path, headers: dict[str, NpyHeader],
                  expected: dict[str, tuple[np.dtype[Any], tuple[int | None, ...]]]) -> None:
    """Check that every expected array is present with its dtype and shape (None = any length).

    Raises:
        DatabaseError: an array is missing or has another dtype or shape.
    """
    for key, (dtype, shape) in expected.items():
        h = headers.get(key)
        if h is None:
            raise DatabaseError(f'{p} is incomplete: missing array {key!r}')
        same_shape = len(h.shape) == len(shape) and all(
            want is None or got == want for got, want in zip(h.shape, shape))
        if h.dtype != dtype or not same_shape:
            raise DatabaseError(f'{p}: array {key!r} is {h.dtype}{list(h.shape)}, expected '
                                f'{dtype}{list(shape)}')


def _read_array(zf: zipfile.ZipFile, header: NpyHeader) -> npt.NDArray[Any]:
    with zf.open(header.member) as fp:
        arr: npt.NDArray[Any] = np.lib.format.read_array(fp, allow_pickle=False,
                                                         max_header_size=_MAX_NPY_HEADER)
    return arr


def _read_meta(zf: zipfile.ZipFile, headers: dict[str, NpyHeader], p: Path) -> dict[str, Any]:
    """The metadata JSON, checked for format, version and well-formed sizes."""
    h = headers.get('meta')
    if h is None:
        raise DatabaseError(f'{p} is not a solid_ros database (no "meta" entry)')
    if h.dtype != np.uint8 or len(h.shape) != 1 or h.nbytes > _MAX_META_BYTES:
        raise DatabaseError(f'{p} is not a solid_ros database ("meta" is {h.dtype}'
                            f'{list(h.shape)}, expected uint8 JSON up to {_MAX_META_BYTES} '
                            'bytes)')

    def no_constants(name: str) -> Any:
        raise ValueError(f'{name} is not allowed')

    try:
        meta = json.loads(_read_array(zf, h).tobytes().decode('utf-8'),
                          parse_constant=no_constants)
    except RecursionError as err:
        raise DatabaseError(f'{p} is not a solid_ros database (its "meta" entry is not valid '
                            'JSON: nested too deeply)') from err
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError, constants
        raise DatabaseError(f'{p} is not a solid_ros database (its "meta" entry is not valid '
                            f'JSON: {_short(str(err) or type(err).__name__)})') from err
    if not isinstance(meta, dict) or meta.get('format') != FORMAT:
        fmt = meta.get('format') if isinstance(meta, dict) else None
        raise DatabaseError(f'{p} is not a solid_ros database (format {_short(repr(fmt))})')
    if meta.get('version') not in _READABLE:
        raise DatabaseError(f'{p} has database format version '
                            f'{_short(repr(meta.get("version")))}; this solid_ros reads '
                            f'versions {", ".join(map(str, _READABLE))}')
    return meta


def _short(text: str, limit: int = 120) -> str:
    text = ' '.join(text.split())
    return text if len(text) <= limit else text[:limit - 3] + '...'


def _expected(meta: dict[str, Any], p: Path) -> dict[str, tuple[np.dtype[Any],
                                                                tuple[int | None, ...]]]:
    sizes = {}
    version = meta.get('version')
    keys = ('count', 'num_range', 'num_angle') + (('cloud_points',) if version in (2, 3)
                                                 else ())
    for key in keys:
        value = meta.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise DatabaseError(f'{p}: database metadata lacks a valid {key}: '
                                f'{_short(repr(value))}')
        sizes[key] = value
    n, n_r, n_a = sizes['count'], sizes['num_range'], sizes['num_angle']
    out: dict[str, tuple[np.dtype[Any], tuple[int | None, ...]]] = {
        'r_solid': (np.dtype(np.float32), (n, n_r)),
        'a_solid': (np.dtype(np.float32), (n, n_a)),
        'stamps_ns': (np.dtype(np.int64), (n,)),
        'indices': (np.dtype(np.int64), (n,)),
        'sessions': (np.dtype(np.int32), (n,)),
        'poses': (np.dtype(np.float32), (n, len(POSE_FIELDS)))}
    if 'cloud_points' in sizes:
        out['cloud_points'] = (np.dtype(np.float32), (sizes['cloud_points'], 3))
        out['cloud_offsets'] = (np.dtype(np.int64), (n + 1,))
        out['cloud_struct'] = (np.dtype(np.int32), (n,))
    if version == 3:
        out['map_poses'] = (np.dtype(np.float64), (n, len(POSE_FIELDS)))
    return out


def _check_arrays(p: Path, meta: dict[str, Any], arrays: dict[str, npt.NDArray[Any]]) -> None:
    for key, (dtype, shape) in _expected(meta, p).items():
        arr = arrays[key]
        if arr.dtype != dtype or arr.shape != shape:
            raise DatabaseError(f'{p}: array {key!r} is {arr.dtype}{list(arr.shape)}, '
                                f'expected {dtype}{list(shape)}')
    for key in ('r_solid', 'a_solid', 'cloud_points', 'cloud_voxel'):
        if key in arrays and not np.all(np.isfinite(arrays[key])):
            raise DatabaseError(f'{p}: array {key!r} holds NaN or infinite values')
    if 'cloud_voxel' in arrays and np.any(arrays['cloud_voxel'] < 0.0):
        raise DatabaseError(f"{p}: array 'cloud_voxel' holds negative voxels")
    if 'map_poses' in arrays:
        mp = arrays['map_poses']
        finite = np.isfinite(mp)
        rows = np.all(finite, axis=1)
        if np.any(finite.any(axis=1) & ~rows) or np.any(
                np.linalg.norm(mp[rows, 3:], axis=1) < 1e-6):
            raise DatabaseError(f"{p}: array 'map_poses' holds partly NaN rows or zero "
                                'quaternions')
    if 'cloud_offsets' in arrays:
        off, struct = arrays['cloud_offsets'], arrays['cloud_struct']
        size = np.diff(off)
        if (off[0] != 0 or off[-1] != len(arrays['cloud_points']) or np.any(size < 0)
                or np.any(struct > size) or np.any((struct < 0) & (size > 0))
                or np.any(struct < -1)):
            raise DatabaseError(f'{p}: the keyframe cloud offsets or structure counts are '
                                'inconsistent')


def load_database(path: str | Path, config: SolidConfig,
                  clouds: CloudStore | None = None) -> DescriptorDatabase:
    """Load a saved database into a new one built from ``config``.

    The loaded scans keep their session ids and indices and are never excluded as recent;
    the new database's own scans get ``config.session_id``. Settings a file does not name
    (it was saved before they existed) count as their defaults.

    Args:
        path: the file.
        config: settings of the new database.
        clouds: store that receives the saved keyframe clouds (None: not loaded).

    Raises:
        DatabaseError: the file cannot be read (see :func:`read_database`), it was made with
            different descriptor settings (each differing setting is named with both values),
            or it already holds ``config.session_id``.
    """
    meta, arrays = read_database(path)
    saved = meta.get('shape_params')
    if not isinstance(saved, dict):
        raise DatabaseError(f'{path}: metadata has no shape_params')
    current = config.shape_params()
    saved = {**SolidConfig().shape_params(), **saved}
    diffs = [f'{_short(str(k), 40)} (file {_short(repr(saved.get(k, "<absent>")), 40)}, '
             f'config {current.get(k, "<absent>")!r})'
             for k in sorted(set(saved) | set(current), key=str) if saved.get(k) != current.get(k)]
    if diffs:
        more = f'; and {len(diffs) - 6} more' if len(diffs) > 6 else ''
        raise DatabaseError(f'{path} was built with different descriptor settings: '
                            + '; '.join(diffs[:6]) + more)
    db = DescriptorDatabase(config)
    first = db.next_seq - max(0, len(arrays['indices']) - config.capacity)
    try:
        db.import_arrays(arrays)
    except DatabaseError as err:
        raise DatabaseError(f'{path}: {err}') from err
    if clouds is not None and 'cloud_offsets' in arrays:
        off, struct, pts = arrays['cloud_offsets'], arrays['cloud_struct'], arrays['cloud_points']
        # Files from before the tight-space grid hold clouds on the configuration's grid.
        voxel = arrays.get('cloud_voxel', np.zeros(len(struct)))
        for seq in range(db.oldest_seq, db.next_seq):
            i = seq - first
            if struct[i] >= 0:
                clouds.put(seq, KeyframeCloud(pts[off[i]:off[i + 1]], int(struct[i]),
                                              float(voxel[i])))
    return db


@dataclass(frozen=True)
class PriorMap:
    """The map-frame poses of a saved database's scans, for relocalising in it.

    Attributes:
        poses: 4x4 ``T_map_sensor`` by ``(session, index)``.
        source: ``'map'`` (the back end's corrected poses, version 3) or ``'odometry'`` (an
            older file: the odometry poses it stored stand in for the map).
    """

    poses: dict[tuple[int, int], npt.NDArray[np.float64]]
    source: str


def read_map_poses(path: str | Path) -> PriorMap:
    """The map-frame poses saved in a database (see :class:`PriorMap`); scans without one
    are left out.

    Raises:
        DatabaseError: the file cannot be read (see :func:`read_database`).
    """
    meta, arrays = read_database(path)
    source = 'map' if 'map_poses' in arrays else 'odometry'
    rows = arrays['map_poses'] if source == 'map' else arrays['poses'].astype(np.float64)
    out = {}
    for session, index, row in zip(arrays['sessions'].tolist(), arrays['indices'].tolist(),
                                   rows):
        if np.all(np.isfinite(row)) and np.linalg.norm(row[3:]) > 1e-6:
            out[(int(session), int(index))] = vector_to_matrix(row)
    return PriorMap(out, source)
