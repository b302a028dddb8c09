"""Procedural street scene made of vertical prisms, so rays intersect it in closed form.

Everything stands on the ground plane z = 0 and is a vertical prism: a box with a (possibly
yawed) rectangular footprint, or a cylinder with a circular one, each spanning heights
[z_low, z_high]. Buildings line both sides of a grid of straight roads; poles, trees (trunk plus
a raised crown cylinder) and parked cars make the street distinctive at close range.

Two styles: 'varied' gives every street side its own character (set-back, height, open lots)
and trees to some streets; 'lookalike' gives every street side the same character and every
street the same furniture, so that places differ only by the random widths, gaps and depths
of buildings and the random positions of furniture (a hard case for a place descriptor, not
an impossible one). ``facade_detail`` adds relief to the otherwise flat building boxes:
recessed entrances, bay fronts and stepped upper floors, all made of more prisms.

:func:`build_room` makes an indoor scene instead: one small room (7.5 x 6 m by default) with a
ceiling, door openings onto corridors, shelves, cabinets, box stacks and pillars along the
walls, a table island with clutter on it and chairs: near-field structure that occludes
different things from viewpoints a metre apart (a handheld recording in a tight space;
:func:`solid_ros.sim.trajectory.handheld_walk` walks it).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import ConfigError

__all__ = ['LOOKALIKE_JITTER', 'SCENE_STYLES', 'Room', 'Scene', 'StreetGrid', 'build_room',
           'build_scene']

FloatArray = npt.NDArray[np.float64]

# Reflectivity classes (the intensity channel of simulated points).
GROUND_REFLECTIVITY = 0.15

SCENE_STYLES = ('varied', 'lookalike')

# Road jitter of a 'lookalike' grid (fraction of a block): nearly regular, not exactly.
LOOKALIKE_JITTER = 0.03


@dataclass(frozen=True)
class _Style:
    """How buildings and furniture vary; None draws a value per street side."""

    setback: float | None
    height: float | None
    open_lots: float | None
    setback_jitter: float
    height_sigma: float
    yaw_probability: float
    trees_always: bool


# 'varied' draws in exactly the order of the first release, so its scenes stay the same.
_STYLES = {
    'varied': _Style(setback=None, height=None, open_lots=None, setback_jitter=2.5,
                     height_sigma=0.35, yaw_probability=0.2, trees_always=False),
    'lookalike': _Style(setback=3.0, height=12.0, open_lots=0.0, setback_jitter=1.0,
                        height_sigma=0.15, yaw_probability=0.0, trees_always=True),
}


@dataclass(frozen=True)
class StreetGrid:
    """A grid of straight roads: ``nx`` roads along y (constant x), ``ny`` along x.

    Road positions and widths vary around the nominal ones (seeded), so blocks differ in size
    and streets in width, as in a real town; a perfectly regular grid would make every
    crossing look alike.

    Attributes:
        block: nominal distance between neighbouring parallel roads, metres.
        nx: number of north-south roads (constant x).
        ny: number of east-west roads (constant y).
        road_half_width: nominal half road width, metres; nothing is built on a road.
        jitter: roads move up to this fraction of ``block`` from the regular grid and widths
            vary by up to this fraction; 0 gives a regular grid.
        seed: seed of the variation.
    """

    block: float = 80.0
    nx: int = 4
    ny: int = 3
    road_half_width: float = 7.0
    jitter: float = 0.2
    seed: int = 0

    def __post_init__(self) -> None:
        if not 30.0 <= self.block <= 1000.0:
            raise ConfigError(f'block: {self.block} is out of range; allowed [30, 1000]')
        if self.nx < 2 or self.ny < 2:
            raise ConfigError(f'nx, ny: need at least 2 roads each way, got {self.nx}, {self.ny}')
        if not 3.0 <= self.road_half_width <= 0.2 * self.block:
            raise ConfigError(f'road_half_width: {self.road_half_width} is out of range; '
                              f'allowed [3, {0.2 * self.block}]')
        if not 0.0 <= self.jitter <= 0.25:
            raise ConfigError(f'jitter: {self.jitter} is out of range; allowed [0, 0.25]')

    @cached_property
    def _layout(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Road positions and half widths, x roads then y roads, with one virtual road
        beyond each end (where the outer blocks end)."""
        rng = np.random.default_rng([self.seed, 0x6A1D])
        out = []
        for n in (self.nx, self.ny):
            pos = (np.arange(-1, n + 1) + self.jitter * rng.uniform(-1.0, 1.0, n + 2)) * self.block
            half = self.road_half_width * (1.0 + self.jitter * rng.uniform(-1.0, 1.0, n + 2))
            out += [pos, half]
        return out[0], out[1], out[2], out[3]

    def road_x(self, i: int) -> tuple[float, float]:
        """Position and half width of north-south road ``i`` (-1 and nx are virtual)."""
        pos, half = self._layout[0], self._layout[1]
        return float(pos[i + 1]), float(half[i + 1])

    def road_y(self, j: int) -> tuple[float, float]:
        """Position and half width of east-west road ``j`` (-1 and ny are virtual)."""
        pos, half = self._layout[2], self._layout[3]
        return float(pos[j + 1]), float(half[j + 1])

    def node(self, i: int, j: int) -> tuple[float, float]:
        """Return the world (x, y) of the crossing of road column ``i`` and row ``j``."""
        return self.road_x(i)[0], self.road_y(j)[0]


