"""Built-in LiDAR drive simulator (numpy only): scene, sensors, route, bag writer.

Typical use::

    from solid_ros.sim import simulate
    for scan in simulate(seed=0, sensor='hdl64', num_scans=200):
        scan.points, scan.odom, scan.pose, scan.stamp_ns, scan.label

``scan.pose`` is the reference pose, ``scan.odom`` the drive's odometry (drifting by about
1.5 % of the path unless ``perfect_odometry=True``; :mod:`solid_ros.sim.odometry`).
``write_drive`` writes a drive as a bag with reference poses (the demo's cache,
:mod:`solid_ros.tools.demo_cache`). Options (all :class:`DriveConfig` fields, also keywords of
``simulate``): sensor ('hdl64', 'avia_like', 'ouster_like', 'vlp16_like', 'mid360_like',
'hesai_like' or a :class:`LidarModel`), route ('revisits', 'no_revisit' or crossings), nx /
ny, scene ('varied', 'lookalike'), facade_detail, mount_roll_deg / mount_pitch_deg,
perfect_odometry, odom_*, and life in the scene, off by default: people and cars (per block,
moving between scans, :mod:`solid_ros.sim.agents`) and foliage (porous crowns and bushes).
"""

from __future__ import annotations

from solid_ros.sim.bagwriter import (
    DEMO_DEFAULTS,
    DEMO_SENSORS,
    BagSummary,
    read_kitti_poses,
    write_bag,
    write_drive,
)
from solid_ros.sim.drive import Drive, DriveConfig, SimScan, pose_matrix, simulate
from solid_ros.sim.lidar import (
    PRESETS,
    LidarModel,
    avia_like,
    cast_scan,
    hdl64,
    hesai_like,
    mid360_like,
    ouster_like,
    sensor_model,
    vlp16_like,
)
from solid_ros.sim.odometry import OdometryDrift
from solid_ros.sim.scene import SCENE_STYLES, Scene, StreetGrid, build_scene
from solid_ros.sim.trajectory import (
    LABELS,
    ROUTES,
    Trajectory,
    build_trajectory,
    revisit_labels,
    serpentine,
)

__all__ = [
    'DEMO_DEFAULTS', 'DEMO_SENSORS', 'LABELS', 'PRESETS', 'ROUTES', 'SCENE_STYLES',
    'BagSummary', 'Drive', 'DriveConfig', 'LidarModel', 'OdometryDrift', 'Scene', 'SimScan',
    'StreetGrid', 'Trajectory', 'avia_like', 'build_scene', 'build_trajectory', 'cast_scan',
    'hdl64', 'hesai_like', 'mid360_like', 'ouster_like', 'pose_matrix', 'read_kitti_poses',
    'revisit_labels', 'sensor_model', 'serpentine', 'simulate', 'vlp16_like', 'write_bag',
    'write_drive',
]
