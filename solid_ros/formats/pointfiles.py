"""Point files: PCD (ascii/binary) and KITTI .bin readers, a binary PCD writer for maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from solid_ros.core.database.atomic import write_atomic
from solid_ros.core.errors import SolidError

__all__ = ['read_kitti_bin', 'read_pcd', 'read_points', 'write_pcd']

_PCD_TYPES = {('F', 4): '<f4', ('F', 8): '<f8', ('I', 1): '<i1', ('I', 2): '<i2',
              ('I', 4): '<i4', ('I', 8): '<i8', ('U', 1): '<u1', ('U', 2): '<u2',
              ('U', 4): '<u4', ('U', 8): '<u8'}


def read_kitti_bin(path: str | Path, fields: int = 4) -> npt.NDArray[np.float32]:
    """Read a KITTI velodyne file of float32 records (x, y, z, intensity) as (N, fields)."""
    data = np.fromfile(path, dtype='<f4')
    if data.size % fields:
        raise SolidError(f'{path}: size is not a multiple of {fields} float32 values')
    return data.reshape(-1, fields)


def read_pcd(path: str | Path) -> npt.NDArray[np.float32]:
    """Read the x, y, z fields of an ascii or binary PCD file as float32 (N, 3)."""
    raw = Path(path).read_bytes()
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b'\n', pos)
        if end < 0:
            raise SolidError(f'{path}: PCD header has no DATA line')
        line = raw[pos:end].decode('ascii', 'replace').strip()
        pos = end + 1
        if not line or line.startswith('#'):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == 'DATA':
            break
    try:
        names = header['FIELDS']
        sizes = [int(s) for s in header['SIZE']]
        types = header['TYPE']
        counts = [int(c) for c in header.get('COUNT', ['1'] * len(names))]
        npts = int(header['POINTS'][0])
        dtype = np.dtype([(n if c == 1 else (n, c), _PCD_TYPES[(t, s)])
                          for n, s, t, c in zip(names, sizes, types, counts)])
    except (KeyError, ValueError, IndexError) as err:
        raise SolidError(f'{path}: unsupported PCD header ({err})') from err
    mode = header['DATA'][0]
    if mode == 'binary':
        rec = np.frombuffer(raw, dtype=dtype, count=npts, offset=pos)
    elif mode == 'ascii':
        table = np.loadtxt(raw[pos:].decode().splitlines(), dtype=np.float64, ndmin=2)
        cols = {n: i for i, n in enumerate(names)}
        return table[:, [cols['x'], cols['y'], cols['z']]].astype(np.float32)
    else:
        raise SolidError(f'{path}: PCD DATA {mode} is not supported')
    return np.stack([rec['x'], rec['y'], rec['z']], axis=1).astype(np.float32)


def read_points(path: str | Path) -> npt.NDArray[np.float32]:
    """Read a .pcd or KITTI .bin file as (N, 3+) float32."""
    if str(path).endswith('.pcd'):
        return read_pcd(path)
    return read_kitti_bin(path)


def write_pcd(path: str | Path, points: npt.ArrayLike) -> Path:
    """Write (N, 3+) points as a binary PCD file of float32 x, y, z (atomically).

    Raises:
        SolidError: the points are not (N, 3+) or the file cannot be written.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise SolidError(f'{path}: expected (N, 3+) points, got shape {pts.shape}')
    xyz = np.ascontiguousarray(pts[:, :3], dtype='<f4')
    n = len(xyz)
    header = ('# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n'
              f'SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n'
              f'VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n')
    data = header.encode('ascii') + xyz.tobytes()
    return write_atomic(path, lambda f: f.write(data))
