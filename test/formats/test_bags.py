"""Tests of solid_ros.formats.bags: MCAP, sqlite3 and ROS 1 round trips, topic choice, bad bags."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from solid_ros.core.errors import BagError
from solid_ros.formats.bags import (
    BAG_FORMATS,
    POINTCLOUD2,
    Bag,
    BagWriter,
    select_cloud_topic,
    select_odom_topic,
    write_cloud_bag,
)
from solid_ros.formats.mcap_check import verify_mcap
from solid_ros.formats.pointcloud2 import CloudLayout, encode_points


def _rz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    return out


def _scans(n: int = 4, seed: int = 0) -> list[tuple[np.ndarray, int, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        pose = _rz(10.0 * i)
        pose[:3, 3] = [i, 2.0 * i, 0.1]
        pts = (rng.normal(size=(50 + i, 4)) * 10).astype(np.float32)
        out.append((pts, 1_600_000_000_000_000_000 + i * 100_000_000, pose))
    return out


@pytest.mark.parametrize('fmt', BAG_FORMATS)
def test_round_trip(tmp_path: Path, fmt: str) -> None:
    scans = _scans()
    path = write_cloud_bag(tmp_path / 'bag', scans, fmt)
    assert path.exists() and (path.suffix == '.bag') == (fmt == 'ros1')
    with Bag(path) as bag:
        assert bag.is_ros1 == (fmt == 'ros1')
        assert select_cloud_topic(bag) == '/points'
        assert select_odom_topic(bag) == '/odom'
        clouds = list(bag.clouds('/points'))
        track = bag.odometry('/odom')
    assert [c.seq for c in clouds] == list(range(4))
    for cloud, (pts, stamp, _) in zip(clouds, scans):
        assert cloud.error is None and cloud.stamp_ns == stamp and cloud.frame_id == 'lidar'
        assert cloud.points is not None
        np.testing.assert_array_equal(cloud.points, pts[:, :3])
    assert track.stamps_ns is not None
    assert track.stamps_ns.tolist() == [s[1] for s in scans]
    np.testing.assert_allclose(track.poses, np.stack([s[2] for s in scans]), atol=1e-9)


def test_mcap_bag_reads_with_the_reference_mcap_library(tmp_path: Path) -> None:
    """Bags written here open in other MCAP tools (Foxglove, ros2 bag): check with mcap."""
    from mcap.reader import make_reader

    path = write_cloud_bag(tmp_path / 'bag', _scans(), 'mcap')
    (storage,) = path.glob('*.mcap')
    with storage.open('rb') as fh:
        reader = make_reader(fh, validate_crcs=True)  # the CRCs seal_crcs filled in
        summary = reader.get_summary()
        assert summary is not None
        channels = {c.topic: c for c in summary.channels.values()}
        assert {t: (c.message_encoding, summary.schemas[c.schema_id].name)
                for t, c in channels.items()} == {
            '/points': ('cdr', 'sensor_msgs/msg/PointCloud2'),
            '/odom': ('cdr', 'nav_msgs/msg/Odometry')}
        stamps = [m.log_time for _, c, m in reader.iter_messages() if c.topic == '/points']
    assert stamps == [s[1] for s in _scans()]


def test_storage_file_path_is_accepted(tmp_path: Path) -> None:
    path = write_cloud_bag(tmp_path / 'bag', _scans(2), 'mcap')
    for alias in (path / 'bag.mcap', path / 'metadata.yaml'):
        with Bag(alias) as bag:
            assert len(list(bag.clouds('/points'))) == 2


def test_topic_selection_lists_choices(tmp_path: Path) -> None:
    path = tmp_path / 'two'
    with BagWriter(path, 'mcap') as w:
        for topic in ('/lidar_front', '/lidar_back'):
            w.add_topic(topic, POINTCLOUD2)
            w.write(topic, 1, w.cloud_msg(np.ones((3, 3)), 1))
        w.add_topic('/chatter', 'std_msgs/msg/String')
        w.write('/chatter', 1, w.message('std_msgs/msg/String', data='hi'))
    with Bag(path) as bag:
        with pytest.raises(BagError, match=r'several .*PointCloud2 topics \(/lidar_back, '
                                           r'/lidar_front\); choose one with --topic'):
            select_cloud_topic(bag)
        assert select_cloud_topic(bag, '/lidar_back') == '/lidar_back'
        with pytest.raises(BagError, match=r'topic /nope not in bag \(topics: /chatter'):
            select_cloud_topic(bag, '/nope')
        with pytest.raises(BagError, match=r'/chatter has type std_msgs/msg/String, expected '
                                           r'sensor_msgs/msg/PointCloud2'):
            select_cloud_topic(bag, '/chatter')
        assert select_odom_topic(bag) is None
        with pytest.raises(BagError, match='expected nav_msgs/msg/Odometry'):
            select_odom_topic(bag, '/lidar_back')


def test_no_cloud_topic(tmp_path: Path) -> None:
    path = tmp_path / 'strings'
    with BagWriter(path, 'sqlite3') as w:
        w.add_topic('/chatter', 'std_msgs/msg/String')
        w.write('/chatter', 1, w.message('std_msgs/msg/String', data='hi'))
    with Bag(path) as bag, pytest.raises(BagError, match=r'no sensor_msgs/msg/PointCloud2 '
                                                         r'topic \(topics: /chatter'):
        select_cloud_topic(bag)


@pytest.mark.parametrize('fmt', BAG_FORMATS)
def test_malformed_clouds_are_reported_not_raised(tmp_path: Path, fmt: str) -> None:
    good = encode_points(np.ones((10, 3)))
    short = CloudLayout(fields=good.fields, width=good.width + 5, point_step=good.point_step,
                        row_step=good.row_step + 60, data=good.data)
    path = tmp_path / 'bag'
    with BagWriter(path, fmt) as w:
        w.add_topic('/points', POINTCLOUD2)
        w.write('/points', 10, w.cloud_msg(good, 10))
        w.write('/points', 20, w.cloud_msg(short, 20))
        w.write_raw('/points', 30, b'\x00\x01\x00\x00garbage')
        w.write('/points', 40, w.cloud_msg(np.zeros((2, 3)), 40))
        path = w.path
    with Bag(path) as bag:
        clouds = list(bag.clouds('/points'))
    assert [c.points is None for c in clouds] == [False, True, True, False]
    assert clouds[1].error is not None and 'bytes' in clouds[1].error
    assert clouds[2].error is not None


def _damage(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    if how == 'truncate':
        path.write_bytes(bytes(data[:len(data) // 2]))
    else:
        rng = np.random.default_rng(5)
        lo = len(data) // 4
        data[lo:lo + len(data) // 2] = rng.integers(0, 256, len(data) // 2,
                                                     dtype=np.uint8).tobytes()
        path.write_bytes(bytes(data))


@pytest.mark.parametrize('fmt', BAG_FORMATS)
@pytest.mark.parametrize('how', ['truncate', 'garble'])
def test_damaged_bags_raise_bag_error(tmp_path: Path, fmt: str, how: str) -> None:
    path = write_cloud_bag(tmp_path / 'bag', _scans(6), fmt)
    storage = path if fmt == 'ros1' else next(p for p in path.iterdir()
                                              if p.name != 'metadata.yaml')
    _damage(storage, how)
    with pytest.raises(BagError, match=str(path.name)):
        with Bag(path) as bag:
            list(bag.clouds('/points'))
            bag.odometry('/odom')


def test_not_a_bag(tmp_path: Path) -> None:
    with pytest.raises(BagError, match='no such file or directory'):
        Bag(tmp_path / 'missing')
    text = tmp_path / 'notes.txt'
    text.write_text('hello')
    with pytest.raises(BagError, match='not a bag'):
        Bag(text)
    with pytest.raises(BagError, match='not a bag'):
        Bag(tmp_path)
    fake = tmp_path / 'fake.bag'
    fake.write_bytes(os.urandom(100))
    with pytest.raises(BagError, match='cannot open bag'):
        Bag(fake)
    copy = tmp_path / 'meta_only'
    copy.mkdir()
    path = write_cloud_bag(tmp_path / 'b', _scans(1), 'mcap')
    shutil.copy(path / 'metadata.yaml', copy / 'metadata.yaml')
    with pytest.raises(BagError, match='cannot open bag'):
        Bag(copy)


def test_writer_refuses_existing_and_unknown(tmp_path: Path) -> None:
    with pytest.raises(BagError, match='unknown bag format'):
        BagWriter(tmp_path / 'x', 'zip')
    (tmp_path / 'x').mkdir()
    with pytest.raises(BagError, match='exists already'):
        BagWriter(tmp_path / 'x', 'mcap')


def test_hku1_bag(shared_data: Path) -> None:
    with Bag(shared_data / 'hku1' / 'bag') as bag:
        topic = select_cloud_topic(bag)
        odom = select_odom_topic(bag)
        assert (topic, odom) == ('/points', '/odom_slam')
        clouds = list(bag.clouds(topic))
        track = bag.odometry(odom)
    assert len(clouds) == 314 and all(c.points is not None for c in clouds)
    assert 'no CRCs in the file' in bag.integrity  # rosbags wrote it without CRCs
    assert all(c.frame_id == 'livox_frame' for c in clouds)
    stamps = [c.stamp_ns for c in clouds]
    assert stamps == sorted(stamps)
    assert track.stamps_ns is not None and track.stamps_ns.tolist() == stamps
    # odometry starts at the origin and the sequence returns near its start (README)
    pos = track.positions
    assert np.linalg.norm(pos[0]) < 0.1 and np.linalg.norm(pos[300] - pos[25]) < 10.0


def test_written_mcap_carries_crcs_and_every_bit_flip_is_caught(tmp_path: Path) -> None:
    path = write_cloud_bag(tmp_path / 'bag', _scans(6), 'mcap')
    (storage,) = path.glob('*.mcap')
    check = verify_mcap(storage)
    assert check.chunks >= 1 and check.chunks_checked == check.chunks
    assert check.data_section_checked and check.summary_checked
    with Bag(path) as bag:
        assert 'verified' in bag.integrity
    data = storage.read_bytes()
    rng = np.random.default_rng(3)
    damaged = tmp_path / 'damaged.mcap'
    for pos in rng.integers(0, len(data), 200):
        flipped = bytearray(data)
        flipped[pos] ^= 1 << int(rng.integers(0, 8))
        damaged.write_bytes(bytes(flipped))
        with pytest.raises(BagError, match='MCAP') as info:
            verify_mcap(damaged)
        assert '\n' not in str(info.value)


def test_unsealed_mcap_is_read_but_said_to_be_unchecked(tmp_path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    with Writer(tmp_path / 'plain', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/s', 'std_msgs/msg/String', typestore=store)
        w.write(conn, 1, store.serialize_cdr(store.types['std_msgs/msg/String'](data='x'),
                                             'std_msgs/msg/String'))
    with Bag(tmp_path / 'plain') as bag:
        assert 'no CRCs in the file: damage cannot be detected' in bag.integrity
