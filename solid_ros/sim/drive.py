"""The simulated drive: scene + sensor + trajectory, yielding scans with reference poses."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import ConfigError
from solid_ros.sim.agents import Agents, street_agents
from solid_ros.sim.lidar import LidarModel, cast_scan, sensor_model
from solid_ros.sim.odometry import OdometryDrift, drift_planar
from solid_ros.sim.scene import LOOKALIKE_JITTER, SCENE_STYLES, Scene, StreetGrid, build_scene
from solid_ros.sim.trajectory import (
    DEFAULT_ROUTE,
    Route,
    Trajectory,
    build_trajectory,
    resolve_route,
    route_grid,
)

__all__ = ['Drive', 'DriveConfig', 'SimScan', 'pose_matrix', 'simulate']

# 2023-11-14T22:13:20Z: bag stamps look like a real recording.
START_NS = 1_700_000_000_000_000_000

# Options added after the first cached demo bags, with the value that reproduces those drives:
# at that value they stay out of the cache key, so an existing cache entry keeps its name.
_KEY_DEFAULTS: dict[str, Any] = {'scene': 'varied', 'facade_detail': False, 'people': 0.0,
                                 'cars': 0.0, 'foliage': 0.0}
_SENSOR_KEY_DEFAULTS: dict[str, Any] = {'mount_roll_deg': 0.0, 'mount_pitch_deg': 0.0,
                                        'edge_mixing': 0.0, 'non_repetitive': False}
# Already in the key as the sensor model's effective tilt.
_KEY_OMITTED = ('mount_roll_deg', 'mount_pitch_deg')
# The odometry's error model; the drives made before it had perfect odometry, which leaves the
# whole model out of the key (a drifting odometry changes the bag's /odom: another entry).
_ODOM_KEYS = ('perfect_odometry', 'odom_scale_error', 'odom_heading_bias_deg_per_m',
              'odom_heading_walk_deg', 'odom_position_walk_m')
_WORLD_RANGES = {'people': (0.0, 50.0), 'cars': (0.0, 20.0), 'foliage': (0.0, 20.0)}
_ODOM_RANGES = {'odom_scale_error': (-0.5, 0.5), 'odom_heading_bias_deg_per_m': (-10.0, 10.0),
                'odom_heading_walk_deg': (0.0, 10.0), 'odom_position_walk_m': (0.0, 10.0)}


@dataclass(frozen=True)
class DriveConfig:
    """Everything that determines a simulated drive (same config, same scans).

    Attributes:
        seed: seed of the scene, the route's lane offsets and the sensor noise.
        sensor: preset name ('hdl64', 'avia_like', 'ouster_like', 'vlp16_like') or a
            :class:`LidarModel`.
        block: distance between parallel roads, metres.
        spacing: distance driven between scans, metres.
        speed: driving speed, m/s (sets the stamps: one scan every spacing / speed s).
        revisit_radius: ground truth: a scan closer than this to an earlier one revisits it.
        exclude_distance: ground truth: earlier scans within this driven distance don't count.
        route: 'revisits' (loops back to earlier places), 'no_revisit' (a serpentine of about
            2 km at 50 m blocks that never returns: every scan is new) or a tuple of (column,
            row) crossings, consecutive ones on one road.
        nx: number of north-south roads; None: the fewest the route needs.
        ny: number of east-west roads; None: the fewest the route needs.
        scene: 'varied' (every street side its own set-back, height and open lots, trees on
            some streets, jittered roads) or 'lookalike' (every street side the same character
            and furniture style on a nearly regular grid; buildings and furniture still placed
            at random).
        facade_detail: add entrances, bay fronts and stepped upper floors to the buildings.
        mount_roll_deg: sensor mounting roll, degrees; None keeps the sensor model's.
        mount_pitch_deg: sensor mounting pitch, degrees; None keeps the sensor model's.
        perfect_odometry: the odometry (:attr:`SimScan.odom`, the bag's /odom) is the
            reference pose; otherwise it drifts as set by the ``odom_*`` values (see
            :mod:`solid_ros.sim.odometry`; the defaults drift by about 1-2 % of the path).
        odom_scale_error: odometry step length error, fraction of the step.
        odom_heading_bias_deg_per_m: odometry heading bias, degrees per metre driven.
        odom_heading_walk_deg: odometry heading random walk, degrees per sqrt(metre).
        odom_position_walk_m: odometry position random walk, metres per sqrt(metre) on x and y.
        people: mean number of people walking round each block's sidewalk, coming and going
            (:func:`~solid_ros.sim.agents.street_agents`); a scan sees them where they are at
            its stamp, so a revisit sees them elsewhere. 0: an empty town, as before.
        cars: mean number of cars driving round each block, coming and going; 0: none.
        foliage: mean free path of a ray in foliage, metres: porous tree crowns and bushes
            along the sidewalks, hit at other depths and missed in other directions by each
            scan (:func:`~solid_ros.sim.scene.build_scene`); 0: solid crowns and no bushes.
    """

    seed: int = 0
    sensor: str | LidarModel = 'hdl64'
    block: float = 80.0
    spacing: float = 2.0
    speed: float = 10.0
    revisit_radius: float = 6.0
    exclude_distance: float = 60.0
    route: str | Route = 'revisits'
    nx: int | None = None
    ny: int | None = None
    scene: str = 'varied'
    facade_detail: bool = False
    mount_roll_deg: float | None = None
    mount_pitch_deg: float | None = None
    perfect_odometry: bool = False
    # About 1.5 % of the path (see solid_ros.sim.odometry for the figures).
    odom_scale_error: float = 0.01
    odom_heading_bias_deg_per_m: float = 0.015
    odom_heading_walk_deg: float = 0.05
    odom_position_walk_m: float = 0.01
    people: float = 0.0
    cars: float = 0.0
    foliage: float = 0.0
    _model: LidarModel = field(init=False, repr=False, compare=False)
    _crossings: Route = field(init=False, repr=False, compare=False)
    _grid_size: tuple[int, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f'seed: expected a non-negative integer, got {self.seed!r}')
        if not 0.1 <= self.speed <= 100.0:
            raise ConfigError(f'speed: {self.speed} is out of range; allowed [0.1, 100]')
        if self.scene not in SCENE_STYLES:
            raise ConfigError(f'scene: {self.scene!r} is not a scene style; use one of '
                              f'{", ".join(map(repr, SCENE_STYLES))}')
        for key in ('facade_detail', 'perfect_odometry'):
            if not isinstance(getattr(self, key), bool):
                raise ConfigError(f'{key}: expected true or false, got {getattr(self, key)!r}')
        for key, (low, high) in {**_ODOM_RANGES, **_WORLD_RANGES}.items():
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                    low <= value <= high):
                raise ConfigError(f'{key}: {value!r} is out of range; allowed [{low}, {high}]')
            object.__setattr__(self, key, float(value))
        crossings = resolve_route(self.route)
        if not isinstance(self.route, str):
            object.__setattr__(self, 'route', crossings)  # lists -> tuples: hashable, frozen
        need = route_grid(crossings)
        size = []
        for key, value, least in (('nx', self.nx, need[0]), ('ny', self.ny, need[1])):
            if value is None:
                size.append(least)
            elif isinstance(value, bool) or not isinstance(value, int) or not (
                    least <= value <= 100):
                raise ConfigError(f'{key}: {value!r} is out of range; the route needs '
                                  f'[{least}, 100]')
            else:
                size.append(value)
        model = sensor_model(self.sensor)
        tilt = {k: float(v) for k, v in (('mount_roll_deg', self.mount_roll_deg),
                                         ('mount_pitch_deg', self.mount_pitch_deg))
                if v is not None}
        object.__setattr__(self, '_model', model.replace(**tilt) if tilt else model)
        object.__setattr__(self, '_crossings', crossings)
        object.__setattr__(self, '_grid_size', (size[0], size[1]))

    @property
    def model(self) -> LidarModel:
        """The sensor model (with the mounting tilt of this config, if set)."""
        return self._model

    @property
    def crossings(self) -> Route:
        """The route's crossings, (column, row) pairs."""
        return self._crossings

    @property
    def drift(self) -> OdometryDrift | None:
        """The odometry's error model (None: perfect odometry)."""
        if self.perfect_odometry:
            return None
        return OdometryDrift(self.odom_scale_error, self.odom_heading_bias_deg_per_m,
                             self.odom_heading_walk_deg, self.odom_position_walk_m)

    @property
    def grid_size(self) -> tuple[int, int]:
        """Number of north-south and east-west roads (nx, ny)."""
        return self._grid_size

    def to_dict(self) -> dict[str, Any]:
        """Return every setting as plain data: the sensor expanded to its model fields, the
        route as given (name or crossings), the grid size as used."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init}
        out['sensor'] = dataclasses.asdict(self._model)
        if not isinstance(self.route, str):
            out['route'] = [list(c) for c in self.route]
        out['nx'], out['ny'] = self._grid_size
        return out

    def fingerprint(self) -> str:
        """Return a short hash of :meth:`to_dict` (names a cache entry).

        Options at the value that reproduces drives made before they existed are left out, so
        the default drive keeps its cache key.
        """
        key = self.to_dict()
        for name in _KEY_OMITTED + (_ODOM_KEYS if self.perfect_odometry else ()):
            del key[name]
        for name, default in _KEY_DEFAULTS.items():
            if key[name] == default:
                del key[name]
        for name, default in _SENSOR_KEY_DEFAULTS.items():
            if key['sensor'][name] == default:
                del key['sensor'][name]
        if self._crossings == DEFAULT_ROUTE and self._grid_size == route_grid(DEFAULT_ROUTE):
            del key['route'], key['nx'], key['ny']
        blob = json.dumps(key, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


@dataclass(frozen=True)
class SimScan:
    """One simulated scan.

    Attributes:
        index: position in the drive.
        cloud: (N, 4) float32 x, y, z, intensity in the sensor frame (x forward, y left, z up).
        pose: (4, 4) float64 world <- sensor transform (reference pose).
        stamp_ns: time stamp, nanoseconds.
        label: 'new', 'same', 'cross' or 'reverse' (see :mod:`solid_ros.sim.trajectory`).
        revisit_of: index of the earlier scan of the same place, -1 when new.
        odom: (4, 4) float64 odometry <- sensor: the drifting odometry's pose (the reference
            pose itself with ``perfect_odometry``); what a bag's /odom carries.
    """

    index: int
    cloud: npt.NDArray[np.float32]
    pose: npt.NDArray[np.float64]
    stamp_ns: int
    label: str
    revisit_of: int
    odom: npt.NDArray[np.float64]

    @property
    def points(self) -> npt.NDArray[np.float32]:
        """(N, 3) x, y, z in the sensor frame (a view of :attr:`cloud`)."""
        return self.cloud[:, :3]

    def __iter__(self) -> Iterator[Any]:
        """Unpack as ``points, pose, stamp_ns``."""
        return iter((self.points, self.pose, self.stamp_ns))


def pose_matrix(x: float, y: float, z: float, yaw: float) -> npt.NDArray[np.float64]:
    """Return the 4x4 transform of a planar pose (rotation about +z by ``yaw``)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, z],
                     [0.0, 0.0, 0.0, 1.0]])


