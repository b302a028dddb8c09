"""Saving and loading a descriptor database as one ``.npz`` file, atomically and safely.

The file's layout and its safe reading: :mod:`solid_ros.core.database.archive`; the atomic
write: :mod:`solid_ros.core.database.atomic`.

A save writes atomically, so a crash leaves either the old file or the new one, never a torn one.
The target must be absent or a regular file holding a solid_ros database: a symbolic link, a
device, a directory or any other file is never replaced (:func:`check_save_target`). The
temporary file is locked while it is written; one left by a killed save is removed by the next
save of the same target
(:func:`~solid_ros.core.database.atomic.remove_stale_temporaries`).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import stat
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.archive import (
    FORMAT,
    VERSION,
    is_database,
    read_database,
    scan_count,
    shorten,
)
from solid_ros.core.database.atomic import fsync_dir, remove_stale_temporaries, write_atomic
from solid_ros.core.database.clouds import CloudStore, KeyframeCloud
from solid_ros.core.database.descriptors import POSE_FIELDS, DescriptorDatabase
from solid_ros.core.errors import DatabaseError, SolidError
from solid_ros.core.geometry import pose_to_vector, vector_to_matrix

__all__ = ['PriorMap', 'backup_if_shrinking', 'check_save_target', 'load_database',
           'read_map_poses', 'save_database']


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
    old = scan_count(target) if target.is_file() and not target.is_symlink() else None
    if old is None or old == 0 or (new_count > 0 and new_count >= ratio * old):
        return None
    backup = target.with_name(target.name + '.bak')
    check_save_target(backup)
    kept = scan_count(backup) if backup.exists() else None
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
        fsync_dir(backup.parent)
    except OSError as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise DatabaseError(f'cannot keep a backup of {target} as {backup}: '
                            f'{err.strerror or err}') from err
    return backup


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
    diffs = [f'{shorten(str(k), 40)} (file {shorten(repr(saved.get(k, "<absent>")), 40)}, '
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
