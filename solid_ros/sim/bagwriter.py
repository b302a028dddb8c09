"""Writing a simulated drive as a ROS 2 MCAP bag plus reference poses, and the demo cache.

A demo directory holds::

    bag/            rosbag2 (metadata version 9, MCAP): /points (PointCloud2), /odom (Odometry)
    poses.txt       one KITTI 3x4 world <- sensor pose per scan (row-major, 12 numbers)
    times.txt       scan stamps in seconds, one per line, same order
    labels.txt      per scan: index, label (new/same/cross/reverse), index of the revisited scan
    drive.json      the DriveConfig that made it (sensor model, route and its crossings, grid
                    size, scene style, facade detail, mounting tilt), the count of each label
                    and the package version
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

from solid_ros.core.errors import BagError
from solid_ros.formats import poses
from solid_ros.formats.bags import ODOMETRY, POINTCLOUD2, BagWriter
from solid_ros.sim.drive import Drive, DriveConfig, SimScan
from solid_ros.sim.lidar import avia_like, hdl64, ouster_like, vlp16_like

__all__ = ['BagSummary', 'DEMO_DEFAULTS', 'DEMO_SENSORS', 'cache_root', 'demo_dir',
           'ensure_demo_bag',
           'read_kitti_poses', 'write_bag', 'write_drive']

POINTS_TOPIC = '/points'
ODOM_TOPIC = '/odom'

# The drive the demo command replays: 64-beam, 360 deg, 50 m blocks (about 1.1 km, 553
# scans every 2 m) at 512 points per ring, so the cached bag stays near 280 MB.
DEMO_DEFAULTS: dict[str, Any] = {'seed': 0, 'sensor': hdl64(points_per_ring=512),
                                 'block': 50.0, 'spacing': 2.0}
# The 360-degree sensors at 512 points per ring, like the hdl64 demo (Ouster's 512 x 10 mode).
DEMO_SENSORS = {'hdl64': DEMO_DEFAULTS['sensor'], 'avia_like': avia_like(),
                'ouster_like': ouster_like(points_per_ring=512), 'vlp16_like': vlp16_like()}


@dataclass(frozen=True)
class BagSummary:
    """What :func:`write_bag` wrote."""

    path: Path
    count: int
    first_ns: int
    last_ns: int


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
    from rosbags.rosbag2.errors import WriterError

    path = Path(path)
    pose_rows: list[npt.NDArray[np.float64]] = []
    times: list[int] = []
    labels: list[str] = []
    try:
        with BagWriter(path, 'mcap') as writer:
            writer.add_topic(POINTS_TOPIC, POINTCLOUD2)
            writer.add_topic(ODOM_TOPIC, ODOMETRY)
            for scan in scans:
                stamp = scan.stamp_ns
                if times and stamp <= times[-1]:
                    raise BagError(f'scan {scan.index}: stamp {stamp} is not after '
                                   f'the previous one ({times[-1]})')
                writer.write(POINTS_TOPIC, stamp, writer.cloud_msg(scan.cloud, stamp, frame_id))
                writer.write(ODOM_TOPIC, stamp,
                             writer.odometry_msg(scan.pose, stamp, odom_frame, frame_id))
                pose_rows.append(scan.pose[:3, :4].reshape(-1))
                times.append(stamp)
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
    """Read the KITTI 3x4 pose rows of a demo directory into (N, 4, 4) matrices.

    :func:`solid_ros.poses.read_kitti_poses` with the simulator's error type.

    Raises:
        BagError: the file is missing, empty or not 12 numbers per line.
    """
    try:
        return poses.read_kitti_poses(path)
    except poses.PoseError as err:
        raise BagError(str(err)) from err


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
    labels = drive.trajectory.label
    meta = {'package_version': __version__, 'num_scans': len(drive),
            'drive': drive.config.to_dict(),
            'route_crossings': [list(c) for c in drive.config.crossings],
            'labels': {str(k): int((labels == k).sum()) for k in sorted(set(labels.tolist()))}}
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
