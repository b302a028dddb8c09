"""PointCloud2 decoding of every layout the node may meet, and rejection of bad messages."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from solid_ros.core.errors import CloudError
from solid_ros.formats.pointcloud2 import (
    FLOAT32,
    FLOAT64,
    cloud_point_times,
    cloud_to_xyz,
    encode_points,
)

RNG = np.random.default_rng(7)
XYZ = RNG.normal(scale=20.0, size=(50, 3))


def _field(name: str, offset: int, datatype: int) -> SimpleNamespace:
    return SimpleNamespace(name=name, offset=offset, datatype=datatype, count=1)


def _cloud(rec: np.ndarray, fields: list[SimpleNamespace], *, height: int = 1,
           row_pad: int = 0, big: bool = False) -> SimpleNamespace:
    """Duck-typed PointCloud2 from a structured array (rows of equal width)."""
    step = rec.dtype.itemsize
    width = rec.size // height
    rows = rec.reshape(height, width).view(np.uint8).reshape(height, width * step)
    data = np.concatenate([rows, np.zeros((height, row_pad), np.uint8)], axis=1)
    return SimpleNamespace(height=height, width=width, point_step=step,
                           row_step=width * step + row_pad, is_bigendian=big,
                           fields=fields, data=data.reshape(-1).tobytes())


@pytest.mark.parametrize('ftype,code', [('f4', FLOAT32), ('f8', FLOAT64)])
def test_float_types_at_offsets_with_extra_fields_and_padding(ftype: str, code: int) -> None:
    dt = np.dtype([('intensity', '<f4'), ('ring', '<u2'), ('x', '<' + ftype),
                   ('y', '<' + ftype), ('z', '<' + ftype), ('pad', 'u1', 5)])
    rec = np.zeros(len(XYZ), dtype=dt)
    rec['x'], rec['y'], rec['z'] = XYZ.T
    fields = [_field('intensity', 0, FLOAT32), _field('ring', 4, 4)] + [
        _field(n, dt.fields[n][1], code) for n in 'xyz']
    out = cloud_to_xyz(_cloud(rec, fields))
    assert out.shape == XYZ.shape
    np.testing.assert_allclose(out, XYZ.astype(ftype))


def test_mixed_float_types_and_uneven_offsets() -> None:
    dt = np.dtype([('z', '<f4'), ('x', '<f8'), ('gap', 'u1', 3), ('y', '<f8')])
    rec = np.zeros(len(XYZ), dtype=dt)
    rec['x'], rec['y'], rec['z'] = XYZ.T
    fields = [_field('z', 0, FLOAT32), _field('x', 4, FLOAT64), _field('y', 15, FLOAT64)]
    out = cloud_to_xyz(_cloud(rec, fields))
    np.testing.assert_allclose(out, np.stack([XYZ[:, 0], XYZ[:, 1],
                                              XYZ[:, 2].astype('f4')], axis=1))


def test_organised_cloud_with_row_padding_and_nans() -> None:
    pts = XYZ[:48].copy()
    pts[5] = np.nan
    dt = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('i', '<f4')])
    rec = np.zeros(48, dtype=dt)
    rec['x'], rec['y'], rec['z'] = pts.T
    fields = [_field(n, 4 * i, FLOAT32) for i, n in enumerate('xyz')]
    out = cloud_to_xyz(_cloud(rec, fields, height=6, row_pad=12))
    assert out.shape == (48, 3)
    assert np.isnan(out[5]).all()
    np.testing.assert_allclose(np.delete(out, 5, 0), np.delete(pts, 5, 0).astype('f4'))


def test_big_endian() -> None:
    dt = np.dtype([('x', '>f8'), ('y', '>f8'), ('z', '>f8')])
    rec = np.zeros(len(XYZ), dtype=dt)
    rec['x'], rec['y'], rec['z'] = XYZ.T
    fields = [_field(n, 8 * i, FLOAT64) for i, n in enumerate('xyz')]
    out = cloud_to_xyz(_cloud(rec, fields, big=True))
    np.testing.assert_array_equal(out, XYZ)
    assert out.dtype.isnative


def test_packed_float32_is_zero_copy() -> None:
    lay = encode_points(np.concatenate([XYZ, np.ones((len(XYZ), 1))], axis=1))
    msg = SimpleNamespace(height=1, width=lay.width, point_step=lay.point_step,
                          row_step=lay.row_step, is_bigendian=False, fields=lay.fields,
                          data=lay.data)
    out = cloud_to_xyz(msg)
    assert np.shares_memory(out, lay.data)
    np.testing.assert_allclose(out, XYZ.astype('f4'))


def _good() -> dict[str, Any]:
    lay = encode_points(XYZ)
    return dict(height=1, width=lay.width, point_step=lay.point_step, row_step=lay.row_step,
                is_bigendian=False, fields=list(lay.fields), data=lay.data.tobytes())


@pytest.mark.parametrize('change,match', [
    (lambda m: m.update(data=m['data'][:-1]), 'bytes'),
    (lambda m: m.update(fields=m['fields'][:2]), "'z'"),
    (lambda m: m.update(fields=[_field('x', 0, 5)] + m['fields'][1:]), 'datatype'),
    (lambda m: m.update(point_step=0), 'point_step'),
    (lambda m: m.update(fields=m['fields'][:2] + [_field('z', 12, FLOAT32)]), 'exceeds'),
    (lambda m: m.update(height=2, row_step=4), 'row_step'),
])
def test_invalid_messages_raise_cloud_error(change: Any, match: str) -> None:
    msg = _good()
    change(msg)
    with pytest.raises(CloudError, match=match):
        cloud_to_xyz(SimpleNamespace(**msg))


def test_not_a_cloud_raises_cloud_error() -> None:
    with pytest.raises(CloudError):
        cloud_to_xyz(object())


def test_rclpy_message_decodes() -> None:
    sensor_msgs = pytest.importorskip('sensor_msgs.msg', reason='sensor_msgs not installed')
    import array

    lay = encode_points(XYZ)
    msg = sensor_msgs.PointCloud2(height=1, width=lay.width, point_step=lay.point_step,
                                  row_step=lay.row_step, is_dense=True)
    msg.fields = [sensor_msgs.PointField(name=f.name, offset=f.offset, datatype=f.datatype,
                                         count=1) for f in lay.fields]
    msg.data = array.array('B', lay.data.tobytes())
    np.testing.assert_allclose(cloud_to_xyz(msg), XYZ.astype('f4'))


def _xyz_f4(offsets: tuple[int, int, int], step: int) -> tuple[np.ndarray, list[Any]]:
    dt = np.dtype({'names': list('xyz'), 'formats': ['<f4'] * 3, 'offsets': list(offsets),
                   'itemsize': step})
    rec = np.zeros(len(XYZ), dtype=dt)
    rec['x'], rec['y'], rec['z'] = XYZ.T
    return rec, [_field(n, o, FLOAT32) for n, o in zip('xyz', offsets)]


def test_uneven_float32_offsets_stay_float32() -> None:
    rec, fields = _xyz_f4((0, 4, 12), 16)
    out = cloud_to_xyz(_cloud(rec, fields))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, XYZ.astype(np.float32))


@pytest.mark.parametrize('count', [0, 2, 3])
def test_xyz_count_other_than_one_is_refused(count: int) -> None:
    rec, fields = _xyz_f4((0, 4, 8), 12)
    fields[1] = SimpleNamespace(name='y', offset=4, datatype=FLOAT32, count=count)
    with pytest.raises(CloudError, match=f"'y' has count {count}"):
        cloud_to_xyz(_cloud(rec, fields))


def test_duplicate_or_overlapping_xyz_fields_are_refused() -> None:
    rec, fields = _xyz_f4((0, 4, 8), 16)
    with pytest.raises(CloudError, match="two fields named 'x'"):
        cloud_to_xyz(_cloud(rec, fields + [_field('x', 12, FLOAT32)]))
    # Another field may repeat a name the decoder does not use.
    extra = [_field('i', 12, FLOAT32), _field('i', 12, FLOAT32)]
    assert cloud_to_xyz(_cloud(rec, fields + extra)).shape == XYZ.shape
    rec, fields = _xyz_f4((0, 4, 8), 12)
    fields[2] = _field('z', 2, FLOAT32)
    with pytest.raises(CloudError, match="'x' and 'z' overlap"):
        cloud_to_xyz(_cloud(rec, fields))


@pytest.mark.parametrize('name,ftype,code', [('t', 'u4', 6), ('offset_time', 'u4', 6),
                                             ('timestamp', 'f8', FLOAT64),
                                             ('time', 'f4', FLOAT32), ('stamp', 'i2', 3)])
def test_point_times_of_each_drivers_field_normalised_over_the_sweep(
        name: str, ftype: str, code: int) -> None:
    rec = np.zeros(50, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('i', 'u1'),
                              (name, ftype)])
    raw = np.arange(50)[::-1] * 7 + (1000 if ftype != 'i2' else 0)
    rec[name] = raw * (1e-6 if ftype.startswith('f') else 1)
    fields = [_field('x', 0, FLOAT32), _field('y', 4, FLOAT32), _field('z', 8, FLOAT32),
              _field('i', 12, 2), _field(name, 13, code)]
    got = cloud_point_times(_cloud(rec, fields), 'stamp' if name == 'stamp' else '')
    assert got is not None and got[1] == name
    np.testing.assert_allclose(got[0], (raw - raw.min()) / (raw.max() - raw.min()), atol=1e-5)


def test_no_usable_time_field_gives_none() -> None:
    rec = np.zeros(20, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('t', 'f4')])
    fields = [_field('x', 0, FLOAT32), _field('y', 4, FLOAT32), _field('z', 8, FLOAT32)]
    assert cloud_point_times(_cloud(rec, fields)) is None  # no field
    fields.append(_field('t', 12, FLOAT32))
    assert cloud_point_times(_cloud(rec, fields)) is None  # all equal
    rec['t'][3] = np.nan
    assert cloud_point_times(_cloud(rec, fields)) is None  # not finite
    rec['t'] = np.arange(20)
    assert cloud_point_times(_cloud(rec, fields), 'offset_time') is None  # not that field
    short = _cloud(rec, fields)
    short.data = short.data[:40]
    assert cloud_point_times(short) is None
    assert cloud_point_times(object()) is None
