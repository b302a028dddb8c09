"""Writing a simulated drive as a ROS 2 MCAP bag plus reference poses.

:func:`write_drive` fills a directory with (the demo's cache entry,
:mod:`solid_ros.tools.demo_cache`)::

    bag/            rosbag2 (metadata version 9, MCAP): /points (PointCloud2), /odom (Odometry:
                    the drive's odometry, drifting unless ``perfect_odometry``)
    poses.txt       one KITTI 3x4 world <- sensor reference pose per scan (row-major, 12
                    numbers): what replays evaluate against
    times.txt       scan stamps in seconds, one per line, same order
    labels.txt      per scan: index, label (new/same/cross/reverse), index of the revisited scan
    drive.json      the DriveConfig that made it (sensor model, route and its crossings, grid
                    size, scene style, facade detail, mounting tilt), the count of each label
                    and the package version
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import BagError
from solid_ros.formats import poses
from solid_ros.formats.bags import write_cloud_bag
from solid_ros.sim.drive import Drive, SimScan
from solid_ros.sim.lidar import (
    avia_like,
    hdl64,
    hesai_like,
    mid360_like,
    ouster_like,
    vlp16_like,
)

__all__ = ['BagSummary', 'DEMO_DEFAULTS', 'DEMO_SENSORS', 'read_kitti_poses', 'write_bag',
           'write_drive']

POINTS_TOPIC = '/points'
ODOM_TOPIC = '/odom'

# The drive the demo command replays: 64-beam, 360 deg, 50 m blocks (about 1.1 km, 553
# scans every 2 m) at 512 points per ring, so the cached bag stays near 280 MB.
DEMO_DEFAULTS: dict[str, Any] = {'seed': 0, 'sensor': hdl64(points_per_ring=512),
                                 'block': 50.0, 'spacing': 2.0}
# The 360-degree sensors at 512 points per ring, like the hdl64 demo (Ouster's 512 x 10 mode).
DEMO_SENSORS = {'hdl64': DEMO_DEFAULTS['sensor'], 'avia_like': avia_like(),
                'ouster_like': ouster_like(points_per_ring=512), 'vlp16_like': vlp16_like(),
                'mid360_like': mid360_like(), 'hesai_like': hesai_like()}


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

    ``/odom`` carries each scan's odometry (:attr:`SimScan.odom`); the reference poses go to
    ``poses_path``.

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
        BagError: the bag cannot be created or written, or a stamp is not after the previous.
    """
    from rosbags.rosbag2.errors import WriterError

    path = Path(path)
    pose_rows: list[npt.NDArray[np.float64]] = []
    times: list[int] = []
    labels: list[str] = []

    def items() -> Iterator[tuple[npt.NDArray[np.float32], int, npt.NDArray[np.float64]]]:
        for scan in scans:
            if times and scan.stamp_ns <= times[-1]:
                raise BagError(f'scan {scan.index}: stamp {scan.stamp_ns} is not after '
                               f'the previous one ({times[-1]})')
            pose_rows.append(scan.pose[:3, :4].reshape(-1))
            times.append(scan.stamp_ns)
            labels.append(f'{scan.index} {scan.label} {scan.revisit_of}')
            yield scan.cloud, scan.stamp_ns, scan.odom

    try:
        write_cloud_bag(path, items(), 'mcap', points_topic=POINTS_TOPIC, odom_topic=ODOM_TOPIC,
                        frame_id=frame_id, odom_frame_id=odom_frame)
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
