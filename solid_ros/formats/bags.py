"""Reading point clouds and odometry from ROS 2 (MCAP, sqlite3) and ROS 1 bags, and writing
small bags in all three formats, through rosbags (no ROS installation needed).

Every failure to open or read a bag becomes a :class:`BagError` with a one-line message that
names the file and the problem. MCAP files are checked against the CRCs they carry before any
message is read (:mod:`solid_ros.formats.mcap_check`), and the MCAP bags written here carry
them. A cloud that cannot be decoded inside a readable bag is not an
error: :meth:`Bag.clouds` yields it with ``points=None`` and the reason, so callers can skip
and count it.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import BagError, CloudError
from solid_ros.core.geometry import matrix_to_quaternion
from solid_ros.formats.mcap_check import seal_crcs, verify_mcap
from solid_ros.formats.pointcloud2 import (
    CloudLayout,
    cloud_point_times,
    cloud_to_xyz,
    encode_points,
)
from solid_ros.formats.poses import PoseError, PoseTrack, odometry_to_pose

__all__ = [
    'BAG_FORMATS', 'ODOMETRY', 'POINTCLOUD2', 'Bag', 'BagWriter', 'CloudScan', 'TopicInfo',
    'select_cloud_topic', 'select_odom_topic', 'write_cloud_bag',
]

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
ODOMETRY = 'nav_msgs/msg/Odometry'
BAG_FORMATS = ('mcap', 'sqlite3', 'ros1')


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag."""

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class CloudScan:
    """One PointCloud2 message of a bag.

    Attributes:
        seq: position of the message in its topic (0-based, malformed ones included).
        stamp_ns: header stamp (the bag's receive time when the header stamp is zero).
        points: (N, 3) x, y, z (may be a read-only view), or None when it could not be decoded.
        error: why it could not be decoded, else None.
        frame_id: header frame.
        times: per-point times normalised to [0, 1] over the sweep (None: the cloud has no
            time field; see :func:`~solid_ros.formats.pointcloud2.cloud_point_times`).
    """

    seq: int
    stamp_ns: int
    points: npt.NDArray[np.floating] | None
    error: str | None = None
    frame_id: str = ''
    times: npt.NDArray[np.float64] | None = None


def _stamp_ns(header: Any, fallback: int) -> int:
    try:
        ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    except (AttributeError, TypeError, ValueError):
        return fallback
    return ns if ns > 0 else fallback


def _bag_path(path: Path) -> Path:
    """Accept a bag directory, its metadata.yaml, one of its storage files, or a .bag file."""
    if path.is_file() and path.suffix != '.bag':
        if path.name == 'metadata.yaml' or (path.parent / 'metadata.yaml').is_file():
            return path.parent
    return path


def _one_line(err: BaseException) -> str:
    text = ' '.join(str(err).split()) or type(err).__name__
    return text if len(text) <= 200 else text[:197] + '...'


def _verify(target: Path) -> str:
    """Check the CRCs of the MCAP files of a bag; describe what could be checked."""
    mcaps = sorted(target.glob('*.mcap')) if target.is_dir() else []
    if not mcaps:
        kind = 'ROS 1 bag' if target.suffix == '.bag' else 'no MCAP storage'
        return f'{kind}: no CRCs to check'
    return '; '.join(f'{f.name}: {verify_mcap(f).describe()}' for f in mcaps)


