"""Routes: the default one with revisits, the serpentine that never revisits, custom crossings;
the handheld walk through a room."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.errors import ConfigError
from solid_ros.sim.scene import Room, StreetGrid
from solid_ros.sim.trajectory import (
    DEFAULT_ROUTE,
    NO_REVISIT_ROUTE,
    ROUTES,
    build_trajectory,
    handheld_walk,
    resolve_route,
    route_grid,
    serpentine,
)


def test_named_routes_and_their_grids() -> None:
    assert ROUTES['revisits'] == DEFAULT_ROUTE and resolve_route('revisits') == DEFAULT_ROUTE
    assert route_grid(DEFAULT_ROUTE) == (4, 3)  # the grid the default drive always had
    assert resolve_route('no_revisit') == NO_REVISIT_ROUTE
    assert route_grid(NO_REVISIT_ROUTE) == (7, 6)
    assert serpentine(3, 2) == ((0, 0), (2, 0), (2, 1), (0, 1))


@pytest.mark.parametrize(('block', 'seed'), [(50.0, 0), (50.0, 1), (80.0, 2), (40.0, 3)])
def test_no_revisit_route_never_comes_back(block: float, seed: int) -> None:
    grid = StreetGrid(block=block, nx=7, ny=6, seed=seed)
    t = build_trajectory(grid, seed, 2.0, route=NO_REVISIT_ROUTE)
    assert t.distance[-1] >= 40 * block  # 41 blocks: about 2 km at 50 m
    assert np.all(t.label == 'new') and np.all(t.revisit_of == -1)
    # Not by a hair: beyond the 60 m exclusion, every earlier place is far away.
    nearest = np.inf
    for i in range(len(t)):
        earlier = t.distance < t.distance[i] - 60.0
        if earlier.any():
            nearest = min(nearest, float(np.hypot(*(t.xy[earlier] - t.xy[i]).T).min()))
    assert nearest > 0.4 * block


def test_default_route_still_revisits() -> None:
    t = build_trajectory(StreetGrid(block=50.0), 0, 2.0, route=resolve_route('revisits'))
    assert {'same', 'cross', 'reverse'} <= set(t.label.tolist())


def test_custom_route() -> None:
    route = resolve_route([[0, 0], [2, 0], [2, 2], [0, 2], [0, 0], [1, 0]])
    assert route == ((0, 0), (2, 0), (2, 2), (0, 2), (0, 0), (1, 0))
    assert route_grid(route) == (3, 3)
    grid = StreetGrid(block=40.0, nx=3, ny=3)
    t = build_trajectory(grid, 0, 4.0, route=route)
    # Driven through its crossings (lane offset and corner rounding aside) ...
    for crossing in route[1:-1]:
        assert np.hypot(*(t.xy - grid.node(*crossing)).T).min() < 5.0
    # ... and driving the first block again is a same-direction revisit of it.
    last = t.distance > t.distance[-1] - 20.0
    assert np.all(t.label[last] == 'same')
    assert np.all(t.distance[t.revisit_of[last]] < 45.0)


@pytest.mark.parametrize('route', ['loop', [(0, 0)], [(0, 0), (1,)], [(0, 0), (-1, 0)],
                                   [(0, 0), (1.5, 0)], [(0, 0), (True, 0)], 7])
def test_bad_routes(route: object) -> None:
    with pytest.raises(ConfigError, match='route'):
        resolve_route(route)  # type: ignore[arg-type]


def test_route_must_fit_the_grid_and_follow_roads() -> None:
    with pytest.raises(ConfigError, match='outside'):
        build_trajectory(StreetGrid(nx=2, ny=2), route=((0, 0), (3, 0)))
    with pytest.raises(ConfigError, match='one road'):
        build_trajectory(StreetGrid(), route=((0, 0), (1, 1)))


def test_handheld_walk_revisits_a_room_in_both_directions() -> None:
    room = Room()
    walk = handheld_walk(room, 2)
    assert len(walk) > 100 and np.all(np.diff(walk.distance) > 0)
    # Inside the walkway ring: off the island and the wall strips.
    off = np.abs(walk.xy - room.centre)
    island = np.array(room.island)
    assert np.all((off > island).any(axis=1))
    assert np.all(off < np.array(room.centre) - room.strip)
    labels = set(walk.label.tolist())
    assert {'same', 'reverse'} <= labels
    # Revisits look around: headings differ from the revisited scan's by degrees, not zero.
    same = walk.label == 'same'
    turn = np.abs(np.angle(np.exp(1j * (walk.yaw[same] - walk.yaw[walk.revisit_of[same]]))))
    assert np.degrees(np.median(turn)) > 3.0
    with pytest.raises(ConfigError, match='laps'):
        handheld_walk(room, laps=1)


def test_a_handheld_walk_can_tilt_in_the_hand() -> None:
    room = Room()
    level, held = handheld_walk(room, 2), handheld_walk(room, 2, tilt_deg=8.0)
    assert level.roll is None and level.pitch is None
    # The same path and heading; roll and pitch of 8 degrees' spread, changing smoothly.
    np.testing.assert_array_equal(held.xy, level.xy)
    np.testing.assert_array_equal(held.yaw, level.yaw)
    assert held.roll is not None and held.pitch is not None
    for angle in (held.roll, held.pitch):
        assert len(angle) == len(held)
        assert np.degrees(np.std(angle)) == pytest.approx(8.0)
        assert np.degrees(np.median(np.abs(np.diff(angle)))) < 4.0
    assert not np.allclose(held.roll, held.pitch)
    with pytest.raises(ConfigError, match='tilt_deg'):
        handheld_walk(room, tilt_deg=45.0)
