"""The saved database file: its format, and reading it safely.

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
"""

from __future__ import annotations

import json
import math
import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.database.descriptors import POSE_FIELDS
from solid_ros.core.errors import DatabaseError

__all__ = ['FORMAT', 'VERSION', 'NpyHeader', 'check_headers', 'is_database',
           'read_database', 'read_npz_headers', 'scan_count', 'shorten']

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
                            f'{shorten(str(err))}') from err
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
                            f'archive: {shorten(str(err))})') from err


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
                            f'{shorten(str(err))}') from err
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
                            f'JSON: {shorten(str(err) or type(err).__name__)})') from err
    if not isinstance(meta, dict) or meta.get('format') != FORMAT:
        fmt = meta.get('format') if isinstance(meta, dict) else None
        raise DatabaseError(f'{p} is not a solid_ros database (format {shorten(repr(fmt))})')
    if meta.get('version') not in _READABLE:
        raise DatabaseError(f'{p} has database format version '
                            f'{shorten(repr(meta.get("version")))}; this solid_ros reads '
                            f'versions {", ".join(map(str, _READABLE))}')
    return meta


def shorten(text: str, limit: int = 120) -> str:
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
                                f'{shorten(repr(value))}')
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


def is_database(path: str | Path) -> bool:
    """Whether ``path`` is a regular file holding a solid_ros database (any version)."""
    try:
        with _open_archive(Path(path)) as zf:
            meta = _read_meta(zf, read_npz_headers(zf, Path(path)), Path(path))
    except (DatabaseError, *_READ_ERRORS):
        return False
    return meta.get('format') == FORMAT


def scan_count(path: Path) -> int | None:
    """Scans held by the database at ``path`` (None: not a readable database)."""
    try:
        with _open_archive(path) as zf:
            meta = _read_meta(zf, read_npz_headers(zf, path), path)
    except (DatabaseError, *_READ_ERRORS):
        return None
    count = meta.get('count')
    return count if isinstance(count, int) and meta.get('format') == FORMAT else None