@dataclass(frozen=True)
class Scene:
    """Static world: ground plane z = 0 plus vertical box and cylinder prisms.

    Attributes:
        grid: the road layout the scene was built around (None for a room).
        boxes: (B, 7) rows cx, cy, hx, hy, yaw, z_low, z_high (half extents in the box frame).
        box_reflectivity: (B,) intensity returned by each box, in [0, 1].
        cylinders: (C, 5) rows cx, cy, radius, z_low, z_high.
        cylinder_reflectivity: (C,) intensity returned by each cylinder.
        box_free_path: (B,) mean free path of a ray inside each box, metres; 0 (or None for
            all): solid, a ray returns where it enters. Above 0 the box is porous, like
            foliage: a ray travels an exponentially distributed distance of that mean into it
            before it returns, and passes through when its path inside is shorter, so each
            scan hits it at other depths and misses it in other directions (a scan cast
            without a random generator sees it solid).
        cylinder_free_path: (C,) the same for the cylinders.
    """

    grid: StreetGrid | None
    boxes: FloatArray
    box_reflectivity: FloatArray
    cylinders: FloatArray
    cylinder_reflectivity: FloatArray
    box_free_path: FloatArray | None = None
    cylinder_free_path: FloatArray | None = None

    def near_mask(self, x: float, y: float, radius: float) -> tuple[npt.NDArray[np.bool_],
                                                                     npt.NDArray[np.bool_]]:
        """Which boxes and which cylinders reach within ``radius`` of (x, y)."""
        b, c = self.boxes, self.cylinders
        bound_b = np.hypot(b[:, 2], b[:, 3])
        keep_b = np.hypot(b[:, 0] - x, b[:, 1] - y) - bound_b < radius
        keep_c = np.hypot(c[:, 0] - x, c[:, 1] - y) - c[:, 2] < radius
        return keep_b, keep_c

    def near(self, x: float, y: float, radius: float) -> tuple[FloatArray, FloatArray,
                                                                FloatArray, FloatArray]:
        """Return the boxes and cylinders (and reflectivities) reaching within ``radius``."""
        keep_b, keep_c = self.near_mask(x, y, radius)
        return (self.boxes[keep_b], self.box_reflectivity[keep_b], self.cylinders[keep_c],
                self.cylinder_reflectivity[keep_c])

    def free_paths(self) -> tuple[FloatArray, FloatArray]:
        """:attr:`box_free_path` and :attr:`cylinder_free_path`, zeros where None."""
        fb = (np.zeros(len(self.boxes)) if self.box_free_path is None
              else np.asarray(self.box_free_path, dtype=np.float64))
        fc = (np.zeros(len(self.cylinders)) if self.cylinder_free_path is None
              else np.asarray(self.cylinder_free_path, dtype=np.float64))
        return fb, fc

    def with_objects(self, boxes: FloatArray, box_reflectivity: FloatArray,
                     cylinders: FloatArray, cylinder_reflectivity: FloatArray) -> Scene:
        """This scene with more (solid) boxes and cylinders: what a scan sees at one time
        (the moving people and cars of :mod:`solid_ros.sim.agents`)."""
        if not len(boxes) and not len(cylinders):
            return self
        porous = self.box_free_path is not None or self.cylinder_free_path is not None
        fb, fc = self.free_paths()
        return Scene(
            grid=self.grid, boxes=np.concatenate([self.boxes, np.reshape(boxes, (-1, 7))]),
            box_reflectivity=np.concatenate([self.box_reflectivity, box_reflectivity]),
            cylinders=np.concatenate([self.cylinders, np.reshape(cylinders, (-1, 5))]),
            cylinder_reflectivity=np.concatenate([self.cylinder_reflectivity,
                                                  cylinder_reflectivity]),
            box_free_path=np.r_[fb, np.zeros(len(boxes))] if porous else None,
            cylinder_free_path=np.r_[fc, np.zeros(len(cylinders))] if porous else None)

    def surface_distance(self, points: npt.ArrayLike, chunk: int = 4096,
                         ground: bool = True) -> FloatArray:
        """Distance from each world point to the nearest surface of the scene.

        Args:
            points: (N, 3+) world coordinates.
            chunk: points handled per vectorised step (bounds memory).
            ground: include the ground plane z = 0 (else only boxes and cylinders count).

        Returns:
            (N,) unsigned distances in metres.
        """
        p = np.asarray(points, dtype=np.float64)[:, :3]
        out: FloatArray = np.abs(p[:, 2]) if ground else np.full(len(p), np.inf)
        if len(p) == 0:
            return out
        lo, hi = p[:, :2].min(axis=0), p[:, :2].max(axis=0)
        centre = 0.5 * (lo + hi)
        reach = 0.5 * float(np.hypot(*(hi - lo))) + 1.0
        boxes, _, cyls, _ = self.near(float(centre[0]), float(centre[1]), reach)
        for start in range(0, len(p), chunk):
            q = p[start:start + chunk]
            d = out[start:start + chunk]
            if len(boxes):
                d = np.minimum(d, np.abs(_box_sdf(q, boxes)).min(axis=1))
            if len(cyls):
                d = np.minimum(d, np.abs(_cylinder_sdf(q, cyls)).min(axis=1))
            out[start:start + chunk] = d
        return out


