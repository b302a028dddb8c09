"""Built-in LiDAR drive simulator (numpy only): scene, sensors, route, bag writer.

Typical use::

    from solid_ros.sim import simulate
    for scan in simulate(seed=0, sensor='hdl64', num_scans=200):
        scan.points, scan.pose, scan.stamp_ns, scan.label

and ``ensure_demo_bag()`` for the cached demo bag the demo command replays.
"""

from __future__ import annotations

from solid_ros.sim.bagwriter import (
    DEMO_DEFAULTS,
    BagSummary,
    cache_root,
    demo_dir,
    ensure_demo_bag,
    read_kitti_poses,
    write_bag,
    write_drive,
)
from solid_ros.sim.drive import Drive, DriveConfig, SimScan, pose_matrix, simulate
from solid_ros.sim.lidar import PRESETS, LidarModel, avia_like, cast_scan, hdl64, sensor_model
from solid_ros.sim.scene import Scene, StreetGrid, build_scene
from solid_ros.sim.trajectory import LABELS, Trajectory, build_trajectory, revisit_labels

__all__ = [
    'DEMO_DEFAULTS', 'LABELS', 'PRESETS', 'BagSummary', 'Drive', 'DriveConfig', 'LidarModel',
    'Scene', 'SimScan', 'StreetGrid', 'Trajectory', 'avia_like', 'build_scene',
    'build_trajectory', 'cache_root', 'cast_scan', 'demo_dir', 'ensure_demo_bag', 'hdl64',
    'pose_matrix', 'read_kitti_poses', 'revisit_labels', 'sensor_model', 'simulate',
    'write_bag', 'write_drive',
]
