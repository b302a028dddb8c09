"""Sensor presets and mounting tilt: scans land on the scene through the tilted reference pose."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.errors import ConfigError
from solid_ros.sim import (
    Drive,
    DriveConfig,
    LidarModel,
    avia_like,
    cast_scan,
    hdl64,
    hesai_like,
    mid360_like,
    ouster_like,
    pose_matrix,
    sensor_model,
    simulate,
    vlp16_like,
)
from solid_ros.sim.scene import Scene


def _to_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return points[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]


def _angles(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elevation and azimuth of sensor-frame points, degrees."""
    p = points[:, :3].astype(np.float64)
    return (np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))),
            np.degrees(np.arctan2(p[:, 1], p[:, 0])))


@pytest.fixture(scope='module')
def drive() -> Drive:
    """A small world (40 m blocks) to cast single scans in."""
    return Drive(DriveConfig(seed=4, block=40.0, spacing=10.0))


def test_presets_as_specified() -> None:
    o, v = ouster_like(), vlp16_like()
    assert (o.rings, o.fov_up_deg, o.fov_down_deg, o.points_per_ring, o.fov_width_deg,
            o.max_range, o.range_noise) == (64, 22.5, -22.5, 1024, 360.0, 120.0, 0.03)
    assert (v.rings, v.fov_up_deg, v.fov_down_deg, v.points_per_ring, v.fov_width_deg) == (
        16, 15.0, -15.0, 1800, 360.0)
    assert sensor_model('ouster_like') == o and sensor_model('vlp16_like') == v
    # The first two presets are as they were.
    h, a = hdl64(), avia_like()
    assert (h.rings, h.fov_up_deg, h.fov_down_deg, h.points_per_ring, h.max_range) == (
        64, 2.0, -24.8, 1024, 100.0)
    assert (a.rings, a.fov_width_deg, a.points_per_ring, a.fov_up_deg) == (64, 70.4, 192, 38.6)
    assert not h.tilted and not o.tilted


@pytest.mark.parametrize('model', [ouster_like(points_per_ring=256),
                                   vlp16_like(points_per_ring=450)], ids=lambda m: m.name)
def test_preset_rings_and_range(drive: Drive, model: LidarModel) -> None:
    x, y = (float(v) for v in drive.trajectory.xy[5])
    cloud = cast_scan(drive.scene, model, x, y, 0.3)
    world = _to_world(cloud, pose_matrix(x, y, model.mount_height, 0.3))
    assert drive.scene.surface_distance(world).max() < 1e-3
    el, _ = _angles(cloud)
    rings = np.unique(np.round(el, 3))
    assert len(rings) == model.rings  # every ring returns something, at its own elevation
    assert rings.min() == pytest.approx(model.fov_down_deg, abs=1e-3)
    assert rings.max() == pytest.approx(model.fov_up_deg, abs=1e-3)
    assert np.linalg.norm(cloud[:, :3], axis=1).max() < model.max_range


def test_mid360_and_hesai_presets() -> None:
    m, h = mid360_like(), hesai_like()
    assert (m.rings, m.fov_up_deg, m.fov_down_deg, m.fov_width_deg, m.max_range,
            m.non_repetitive) == (64, 52.0, -7.0, 360.0, 40.0, True)
    assert (h.rings, h.fov_up_deg, h.fov_down_deg, h.points_per_ring, h.max_range) == (
        32, 15.0, -16.0, 1000, 120.0)
    assert sensor_model('mid360_like') == m and sensor_model('hesai_like') == h
    assert not h.non_repetitive and not hdl64().non_repetitive


def test_non_repetitive_rays_land_on_the_scene_without_rings(drive: Drive) -> None:
    model = mid360_like(range_noise=0.0, dropout=0.0)
    x, y = (float(v) for v in drive.trajectory.xy[5])
    pose = pose_matrix(x, y, model.mount_height, 0.3)
    scans = [cast_scan(drive.scene, model, x, y, 0.3, np.random.default_rng(k))
             for k in range(2)]
    for cloud in scans:
        assert len(cloud) > 0.3 * model.num_rays
        assert drive.scene.surface_distance(_to_world(cloud, pose)).max() < 1e-3
        el, _ = _angles(cloud)
        assert el.min() >= -7.0 - 1e-3 and el.max() <= 52.0 + 1e-3
        assert len(np.unique(np.round(el, 3))) > 20 * model.rings  # no rings
    assert not np.array_equal(_angles(scans[0])[0][:100], _angles(scans[1])[0][:100])
    # Without noise (no generator) the grid is the regular one, rings and all.
    el, _ = _angles(cast_scan(drive.scene, model, x, y, 0.3))
    assert len(np.unique(np.round(el, 3))) <= model.rings


TILTED = [
    ouster_like(points_per_ring=256, mount_roll_deg=3.0, mount_pitch_deg=5.0),
    hdl64(points_per_ring=256, mount_roll_deg=-4.0, mount_pitch_deg=-6.0),
    vlp16_like(points_per_ring=450, mount_roll_deg=-5.0),
    avia_like(mount_roll_deg=10.0, mount_pitch_deg=8.0),
]