def _prism_sdf(d_xy: FloatArray, z: FloatArray, z_low: FloatArray,
               z_high: FloatArray) -> FloatArray:
    """Signed distance of a vertical prism given the 2-D footprint distance ``d_xy``."""
    zc, hz = 0.5 * (z_low + z_high), 0.5 * (z_high - z_low)
    d_z = np.abs(z[:, None] - zc[None, :]) - hz[None, :]
    outside = np.hypot(np.maximum(d_xy, 0.0), np.maximum(d_z, 0.0))
    dist: FloatArray = outside + np.minimum(np.maximum(d_xy, d_z), 0.0)
    return dist


def _box_sdf(q: FloatArray, boxes: FloatArray) -> FloatArray:
    """Signed distances (N, B) from points to boxes."""
    cos, sin = np.cos(boxes[:, 4]), np.sin(boxes[:, 4])
    dx = q[:, 0:1] - boxes[None, :, 0]
    dy = q[:, 1:2] - boxes[None, :, 1]
    lx = np.abs(cos * dx + sin * dy) - boxes[None, :, 2]
    ly = np.abs(-sin * dx + cos * dy) - boxes[None, :, 3]
    d_xy = np.hypot(np.maximum(lx, 0.0), np.maximum(ly, 0.0)) + np.minimum(
        np.maximum(lx, ly), 0.0)
    return _prism_sdf(d_xy, q[:, 2], boxes[:, 5], boxes[:, 6])


def _cylinder_sdf(q: FloatArray, cyls: FloatArray) -> FloatArray:
    """Signed distances (N, C) from points to vertical cylinders."""
    d_xy = np.hypot(q[:, 0:1] - cyls[None, :, 0], q[:, 1:2] - cyls[None, :, 1]) - cyls[None, :, 2]
    return _prism_sdf(d_xy, q[:, 2], cyls[:, 3], cyls[:, 4])


def _frontage(rng: np.random.Generator, length: float,
              open_lots: float) -> list[tuple[float, float]]:
    """Split a street side of ``length`` metres into (start, width) building plots."""
    plots = []
    pos = float(rng.uniform(0.0, 6.0))
    while True:
        width = float(rng.uniform(8.0, 28.0))
        if pos + width > length:
            break
        plots.append((pos, width))
        # Mostly narrow gaps, sometimes an open lot: both make places distinctive.
        gap = rng.uniform(12.0, 30.0) if rng.random() < open_lots else rng.uniform(1.0, 8.0)
        pos += width + float(gap)
    return plots


