"""Writing a simulated drive as a ROS 2 MCAP bag plus reference poses, and the demo cache.

A demo directory holds::

    bag/            rosbag2 (metadata version 9, MCAP): /points (PointCloud2), /odom (Odometry)
    poses.txt       one KITTI 3x4 world <- sensor pose per scan (row-major, 12 numbers)
    times.txt       scan stamps in seconds, one per line, same order
    labels.txt      per scan: index, label (new/same/cross/reverse), index of the revisited scan
    drive.json      the DriveConfig that made it (with the package version)
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.errors import BagError
from solid_ros.pointcloud2 import encode_points
from solid_ros.sim.drive import Drive, DriveConfig, SimScan
from solid_ros.sim.lidar import avia_like, hdl64

__all__ = ['BagSummary', 'DEMO_DEFAULTS', 'DEMO_SENSORS', 'cache_root', 'demo_dir',
           'ensure_demo_bag',
           'quaternion', 'read_kitti_poses', 'write_bag', 'write_drive']

POINTS_TOPIC = '/points'
ODOM_TOPIC = '/odom'

# The drive the demo command replays: 64-beam, 360 deg, 50 m blocks (about 1.1 km, 553
# scans every 2 m) at 512 points per ring, so the cached bag stays near 280 MB.
DEMO_DEFAULTS: dict[str, Any] = {'seed': 0, 'sensor': hdl64(points_per_ring=512),
                                 'block': 50.0, 'spacing': 2.0}
DEMO_SENSORS = {'hdl64': DEMO_DEFAULTS['sensor'], 'avia_like': avia_like()}


@dataclass(frozen=True)
class BagSummary:
    """What :func:`write_bag` wrote."""

    path: Path
    count: int
    first_ns: int
    last_ns: int


def quaternion(rotation: npt.ArrayLike) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a 3x3 rotation matrix, w >= 0."""
    r = np.asarray(rotation, dtype=np.float64)
    w = 0.5 * np.sqrt(max(1.0 + r[0, 0] + r[1, 1] + r[2, 2], 0.0))
    x = 0.5 * np.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0))
    y = 0.5 * np.sqrt(max(1.0 - r[0, 0] + r[1, 1] - r[2, 2], 0.0))
    z = 0.5 * np.sqrt(max(1.0 - r[0, 0] - r[1, 1] + r[2, 2], 0.0))
    x = float(np.copysign(x, r[2, 1] - r[1, 2]))
    y = float(np.copysign(y, r[0, 2] - r[2, 0]))
    z = float(np.copysign(z, r[1, 0] - r[0, 1]))
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


