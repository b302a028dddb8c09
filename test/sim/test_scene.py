"""Scene styles ('varied', 'lookalike'), facade detail, and the indoor room."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.config import SolidConfig
from solid_ros.core.descriptor.solid import describe
from solid_ros.core.errors import ConfigError
from solid_ros.sim import Drive, DriveConfig, StreetGrid, avia_like, build_scene, cast_scan, hdl64
from solid_ros.sim.drive import pose_matrix
from solid_ros.sim.scene import LOOKALIKE_JITTER, Room, build_room
from solid_ros.sim.trajectory import handheld_walk


def _buildings(scene_boxes: np.ndarray) -> np.ndarray:
    """Building rows (cars are the boxes raised 0.3 m off the ground)."""
    return scene_boxes[scene_boxes[:, 5] == 0.0]


def test_unknown_style() -> None:
    with pytest.raises(ConfigError, match='scene'):
        build_scene(style='identical')
    with pytest.raises(ConfigError, match='scene'):
        DriveConfig(scene='identical')
    with pytest.raises(ConfigError, match='facade_detail'):
        DriveConfig(facade_detail='yes')  # type: ignore[arg-type]


def test_lookalike_streets_share_one_character() -> None:
    grid = StreetGrid(block=50.0, nx=5, ny=4, jitter=LOOKALIKE_JITTER, seed=1)
    varied = _buildings(build_scene(StreetGrid(block=50.0, nx=5, ny=4, seed=1), 1).boxes)
    alike = _buildings(build_scene(grid, 1, style='lookalike').boxes)
    # Heights: one distribution everywhere instead of a character per street side.
    p5, p95 = np.percentile(alike[:, 6], [5, 95])
    assert 8.0 < p5 and p95 < 18.0
    v5, v95 = np.percentile(varied[:, 6], [5, 95])
    assert v95 / v5 > 3.0
    # Buildings square to their street ...
    assert np.all(np.isclose(np.mod(alike[:, 4], np.pi / 2), 0.0, atol=1e-9)
                  | np.isclose(np.mod(alike[:, 4], np.pi / 2), np.pi / 2, atol=1e-9))
    # ... but not copies: widths and depths still differ.
    assert np.std(2 * alike[:, 2]) > 3.0 and np.std(2 * alike[:, 3]) > 1.0
    # A nearly regular grid.
    for i in range(grid.nx):
        assert abs(grid.road_x(i)[0] - 50.0 * i) <= LOOKALIKE_JITTER * 50.0 + 1e-9
    # Trees on every street (crowns are cylinders off the ground).
    crowns = [c for c in build_scene(grid, 1, style='lookalike').cylinders if c[3] > 1.0]
    crowns_v = [c for c in build_scene(StreetGrid(block=50.0, nx=5, ny=4, seed=1), 1).cylinders
                if c[3] > 1.0]
    assert len(crowns) > 1.5 * len(crowns_v)


def _best_far_distances(scene: str, seed: int) -> np.ndarray:
    """For every 25th scan of a drive that never revisits: the smallest cosine distance of
    its R-SOLiD to a scan of a place at least 20 m away."""
    drive = Drive(DriveConfig(seed=seed, sensor=hdl64(points_per_ring=512), block=50.0,
                              route='no_revisit', scene=scene))
    idx = np.arange(0, len(drive), 25)
    r = np.stack([describe(drive.scan(int(i)).points, SolidConfig()).r_solid for i in idx])
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    xy = drive.trajectory.xy[idx]
    far = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) >= 20.0
    out: np.ndarray = np.where(far, 1.0 - r @ r.T, np.inf).min(axis=1)
    return out


@pytest.mark.slow
def test_lookalike_places_look_alike_to_the_descriptor() -> None:
    varied = np.concatenate([_best_far_distances('varied', s) for s in (0, 1)])
    alike = np.concatenate([_best_far_distances('lookalike', s) for s in (0, 1)])
    ratio = float(np.median(alike) / np.median(varied))
    print(f'best distance to a place >= 20 m away, median: varied {np.median(varied):.4f}, '
          f'lookalike {np.median(alike):.4f} ({ratio:.2f})')
    assert ratio < 0.9
    assert alike.min() > 1e-3  # similar, never copies


def test_facade_detail_adds_relief_and_nothing_else() -> None:
    grid = StreetGrid(block=40.0, seed=2)
    flat = build_scene(grid, 2)
    relief = build_scene(grid, 2, facade_detail=True)
    # The rest of the scene is drawn as before: same furniture, same cars, same plots.
    np.testing.assert_array_equal(relief.cylinders, flat.cylinders)
    n = len(flat.boxes)
    assert len(relief.boxes) > n + 0.5 * len(_buildings(flat.boxes))
    changed = np.any(relief.boxes[:n] != flat.boxes[:n], axis=1)
    building = flat.boxes[:, 5] == 0.0
    assert 0.3 < changed[building].mean() < 0.9  # many buildings, not all
    assert not changed[~building].any()  # never a car
    body, before = relief.boxes[:n][changed], flat.boxes[changed]
    assert np.all(body[:, 2:4] <= before[:, 2:4] + 1e-9) and np.all(body[:, 6] <= before[:, 6])
    parts = relief.boxes[n:]
    assert np.any(parts[:, 5] > 2.0)  # bay fronts and lintels hang above the pavement


def test_facade_detail_scan_lands_on_the_scene() -> None:
    drive = Drive(DriveConfig(seed=2, block=40.0, spacing=10.0, facade_detail=True,
                              scene='lookalike'))
    flat = Drive(DriveConfig(seed=2, block=40.0, spacing=10.0, scene='lookalike'))
    model = hdl64(points_per_ring=256)
    for i in (3, 11):
        x, y, yaw = (float(v) for v in (*drive.trajectory.xy[i], drive.trajectory.yaw[i]))
        cloud = cast_scan(drive.scene, model, x, y, yaw)
        world = cloud[:, :3].astype(np.float64) @ pose_matrix(x, y, model.mount_height,
                                                             yaw)[:3, :3].T
        world += [x, y, model.mount_height]
        assert drive.scene.surface_distance(world).max() < 1e-3
        # Relief was seen: points on bays, recesses and set-back floors are off the flat boxes.
        assert np.sum(flat.scene.surface_distance(world) > 0.3) > 20


def test_room_is_reproducible_and_its_walkway_stays_free() -> None:
    room = Room()
    a, b, other = build_room(room, 3), build_room(room, 3), build_room(room, 4)
    assert a.grid is None
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.cylinders, b.cylinders)
    assert a.boxes.shape != other.boxes.shape or not np.array_equal(a.boxes, other.boxes)
    # Cluttered: shelves, boxes, a table with things on it, chairs.
    assert len(a.boxes) > 40
    walk = handheld_walk(room, 3)
    at_hand = np.c_[walk.xy, np.full(len(walk), 1.4)]
    # The walker never stands in furniture: at least 0.25 m clear at sensor height ...
    assert a.surface_distance(at_hand, ground=False).min() > 0.25
    # ... yet close to it: a tight space.
    assert np.median(a.surface_distance(at_hand, ground=False)) < 1.5
    # The street scenes are built by build_scene as before: a room is a separate builder.
    assert build_scene(seed=5).grid is not None


def test_room_scan_lands_on_the_room() -> None:
    room = Room()
    scene, walk = build_room(room, 1), handheld_walk(room, 1)
    model = avia_like(min_range=0.5, mount_height=1.4)
    for i in (0, 40, 90):
        x, y, yaw = float(walk.xy[i, 0]), float(walk.xy[i, 1]), float(walk.yaw[i])
        cloud = cast_scan(scene, model, x, y, yaw)
        world = cloud[:, :3].astype(np.float64) @ pose_matrix(x, y, 1.4, yaw)[:3, :3].T
        world += [x, y, 1.4]
        assert scene.surface_distance(world).max() < 1e-3
        # Enclosed: every ray returns (ceiling, walls, furniture), all within the room's reach.
        assert len(cloud) == model.num_rays
        assert np.linalg.norm(cloud[:, :3], axis=1).max() < 12.0
        assert (world[:, 2] > room.height - 0.01).sum() > 100  # the ceiling is seen


def test_room_validation() -> None:
    with pytest.raises(ConfigError, match='width'):
        Room(width=3.0)
    with pytest.raises(ConfigError, match='island'):
        Room(width=4.5, depth=4.5, strip=1.0, walkway=1.2)