def _side_frame(x0: float, x1: float, y0: float, y1: float,
                side: int) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Origin, along-street unit vector, inward normal and length of one side of a cell."""
    if side == 0:  # south side, facing the road below
        return np.array([x0, y0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), x1 - x0
    if side == 1:  # north
        return np.array([x0, y1]), np.array([1.0, 0.0]), np.array([0.0, -1.0]), x1 - x0
    if side == 2:  # west
        return np.array([x0, y0]), np.array([0.0, 1.0]), np.array([1.0, 0.0]), y1 - y0
    return np.array([x1, y0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), y1 - y0


def build_scene(grid: StreetGrid | None = None, seed: int = 0, style: str = 'varied',
                facade_detail: bool = False, foliage: float = 0.0) -> Scene:
    """Build a random street scene around ``grid``; the same seed gives the same scene.

    Every city block (including one ring of blocks outside the grid) gets buildings of random
    width, depth, set-back, height and occasional yaw along each of its four street sides;
    every road edge gets poles, rows of trees on some streets and parked cars.

    Args:
        grid: road layout; ``StreetGrid()`` when omitted.
        seed: seed of the numpy Generator that places everything.
        style: 'varied' (each street side its own character) or 'lookalike' (every street
            side the same character and furniture style; see the module docstring).
        facade_detail: give buildings recessed entrances, bay fronts and stepped upper floors
            (drawn from a separate random stream: the rest of the scene stays the same).
        foliage: mean free path of a ray in foliage, metres (see :attr:`Scene.cylinder_free_path`):
            above 0 the tree crowns are porous and bushes line the sidewalks (their own
            random stream); 0: solid crowns and no bushes, as before.

    Returns:
        The scene.

    Raises:
        ConfigError: unknown style, or ``foliage`` out of [0, 20].
    """
    g = grid if grid is not None else StreetGrid()
    if not 0.0 <= foliage <= 20.0:
        raise ConfigError(f'foliage: {foliage!r} is out of range; allowed [0, 20]')
    if style not in _STYLES:
        raise ConfigError(f'scene: {style!r} is not a scene style; use one of '
                          f'{", ".join(map(repr, SCENE_STYLES))}')
    st = _STYLES[style]
    rng = np.random.default_rng([seed, 0x5CE7E])
    boxes: list[list[float]] = []
    box_refl: list[float] = []
    cyls: list[list[float]] = []
    cyl_refl: list[float] = []
    fronts: list[tuple[int, float]] = []  # building row, side of its front in the box frame
    crowns: list[int] = []  # cylinder rows of the tree crowns

    for i in range(-1, g.nx):
        for j in range(-1, g.ny):
            (xa, wa), (xb, wb) = g.road_x(i), g.road_x(i + 1)
            (ya, va), (yb, vb) = g.road_y(j), g.road_y(j + 1)
            x0, x1, y0, y1 = xa + wa, xb - wb, ya + va, yb - vb
            half_depth = 0.5 * min(x1 - x0, y1 - y0)
            for side in range(4):
                origin, along, inward, length = _side_frame(x0, x1, y0, y1, side)
                # Each street side has a character (set-back, height, open lots), so streets
                # differ from each other more than buildings along one street do ('varied').
                base_setback = (rng.uniform(0.5, 9.0) if st.setback is None else st.setback)
                base_height = (np.exp(rng.uniform(np.log(5.0), np.log(25.0)))
                               if st.height is None else st.height)
                open_lots = (float(rng.uniform(0.0, 0.35)) if st.open_lots is None
                             else st.open_lots)
                # The road is on the side of -inward: which side of the box frame that is.
                front = float(np.dot(inward, [-along[1], along[0]]))
                for start, width in _frontage(rng, length, open_lots):
                    setback = base_setback + rng.uniform(0.0, st.setback_jitter)
                    depth = rng.uniform(8.0, max(9.0, min(22.0, half_depth - setback)))
                    height = float(np.clip(base_height * np.exp(rng.normal(0.0,
                                                                           st.height_sigma)),
                                           3.0, 60.0))
                    centre = origin + along * (start + 0.5 * width) + inward * (
                        setback + 0.5 * depth)
                    yaw = float(np.arctan2(along[1], along[0]))
                    if rng.random() < st.yaw_probability:
                        yaw += np.radians(rng.uniform(-10.0, 10.0))
                    fronts.append((len(boxes), front))
                    boxes.append([centre[0], centre[1], 0.5 * width, 0.5 * depth, yaw, 0.0,
                                  height])
                    box_refl.append(float(rng.uniform(0.2, 0.9)))

    # Street furniture along both edges of every road segment of the grid.
    for horizontal in (True, False):
        count, span = (g.ny, g.nx) if horizontal else (g.nx, g.ny)
        road, cross = (g.road_y, g.road_x) if horizontal else (g.road_x, g.road_y)
        for k in range(count):
            at, width = road(k)
            for seg in range(span - 1):
                (a, wa), (b, wb) = cross(seg), cross(seg + 1)
                for edge in (-1.0, 1.0):
                    _furnish(rng, horizontal, at, width, a + wa, b - wb, edge, boxes, box_refl,
                             cyls, cyl_refl, st.trees_always, crowns)

    if facade_detail:
        _add_facade_detail(np.random.default_rng([seed, 0xFACADE]), boxes, box_refl, fronts)
    free: FloatArray | None = None
    if foliage > 0.0:
        crowns += _plant_bushes(np.random.default_rng([seed, 0xB05E]), g, cyls, cyl_refl)
        free = np.zeros(len(cyls))
        free[crowns] = foliage

    return Scene(grid=g, boxes=np.asarray(boxes, dtype=np.float64).reshape(-1, 7),
                 box_reflectivity=np.asarray(box_refl, dtype=np.float64),
                 cylinders=np.asarray(cyls, dtype=np.float64).reshape(-1, 5),
                 cylinder_reflectivity=np.asarray(cyl_refl, dtype=np.float64),
                 cylinder_free_path=free)


def _plant_bushes(rng: np.random.Generator, g: StreetGrid, cyls: list[list[float]],
                  cyl_refl: list[float]) -> list[int]:
    """Bushes (0.5-1.3 m across, 0.8-2 m high) 2.5-4 m from both kerbs of every road segment,
    5-25 m apart; return their cylinder rows."""
    rows = []
    for horizontal in (True, False):
        count, span = (g.ny, g.nx) if horizontal else (g.nx, g.ny)
        road, cross = (g.road_y, g.road_x) if horizontal else (g.road_x, g.road_y)
        for k in range(count):
            at, w = road(k)
            for seg in range(span - 1):
                (a, wa), (b, wb) = cross(seg), cross(seg + 1)
                for edge in (-1.0, 1.0):
                    s = a + wa + float(rng.uniform(0.0, 10.0))
                    while s < b - wb:
                        off = at + edge * (w + float(rng.uniform(2.5, 4.0)))
                        x, y = (s, off) if horizontal else (off, s)
                        rows.append(len(cyls))
                        cyls.append([x, y, float(rng.uniform(0.5, 1.3)), 0.0,
                                     float(rng.uniform(0.8, 2.0))])
                        cyl_refl.append(float(rng.uniform(0.05, 0.3)))
                        s += float(rng.uniform(5.0, 25.0))
    return rows


def _furnish(rng: np.random.Generator, horizontal: bool, road: float, w: float,
             start: float, end: float, edge: float, boxes: list[list[float]],
             box_refl: list[float], cyls: list[list[float]], cyl_refl: list[float],
             trees_always: bool = False, crowns: list[int] | None = None) -> None:
    """Add poles, trees and parked cars along one edge (half width ``w``) of a road segment.

    Trees line the edge with probability 1/2, or always with ``trees_always``; the crowns'
    cylinder rows go to ``crowns``.
    """

    def at(s: float, offset: float) -> tuple[float, float]:
        return (s, road + edge * offset) if horizontal else (road + edge * offset, s)

    s = start + rng.uniform(0.0, 20.0)
    while s < end:  # poles (lamp posts, signs)
        x, y = at(s, w + 0.6)
        cyls.append([x, y, rng.uniform(0.1, 0.2), 0.0, rng.uniform(4.0, 9.0)])
        cyl_refl.append(float(rng.uniform(0.5, 1.0)))
        s += rng.uniform(15.0, 40.0)
    if trees_always or rng.random() < 0.5:  # a row of trees on some streets
        s = start + rng.uniform(2.0, 10.0)
        while s < end:
            x, y = at(s, w + 1.8)
            trunk = rng.uniform(2.2, 3.5)
            cyls.append([x, y, rng.uniform(0.15, 0.35), 0.0, trunk])
            if crowns is not None:
                crowns.append(len(cyls))
            cyls.append([x, y, rng.uniform(1.2, 2.8), trunk, trunk + rng.uniform(2.0, 5.0)])
            cyl_refl.extend([0.3, float(rng.uniform(0.05, 0.3))])
            s += rng.uniform(7.0, 16.0)
    s = start + rng.uniform(0.0, 15.0)
    while s < end - 5.0:  # parked cars in the kerb lane
        if rng.random() < 0.5:
            x, y = at(s, w - 1.2)
            yaw = (0.0 if horizontal else 0.5 * np.pi) + np.radians(rng.uniform(-4.0, 4.0))
            boxes.append([x, y, rng.uniform(2.0, 2.5), rng.uniform(0.85, 1.0), yaw, 0.3,
                          rng.uniform(1.3, 1.8)])
            box_refl.append(float(rng.uniform(0.3, 1.0)))
        s += rng.uniform(6.0, 12.0)


def _add_facade_detail(rng: np.random.Generator, boxes: list[list[float]],
                       box_refl: list[float], fronts: list[tuple[int, float]]) -> None:
    """Give the buildings ``fronts`` (box row, front side) relief, as more prisms.

    A building may get stepped upper floors (a lower front part, the full height set back),
    a recessed entrance (the front wall moved back except beside the door, with a lintel above
    it) and bay fronts (boxes standing out of the facade from the first floor up).
    """
    for row, side in fronts:
        body, parts = _relief(rng, boxes[row], side)
        boxes[row] = body
        boxes.extend(parts)
        box_refl.extend([box_refl[row]] * len(parts))


def _relief(rng: np.random.Generator, building: list[float],
            side: float) -> tuple[list[float], list[list[float]]]:
    """The building's main body and its added parts, in the building's frame: u along the
    street in [-hx, hx], v from the front face into the building in [0, depth]."""
    hx, height, depth = building[2], building[6], 2.0 * building[3]
    parts = []
    front_height = height
    if height > 9.0 and depth > 10.0 and rng.random() < 0.4:  # stepped upper floors
        front_height = height * float(rng.uniform(0.4, 0.7))
        back = float(rng.uniform(2.0, min(5.0, depth - 6.0)))
        parts.append(_part(building, side, (-hx, hx), (back, depth), (0.0, height)))
    body_front = 0.0
    if hx >= 4.0 and rng.random() < 0.5:  # recessed entrance with a lintel
        recess = float(rng.uniform(0.8, 1.6))
        door = float(rng.uniform(2.0, 4.0))
        u0 = float(rng.uniform(-hx + 1.0, hx - 1.0 - door))
        lintel = min(float(rng.uniform(2.6, 3.5)), front_height - 0.5)
        parts += [_part(building, side, (-hx, u0), (0.0, recess), (0.0, front_height)),
                  _part(building, side, (u0 + door, hx), (0.0, recess), (0.0, front_height)),
                  _part(building, side, (u0, u0 + door), (0.0, recess), (lintel, front_height))]
        body_front = recess
    if front_height > 6.0 and rng.random() < 0.5:  # bay fronts from the first floor up
        count = int(rng.integers(1, 4))
        slot = 2.0 * hx / count
        for k in range(count):
            width = float(rng.uniform(2.0, max(2.0, min(4.0, slot - 1.0))))
            u0 = -hx + k * slot + float(rng.uniform(0.0, max(slot - width, 0.0)))
            out = float(rng.uniform(0.5, 1.2))
            z0 = float(rng.uniform(2.8, 4.0))
            z1 = front_height - float(rng.uniform(0.0, 1.5))
            if z1 > z0 + 1.0:
                parts.append(_part(building, side, (u0, min(u0 + width, hx)), (-out, 0.0),
                                   (z0, z1)))
    body = _part(building, side, (-hx, hx), (body_front, depth), (0.0, front_height))
    return body, parts


def _part(building: list[float], side: float, u: tuple[float, float], v: tuple[float, float],
          z: tuple[float, float]) -> list[float]:
    """Box row of the part u x v x z of ``building`` (frame of :func:`_relief`); ``side`` is
    +1 or -1: the front face is at box-frame y = -side * hy."""
    cx, cy, _, hy, yaw = building[:5]
    uc, ly = 0.5 * (u[0] + u[1]), side * (0.5 * (v[0] + v[1]) - hy)
    cos, sin = float(np.cos(yaw)), float(np.sin(yaw))
    return [cx + cos * uc - sin * ly, cy + sin * uc + cos * ly, 0.5 * (u[1] - u[0]),
            0.5 * (v[1] - v[0]), yaw, z[0], z[1]]


@dataclass(frozen=True)
class Room:
    """An indoor room: interior [0, width] x [0, depth], floor z = 0, ceiling at ``height``.

    Furniture stands in a ``strip`` along each wall and on the ``island`` in the middle; the
    ``walkway`` between them, a rectangular ring, stays free for the walker.

    Attributes:
        width: interior extent along x, metres.
        depth: interior extent along y, metres.
        height: ceiling height, metres.
        strip: depth of the furniture strip along the walls, metres.
        walkway: width of the free ring between the strips and the island, metres.
    """

    width: float = 7.5
    depth: float = 6.0
    height: float = 2.7
    strip: float = 0.8
    walkway: float = 1.4

    def __post_init__(self) -> None:
        for key, value, low, high in (('width', self.width, 4.0, 30.0),
                                      ('depth', self.depth, 4.0, 30.0),
                                      ('height', self.height, 2.2, 6.0),
                                      ('strip', self.strip, 0.4, 2.0),
                                      ('walkway', self.walkway, 0.8, 3.0)):
            if not low <= value <= high:
                raise ConfigError(f'{key}: {value} is out of range; allowed [{low}, {high}]')
        if min(self.island) < 0.3:
            raise ConfigError(f'room: {self.width} x {self.depth} m leaves no island inside '
                              f'strips of {self.strip} m and a walkway of {self.walkway} m')

    @property
    def centre(self) -> tuple[float, float]:
        """The room centre (x, y)."""
        return 0.5 * self.width, 0.5 * self.depth

    @property
    def island(self) -> tuple[float, float]:
        """Half extents (x, y) of the island in the middle, metres."""
        inset = self.strip + self.walkway
        return 0.5 * self.width - inset, 0.5 * self.depth - inset


class _Props:
    """Box and cylinder rows of a room under construction, with their reflectivities."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.boxes: list[list[float]] = []
        self.box_refl: list[float] = []
        self.cyls: list[list[float]] = []
        self.cyl_refl: list[float] = []

    def box(self, cx: float, cy: float, hx: float, hy: float, yaw: float, z0: float,
            z1: float) -> None:
        self.boxes.append([cx, cy, hx, hy, yaw, z0, z1])
        self.box_refl.append(float(self.rng.uniform(0.2, 0.9)))

    def cylinder(self, cx: float, cy: float, r: float, z0: float, z1: float) -> None:
        self.cyls.append([cx, cy, r, z0, z1])
        self.cyl_refl.append(float(self.rng.uniform(0.3, 0.9)))

    def scene(self) -> Scene:
        return Scene(grid=None, boxes=np.asarray(self.boxes, dtype=np.float64).reshape(-1, 7),
                     box_reflectivity=np.asarray(self.box_refl, dtype=np.float64),
                     cylinders=np.asarray(self.cyls, dtype=np.float64).reshape(-1, 5),
                     cylinder_reflectivity=np.asarray(self.cyl_refl, dtype=np.float64))