class _Messages:
    """Builds and serialises the rosbags message objects (ROS 2 Jazzy definitions)."""

    def __init__(self, frame_id: str, odom_frame: str) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.store = get_typestore(Stores.ROS2_JAZZY)
        self.t = self.store.types
        self.frame_id = frame_id
        self.odom_frame = odom_frame

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        return self.t['std_msgs/msg/Header'](
            stamp=self.t['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec),
            frame_id=frame_id)

    def cloud(self, scan: SimScan) -> bytes:
        layout = encode_points(scan.cloud)
        field_type = self.t['sensor_msgs/msg/PointField']
        fields = [field_type(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                  for f in layout.fields]
        msg = self.t['sensor_msgs/msg/PointCloud2'](
            header=self.header(scan.stamp_ns, self.frame_id), height=layout.height,
            width=layout.width, fields=fields, is_bigendian=layout.is_bigendian,
            point_step=layout.point_step, row_step=layout.row_step, data=layout.data,
            is_dense=layout.is_dense)
        return bytes(self.store.serialize_cdr(msg, msg.__msgtype__))

    def odom(self, scan: SimScan) -> bytes:
        t = self.t
        qx, qy, qz, qw = quaternion(scan.pose[:3, :3])
        px, py, pz = (float(v) for v in scan.pose[:3, 3])
        pose = t['geometry_msgs/msg/PoseWithCovariance'](
            pose=t['geometry_msgs/msg/Pose'](
                position=t['geometry_msgs/msg/Point'](x=px, y=py, z=pz),
                orientation=t['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw)),
            covariance=np.zeros(36))
        vec = t['geometry_msgs/msg/Vector3']
        twist = t['geometry_msgs/msg/TwistWithCovariance'](
            twist=t['geometry_msgs/msg/Twist'](linear=vec(x=0.0, y=0.0, z=0.0),
                                               angular=vec(x=0.0, y=0.0, z=0.0)),
            covariance=np.zeros(36))
        msg = t['nav_msgs/msg/Odometry'](header=self.header(scan.stamp_ns, self.odom_frame),
                                         child_frame_id=self.frame_id, pose=pose, twist=twist)
        return bytes(self.store.serialize_cdr(msg, msg.__msgtype__))


def write_bag(path: str | Path, scans: Iterable[SimScan], *, frame_id: str = 'lidar',
              odom_frame: str = 'map', poses_path: str | Path | None = None,
              times_path: str | Path | None = None,
              labels_path: str | Path | None = None) -> BagSummary:
    """Write scans as a rosbag2 (version 9, MCAP) with ``/points`` and ``/odom``.

    Args:
        path: bag directory to create (must not exist).
        scans: scans in time order (any iterable, consumed once).
        frame_id: frame of the clouds and child frame of the odometry.
        odom_frame: parent frame of the odometry.
        poses_path: if given, also write the reference poses there (KITTI 3x4 rows).
        times_path: if given, also write the stamps there (seconds, one per line).
        labels_path: if given, also write 'index label revisit_of' lines there.

    Returns:
        Summary of what was written.

    Raises:
        BagError: the bag cannot be created or written.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.errors import WriterError

    path = Path(path)
    msgs = _Messages(frame_id, odom_frame)
    pose_rows: list[npt.NDArray[np.float64]] = []
    times: list[int] = []
    labels: list[str] = []
    try:
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            points_conn = writer.add_connection(POINTS_TOPIC, 'sensor_msgs/msg/PointCloud2',
                                                typestore=msgs.store)
            odom_conn = writer.add_connection(ODOM_TOPIC, 'nav_msgs/msg/Odometry',
                                              typestore=msgs.store)
            for scan in scans:
                if times and scan.stamp_ns <= times[-1]:
                    raise BagError(f'scan {scan.index}: stamp {scan.stamp_ns} is not after '
                                   f'the previous one ({times[-1]})')
                writer.write(points_conn, scan.stamp_ns, msgs.cloud(scan))
                writer.write(odom_conn, scan.stamp_ns, msgs.odom(scan))
                pose_rows.append(scan.pose[:3, :4].reshape(-1))
                times.append(scan.stamp_ns)
                labels.append(f'{scan.index} {scan.label} {scan.revisit_of}')
    except (WriterError, OSError) as err:
        raise BagError(f'cannot write bag {path}: {err}') from err
    rows = np.asarray(pose_rows).reshape(-1, 12)
    if poses_path is not None:
        np.savetxt(poses_path, rows, fmt='%.9e')
    if times_path is not None:
        np.savetxt(times_path, np.asarray(times, dtype=np.float64) * 1e-9, fmt='%.9f')
    if labels_path is not None:
        Path(labels_path).write_text(''.join(line + '\n' for line in labels), encoding='utf-8')
    return BagSummary(path=path, count=len(times), first_ns=times[0] if times else 0,
                      last_ns=times[-1] if times else 0)


def read_kitti_poses(path: str | Path) -> npt.NDArray[np.float64]:
    """Read KITTI 3x4 pose rows into (N, 4, 4) matrices.

    Raises:
        BagError: the file is missing or not 12 numbers per line.
    """
    try:
        rows = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as err:
        raise BagError(f'cannot read poses {path}: {err}') from err
    if rows.size and rows.shape[1] != 12:
        raise BagError(f'{path}: expected 12 numbers per line, got {rows.shape[1]}')
    out = np.tile(np.eye(4), (len(rows), 1, 1))
    out[:, :3, :4] = rows.reshape(-1, 3, 4)
    return out


def write_drive(directory: str | Path, drive: Drive) -> Path:
    """Write ``drive`` into ``directory`` (bag, poses, times, labels, drive.json).

    Returns:
        The bag directory.
    """
    from solid_ros import __version__

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    bag = d / 'bag'
    write_bag(bag, drive, poses_path=d / 'poses.txt', times_path=d / 'times.txt',
              labels_path=d / 'labels.txt')
    meta = {'package_version': __version__, 'num_scans': len(drive),
            'drive': drive.config.to_dict()}
    (d / 'drive.json').write_text(json.dumps(meta, indent=2, sort_keys=True) + '\n',
                                  encoding='utf-8')
    return bag


def cache_root() -> Path:
    """``$XDG_CACHE_HOME/solid_ros/demo`` (``~/.cache/solid_ros/demo`` by default)."""
    base = os.environ.get('XDG_CACHE_HOME') or str(Path.home() / '.cache')
    return Path(base) / 'solid_ros' / 'demo'


def demo_dir(config: DriveConfig, cache_dir: str | Path | None = None) -> Path:
    """Directory a drive is cached in: ``<root>/<sensor>-<hash of config and version>``."""
    from solid_ros import __version__

    root = Path(cache_dir) if cache_dir is not None else cache_root()
    tag = f'{config.fingerprint()}-{__version__}'
    return root / f'{config.model.name}-{tag}'


def ensure_demo_bag(cache_dir: str | Path | None = None, **options: Any) -> Path:
    """Return the demo bag, simulating and writing it first if it is not cached yet.

    The drive is written into a temporary directory beside the cache entry and renamed into
    place, so an interrupted run never leaves a half-written entry behind.

    Args:
        cache_dir: cache root; :func:`cache_root` when omitted.
        **options: :class:`DriveConfig` fields overriding :data:`DEMO_DEFAULTS`.

    Returns:
        Path of the bag directory; ``poses.txt``, ``times.txt``, ``labels.txt`` and
        ``drive.json`` sit in its parent.

    Raises:
        BagError: the cache directory cannot be written.
    """
    config = DriveConfig(**{**DEMO_DEFAULTS, **options})
    target = demo_dir(config, cache_dir)
    bag = target / 'bag'
    if (bag / 'metadata.yaml').is_file():
        return bag
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f'.{target.name}.', dir=target.parent))
    except OSError as err:
        raise BagError(f'cannot create cache directory {target.parent}: {err}') from err
    try:
        write_drive(tmp, Drive(config))
        try:
            os.rename(tmp, target)
        except OSError:
            # Another run finished first: keep its entry.
            if not (bag / 'metadata.yaml').is_file():
                raise
    except OSError as err:
        raise BagError(f'cannot write demo bag into {target}: {err}') from err
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return bag
