"""Drives through the street grid, with ground-truth revisit labels.

Routes are grid crossings as (column, row) indices. The default route, 'revisits', first
drives one loop, then returns to stretches of it in the same direction, crosses earlier
crossings from other streets, and ends by driving two earlier blocks in the reverse direction.
'no_revisit' is a serpentine that drives every row of a larger grid once, alternately east and
west, and never comes back to a place: every scan is new (for false-positive rates). Every
road segment gets its own lane offset and a gentle weave, and the heading carries a small
smooth jitter, so a revisit is never the same pose twice: the sensor is metres to the side and
degrees off.

:func:`handheld_walk` walks a room (:class:`solid_ros.sim.scene.Room`) instead: laps around its
centre inside the free walking band, a different line and a look-around sway of the heading
on each lap, the last lap the other way round; optionally the hand's roll and pitch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import ConfigError
from solid_ros.sim.scene import Room, StreetGrid

__all__ = ['DEFAULT_ROUTE', 'LABELS', 'NO_REVISIT_ROUTE', 'ROUTES', 'Route', 'Trajectory',
           'build_trajectory', 'handheld_walk', 'resolve_route', 'revisit_labels', 'route_grid',
           'serpentine']

FloatArray = npt.NDArray[np.float64]

Route = tuple[tuple[int, int], ...]

# Needs a grid of at least 4 x 3 roads.
DEFAULT_ROUTE: Route = (
    (0, 0), (2, 0), (2, 1), (0, 1), (0, 0),  # first loop: everything new
    (1, 0),  # same direction as the loop
    (1, 1),  # new street, reaching a crossing of the loop from the south
    (1, 2), (0, 2), (0, 1),  # new, reaching a loop crossing from the north
    (0, 0), (2, 0),  # same direction again
    (3, 0), (3, 1), (2, 1),  # new
    (1, 1),  # same direction
    (1, 0), (0, 0),  # reverse: earlier blocks driven the other way
)



def serpentine(nx: int, ny: int) -> Route:
    """Every east-west road of an ``nx`` x ``ny`` grid once, alternately east and west, joined
    at the ends by one block of the outermost north-south roads: no road piece twice."""
    if nx < 2 or ny < 1:
        raise ConfigError(f'serpentine: needs nx >= 2 and ny >= 1, got {nx}, {ny}')
    route: list[tuple[int, int]] = []
    for j in range(ny):
        first, last = (0, nx - 1) if j % 2 == 0 else (nx - 1, 0)
        route += [(first, j), (last, j)]
    return tuple(route)


# 6 rows of 6 blocks plus 5 joining blocks: 41 blocks, about 2 km at 50 m blocks (3.3 km at
# 80 m). Neighbouring rows are at least 0.6 blocks apart (road jitter), far beyond any
# revisit radius.
NO_REVISIT_ROUTE: Route = serpentine(7, 6)

ROUTES: dict[str, Route] = {'revisits': DEFAULT_ROUTE, 'no_revisit': NO_REVISIT_ROUTE}

LABELS = ('new', 'same', 'cross', 'reverse')


def resolve_route(route: str | Sequence[Sequence[int]]) -> Route:
    """Return the crossings of a named route (see :data:`ROUTES`) or a custom one.

    Raises:
        ConfigError: unknown name, fewer than two crossings, or a crossing that is not two
            non-negative integers. (Steps along one road are checked by
            :func:`build_trajectory`, which knows the grid.)
    """
    if isinstance(route, str):
        try:
            return ROUTES[route]
        except KeyError as err:
            raise ConfigError(f'route: {route!r} is not a route; use one of '
                              f'{", ".join(map(repr, ROUTES))} or a tuple of (column, row) '
                              'crossings') from err
    out: list[tuple[int, int]] = []
    try:
        for c in route:
            i, j = c
            if any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0
                   for v in (i, j)):
                raise ValueError
            out.append((int(i), int(j)))
    except (TypeError, ValueError) as err:
        raise ConfigError(f'route: expected a route name or (column, row) pairs of '
                          f'non-negative integers, got {route!r}') from err
    if len(out) < 2:
        raise ConfigError('route: needs at least two crossings')
    return tuple(out)


def route_grid(route: Route) -> tuple[int, int]:
    """The smallest grid (nx, ny) that holds ``route`` (at least 2 x 2)."""
    return max(2, max(i for i, _ in route) + 1), max(2, max(j for _, j in route) + 1)

_STEP = 0.25  # metres between samples of the fine path


@dataclass(frozen=True)
class Trajectory:
    """Planar sensor poses along the route, one per scan.

    Attributes:
        xy: (N, 2) sensor positions in the world, metres.
        yaw: (N,) sensor headings, radians CCW from world +x.
        distance: (N,) distance driven so far, metres.
        label: (N,) per scan 'new', 'same' (an earlier place, similar heading), 'cross'
            (an earlier place, heading differs by 45-135 degrees) or 'reverse'.
        revisit_of: (N,) index of the nearest earlier scan of the same place, -1 for 'new'.
        roll: (N,) sensor roll, radians (a handheld sensor's tilt; None: level).
        pitch: (N,) sensor pitch, radians (None: level).
    """

    xy: FloatArray
    yaw: FloatArray
    distance: FloatArray
    label: npt.NDArray[np.str_]
    revisit_of: npt.NDArray[np.int64]
    roll: FloatArray | None = None
    pitch: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.yaw)


def _smooth(values: FloatArray, window: int) -> FloatArray:
    """Moving average along axis 0 with edge padding (keeps the length)."""
    if window <= 1:
        return values
    pad = window // 2
    padded = np.concatenate([np.repeat(values[:1], pad, axis=0), values,
                             np.repeat(values[-1:], window - 1 - pad, axis=0)])
    csum = np.cumsum(padded, axis=0)
    csum = np.concatenate([np.zeros_like(csum[:1]), csum])
    out: FloatArray = (csum[window:] - csum[:-window]) / window
    return out


def build_trajectory(grid: StreetGrid, seed: int = 0, spacing: float = 2.0,
                     route: Route = DEFAULT_ROUTE,
                     revisit_radius: float = 6.0, exclude_distance: float = 60.0) -> Trajectory:
    """Sample sensor poses every ``spacing`` metres along ``route``.

    Args:
        grid: road layout the route's crossing indices refer to.
        seed: seed of the lane offsets, weave and heading jitter.
        spacing: distance between scans, metres.
        route: crossings to drive through, as (column, row) indices; consecutive crossings
            share a column or a row.
        revisit_radius: a scan revisits an earlier one closer than this, metres.
        exclude_distance: earlier scans driven less than this many metres before do not count
            as revisits (they are just the previous scans).

    Returns:
        The trajectory with its revisit labels.

    Raises:
        ConfigError: the route leaves the grid or has a diagonal step, or a value is out of
            range.
    """
    if not 0.25 <= spacing <= 50.0:
        raise ConfigError(f'spacing: {spacing} is out of range; allowed [0.25, 50]')
    if len(route) < 2:
        raise ConfigError('route: needs at least two crossings')
    for (i0, j0), (i1, j1) in zip(route[:-1], route[1:]):
        if not (0 <= i1 < grid.nx and 0 <= j1 < grid.ny and 0 <= i0 < grid.nx
                and 0 <= j0 < grid.ny):
            raise ConfigError(f'route: crossing {(i1, j1)} or {(i0, j0)} is outside the '
                              f'{grid.nx} x {grid.ny} grid')
        if (i0 != i1) == (j0 != j1):
            raise ConfigError(f'route: step {(i0, j0)} -> {(i1, j1)} is not along one road')
    rng = np.random.default_rng([seed, 0x7AC])

    # Fine centre line, one sample every _STEP metres, with the segment index of each sample.
    pieces: list[npt.NDArray[np.float64]] = []
    seg_ids: list[npt.NDArray[np.int64]] = []
    for k, (a, b) in enumerate(zip(route[:-1], route[1:])):
        p0, p1 = np.array(grid.node(*a)), np.array(grid.node(*b))
        n = max(int(round(np.linalg.norm(p1 - p0) / _STEP)), 1)
        t = np.arange(n) / n
        pieces.append(p0 + t[:, None] * (p1 - p0))
        seg_ids.append(np.full(n, k))
    pieces.append(np.array([grid.node(*route[-1])]))
    seg_ids.append(np.array([len(route) - 2]))
    centre = np.concatenate(pieces)
    seg = np.concatenate(seg_ids)

    # Round the corners (turn radius of a few metres) and derive the driving direction.
    window = int(round(10.0 / _STEP))
    centre = _smooth(centre, window)
    tangent = np.gradient(centre, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    left = np.c_[-tangent[:, 1], tangent[:, 0]]
    s_fine = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(centre, axis=0), axis=1))]

    # Per segment: right-hand lane offset, weave amplitude, wavelength and phase.
    n_seg = len(route) - 1
    lane = rng.uniform(1.0, 3.0, n_seg)
    amp = rng.uniform(0.0, 0.8, n_seg)
    wavelength = rng.uniform(30.0, 70.0, n_seg)
    phase = rng.uniform(0.0, 2.0 * np.pi, n_seg)
    lateral = -lane[seg] + amp[seg] * np.sin(2.0 * np.pi * s_fine / wavelength[seg] + phase[seg])
    lateral = _smooth(lateral, window)
    xy_fine = centre + lateral[:, None] * left
    step = np.gradient(xy_fine, axis=0)
    heading = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
    # Smooth heading jitter of a couple of degrees (vehicle not aligned with its path).
    heading = heading + _sway(rng, len(heading), int(round(15.0 / _STEP)), 2.5)
    return _sample(xy_fine, heading, s_fine, spacing, revisit_radius, exclude_distance)


def _sway(rng: np.random.Generator, n: int, window: int, std_deg: float) -> FloatArray:
    """Smooth random heading offsets, radians, scaled to a standard deviation of ``std_deg``."""
    sway = _smooth(rng.normal(0.0, 1.0, n), window)
    sway *= np.radians(std_deg) / max(float(np.std(sway)), 1e-12)
    return sway


def _sample(path: FloatArray, heading: FloatArray, s_fine: FloatArray, spacing: float,
            revisit_radius: float, exclude_distance: float) -> Trajectory:
    """A pose every ``spacing`` metres along a fine path, with its revisit labels."""
    take = np.searchsorted(s_fine, np.arange(0.0, s_fine[-1], spacing))
    xy = path[take]
    yaw = np.angle(np.exp(1j * heading[take]))
    distance = s_fine[take]
    label, revisit_of = revisit_labels(xy, yaw, distance, revisit_radius, exclude_distance)
    return Trajectory(xy=xy, yaw=yaw, distance=distance, label=label, revisit_of=revisit_of)


def revisit_labels(xy: FloatArray, yaw: FloatArray, distance: FloatArray,
                   radius: float = 6.0, exclude_distance: float = 60.0
                   ) -> tuple[npt.NDArray[np.str_], npt.NDArray[np.int64]]:
    """Label each pose by its nearest earlier pose of the same place.

    Args:
        xy: (N, 2) positions.
        yaw: (N,) headings, radians.
        distance: (N,) distance driven, metres (non-decreasing).
        radius: places closer than this are the same place, metres.
        exclude_distance: earlier poses within this driven distance are ignored, metres.

    Returns:
        Labels ('new', 'same', 'cross', 'reverse') and the index of the matched earlier pose
        (-1 for 'new').
    """
    n = len(xy)
    label = np.full(n, 'new', dtype='<U7')
    match = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        earlier = int(np.searchsorted(distance, distance[i] - exclude_distance, side='right'))
        if earlier == 0:
            continue
        d = np.hypot(*(xy[:earlier] - xy[i]).T)
        j = int(np.argmin(d))
        if d[j] >= radius:
            continue
        turn = abs(float(np.angle(np.exp(1j * (yaw[i] - yaw[j])))))
        match[i] = j
        label[i] = ('same' if turn <= np.radians(45.0) else
                    'reverse' if turn >= np.radians(135.0) else 'cross')
    return label, match


def handheld_walk(room: Room, seed: int = 0, laps: int = 3, spacing: float = 0.25,
                  sway_deg: float = 30.0, revisit_radius: float = 1.5,
                  exclude_distance: float = 8.0, tilt_deg: float = 0.0) -> Trajectory:
    """Walk laps around the centre of ``room``, a scan every ``spacing`` metres.

    Each lap follows a rounded rectangle (a superellipse) along the room's walkway, straying
    from its centre line by different amounts along the lap and from lap to lap; the heading
    follows the path plus a smooth look-around sway (standard deviation ``sway_deg``), as a
    person carrying the sensor looks around. The last lap goes the other way round (reverse
    revisits); the first laps revisit each other in the same direction, never on the same
    line nor with the same heading.

    Args:
        room: the room (its walkway).
        seed: seed of the lines and the sway.
        laps: number of laps (at least 2).
        spacing: distance between scans, metres.
        sway_deg: standard deviation of the heading's sway about the path, degrees.
        revisit_radius: a scan revisits an earlier one closer than this, metres.
        exclude_distance: earlier scans walked less than this many metres before do not count
            as revisits.
        tilt_deg: standard deviation of the hand's roll and pitch, degrees (0: the sensor is
            held level); they wander smoothly from scan to scan, as a carried sensor does.

    Raises:
        ConfigError: a value out of range.
    """
    if not 2 <= laps <= 20:
        raise ConfigError(f'laps: {laps} is out of range; allowed [2, 20]')
    if not 0.05 <= spacing <= 2.0:
        raise ConfigError(f'spacing: {spacing} is out of range; allowed [0.05, 2]')
    if not 0.0 <= sway_deg <= 90.0:
        raise ConfigError(f'sway_deg: {sway_deg} is out of range; allowed [0, 90]')
    if not 0.0 <= tilt_deg <= 30.0:
        raise ConfigError(f'tilt_deg: {tilt_deg} is out of range; allowed [0, 30]')
    rng = np.random.default_rng([seed, 0x4A1C])
    cx, cy = room.centre
    # Half axes of the walkway's centre line, and how far a lap may stray from it.
    inset = room.strip + 0.5 * room.walkway
    half = np.array([0.5 * room.width - inset, 0.5 * room.depth - inset])
    stray = 0.5 * room.walkway - 0.3
    theta = np.linspace(0.0, 2.0 * np.pi, 721)[:-1]
    pieces = []
    for lap in range(laps):
        offset = float(rng.uniform(-0.6, 0.6))
        wave = float(rng.uniform(0.2, 0.4))
        phase = float(rng.uniform(0.0, 2.0 * np.pi))
        out = stray * np.clip(offset + wave * np.sin(2.0 * theta + phase), -1.0, 1.0)
        c, s = np.cos(theta), np.sin(theta)
        # Superellipse of exponent 4: a rectangle with rounded corners.
        loop = np.c_[np.sign(c) * np.abs(c) ** 0.5 * (half[0] + out),
                     np.sign(s) * np.abs(s) ** 0.5 * (half[1] + out)]
        pieces.append(loop if lap < laps - 1 else loop[::-1])
    path = np.concatenate(pieces) + [cx, cy]
    s_fine = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
    step = np.gradient(path, axis=0)
    heading = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
    heading = _smooth(heading, 9) + _sway(rng, len(heading), 60, sway_deg)
    walk = _sample(path, heading, s_fine, spacing, revisit_radius, exclude_distance)
    if tilt_deg > 0.0:
        # Their own stream: the same seed walks the same path at any tilt.
        hand = np.random.default_rng([seed, 0x711])
        walk = replace(walk, roll=_sway(hand, len(walk), 5, tilt_deg),
                       pitch=_sway(hand, len(walk), 5, tilt_deg))
    return walk