def build_room(room: Room | None = None, seed: int = 0) -> Scene:
    """Build a furnished room; the same seed gives the same room.

    Walls (0.2 m thick) and a ceiling slab enclose the interior; two of the walls have a door
    opening onto a short corridor behind them. Each wall's strip holds its own run of shelves
    (boards at several heights, things on them), cabinets, stacks of boxes, pillars and
    partition stubs, with wall-hung cabinets and radiators above and below them; the
    island holds a table with monitors, boxes and clutter on it, chairs around it and maybe a
    pillar. Nothing stands in the walkway.

    Args:
        room: room size, strips and walkway; ``Room()`` when omitted.
        seed: seed of the numpy Generator that places the doors and the furniture.

    Returns:
        The scene (its ``grid`` is None).
    """
    rm = room if room is not None else Room()
    p = _Props(np.random.default_rng([seed, 0x2003]))
    doors = set(p.rng.choice(4, size=2, replace=False).tolist())
    for side in range(4):
        _wall(p, rm, side, side in doors)
    t = 0.2
    reach = 2.5  # the ceiling also covers the corridors
    p.box(0.5 * rm.width, 0.5 * rm.depth, 0.5 * rm.width + reach, 0.5 * rm.depth + reach, 0.0,
          rm.height, rm.height + t)
    for side in range(4):
        _furnish_strip(p, rm, side)
    _furnish_island(p, rm)
    return p.scene()


