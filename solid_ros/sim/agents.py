"""People and cars that move between scans: the scene a scan sees depends on its time.

Real recordings are not static: people walk past, cars drive by, and a place revisited minutes
later has them elsewhere. Each agent here goes round a closed rectangular path at constant
speed (people on a block's sidewalk or a room's walkway, cars round a block in the right-hand
lane) and comes and goes (a person enters a building or leaves the room, a car parks): it is
present for a share of a cycle of its own. Where an agent is at time ``t`` is a function of
``t`` and the seed alone, so any scan can be made on its own and the same seed gives the same
scans.

An agent is a vertical prism the ray caster hits like the static scene: a person a cylinder,
a car a box along its path. :meth:`Agents.objects` gives the prisms at a time, leaving out
those that would stand where the sensor is (its carrier steps round them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import ConfigError
from solid_ros.sim.scene import Room, StreetGrid

__all__ = ['Agents', 'room_agents', 'street_agents']

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

WALK_SPEED = 1.4  # m/s, a person's usual pace
# Nothing stands closer than this to the sensor (beyond the agent's own extent), metres.
CLEARANCE_M = 0.6


@dataclass(frozen=True)
class Agents:
    """Agents going round closed rectangular paths, each its own speed, phase and presence.

    Attributes:
        corners: (N, 4, 2) each path's corners in walking order (it closes back to the first).
        speed: (N,) m/s along the path.
        phase: (N,) metres along the path at t = 0.
        person: (N,) True: a cylinder of radius ``size[:, 0]``; False: a car, a box of half
            length ``size[:, 0]`` and half width ``size[:, 1]`` along its path.
        size: (N, 2) radius or half length, and half width.
        z: (N, 2) bottom and top height, metres.
        reflectivity: (N,) intensity the agent returns.
        cycle: (N,) seconds of one come-and-go cycle (inf: always present).
        present: (N,) share of its cycle the agent is present.
        offset: (N,) seconds into its cycle at t = 0.
    """

    corners: FloatArray
    speed: FloatArray
    phase: FloatArray
    person: BoolArray
    size: FloatArray
    z: FloatArray
    reflectivity: FloatArray
    cycle: FloatArray
    present: FloatArray
    offset: FloatArray

    def __len__(self) -> int:
        return len(self.speed)

    def poses(self, t: float) -> tuple[FloatArray, FloatArray]:
        """Positions (N, 2) and headings (N,) of all agents at time ``t``, seconds."""
        if not len(self):
            return np.zeros((0, 2)), np.zeros(0)
        closed = np.concatenate([self.corners, self.corners[:, :1]], axis=1)  # (N, 5, 2)
        legs = np.diff(closed, axis=1)  # (N, 4, 2)
        length = np.hypot(legs[..., 0], legs[..., 1])
        ends = np.cumsum(length, axis=1)  # (N, 4)
        s = np.mod(self.phase + self.speed * t, ends[:, -1])
        leg = np.minimum((s[:, None] >= ends).sum(axis=1), 3)
        rows = np.arange(len(self))
        into = s - (ends[rows, leg] - length[rows, leg])
        along = legs[rows, leg] / np.maximum(length[rows, leg], 1e-12)[:, None]
        xy: FloatArray = closed[rows, leg] + into[:, None] * along
        yaw: FloatArray = np.arctan2(along[:, 1], along[:, 0])
        return xy, yaw

    def here(self, t: float) -> BoolArray:
        """Which agents are present at time ``t`` (the others are away)."""
        with np.errstate(invalid='ignore'):
            frac = np.mod(t + self.offset, self.cycle) / self.cycle
        out: BoolArray = ~np.isfinite(self.cycle) | (frac < self.present)
        return out

    def objects(self, t: float, x: float | None = None, y: float | None = None
                ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The prisms of the agents present at time ``t``, as scene rows.

        Args:
            t: time, seconds.
            x: sensor x; with ``y``, agents within :data:`CLEARANCE_M` of it are left out.
            y: sensor y.

        Returns:
            Boxes (B, 7), their reflectivities, cylinders (C, 5), their reflectivities (the
            rows of :class:`~solid_ros.sim.scene.Scene`).
        """
        xy, yaw = self.poses(t)
        keep = self.here(t)
        if x is not None and y is not None:
            reach = np.hypot(self.size[:, 0], self.size[:, 1])
            keep &= np.hypot(xy[:, 0] - x, xy[:, 1] - y) - reach > CLEARANCE_M
        cyl, box = keep & self.person, keep & ~self.person
        cyls = np.c_[xy[cyl], self.size[cyl, 0], self.z[cyl]]
        boxes = np.c_[xy[box], self.size[box], yaw[box], self.z[box]]
        return (boxes.reshape(-1, 7), self.reflectivity[box], cyls.reshape(-1, 5),
                self.reflectivity[cyl])


def _rectangle(x0: float, x1: float, y0: float, y1: float, clockwise: bool) -> FloatArray:
    """Corners of an axis-aligned rectangle, counter-clockwise unless ``clockwise``."""
    out = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
    return out[::-1].copy() if clockwise else out