@pytest.mark.parametrize('model', TILTED, ids=lambda m: m.name)
def test_tilted_scan_lands_on_the_scene(drive: Drive, model: LidarModel) -> None:
    d = Drive(DriveConfig(seed=4, block=40.0, spacing=10.0, sensor=model))
    i = 6
    pose = d.pose(i)
    level = pose_matrix(float(d.trajectory.xy[i, 0]), float(d.trajectory.xy[i, 1]),
                        model.mount_height, float(d.trajectory.yaw[i]))
    np.testing.assert_allclose(pose[:3, :3], level[:3, :3] @ model.mount_rotation(), atol=1e-12)
    cloud = cast_scan(d.scene, model, float(d.trajectory.xy[i, 0]),
                      float(d.trajectory.xy[i, 1]), float(d.trajectory.yaw[i]))
    assert len(cloud) > 0.4 * model.num_rays
    # p_world = pose @ p_sensor: exact without noise ...
    assert d.scene.surface_distance(_to_world(cloud, pose)).max() < 1e-3
    # ... and not with the level pose, so the points really are in the tilted frame.
    assert np.mean(d.scene.surface_distance(_to_world(cloud, level)) < 0.05) < 0.5
    # Points stay in the sensor's own field of view.
    el, az = _angles(cloud)
    assert el.min() >= model.fov_down_deg - 1e-3 and el.max() <= model.fov_up_deg + 1e-3
    if model.fov_width_deg < 360.0:
        assert np.abs(az - model.fov_center_deg).max() <= 0.5 * model.fov_width_deg + 1e-3
    # With noise: range noise moves points along their rays only.
    scan = d.scan(i)
    np.testing.assert_array_equal(scan.pose, pose)
    dist = d.scene.surface_distance(_to_world(scan.points, scan.pose))
    assert np.mean(dist < 5 * model.range_noise) > 0.99


def test_tilt_keeps_the_ray_density(drive: Drive) -> None:
    x, y = (float(v) for v in drive.trajectory.xy[5])
    base = ouster_like(points_per_ring=256)
    level = cast_scan(drive.scene, base, x, y, 0.0)
    tilted = cast_scan(drive.scene, base.replace(mount_pitch_deg=4.0), x, y, 0.0)
    # Same angular spacing over the same solid angle: about as many returns (the tilt trades
    # a little sky for a little ground), not a denser or sparser scan.
    assert 0.85 < len(tilted) / len(level) < 1.15


def test_tilt_sign_convention() -> None:
    # Positive pitch tips the sensor's forward axis down, positive roll its left axis up.
    pitched = Drive(DriveConfig(block=40.0, spacing=10.0, sensor='vlp16_like',
                                mount_pitch_deg=10.0)).pose(0)
    assert pitched[2, 0] == pytest.approx(-np.sin(np.radians(10.0)))
    rolled = Drive(DriveConfig(block=40.0, spacing=10.0, sensor='vlp16_like',
                               mount_roll_deg=10.0)).pose(0)
    assert rolled[2, 1] == pytest.approx(np.sin(np.radians(10.0)))


def test_zero_tilt_is_the_level_sensor() -> None:
    a = next(simulate(seed=2, sensor=vlp16_like(points_per_ring=300), num_scans=1))
    b = next(simulate(seed=2, sensor=vlp16_like(points_per_ring=300, mount_roll_deg=0.0),
                      num_scans=1, mount_pitch_deg=0.0))
    np.testing.assert_array_equal(a.cloud, b.cloud)
    np.testing.assert_array_equal(a.pose, b.pose)


def test_tilt_validation() -> None:
    with pytest.raises(ConfigError, match='mount_pitch_deg'):
        hdl64(mount_pitch_deg=50.0)
    with pytest.raises(ConfigError, match='mount_roll_deg'):
        DriveConfig(sensor='hdl64', mount_roll_deg=-46.0)
    with pytest.raises(ConfigError, match='rings'):
        LidarModel(name='x', rings=1, fov_up_deg=0.0, fov_down_deg=0.0, points_per_ring=360,
                   mount_roll_deg=2.0)
    with pytest.raises(ConfigError, match='points_per_ring'):
        avia_like(points_per_ring=1, mount_pitch_deg=2.0)


def _shelf_before_wall() -> Scene:
    """A shelf 2 m ahead of a wall 5 m ahead: a depth edge at each of the shelf's sides."""
    boxes = np.array([[2.2, 0.0, 0.2, 0.6, 0.0, 0.0, 1.8],     # the shelf
                      [5.2, 0.0, 0.2, 6.0, 0.0, 0.0, 3.0]])    # the wall
    return Scene(None, boxes, np.full(2, 0.5), np.zeros((0, 5)), np.zeros(0))


def test_edge_mixing_puts_points_between_the_surfaces_at_depth_edges() -> None:
    scene, model = _shelf_before_wall(), avia_like(min_range=0.5, mount_height=1.4)
    clean = cast_scan(scene, model, 0.0, 0.0, 0.0, np.random.default_rng(3))
    mixed = cast_scan(scene, model.replace(edge_mixing=1.0), 0.0, 0.0, 0.0,
                      np.random.default_rng(3))

    def floating(cloud: np.ndarray) -> np.ndarray:
        return scene.surface_distance(cloud[:, :3] + [0.0, 0.0, 1.4]) > 0.15

    assert np.sum(floating(clean)) == 0
    ghosts = mixed[floating(mixed)]
    # At the shelf's sides and top, between the shelf's front (2 m) and the wall (5 m).
    assert len(ghosts) > 50
    assert np.all((ghosts[:, 0] > 1.9) & (ghosts[:, 0] < 5.1))
    # Away from edges nothing changes: the ground and the wall's middle are not edges.
    assert len(ghosts) < 0.1 * len(mixed)
    # 0 keeps the scan as it was; the probability is validated.
    np.testing.assert_array_equal(
        clean, cast_scan(scene, model.replace(edge_mixing=0.0), 0.0, 0.0, 0.0,
                         np.random.default_rng(3)))
    with pytest.raises(ConfigError, match='edge_mixing'):
        avia_like(edge_mixing=1.5)