def _wall_length(rm: Room, side: int) -> float:
    return rm.width if side < 2 else rm.depth


def _wall_box(p: _Props, rm: Room, side: int, u0: float, u1: float, v0: float, v1: float,
              z0: float, z1: float) -> None:
    """A box spanning u in [u0, u1] along wall ``side`` (0 south, 1 north, 2 west, 3 east;
    u counter-clockwise seen from inside) and v in [v0, v1] from the wall into the room
    (negative: behind the wall)."""
    w, d = rm.width, rm.depth
    uc, vc = 0.5 * (u0 + u1), 0.5 * (v0 + v1)
    hu, hv = 0.5 * (u1 - u0), 0.5 * (v1 - v0)
    if side == 0:  # y = 0, u along +x
        p.box(uc, vc, hu, hv, 0.0, z0, z1)
    elif side == 1:  # y = depth, u along -x
        p.box(w - uc, d - vc, hu, hv, 0.0, z0, z1)
    elif side == 2:  # x = 0, u along -y
        p.box(vc, d - uc, hv, hu, 0.0, z0, z1)
    else:  # x = width, u along +y
        p.box(w - vc, uc, hv, hu, 0.0, z0, z1)


def _wall(p: _Props, rm: Room, side: int, door: bool) -> None:
    """Wall ``side`` (0.2 m thick, behind the interior); with ``door`` an opening onto a
    corridor 1.2-2 m deep behind it."""
    length, t, h = _wall_length(rm, side), 0.2, rm.height
    if not door:
        _wall_box(p, rm, side, -t, length + t, -t, 0.0, 0.0, h)
        return
    rng = p.rng
    width = float(rng.uniform(0.9, 1.3))
    u0 = float(rng.uniform(0.6, length - 0.6 - width))
    _wall_box(p, rm, side, -t, u0, -t, 0.0, 0.0, h)
    _wall_box(p, rm, side, u0 + width, length + t, -t, 0.0, 0.0, h)
    _wall_box(p, rm, side, u0, u0 + width, -t, 0.0, 2.05, h)  # lintel
    deep = float(rng.uniform(1.2, 2.0))
    _wall_box(p, rm, side, -t, length + t, -deep - t, -deep, 0.0, h)  # the corridor's far wall
    for u in (-t, length):  # its ends
        _wall_box(p, rm, side, u, u + t, -deep, -t, 0.0, h)


