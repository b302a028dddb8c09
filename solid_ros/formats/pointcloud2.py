"""sensor_msgs/PointCloud2 to numpy and back, without ROS imports.

Works on any object with the PointCloud2 attributes (rclpy messages, rosbags messages), so the
node and the bag tools decode identically. Decoding is zero-copy when x, y, z are evenly spaced
fields of one native float type; otherwise it copies once.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import CloudError

__all__ = ['FLOAT32', 'FLOAT64', 'TIME_FIELDS', 'CloudLayout', 'Field', 'cloud_point_times',
           'cloud_to_xyz', 'encode_points']

# sensor_msgs/PointField datatype constants.
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
_FLOAT_TYPES = {FLOAT32: 'f4', FLOAT64: 'f8'}
_NUMERIC = {INT8: 'i1', UINT8: 'u1', INT16: 'i2', UINT16: 'u2', INT32: 'i4', UINT32: 'u4',
            FLOAT32: 'f4', FLOAT64: 'f8'}
# Per-point time fields of the common drivers: Ouster (t, ns), Livox (offset_time ns;
# timestamp, absolute), Velodyne and Hesai (time, s), in the order they are looked for.
TIME_FIELDS = ('t', 'offset_time', 'timestamp', 'time')
_SIZES = {INT8: 1, UINT8: 1, INT16: 2, UINT16: 2, INT32: 4, UINT32: 4, FLOAT32: 4, FLOAT64: 8}


@dataclass(frozen=True)
class Field:
    """One sensor_msgs/PointField."""

    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass(frozen=True)
class CloudLayout:
    """Everything needed to fill a PointCloud2 message (unorganised, little-endian)."""

    fields: tuple[Field, ...]
    width: int
    point_step: int
    row_step: int
    data: npt.NDArray[np.uint8]
    height: int = 1
    is_bigendian: bool = False
    is_dense: bool = True


def _buffer(msg: Any) -> npt.NDArray[np.uint8]:
    data = msg.data
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except (TypeError, ValueError) as err:
        raise CloudError(f'cloud data is not a byte buffer ({type(data).__name__})') from err


def cloud_to_xyz(msg: Any) -> npt.NDArray[np.floating]:
    """Return the x, y, z of a PointCloud2 as an (N, 3) float array.

    Organised clouds (height > 1) are flattened row by row; NaN points are kept (the core
    drops them). The result may be a read-only view into ``msg.data``.

    Raises:
        CloudError: the message is inconsistent (short data, missing, duplicated,
            overlapping or non-float x/y/z, x/y/z with a count other than 1, zero point_step,
            fields beyond point_step).
    """
    try:
        height, width = int(msg.height), int(msg.width)
        point_step, row_step = int(msg.point_step), int(msg.row_step)
        big = bool(msg.is_bigendian)
        fields: dict[str, Any] = {}
        for f in msg.fields:
            if f.name in fields and f.name in ('x', 'y', 'z'):
                raise CloudError(f'cloud has two fields named {f.name!r}')
            fields[f.name] = f
    except (AttributeError, TypeError, ValueError) as err:
        raise CloudError(f'not a PointCloud2 message: {err}') from err
    n = height * width
    if height < 0 or width < 0:
        raise CloudError(f'negative cloud size {height}x{width}')
    if n == 0:
        return np.empty((0, 3), dtype=np.float32)
    if point_step <= 0:
        raise CloudError(f'point_step is {point_step}')
    if row_step < width * point_step:
        if height == 1 and row_step == 0:
            row_step = width * point_step  # some drivers leave row_step unset
        else:
            raise CloudError(f'row_step {row_step} < width {width} x point_step {point_step}')
    missing = [k for k in 'xyz' if k not in fields]
    if missing:
        raise CloudError(f'cloud has no field {missing[0]!r} (fields: {", ".join(fields)})')
    xyz = [fields[k] for k in 'xyz']
    for f in xyz:
        if int(f.datatype) not in _FLOAT_TYPES:
            raise CloudError(f'field {f.name!r} has unsupported datatype {f.datatype} '
                             '(need FLOAT32=7 or FLOAT64=8)')
        if int(f.count) != 1:
            raise CloudError(f'field {f.name!r} has count {f.count} (need 1)')
        if int(f.offset) < 0 or int(f.offset) + _SIZES[int(f.datatype)] > point_step:
            raise CloudError(f'field {f.name!r} at offset {f.offset} exceeds point_step '
                             f'{point_step}')
    spans = sorted((int(f.offset), int(f.offset) + _SIZES[int(f.datatype)], f.name) for f in xyz)
    for (_, end, a), (start, _, b) in zip(spans, spans[1:]):
        if start < end:
            raise CloudError(f'fields {a!r} and {b!r} overlap')
    buf = _buffer(msg)
    need = (height - 1) * row_step + width * point_step
    if buf.size < need:
        raise CloudError(f'data has {buf.size} bytes, {height}x{width} points need {need}')
    order = '>' if big else '<'
    kinds = {int(f.datatype) for f in xyz}
    offs = [int(f.offset) for f in xyz]
    if len(kinds) == 1:
        dt = np.dtype(order + _FLOAT_TYPES[next(iter(kinds))])
        step = offs[1] - offs[0]
        if step == offs[2] - offs[1] and step > 0:
            view = _strided(buf, dt, offs[0], (height, width, 3), (row_step, point_step, step))
            return _native(view.reshape(n, 3) if height > 1 else view[0])
    cols = [_strided(buf, np.dtype(order + _FLOAT_TYPES[int(f.datatype)]), int(f.offset),
                     (height, width), (row_step, point_step)).reshape(n) for f in xyz]
    out_type = np.float32 if kinds == {FLOAT32} else np.float64
    return np.stack(cols, axis=1).astype(out_type)


def cloud_point_times(msg: Any, field: str = '') -> tuple[npt.NDArray[np.float64], str] | None:
    """Per-point times of a PointCloud2, normalised to [0, 1] over the sweep, as KISS-ICP's
    deskew takes them, with the field's name.

    Args:
        msg: the PointCloud2 (any object with its attributes).
        field: the time field's name; empty: the first of :data:`TIME_FIELDS` it has.

    Returns:
        (N,) times in point order (organised clouds row by row, as :func:`cloud_to_xyz`), and
        the field; None when there is no such field of count 1, the data is too short, or
        the times are not finite or do not spread (all equal).
    """
    try:
        fields = {f.name: f for f in msg.fields}
        height, width = int(msg.height), int(msg.width)
        point_step, row_step = int(msg.point_step), int(msg.row_step)
        big = bool(msg.is_bigendian)
    except (AttributeError, TypeError, ValueError):
        return None
    name = field or next((k for k in TIME_FIELDS if k in fields), '')
    f = fields.get(name)
    if f is None or int(f.datatype) not in _NUMERIC or int(f.count) != 1:
        return None
    row_step = row_step or width * point_step
    try:
        buf = _buffer(msg)
    except CloudError:
        return None
    size = _SIZES[int(f.datatype)]
    if (height <= 0 or width <= 0 or int(f.offset) < 0 or int(f.offset) + size > point_step
            or buf.size < (height - 1) * row_step + width * point_step):
        return None
    dt = np.dtype(('>' if big else '<') + _NUMERIC[int(f.datatype)])
    t = _strided(buf, dt, int(f.offset), (height, width),
                 (row_step, point_step)).reshape(-1).astype(np.float64)
    if not np.all(np.isfinite(t)):
        return None
    low, high = float(t.min()), float(t.max())
    if high <= low:
        return None
    return (t - low) / (high - low), name


def _strided(buf: npt.NDArray[np.uint8], dt: np.dtype[Any], offset: int,
             shape: tuple[int, ...], strides: tuple[int, ...]) -> npt.NDArray[Any]:
    arr: npt.NDArray[Any] = np.ndarray(shape=shape, dtype=dt, buffer=buf, offset=offset,
                                       strides=strides)
    arr.flags.writeable = False
    return arr


def _native(arr: npt.NDArray[Any]) -> npt.NDArray[np.floating]:
    if arr.dtype.byteorder not in ('=', '|', '<' if sys.byteorder == 'little' else '>'):
        return arr.astype(arr.dtype.newbyteorder('='))
    return arr


def encode_points(points: npt.ArrayLike,
                  names: tuple[str, ...] = ('x', 'y', 'z', 'intensity')) -> CloudLayout:
    """Pack an (N, K) array as float32 PointCloud2 fields named ``names[:K]``.

    Args:
        points: (N, 3+) array; columns beyond ``len(names)`` are ignored.
        names: field names for the columns.

    Returns:
        A :class:`CloudLayout` the ROS or rosbags adapters turn into a message.
    """
    arr = np.asarray(points, dtype='<f4')
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise CloudError(f'points must have shape (N, 3+), got {arr.shape}')
    k = min(arr.shape[1], len(names))
    arr = np.ascontiguousarray(arr[:, :k])
    fields = tuple(Field(names[i], 4 * i, FLOAT32, 1) for i in range(k))
    dense = bool(np.isfinite(arr[:, :3]).all())
    return CloudLayout(fields=fields, width=len(arr), point_step=4 * k, row_step=4 * k * len(arr),
                       data=arr.view(np.uint8).reshape(-1), is_dense=dense)