class Drive:
    """A simulated drive; scans are made on demand and are reproducible one by one.

    Example:
        >>> drive = Drive(DriveConfig(seed=1))
        >>> for scan in drive:  # doctest: +SKIP
        ...     detector.process(scan.points, scan.stamp_ns, scan.pose).loops
    """

    def __init__(self, config: DriveConfig | None = None) -> None:
        self.config = config if config is not None else DriveConfig()
        c = self.config
        nx, ny = c.grid_size
        if c.scene == 'lookalike':
            self.grid = StreetGrid(block=c.block, nx=nx, ny=ny, jitter=LOOKALIKE_JITTER,
                                   seed=c.seed)
        else:
            self.grid = StreetGrid(block=c.block, nx=nx, ny=ny, seed=c.seed)
        self.model = c.model
        self._mount = np.eye(4)
        self._mount[:3, :3] = self.model.mount_rotation()

    @cached_property
    def scene(self) -> Scene:
        """The world."""
        c = self.config
        return build_scene(self.grid, c.seed, style=c.scene, facade_detail=c.facade_detail,
                           foliage=c.foliage)

    @cached_property
    def agents(self) -> Agents:
        """The people and cars moving through the scene (none by default)."""
        c = self.config
        return street_agents(self.grid, c.seed, people=c.people, cars=c.cars)

    def scene_at(self, seconds: float, x: float, y: float) -> Scene:
        """The scene a scan at (x, y) sees ``seconds`` after the drive's start: the static
        scene with the agents present then, but for those where the sensor is."""
        if not len(self.agents):
            return self.scene
        return self.scene.with_objects(*self.agents.objects(seconds, x, y))

    def cast(self, index: int, rng: np.random.Generator, stamp_ns: int) -> npt.NDArray[
            np.float32]:
        """The cloud of scan ``index`` of the route as cast at ``stamp_ns`` (the agents move
        with the stamp: a later lap sees them elsewhere)."""
        t = self.trajectory
        x, y = float(t.xy[index, 0]), float(t.xy[index, 1])
        scene = self.scene_at((stamp_ns - START_NS) * 1e-9, x, y)
        return cast_scan(scene, self.model, x, y, float(t.yaw[index]), rng)

    @cached_property
    def trajectory(self) -> Trajectory:
        """Sensor poses and revisit labels."""
        c = self.config
        return build_trajectory(self.grid, c.seed, c.spacing, route=c.crossings,
                                revisit_radius=c.revisit_radius,
                                exclude_distance=c.exclude_distance)

    def __len__(self) -> int:
        return len(self.trajectory)

    def stamp_ns(self, index: int) -> int:
        """Stamp of scan ``index``, nanoseconds."""
        return START_NS + int(round(self.trajectory.distance[index] / self.config.speed * 1e9))

    def _sensor_pose(self, x: float, y: float, yaw: float) -> npt.NDArray[np.float64]:
        level = pose_matrix(x, y, self.model.mount_height, yaw)
        if not self.model.tilted:
            return level
        out: npt.NDArray[np.float64] = level @ self._mount
        return out

    def pose(self, index: int) -> npt.NDArray[np.float64]:
        """Reference pose (world <- sensor) of scan ``index``; a tilted sensor's own frame:
        ``Rz(yaw) Ry(pitch) Rx(roll)``, so ``p_world = pose @ p_sensor`` holds."""
        t = self.trajectory
        return self._sensor_pose(float(t.xy[index, 0]), float(t.xy[index, 1]),
                                 float(t.yaw[index]))

    def poses(self) -> npt.NDArray[np.float64]:
        """All reference poses, shape (N, 4, 4)."""
        return np.stack([self.pose(i) for i in range(len(self))]) if len(self) else np.zeros(
            (0, 4, 4))

    def _planar_odometry(self, laps: int) -> tuple[npt.NDArray[np.float64],
                                                   npt.NDArray[np.float64]]:
        """Odometry positions and headings over ``laps`` laps of the route (the drift goes
        on from lap to lap; every lap draws its own noise, so lap 0 never changes)."""
        t = self.trajectory
        xy, yaw = np.tile(t.xy, (laps, 1)), np.tile(t.yaw, laps)
        drift = self.config.drift
        if drift is None:
            return xy, yaw
        noise = np.concatenate([np.random.default_rng([self.config.seed, lap, 0x0D0])
                                .standard_normal((len(t), 3)) for lap in range(laps)])
        return drift_planar(xy, yaw, drift, noise)

    @cached_property
    def _odometry_lap(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        return self._planar_odometry(1)

    def odometry(self, index: int) -> npt.NDArray[np.float64]:
        """Odometry pose (odometry <- sensor) of scan ``index``: the reference pose with the
        configured drift, exactly the reference pose with ``perfect_odometry``."""
        if self.config.drift is None:
            return self.pose(index)
        xy, yaw = self._odometry_lap
        return self._sensor_pose(float(xy[index, 0]), float(xy[index, 1]), float(yaw[index]))

    def odometry_poses(self, laps: int = 1) -> npt.NDArray[np.float64]:
        """Odometry poses of ``laps`` laps of the route, shape (laps * N, 4, 4)."""
        if self.config.drift is None:
            return np.tile(self.poses(), (laps, 1, 1))
        xy, yaw = self._planar_odometry(laps)
        out = [self._sensor_pose(float(x), float(y), float(a)) for (x, y), a in zip(xy, yaw)]
        return np.stack(out) if out else np.zeros((0, 4, 4))

    def scan(self, index: int) -> SimScan:
        """Simulate scan ``index`` (noise seeded by the drive seed and the index)."""
        t = self.trajectory
        if not 0 <= index < len(t):
            raise IndexError(f'scan index {index} outside 0..{len(t) - 1}')
        rng = np.random.default_rng([self.config.seed, index, 0x1D4])
        stamp = self.stamp_ns(index)
        return SimScan(index=index, cloud=self.cast(index, rng, stamp), pose=self.pose(index),
                       stamp_ns=stamp, label=str(t.label[index]),
                       revisit_of=int(t.revisit_of[index]), odom=self.odometry(index))

    def __iter__(self) -> Iterator[SimScan]:
        for i in range(len(self)):
            yield self.scan(i)


def simulate(seed: int = 0, sensor: str | LidarModel = 'hdl64', num_scans: int | None = None,
             **options: Any) -> Iterator[SimScan]:
    """Yield the scans of a simulated drive.

    Args:
        seed: seed of scene, route and noise.
        sensor: preset name or sensor model.
        num_scans: stop after this many scans (None: the whole route). Beyond the route's
            length the drive repeats from the start (places revisited again), with new noise.
        **options: further :class:`DriveConfig` fields (block, spacing, speed, route, nx, ny,
            scene, facade_detail, mount_roll_deg, mount_pitch_deg, perfect_odometry, odom_*,
            people, cars, foliage).

    Yields:
        :class:`SimScan` in driving order.
    """
    drive = Drive(DriveConfig(seed=seed, sensor=sensor, **options))
    n = len(drive)
    total = n if num_scans is None else num_scans
    if total < 0:
        raise ConfigError(f'num_scans: expected >= 0, got {total}')
    period = int(round(drive.trajectory.distance[-1] / drive.config.speed * 1e9)) + 10**9
    odom: npt.NDArray[np.float64] | None = None
    for k in range(total):
        lap, i = divmod(k, n)
        if lap == 0:
            yield drive.scan(i)
            continue
        if odom is None:
            odom = drive.odometry_poses(-(-total // n))
        rng = np.random.default_rng([seed, i, lap, 0x1D4])
        stamp = drive.stamp_ns(i) + lap * period
        yield SimScan(index=k, cloud=drive.cast(i, rng, stamp), pose=drive.pose(i),
                      stamp_ns=stamp, label='same', revisit_of=i, odom=odom[k])