def _furnish_strip(p: _Props, rm: Room, side: int) -> None:
    """Shelves, cabinets, box stacks, pillars and partition stubs along one wall's strip, and
    wall-hung cabinets and radiators on the wall above and below them."""
    rng = p.rng
    length = _wall_length(rm, side)
    pos = float(rng.uniform(0.0, 0.3))
    while pos < length - 0.5:
        width = float(rng.uniform(0.5, 1.8))
        if pos + width > length:
            break
        kind = rng.random()
        depth = float(rng.uniform(0.3, rm.strip - 0.2))
        if kind < 0.3:
            _shelf(p, rm, side, pos, width, depth)
        elif kind < 0.5:  # cabinet
            _wall_box(p, rm, side, pos, pos + width, 0.0, depth, 0.0,
                      float(rng.uniform(0.7, 1.3)))
        elif kind < 0.75:  # a stack of boxes
            z = 0.0
            for _ in range(int(rng.integers(1, 4))):
                bw, bh = float(rng.uniform(0.3, min(0.8, width))), float(rng.uniform(0.2, 0.5))
                u0 = pos + float(rng.uniform(0.0, width - bw))
                _wall_box(p, rm, side, u0, u0 + bw, float(rng.uniform(0.0, 0.1)),
                          float(rng.uniform(0.25, depth)), z, z + bh)
                z += bh
        elif kind < 0.87:  # a pillar standing off the wall
            r = float(rng.uniform(0.12, 0.25))
            u, v = pos + 0.5 * width, float(rng.uniform(r, rm.strip - r))
            _wall_box(p, rm, side, u - r, u + r, v - r, v + r, 0.0, rm.height)
        else:  # a partition stub reaching across the strip
            u = pos + float(rng.uniform(0.0, width - 0.15))
            _wall_box(p, rm, side, u, u + float(rng.uniform(0.08, 0.15)), 0.0,
                      rm.strip - float(rng.uniform(0.0, 0.1)), 0.0,
                      float(rng.uniform(1.8, rm.height)))
        pos += width + float(rng.uniform(0.05, 0.5))
    for _ in range(int(rng.integers(1, 4))):  # wall-hung cabinets and radiators
        width = float(rng.uniform(0.6, 1.6))
        u0 = float(rng.uniform(0.0, length - width))
        if rng.random() < 0.6:
            z0 = float(rng.uniform(1.5, rm.height - 0.8))
            _wall_box(p, rm, side, u0, u0 + width, 0.0, float(rng.uniform(0.25, 0.4)), z0,
                      z0 + float(rng.uniform(0.4, 0.7)))
        else:
            _wall_box(p, rm, side, u0, u0 + width, 0.0, 0.1, 0.15, 0.75)


