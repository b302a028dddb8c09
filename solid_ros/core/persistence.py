"""Saving and loading a descriptor database as one ``.npz`` file, atomically and safely.

File layout (``numpy.savez``, no pickled objects; loaded with ``allow_pickle=False``):

- ``meta``: UTF-8 JSON as a uint8 array: ``format`` (``'solid_ros.database'``), ``version``,
  ``count``, ``shape_params`` (every setting that changes descriptor values), ``fingerprint``,
  ``sessions`` (the session ids held).
- ``r_solid`` (n, N_r) float32, unit-normalised (all-zero rows for empty scans);
  ``a_solid`` (n, N_a) float32, unit-normalised; ``stamps_ns`` (n,) int64; ``indices`` (n,)
  int64 (index of the scan within its session); ``sessions`` (n,) int32; ``poses`` (n, 7)
  float32 ``x y z qx qy qz qw`` (NaN rows where the scan had no pose). Rows are oldest first.

Writing goes to a temporary file in the target directory, which is flushed, fsynced and then
renamed over the target, so a crash leaves either the old file or the new one, never a torn one.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.database import POSE_FIELDS, DescriptorDatabase
from solid_ros.core.errors import DatabaseError

__all__ = ['FORMAT', 'VERSION', 'load_database', 'read_database', 'save_database']

FORMAT = 'solid_ros.database'
VERSION = 1

_READ_ERRORS = (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile,
                zlib.error, UnicodeDecodeError)


def save_database(db: DescriptorDatabase, path: str | Path) -> Path:
    """Write every stored scan of ``db`` (all sessions) to ``path`` atomically.

    Args:
        db: the database.
        path: target file; written exactly as named (no ``.npz`` is appended).

    Returns:
        The path written.

    Raises:
        DatabaseError: the file cannot be written (the message names it and the reason).
    """
    target = Path(path)
    arrays: dict[str, Any] = db.export_arrays()
    meta = {'format': FORMAT, 'version': VERSION, 'count': int(len(arrays['indices'])),
            'num_range': db.num_range, 'num_angle': db.num_angle,
            'shape_params': db.config.shape_params(), 'fingerprint': db.config.fingerprint(),
            'sessions': sorted({int(s) for s in arrays['sessions']})}
    arrays['meta'] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    tmp_name = ''
    try:
        directory = target.resolve().parent
        fd, tmp_name = tempfile.mkstemp(prefix=f'.{target.name}.', suffix='.tmp',
                                        dir=directory)
        with os.fdopen(fd, 'wb') as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp_name, target)
        tmp_name = ''
        _fsync_dir(directory)
    except OSError as err:
        raise DatabaseError(f'cannot write database {target}: {err.strerror or err}') from err
    finally:
        if tmp_name:
            with contextlib.suppress(OSError):
                os.unlink(tmp_name)
    return target


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

    Returns:
        ``(meta, arrays)`` with the keys described in the module docstring.

    Raises:
        DatabaseError: the file is missing, unreadable, truncated, not a database, of another
            format version, or its arrays have wrong keys, types or shapes.
    """
    p = Path(path)
    try:
        loaded = np.load(p, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise DatabaseError(f'{p} is a single .npy array, not a solid_ros database')
        with loaded as npz:
            if 'meta' not in npz.files:
                raise DatabaseError(f'{p} is not a solid_ros database (no "meta" entry)')
            meta = json.loads(npz['meta'].tobytes().decode('utf-8'))
            if not isinstance(meta, dict) or meta.get('format') != FORMAT:
                raise DatabaseError(f'{p} is not a solid_ros database (format '
                                    f'{meta.get("format") if isinstance(meta, dict) else None!r})')
            if meta.get('version') != VERSION:
                raise DatabaseError(f'{p} has database format version {meta.get("version")!r}; '
                                    f'this solid_ros reads version {VERSION}')
            missing = [k for k in _expected(meta) if k not in npz.files]
            if missing:
                raise DatabaseError(f'{p} is incomplete: missing array {missing[0]!r}')
            arrays = {k: npz[k] for k in _expected(meta)}
    except DatabaseError:
        raise
    except FileNotFoundError as err:
        raise DatabaseError(f'database file {p} does not exist') from err
    except _READ_ERRORS as err:
        raise DatabaseError(f'{p} is not a readable solid_ros database (truncated, corrupt or '
                            f'another kind of file): {type(err).__name__}: {err}') from err
    _check_arrays(p, meta, arrays)
    return meta, arrays


def _expected(meta: dict[str, Any]) -> dict[str, tuple[np.dtype[Any], tuple[int, ...]]]:
    try:
        n, n_r, n_a = int(meta['count']), int(meta['num_range']), int(meta['num_angle'])
    except (KeyError, TypeError, ValueError) as err:
        raise DatabaseError(f'database metadata lacks a valid count/num_range/num_angle: '
                            f'{err}') from err
    return {'r_solid': (np.dtype(np.float32), (n, n_r)),
            'a_solid': (np.dtype(np.float32), (n, n_a)),
            'stamps_ns': (np.dtype(np.int64), (n,)),
            'indices': (np.dtype(np.int64), (n,)),
            'sessions': (np.dtype(np.int32), (n,)),
            'poses': (np.dtype(np.float32), (n, len(POSE_FIELDS)))}


def _check_arrays(p: Path, meta: dict[str, Any], arrays: dict[str, npt.NDArray[Any]]) -> None:
    for key, (dtype, shape) in _expected(meta).items():
        arr = arrays[key]
        if arr.dtype != dtype or arr.shape != shape:
            raise DatabaseError(f'{p}: array {key!r} is {arr.dtype}{list(arr.shape)}, '
                                f'expected {dtype}{list(shape)}')
    for key in ('r_solid', 'a_solid'):
        if not np.all(np.isfinite(arrays[key])):
            raise DatabaseError(f'{p}: array {key!r} holds NaN or infinite values')


def load_database(path: str | Path, config: SolidConfig) -> DescriptorDatabase:
    """Load a saved database into a new one built from ``config``.

    The loaded scans keep their session ids and indices and are never excluded as recent;
    the new database's own scans get ``config.session_id``.

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
    diffs = [f'{k} (file {saved.get(k, "<absent>")!r}, config {current.get(k, "<absent>")!r})'
             for k in sorted(set(saved) | set(current)) if saved.get(k) != current.get(k)]
    if diffs:
        raise DatabaseError(f'{path} was built with different descriptor settings: '
                            + '; '.join(diffs))
    db = DescriptorDatabase(config)
    db.import_arrays(arrays)
    return db
