"""Simulator: determinism, geometry against the scene, labels, bag round trip."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import BagError, ConfigError
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.results import LoopCandidate
from solid_ros.formats.pointcloud2 import cloud_to_xyz
from solid_ros.sim import (
    Drive,
    DriveConfig,
    LidarModel,
    SimScan,
    StreetGrid,
    avia_like,
    build_scene,
    build_trajectory,
    cast_scan,
    hdl64,
    read_kitti_poses,
    sensor_model,
    simulate,
    write_bag,
)

# A small, fast drive for most tests: 40 m blocks, a scan every 10 m.
SMALL = {'sensor': 'avia_like', 'block': 40.0, 'spacing': 10.0}


def _to_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return points[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]


@pytest.fixture(scope='module')
def drive() -> Drive:
    return Drive(DriveConfig(seed=3))


def test_same_seed_same_scans() -> None:
    a = list(simulate(seed=5, num_scans=3))
    b = list(simulate(seed=5, num_scans=3))
    for sa, sb in zip(a, b):
        np.testing.assert_array_equal(sa.cloud, sb.cloud)
        np.testing.assert_array_equal(sa.pose, sb.pose)
        assert sa.stamp_ns == sb.stamp_ns


def test_different_seed_different_scans() -> None:
    a = next(simulate(seed=5, num_scans=1))
    b = next(simulate(seed=6, num_scans=1))
    assert a.cloud.shape != b.cloud.shape or not np.array_equal(a.cloud, b.cloud)
    scenes = build_scene(seed=5), build_scene(seed=6)
    assert scenes[0].boxes.shape != scenes[1].boxes.shape or not np.array_equal(
        scenes[0].boxes, scenes[1].boxes)


def test_scan_by_index_equals_iteration(drive: Drive) -> None:
    first = list(itertools.islice(iter(drive), 3))
    again = drive.scan(2)
    np.testing.assert_array_equal(first[2].cloud, again.cloud)
    points, pose, stamp = first[2]
    assert points.shape == (len(again.cloud), 3) and points.dtype == np.float32
    assert pose.shape == (4, 4) and stamp == again.stamp_ns


@pytest.mark.slow
@pytest.mark.parametrize('index', [0, 57, 150, 400, 700])
def test_scan_lands_on_the_scene(drive: Drive, index: int) -> None:
    scan = drive.scan(index)
    world = _to_world(scan.points, scan.pose)
    dist = drive.scene.surface_distance(world)
    sigma = drive.model.range_noise
    # Range noise only moves points along their rays: within 5 sigma of a surface.
    assert np.mean(dist < 5 * sigma) > 0.99
    assert len(scan.points) > 0.5 * drive.model.num_rays
    ground = (world[:, 2] < 0.3) & (drive.scene.surface_distance(world, ground=False) > 0.5)
    assert ground.mean() > 0.2
    assert np.abs(world[ground, 2]).max() < 6 * sigma + 1e-3
    # Not everything is ground: walls, poles and trees stand up.
    assert (world[:, 2] > 2.0).sum() > 1000


def test_noise_free_scan_is_exact(drive: Drive) -> None:
    t = drive.trajectory
    cloud = cast_scan(drive.scene, drive.model, float(t.xy[80, 0]), float(t.xy[80, 1]),
                      float(t.yaw[80]))
    world = _to_world(cloud, drive.pose(80))
    assert drive.scene.surface_distance(world).max() < 1e-3
    assert len(cloud) < drive.model.num_rays  # some rays see only sky


def test_wrong_pose_does_not_land_on_the_scene(drive: Drive) -> None:
    scan = drive.scan(57)
    shifted = scan.pose.copy()
    shifted[0, 3] += 1.5
    c, s = np.cos(0.05), np.sin(0.05)
    shifted[:3, :3] = shifted[:3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    dist = drive.scene.surface_distance(_to_world(scan.points, shifted))
    above_ground = _to_world(scan.points, shifted)[:, 2] > 0.5
    assert np.mean(dist[above_ground] < 0.1) < 0.5


def test_solid_state_points_stay_in_its_field_of_view() -> None:
    model = avia_like()
    scan = next(simulate(seed=1, sensor=model, num_scans=1))
    p = scan.points.astype(np.float64)
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    assert np.abs(az).max() <= 0.5 * model.fov_width_deg + 1e-3
    assert el.min() >= model.fov_down_deg - 0.1 and el.max() <= model.fov_up_deg + 0.1
    assert len(p) <= model.num_rays


def test_dropout_and_range_limits(drive: Drive) -> None:
    scene = drive.scene
    x, y = (float(v) for v in drive.trajectory.xy[20])
    dense = cast_scan(scene, hdl64(), x, y, 0.0)
    lossy = cast_scan(scene, hdl64(dropout=0.3), x, y, 0.0, np.random.default_rng(0))
    assert abs(len(lossy) / len(dense) - 0.7) < 0.02
    short = cast_scan(scene, hdl64(max_range=20.0), x, y, 0.0)
    assert np.linalg.norm(short[:, :3], axis=1).max() < 20.0
    assert len(short) < len(dense)


def test_presets_and_validation() -> None:
    assert hdl64().rings == 64 and hdl64().fov_width_deg == 360.0
    assert avia_like().fov_width_deg == pytest.approx(70.4)
    assert sensor_model('hdl64') == hdl64()
    with pytest.raises(ConfigError, match='sensor'):
        sensor_model('velodyne')
    with pytest.raises(ConfigError, match='rings'):
        LidarModel(name='x', rings=0, fov_up_deg=2.0, fov_down_deg=-20.0, points_per_ring=10)
    with pytest.raises(ConfigError, match='fov_down_deg'):
        hdl64(fov_down_deg=10.0)
    with pytest.raises(ConfigError, match='dropout'):
        hdl64(dropout=1.0)
    with pytest.raises(ConfigError, match='route'):
        build_trajectory(StreetGrid(), route=((0, 0), (1, 1)))
    with pytest.raises(ConfigError, match='route'):
        build_trajectory(StreetGrid(nx=2, ny=2))
    with pytest.raises(ConfigError, match='seed'):
        DriveConfig(seed=-1)


def test_route_labels(drive: Drive) -> None:
    t = drive.trajectory
    counts = {lab: int((t.label == lab).sum()) for lab in ('new', 'same', 'cross', 'reverse')}
    assert counts['same'] > 100 and counts['reverse'] > 20 and counts['cross'] > 5
    rev = t.revisit_of
    assert np.all((rev >= 0) == (t.label != 'new'))
    idx = np.flatnonzero(rev >= 0)
    assert np.all(rev[idx] < idx)
    gap = np.hypot(*(t.xy[idx] - t.xy[rev[idx]]).T)
    assert gap.max() < drive.config.revisit_radius
    turn = np.degrees(np.abs(np.angle(np.exp(1j * (t.yaw[idx] - t.yaw[rev[idx]])))))
    same = t.label[idx] == 'same'
    assert turn[same].max() <= 45.0 and turn[t.label[idx] == 'reverse'].min() >= 135.0
    # Revisits are never the same pose again: lane offsets and heading changes.
    assert np.median(gap[same]) > 0.5 and np.median(turn[same]) > 1.0
    # The first loop is new until it closes back at its start.
    first_loop = t.distance < 6 * drive.config.block - 2 * drive.config.revisit_radius
    assert np.all(t.label[first_loop] == 'new')


def test_simulate_beyond_the_route_repeats_it() -> None:
    n = len(Drive(DriveConfig(**SMALL)))
    scans = list(simulate(num_scans=n + 3, **SMALL))
    stamps = [s.stamp_ns for s in scans]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert scans[n].label == 'same' and scans[n].revisit_of == 0
    np.testing.assert_array_equal(scans[n].pose, scans[0].pose)
    assert not np.array_equal(scans[n].cloud, scans[0].cloud)  # fresh noise
    with pytest.raises(ConfigError, match='num_scans'):
        next(simulate(num_scans=-1))


def test_bag_round_trip(tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader

    scans = list(simulate(seed=2, num_scans=12, **SMALL))
    bag = tmp_path / 'bag'
    summary = write_bag(bag, scans, poses_path=tmp_path / 'poses.txt',
                        times_path=tmp_path / 'times.txt')
    assert summary.count == 12
    with AnyReader([bag]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {'/points': 'sensor_msgs/msg/PointCloud2',
                         '/odom': 'nav_msgs/msg/Odometry'}
        clouds, odoms = [], []
        for conn, stamp, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            (clouds if conn.topic == '/points' else odoms).append((stamp, msg))
    assert len(clouds) == len(odoms) == 12
    assert all(b[0] > a[0] for a, b in zip(clouds, clouds[1:]))
    for scan, (stamp, msg), (_, odom) in zip(scans, clouds, odoms):
        assert stamp == scan.stamp_ns
        assert msg.header.frame_id == 'lidar' and msg.point_step == 16
        assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'intensity']
        np.testing.assert_array_equal(np.asarray(cloud_to_xyz(msg)), scan.points)
        assert odom.header.frame_id == 'map' and odom.child_frame_id == 'lidar'
        # /odom carries the drifting odometry, poses.txt the reference.
        p, q = odom.pose.pose.position, odom.pose.pose.orientation
        np.testing.assert_allclose([p.x, p.y, p.z], scan.odom[:3, 3])
        yaw = 2.0 * np.arctan2(q.z, q.w)
        assert np.cos(yaw - np.arctan2(scan.odom[1, 0], scan.odom[0, 0])) > 1 - 1e-12
    assert np.linalg.norm(scans[-1].odom[:3, 3] - scans[-1].pose[:3, 3]) > 0.05
    poses = read_kitti_poses(tmp_path / 'poses.txt')
    np.testing.assert_allclose(poses, np.stack([s.pose for s in scans]), atol=1e-8)
    times = np.loadtxt(tmp_path / 'times.txt')
    np.testing.assert_allclose(times, [s.stamp_ns * 1e-9 for s in scans], rtol=0, atol=1e-6)
    with pytest.raises(BagError):
        write_bag(bag, scans)  # exists already


def test_read_kitti_poses_rejects_bad_files(tmp_path: Path) -> None:
    bad = tmp_path / 'poses.txt'
    bad.write_text('1 2 3\n')
    with pytest.raises(BagError, match='12 numbers'):
        read_kitti_poses(bad)
    with pytest.raises(BagError):
        read_kitti_poses(tmp_path / 'missing.txt')


# --- Loop closure on the simulated drive (the demo's claim, at test size) -------------------

RECALL_DRIVE = {'seed': 0, 'block': 50.0, 'spacing': 2.0}
MATCH_RADIUS = 8.0  # a top-1 match within this distance of the query is correct


@pytest.fixture(scope='module')
def recall_scans() -> tuple[Drive, list[SimScan]]:
    drive = Drive(DriveConfig(**RECALL_DRIVE))
    return drive, list(drive)


def _recall(drive: Drive, scans: list[SimScan], fov: float,
            heading_weight: str = 'count') -> dict[str, tuple[float, list[float]]]:
    """Recall@1 and yaw errors (degrees, correct matches) per label, threshold off."""
    t = drive.trajectory
    exclude = int(drive.config.exclude_distance / drive.config.spacing)
    # The reference poses as odometry (scan.pose, not the drifting scan.odom) and the
    # odometry check off: perfect poses would hide the descriptor's misses.
    det = LoopDetector(SolidConfig(fov_width_deg=fov, distance_threshold=2.0, verify=False,
                                   exclude_recent_frames=exclude, odom_check_drift=0.0,
                                   heading_weight=heading_weight))
    top: dict[int, LoopCandidate] = {}
    for scan in scans:
        found = det.process(scan.points, scan.stamp_ns, scan.pose).loops
        if found:
            top[scan.index] = found[0]
    out: dict[str, tuple[float, list[float]]] = {}
    for label in ('same', 'cross', 'reverse'):
        queries = np.flatnonzero(t.label == label)
        hits, errors = 0, []
        for i in queries:
            cand = top.get(int(i))
            if cand is None:
                continue
            j = cand.match_index
            if np.hypot(*(t.xy[i] - t.xy[j])) < MATCH_RADIUS:
                hits += 1
                truth = t.yaw[i] - t.yaw[j]  # p_match = Rz(yaw_q - yaw_m) p_query
                errors.append(abs(float(np.degrees(np.angle(np.exp(1j * (cand.yaw - truth)))))))
        out[label] = (hits / max(len(queries), 1), errors)
    return out


@pytest.mark.slow
def test_recall_360(recall_scans: tuple[Drive, list[SimScan]]) -> None:
    drive, scans = recall_scans
    res = _recall(drive, scans, 360.0)
    recall, errors = res['same']
    print(f'360 deg: same R@1 {recall:.3f}, yaw error mean {np.mean(errors):.2f} deg; '
          f'reverse R@1 {res["reverse"][0]:.3f}; cross R@1 {res["cross"][0]:.3f}')
    assert (drive.trajectory.label == 'same').sum() > 80
    assert recall >= 0.9
    assert np.mean(errors) < 2.0


@pytest.mark.slow
def test_recall_90_degree_clip(recall_scans: tuple[Drive, list[SimScan]]) -> None:
    drive, scans = recall_scans
    # The shipped 90-degree preset weights the heading signature by range: with the paper's
    # counts, near objects' parallax pulls a few headings tens of degrees off (mean 2.1 deg).
    res = _recall(drive, scans, 90.0, heading_weight='range')
    recall, errors = res['same']
    print(f'90 deg: same R@1 {recall:.3f}, yaw error mean {np.mean(errors):.2f} deg, '
          f'median {np.median(errors):.2f} deg; reverse R@1 {res["reverse"][0]:.3f}')
    assert recall >= 0.8
    assert np.mean(errors) < 2.0
    # Facing the other way, a 90-degree sensor sees a different street: no overlap, no loop.
    assert res['reverse'][0] < 0.2