def _shelf(p: _Props, rm: Room, side: int, pos: float, width: float, depth: float) -> None:
    """An open shelf: back panel, sides, boards at several heights, things on the boards."""
    rng = p.rng
    top = float(rng.uniform(1.6, min(2.3, rm.height - 0.1)))
    heights = np.linspace(0.05, top - 0.03, int(rng.integers(3, 6))).tolist()
    _wall_box(p, rm, side, pos, pos + width, 0.0, 0.02, 0.0, top)
    for z in heights:
        _wall_box(p, rm, side, pos, pos + width, 0.02, depth, z, z + 0.03)
    for u in (pos, pos + width - 0.03):
        _wall_box(p, rm, side, u, u + 0.03, 0.0, depth, 0.0, top)
    for _ in range(int(rng.integers(1, 5))):
        u0 = pos + float(rng.uniform(0.05, max(width - 0.35, 0.06)))
        z0 = heights[int(rng.integers(0, len(heights) - 1))] + 0.03
        _wall_box(p, rm, side, u0, u0 + float(rng.uniform(0.1, 0.3)), 0.05,
                  float(rng.uniform(0.15, depth)), z0, z0 + float(rng.uniform(0.1, 0.3)))


def _furnish_island(p: _Props, rm: Room) -> None:
    """A table with things on it, chairs around it and maybe a pillar, inside the island."""
    rng = p.rng
    cx, cy = rm.centre
    ix, iy = rm.island
    hx = float(rng.uniform(0.6, 0.9)) * ix
    hy = float(rng.uniform(0.5, 0.7)) * iy
    top = float(rng.uniform(0.72, 0.78))
    p.box(cx, cy, hx, hy, 0.0, top - 0.04, top)  # table top
    for su in (-1.0, 1.0):  # legs
        for sv in (-1.0, 1.0):
            p.cylinder(cx + su * (hx - 0.06), cy + sv * (hy - 0.06), 0.03, 0.0, top - 0.04)
    for _ in range(int(rng.integers(3, 8))):  # monitors, boxes, clutter on the table
        bx, by = float(rng.uniform(0.05, 0.35)), float(rng.uniform(0.03, 0.25))
        u = float(rng.uniform(-hx + bx, hx - bx))
        v = float(rng.uniform(-hy + by, hy - by))
        p.box(cx + u, cy + v, bx, by, float(rng.uniform(-0.5, 0.5)), top,
              top + float(rng.uniform(0.05, 0.5)))
    room_y = iy - hy  # chairs stand between the table and the walkway
    if room_y >= 0.35:
        for _ in range(int(rng.integers(2, 5))):
            sv = float(rng.choice([-1.0, 1.0]))
            u = float(rng.uniform(-hx + 0.25, hx - 0.25))
            v = sv * (hy + min(0.22, room_y - 0.25))
            p.box(cx + u, cy + v, 0.22, 0.2, 0.0, 0.42, 0.47)
            p.box(cx + u, cy + v + sv * 0.17, 0.22, 0.03, 0.0, 0.47, 0.95)
    if ix - hx >= 0.4 and rng.random() < 0.7:  # a pillar at one end of the table
        end = float(rng.choice([-1.0, 1.0]))
        r = min(float(rng.uniform(0.15, 0.25)), 0.5 * (ix - hx) - 0.05)
        p.cylinder(cx + end * (hx + 0.5 * (ix - hx)), cy, r, 0.0, rm.height)
