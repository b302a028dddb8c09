"""Mixed pixels: points floating between two surfaces at a depth edge are found and dropped."""

from __future__ import annotations

import numpy as np

from solid_ros.core.verification.mixed_pixels import drop_mixed_pixels, mixed_pixels
from solid_ros.sim import avia_like, cast_scan
from solid_ros.sim.scene import Room, Scene, build_room
from solid_ros.sim.trajectory import handheld_walk

ROOM_SENSOR = avia_like(min_range=0.5, mount_height=1.4)


def _off_surface(scene: Scene, cloud: np.ndarray, x: float, y: float, height: float,
                 yaw: float) -> np.ndarray:
    """Distance of each sensor-frame point of a level scan from the scene's surfaces."""
    c, s = np.cos(yaw), np.sin(yaw)
    world = cloud[:, :3] @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return scene.surface_distance(world + [x, y, height])


def test_the_rooms_mixed_pixels_go_and_its_surfaces_stay() -> None:
    room = Room()
    scene, walk = build_room(room, 0), handheld_walk(room, 0)
    found = ghosts = lost = kept = 0
    for i in range(0, 150, 30):
        x, y, yaw = float(walk.xy[i, 0]), float(walk.xy[i, 1]), float(walk.yaw[i])
        scan = cast_scan(scene, ROOM_SENSOR.replace(edge_mixing=0.5), x, y, yaw,
                         np.random.default_rng(i))[:, :3]
        off = _off_surface(scene, scan, x, y, 1.4, yaw)
        ghost, surface = off > 0.15, off < 0.05
        flagged = mixed_pixels(scan)
        found += int(np.sum(flagged & ghost))
        ghosts += int(ghost.sum())
        lost += int(np.sum(flagged & surface))
        kept += int(surface.sum())
        clean = cast_scan(scene, ROOM_SENSOR, x, y, yaw, np.random.default_rng(i))[:, :3]
        assert mixed_pixels(clean).sum() < 0.005 * len(clean)
    # Measured: 0.82 of the points floating 0.15 m or more off every surface found, 0.16 % of
    # the surfaces' own points taken.
    assert found > 0.7 * ghosts
    assert lost < 0.003 * kept


def test_sparse_scans_keep_their_points() -> None:
    # Too few neighbours to tell (a voxelised or sparse cloud): nothing goes.
    rng = np.random.default_rng(1)
    sparse = rng.uniform(-20.0, 20.0, (300, 3))
    assert not mixed_pixels(sparse).any()


def test_drop_keeps_rows_and_columns_and_takes_any_input() -> None:
    front = np.column_stack([np.full(200, 2.0), np.linspace(-0.5, 0.5, 200), np.zeros(200)])
    wall = np.column_stack([np.full(200, 5.0), np.linspace(-1.2, 1.2, 200), np.zeros(200)])
    # Floating between them, each in its own direction among the front's and the wall's.
    ghost = np.array([[3.1, 0.40, 0.0], [3.6, -0.50, 0.0]])
    pts = np.vstack([front, wall, ghost])
    pts = np.column_stack([pts, np.arange(len(pts), dtype=np.float64)])  # an intensity column
    out = drop_mixed_pixels(pts)
    assert out.shape[1] == 4
    assert set(out[:, 3].astype(int)) == set(range(400))
    assert mixed_pixels(np.zeros((0, 3))).shape == (0,)
    assert drop_mixed_pixels(np.zeros((0, 3))).shape == (0, 3)
    bad = np.array([[np.nan, 0.0, 0.0], [np.inf, 1.0, 0.0], [0.0, 0.0, 0.0]])
    assert not mixed_pixels(bad).any()