def _people(rng: np.random.Generator, paths: list[FloatArray], cycle: tuple[float, float],
            present: tuple[float, float]) -> Agents:
    """People walking ``paths`` at about :data:`WALK_SPEED`, either way round."""
    n = len(paths)
    speed = np.clip(rng.normal(WALK_SPEED, 0.15, n), 0.8, 2.0)
    return Agents(
        corners=np.asarray(paths, dtype=np.float64).reshape(n, 4, 2),
        speed=speed * rng.choice([-1.0, 1.0], n), phase=rng.uniform(0.0, 1000.0, n),
        person=np.ones(n, dtype=bool), size=np.repeat(rng.uniform(0.2, 0.28, n)[:, None], 2, 1),
        z=np.c_[np.zeros(n), rng.uniform(1.55, 1.9, n)], reflectivity=rng.uniform(0.1, 0.5, n),
        cycle=rng.uniform(*cycle, n), present=rng.uniform(*present, n),
        offset=rng.uniform(0.0, cycle[1], n))


def _cars(rng: np.random.Generator, paths: list[FloatArray]) -> Agents:
    """Cars driving ``paths`` (already in their direction of travel) at 5-10 m/s."""
    n = len(paths)
    return Agents(
        corners=np.asarray(paths, dtype=np.float64).reshape(n, 4, 2),
        speed=rng.uniform(5.0, 10.0, n), phase=rng.uniform(0.0, 1000.0, n),
        person=np.zeros(n, dtype=bool), size=np.c_[rng.uniform(2.0, 2.5, n),
                                                   rng.uniform(0.85, 1.0, n)],
        z=np.c_[np.full(n, 0.3), rng.uniform(1.4, 1.9, n)],
        reflectivity=rng.uniform(0.3, 1.0, n), cycle=rng.uniform(60.0, 300.0, n),
        present=rng.uniform(0.5, 0.9, n), offset=rng.uniform(0.0, 300.0, n))


def _join(parts: list[Agents]) -> Agents:
    """All agents of ``parts`` as one set."""
    names = Agents.__dataclass_fields__
    return Agents(**{k: np.concatenate([getattr(p, k) for p in parts]) for k in names})


def street_agents(grid: StreetGrid, seed: int = 0, people: float = 0.0,
                  cars: float = 0.0) -> Agents:
    """People on the sidewalks and cars on the roads of ``grid``.

    Each block (the grid's cells and the ring of blocks round it) gets a Poisson number of
    people (mean ``people``), each walking round the block 0.8-2.5 m from the kerb, and of cars
    (mean ``cars``), each driving round it clockwise (right-hand traffic, the block on its
    right) 1.6-3 m from the road's centre line. People come and go over a few minutes (away
    10-50 % of the time: into a building, out of sight), cars too (parked, gone elsewhere).

    Args:
        grid: the road layout.
        seed: seed of the agents (its own stream: the scene stays the same).
        people: mean number of people per block, >= 0.
        cars: mean number of cars per block, >= 0.

    Raises:
        ConfigError: a negative count.
    """
    if not (people >= 0.0 and cars >= 0.0):
        raise ConfigError(f'people, cars: expected >= 0, got {people}, {cars}')
    rng = np.random.default_rng([seed, 0xA6E47])
    walks: list[FloatArray] = []
    drives: list[FloatArray] = []
    for i in range(-1, grid.nx):
        for j in range(-1, grid.ny):
            (xa, wa), (xb, wb) = grid.road_x(i), grid.road_x(i + 1)
            (ya, va), (yb, vb) = grid.road_y(j), grid.road_y(j + 1)
            for _ in range(int(rng.poisson(people))):
                d = float(rng.uniform(0.8, 2.5))
                walks.append(_rectangle(xa + wa + d, xb - wb - d, ya + va + d, yb - vb - d,
                                        False))
            for _ in range(int(rng.poisson(cars))):
                off = float(rng.uniform(1.6, 3.0))
                drives.append(_rectangle(xa + off, xb - off, ya + off, yb - off, True))
    return _join([_people(rng, walks, (120.0, 600.0), (0.5, 0.9)), _cars(rng, drives)])


def room_agents(room: Room, seed: int = 0, people: int = 0) -> Agents:
    """``people`` people walking round the room's walkway, coming and going through its doors.

    Each walks a rectangle 0.35 m or more inside the walkway's edges, either way round, at
    about :data:`WALK_SPEED`, and is in the room for 60-90 % of a cycle of 20-60 s.

    Raises:
        ConfigError: ``people`` out of [0, 50].
    """
    if not 0 <= people <= 50:
        raise ConfigError(f'people: {people!r} is out of range; allowed [0, 50]')
    rng = np.random.default_rng([seed, 0xA6E47, 1])
    walks = []
    for _ in range(people):
        inset = room.strip + float(rng.uniform(0.35, max(room.walkway - 0.35, 0.35)))
        walks.append(_rectangle(inset, room.width - inset, inset, room.depth - inset, False))
    return _people(rng, walks, (20.0, 60.0), (0.6, 0.9))
