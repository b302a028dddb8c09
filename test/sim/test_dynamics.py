"""A scene that changes between scans: people and cars moving through it, porous foliage.

Off by default: the default drive, its scans and its cache key stay as they were.
"""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.errors import ConfigError
from solid_ros.sim import DEMO_DEFAULTS, Drive, DriveConfig, avia_like, cast_scan, simulate
from solid_ros.sim.agents import CLEARANCE_M, room_agents, street_agents
from solid_ros.sim.drive import START_NS
from solid_ros.sim.scene import Room, Scene, StreetGrid, build_room, build_scene

SMALL = {'seed': 2, 'block': 40.0, 'spacing': 10.0, 'sensor': avia_like(points_per_ring=96)}


def _seconds(stamp_ns: int) -> float:
    return (stamp_ns - START_NS) * 1e-9


def test_options_at_zero_change_nothing() -> None:
    spelt = DriveConfig(**DEMO_DEFAULTS, people=0, cars=0.0, foliage=0)
    assert spelt.fingerprint() == DriveConfig(**DEMO_DEFAULTS).fingerprint()
    plain, zero = Drive(DriveConfig(**SMALL)), Drive(DriveConfig(**SMALL, people=0.0,
                                                                  cars=0.0, foliage=0.0))
    assert zero.scene.cylinder_free_path is None and len(zero.agents) == 0
    for i in (0, 3):
        np.testing.assert_array_equal(plain.scan(i).cloud, zero.scan(i).cloud)
    for bad in ({'people': -1.0}, {'cars': 21.0}, {'foliage': 25.0}, {'people': True}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            DriveConfig(**bad)  # type: ignore[arg-type]


def test_same_seed_same_dynamic_scans() -> None:
    options = {**SMALL, 'people': 4.0, 'cars': 2.0, 'foliage': 1.5}
    a, b = Drive(DriveConfig(**options)), Drive(DriveConfig(**options))
    for i in (1, 6):
        np.testing.assert_array_equal(a.scan(i).cloud, b.scan(i).cloud)
    t = _seconds(a.stamp_ns(6))
    np.testing.assert_array_equal(a.agents.poses(t)[0], b.agents.poses(t)[0])
    # Another seed: other people, elsewhere.
    other = Drive(DriveConfig(**{**options, 'seed': 3}))
    assert not np.array_equal(other.agents.poses(t)[0][:5], a.agents.poses(t)[0][:5])


def test_people_and_cars_move_between_scans_and_come_and_go() -> None:
    grid = StreetGrid(block=50.0, seed=1)
    agents = street_agents(grid, seed=1, people=5.0, cars=2.0)
    people, cars = agents.person, ~agents.person
    assert people.sum() > 50 and cars.sum() > 20
    (xy0, _), (xy1, yaw1) = agents.poses(100.0), agents.poses(101.0)
    step = np.hypot(*(xy1 - xy0).T)
    # A person walks about 1.4 m in a second, a car 5-10 m (less where it turned a corner).
    assert 1.2 < np.median(step[people]) < 1.6 and np.all(step[people] <= 2.0 + 1e-9)
    assert 5.0 <= np.median(step[cars]) <= 10.0
    # Cars keep the block on their right: right-hand traffic, clockwise round it.
    blocks = [(0.5 * (grid.road_x(i)[0] + grid.road_x(i + 1)[0]),
               0.5 * (grid.road_y(j)[0] + grid.road_y(j + 1)[0]))
              for i in range(-1, grid.nx) for j in range(-1, grid.ny)]
    centre = agents.corners[cars].mean(axis=1)
    assert np.allclose([min(np.hypot(*(np.array(blocks) - c).T)) for c in centre], 0.0)
    heading = np.c_[np.cos(yaw1[cars]), np.sin(yaw1[cars])]
    to_block = centre - xy1[cars]
    assert np.all(heading[:, 0] * to_block[:, 1] - heading[:, 1] * to_block[:, 0] < 0.0)
    # Each comes and goes: present at some times and away at others.
    here = np.array([agents.here(t) for t in np.arange(0.0, 1200.0, 5.0)])
    assert np.all(here.any(axis=0)) and np.all(~here.all(axis=0))
    assert 0.5 < here.mean() < 0.9


def test_a_revisit_sees_the_people_elsewhere() -> None:
    drive = Drive(DriveConfig(**SMALL, people=8.0, cars=2.0))
    x, y = map(float, drive.trajectory.xy[2])
    now, later = drive.scene_at(10.0, x, y), drive.scene_at(70.0, x, y)
    n_static = len(drive.scene.cylinders)
    assert not np.array_equal(now.cylinders[n_static:, :2][:10],
                              later.cylinders[n_static:, :2][:10])
    # A second lap of the route (simulate beyond its length) casts the same place at another
    # time: the static scene is the same, the agents are not.
    n = len(drive)
    scans = list(simulate(num_scans=n + 3, **{**SMALL, 'people': 8.0, 'cars': 2.0}))
    first, again = scans[2], scans[n + 2]
    assert first.revisit_of == -1 and again.revisit_of == 2
    off = [drive.scene.surface_distance(s.points.astype(float) @ s.pose[:3, :3].T
                                        + s.pose[:3, 3]) > 0.1 for s in (first, again)]
    assert off[0].sum() > 5 and off[1].sum() > 5
    assert not np.array_equal(first.points[off[0]][:5], again.points[off[1]][:5])


def test_points_land_on_the_scene_of_their_time_and_nothing_stands_on_the_sensor() -> None:
    drive = Drive(DriveConfig(**SMALL, people=10.0, cars=4.0))
    model = drive.model.replace(range_noise=0.0, dropout=0.0)
    for i in (0, 4, 9):
        x, y, yaw = *map(float, drive.trajectory.xy[i]), float(drive.trajectory.yaw[i])
        t = _seconds(drive.stamp_ns(i))
        boxes, _, cyls, _ = drive.agents.objects(t, x, y)
        reach = np.r_[np.hypot(boxes[:, 0] - x, boxes[:, 1] - y) - np.hypot(boxes[:, 2],
                                                                            boxes[:, 3]),
                      np.hypot(cyls[:, 0] - x, cyls[:, 1] - y) - cyls[:, 2]]
        assert np.all(reach > CLEARANCE_M)
        scene = drive.scene_at(t, x, y)
        cloud = cast_scan(scene, model, x, y, yaw)
        pose = drive.pose(i)
        world = cloud[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        assert scene.surface_distance(world).max() < 1e-3


def _crown_before_wall(free_path: float | None) -> Scene:
    """A crown (r 1.5 m, 0.5-3 m high) 6 m ahead of the sensor, a wall 12 m ahead."""
    boxes = np.array([[12.2, 0.0, 0.2, 8.0, 0.0, 0.0, 4.0]])
    cyls = np.array([[6.0, 0.0, 1.5, 0.5, 3.0]])
    return Scene(None, boxes, np.full(1, 0.5), cyls, np.full(1, 0.2),
                 cylinder_free_path=None if free_path is None else np.full(1, free_path))


def test_porous_crowns_are_hit_at_other_depths_and_missed_in_other_directions() -> None:
    model = avia_like(range_noise=0.0, dropout=0.0)
    solid, porous = _crown_before_wall(None), _crown_before_wall(1.0)
    clean = cast_scan(solid, model, 0.0, 0.0, 0.0, np.random.default_rng(0))
    # A free path of 0 is solid, and so is a porous crown cast without a generator.
    np.testing.assert_array_equal(clean, cast_scan(_crown_before_wall(0.0), model, 0.0, 0.0,
                                                   0.0, np.random.default_rng(0)))
    np.testing.assert_array_equal(cast_scan(solid, model, 0.0, 0.0, 0.0),
                                  cast_scan(porous, model, 0.0, 0.0, 0.0))
    scans = [cast_scan(porous, model, 0.0, 0.0, 0.0, np.random.default_rng(k)) for k in (1, 2)]
    crown = np.array([6.0, 0.0])

    def inside(cloud: np.ndarray) -> np.ndarray:
        world = cloud[:, :3] + [0.0, 0.0, model.mount_height]
        return (np.hypot(*(world[:, :2] - crown).T) < 1.5 - 0.05) & (world[:, 2] > 0.55)

    def behind(cloud: np.ndarray) -> np.ndarray:
        """On the wall, in the crown's shadow."""
        return (cloud[:, 0] > 11.9) & (np.abs(np.arctan2(cloud[:, 1], cloud[:, 0])) < 0.2)

    assert not inside(clean).any() and not behind(clean).any()
    for cloud in scans:
        # Hit inside the crown (not only on its skin), and seen through onto the wall.
        assert inside(cloud).sum() > 50 and behind(cloud).sum() > 10
    # Another scan, other depths and other directions.
    depth = [np.sort(np.hypot(c[inside(c), 0], c[inside(c), 1]))[:50] for c in scans]
    assert not np.allclose(depth[0], depth[1])
    assert not np.array_equal(scans[0][behind(scans[0]), :2], scans[1][behind(scans[1]), :2])


def test_foliage_makes_crowns_porous_and_adds_bushes_leaving_the_rest() -> None:
    grid = StreetGrid(block=50.0, seed=5)
    plain, leafy = build_scene(grid, 5), build_scene(grid, 5, foliage=2.0)
    np.testing.assert_array_equal(plain.boxes, leafy.boxes)
    n = len(plain.cylinders)
    np.testing.assert_array_equal(plain.cylinders, leafy.cylinders[:n])
    free = leafy.cylinder_free_path
    assert free is not None and plain.cylinder_free_path is None
    # Porous: the crowns (raised cylinders) and the bushes; solid: trunks and poles.
    raised = leafy.cylinders[:n, 3] > 0.0
    assert np.all(free[:n][raised] == 2.0) and np.all(free[:n][~raised] == 0.0)
    assert len(leafy.cylinders) > n + 20 and np.all(free[n:] == 2.0)
    with pytest.raises(ConfigError, match='foliage'):
        build_scene(grid, 5, foliage=-1.0)


def test_room_people_walk_the_walkway() -> None:
    room = Room()
    agents = room_agents(room, seed=3, people=4)
    assert len(agents) == 4 and agents.person.all()
    (cx, cy), (ix, iy) = room.centre, room.island
    for t in np.arange(0.0, 60.0, 0.5):
        xy, _ = agents.poses(float(t))
        # Inside the strips along the walls, outside the island.
        assert np.all((xy[:, 0] >= room.strip) & (xy[:, 0] <= room.width - room.strip))
        assert np.all((xy[:, 1] >= room.strip) & (xy[:, 1] <= room.depth - room.strip))
        assert np.all((np.abs(xy[:, 0] - cx) > ix) | (np.abs(xy[:, 1] - cy) > iy))
    scene = build_room(room, 3)
    a = scene.with_objects(*agents.objects(1.0))
    b = scene.with_objects(*agents.objects(3.0))
    assert len(a.cylinders) > len(scene.cylinders)
    assert not np.array_equal(a.cylinders[len(scene.cylinders):, :2],
                              b.cylinders[len(scene.cylinders):, :2])
    assert room_agents(room, seed=3, people=0).objects(1.0)[2].shape == (0, 5)
    with pytest.raises(ConfigError, match='people'):
        room_agents(room, people=51)