class Bag:
    """A bag opened for reading; use as a context manager.

    Attributes:
        integrity: what the CRC check of the MCAP files found (or why there was none).

    Raises:
        BagError: the path is missing, not a bag, the bag is truncated or corrupt, or an MCAP
            file fails a CRC check.
    """

    def __init__(self, path: str | Path) -> None:
        from rosbags.highlevel import AnyReader

        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f'{self.path}: no such file or directory')
        target = _bag_path(self.path)
        if target.is_dir() and not (target / 'metadata.yaml').is_file():
            raise BagError(f'{self.path}: not a bag (directory without metadata.yaml)')
        if target.is_file() and target.suffix != '.bag':
            raise BagError(f'{self.path}: not a bag (expected a ROS 2 bag directory or a ROS 1 '
                           '.bag file)')
        # Before rosbags reads anything: damage must stop the replay, not change its results.
        self.integrity = _verify(target)
        try:
            self._reader = AnyReader([target])
            self._reader.open()
        except Exception as err:  # rosbags raises many types for damaged files
            raise BagError(f'{self.path}: cannot open bag: {_one_line(err)}') from err
        self.is_ros1 = not self._reader.is2
        self.topics: dict[str, TopicInfo] = {}
        for conn in self._reader.connections:
            old = self.topics.get(conn.topic)
            count = conn.msgcount + (old.count if old else 0)
            self.topics[conn.topic] = TopicInfo(conn.topic, conn.msgtype, count)

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Close the underlying reader (idempotent)."""
        reader = getattr(self, '_reader', None)
        if reader is not None and reader.stack is not None:
            reader.close()

    def topics_of_type(self, msgtype: str) -> list[str]:
        """Names of the topics carrying ``msgtype``, sorted."""
        return sorted(t.name for t in self.topics.values() if t.msgtype == msgtype)

    def _connections(self, topic: str, msgtype: str) -> list[Any]:
        info = self.topics.get(topic)
        if info is None:
            raise BagError(f'{self.path}: topic {topic} not in bag (topics: '
                           f'{", ".join(sorted(self.topics)) or "none"})')
        if info.msgtype != msgtype:
            raise BagError(f'{self.path}: topic {topic} has type {info.msgtype}, '
                           f'expected {msgtype}')
        return [c for c in self._reader.connections if c.topic == topic]

    def _messages(self, conns: list[Any]) -> Iterator[tuple[int, bytes]]:
        it = self._reader.messages(connections=conns)
        expected = sum(int(c.msgcount) for c in conns)
        seen = 0
        while True:
            try:
                _, stamp, raw = next(it)
            except StopIteration:
                # A damaged chunk can end reading early without an error: compare counts.
                if seen < expected:
                    raise BagError(f'{self.path}: bag is truncated or corrupt: read {seen} of '
                                   f'{expected} messages on {conns[0].topic}') from None
                return
            except Exception as err:  # truncated chunk, bad compression, sqlite error...
                raise BagError(f'{self.path}: bag is truncated or corrupt: '
                               f'{_one_line(err)}') from err
            seen += 1
            yield stamp, raw

    def _deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self._reader.deserialize(raw, msgtype)

    def clouds(self, topic: str, time_field: str = '') -> Iterator[CloudScan]:
        """Yield every PointCloud2 of ``topic`` in bag order, with per-point times when the
        clouds carry them (``time_field``, or the first of the drivers' usual names).

        Raises:
            BagError: topic missing or of another type; the bag is unreadable mid-way.
        """
        conns = self._connections(topic, POINTCLOUD2)
        for seq, (bag_ns, raw) in enumerate(self._messages(conns)):
            try:
                msg = self._deserialize(raw, POINTCLOUD2)
            except Exception as err:  # any damage inside one message only skips it
                yield CloudScan(seq, bag_ns, None, f'cannot deserialize: {_one_line(err)}')
                continue
            stamp = _stamp_ns(msg.header, bag_ns)
            frame = str(getattr(msg.header, 'frame_id', ''))
            try:
                points = cloud_to_xyz(msg)
            except CloudError as err:
                yield CloudScan(seq, stamp, None, str(err), frame)
                continue
            times = cloud_point_times(msg, time_field)
            yield CloudScan(seq, stamp, points, None, frame, None if times is None else times[0])

    def odometry(self, topic: str) -> PoseTrack:
        """Read all poses of an Odometry topic (header stamps; bad messages skipped).

        Raises:
            BagError: topic missing or of another type, unreadable bag, or no usable pose.
        """
        conns = self._connections(topic, ODOMETRY)
        stamps: list[int] = []
        poses: list[npt.NDArray[np.float64]] = []
        for bag_ns, raw in self._messages(conns):
            try:
                msg = self._deserialize(raw, ODOMETRY)
                pose = odometry_to_pose(msg)
            except (PoseError, Exception):  # noqa: B014 - one bad message only skips it
                continue
            stamps.append(_stamp_ns(msg.header, bag_ns))
            poses.append(pose)
        if not poses:
            raise BagError(f'{self.path}: topic {topic} holds no usable Odometry message')
        return PoseTrack(np.stack(poses), np.asarray(stamps, dtype=np.int64), topic)


def _select(bag: Bag, wanted: str | None, msgtype: str, flag: str) -> str | None:
    names = bag.topics_of_type(msgtype)
    if wanted is not None:
        bag._connections(wanted, msgtype)  # raises with the reason
        return wanted
    if len(names) == 1:
        return names[0]
    if not names:
        return None
    raise BagError(f'{bag.path}: several {msgtype} topics ({", ".join(names)}); '
                   f'choose one with {flag}')


def select_cloud_topic(bag: Bag, wanted: str | None = None) -> str:
    """The PointCloud2 topic to replay: ``wanted``, or the bag's only one.

    Raises:
        BagError: ``wanted`` is absent or not a PointCloud2; there is none; there are
            several (the message lists them).
    """
    topic = _select(bag, wanted, POINTCLOUD2, '--topic')
    if topic is None:
        raise BagError(f'{bag.path}: no {POINTCLOUD2} topic (topics: '
                       f'{", ".join(f"{t.name} [{t.msgtype}]" for t in bag.topics.values())})')
    return topic


def select_odom_topic(bag: Bag, wanted: str | None = None) -> str | None:
    """The Odometry topic: ``wanted``, the bag's only one, or None when there is none.

    Raises:
        BagError: ``wanted`` is absent or of another type; there are several.
    """
    return _select(bag, wanted, ODOMETRY, '--odom-topic')


class BagWriter:
    """Write a small bag (MCAP, sqlite3 or ROS 1) with rosbags; use as a context manager.

    Args:
        path: bag directory (ROS 2) or .bag file (ROS 1; the suffix is added if missing).
        fmt: 'mcap', 'sqlite3' or 'ros1'.

    Raises:
        BagError: unknown format or the target exists.
    """

    def __init__(self, path: str | Path, fmt: str = 'mcap') -> None:
        from rosbags.typesys import Stores, get_typestore

        if fmt not in BAG_FORMATS:
            raise BagError(f'unknown bag format {fmt!r}; use one of {", ".join(BAG_FORMATS)}')
        self.fmt = fmt
        path = Path(path)
        if fmt == 'ros1' and path.suffix != '.bag':
            path = path.with_suffix('.bag')
        self.path = path
        if path.exists():
            raise BagError(f'{path} exists already')
        self.typestore = get_typestore(Stores.ROS1_NOETIC if fmt == 'ros1' else
                                       Stores.ROS2_JAZZY)
        self._writer: Any
        if fmt == 'ros1':
            from rosbags.rosbag1 import Writer as Writer1
            self._writer = Writer1(path)
        else:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Writer2
            plugin = StoragePlugin.MCAP if fmt == 'mcap' else StoragePlugin.SQLITE3
            self._writer = Writer2(path, version=9, storage_plugin=plugin)
        self._conns: dict[str, tuple[Any, str]] = {}

    def __enter__(self) -> BagWriter:
        self._writer.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._writer.close()
        if exc_type is None and self.fmt == 'mcap':
            for f in sorted(self.path.glob('*.mcap')):
                seal_crcs(f)  # rosbags leaves every CRC 0

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Register ``topic`` with message type ``msgtype`` (e.g. 'std_msgs/msg/String')."""
        conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
        self._conns[topic] = (conn, msgtype)

    def write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Serialise a typestore message (see :meth:`cloud_msg`) and write it."""
        conn, msgtype = self._conns[topic]
        if self.fmt == 'ros1':
            data = self.typestore.serialize_ros1(msg, msgtype)
        else:
            data = self.typestore.serialize_cdr(msg, msgtype)
        self._writer.write(conn, int(stamp_ns), data)

    def write_raw(self, topic: str, stamp_ns: int, data: bytes) -> None:
        """Write already serialised bytes (tests use this for damaged messages)."""
        self._writer.write(self._conns[topic][0], int(stamp_ns), data)

    def message(self, msgtype: str, **fields: Any) -> Any:
        """Build a typestore message of ``msgtype`` from keyword fields."""
        return self.typestore.types[msgtype](**fields)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        """A std_msgs/Header for this bag's ROS version."""
        t = self.typestore.types
        stamp = t['builtin_interfaces/msg/Time'](sec=int(stamp_ns) // 1_000_000_000,
                                                 nanosec=int(stamp_ns) % 1_000_000_000)
        if self.fmt == 'ros1':
            return t['std_msgs/msg/Header'](seq=0, stamp=stamp, frame_id=frame_id)
        return t['std_msgs/msg/Header'](stamp=stamp, frame_id=frame_id)

    def cloud_msg(self, points: npt.ArrayLike | CloudLayout, stamp_ns: int,
                  frame_id: str = 'lidar') -> Any:
        """A PointCloud2 from an (N, 3+) array (x y z [intensity]) or a prepared layout."""
        layout = points if isinstance(points, CloudLayout) else encode_points(points)
        t = self.typestore.types
        fields = [t['sensor_msgs/msg/PointField'](name=f.name, offset=f.offset,
                                                  datatype=f.datatype, count=f.count)
                  for f in layout.fields]
        return t[POINTCLOUD2](header=self.header(stamp_ns, frame_id), height=layout.height,
                              width=layout.width, fields=fields,
                              is_bigendian=layout.is_bigendian, point_step=layout.point_step,
                              row_step=layout.row_step,
                              data=np.ascontiguousarray(layout.data, dtype=np.uint8),
                              is_dense=layout.is_dense)

    def odometry_msg(self, pose: npt.ArrayLike, stamp_ns: int, frame_id: str = 'map',
                     child_frame_id: str = 'lidar') -> Any:
        """A nav_msgs/Odometry holding the 4x4 pose T_frame_child (zero twist)."""
        t = self.typestore.types
        p = np.asarray(pose, dtype=np.float64)
        qx, qy, qz, qw = matrix_to_quaternion(p[:3, :3])
        geo = 'geometry_msgs/msg/'
        pose_msg = t[geo + 'Pose'](
            position=t[geo + 'Point'](x=float(p[0, 3]), y=float(p[1, 3]), z=float(p[2, 3])),
            orientation=t[geo + 'Quaternion'](x=qx, y=qy, z=qz, w=qw))
        zero = t[geo + 'Vector3'](x=0.0, y=0.0, z=0.0)
        return t[ODOMETRY](
            header=self.header(stamp_ns, frame_id), child_frame_id=child_frame_id,
            pose=t[geo + 'PoseWithCovariance'](pose=pose_msg, covariance=np.zeros(36)),
            twist=t[geo + 'TwistWithCovariance'](
                twist=t[geo + 'Twist'](linear=zero, angular=zero), covariance=np.zeros(36)))


ScanItem = tuple[Any, int] | tuple[Any, int, Any]


def write_cloud_bag(path: str | Path, scans: Iterable[ScanItem], fmt: str = 'mcap', *,
                    points_topic: str = '/points', odom_topic: str | None = '/odom',
                    frame_id: str = 'lidar', odom_frame_id: str = 'map') -> Path:
    """Write clouds (and odometry where a pose is given) to a new bag.

    Args:
        path: target (must not exist); ROS 1 bags get a .bag suffix.
        scans: (points, stamp_ns) or (points, stamp_ns, pose) items; points is an (N, 3+)
            array or a :class:`~solid_ros.pointcloud2.CloudLayout`; pose a 4x4 matrix or
            None. Odometry is written with the cloud's stamp.
        fmt: 'mcap', 'sqlite3' or 'ros1'.
        points_topic: PointCloud2 topic.
        odom_topic: Odometry topic (None: never write odometry).
        frame_id: cloud frame (odometry child frame).
        odom_frame_id: odometry parent frame.

    Returns:
        The path written.
    """
    with BagWriter(path, fmt) as writer:
        writer.add_topic(points_topic, POINTCLOUD2)
        have_odom = False
        for item in scans:
            points, stamp = item[0], int(item[1])
            pose = item[2] if len(item) > 2 else None
            writer.write(points_topic, stamp, writer.cloud_msg(points, stamp, frame_id))
            if pose is not None and odom_topic is not None:
                if not have_odom:
                    writer.add_topic(odom_topic, ODOMETRY)
                    have_odom = True
                writer.write(odom_topic, stamp,
                             writer.odometry_msg(pose, stamp, odom_frame_id, frame_id))
    return writer.path
