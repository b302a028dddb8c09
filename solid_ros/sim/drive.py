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
from solid_ros.sim.lidar import LidarModel, cast_scan, sensor_model
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
_KEY_DEFAULTS: dict[str, Any] = {'scene': 'varied', 'facade_detail': False}
_SENSOR_KEY_DEFAULTS: dict[str, Any] = {'mount_roll_deg': 0.0, 'mount_pitch_deg': 0.0}
# Already in the key as the sensor model's effective tilt.
_KEY_OMITTED = ('mount_roll_deg', 'mount_pitch_deg')


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
        if not isinstance(self.facade_detail, bool):
            raise ConfigError(f'facade_detail: expected true or false, got '
                              f'{self.facade_detail!r}')
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
        for name in _KEY_OMITTED:
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
    """

    index: int
    cloud: npt.NDArray[np.float32]
    pose: npt.NDArray[np.float64]
    stamp_ns: int
    label: str
    revisit_of: int

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
        return build_scene(self.grid, c.seed, style=c.scene, facade_detail=c.facade_detail)

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

    def pose(self, index: int) -> npt.NDArray[np.float64]:
        """Reference pose (world <- sensor) of scan ``index``; a tilted sensor's own frame:
        ``Rz(yaw) Ry(pitch) Rx(roll)``, so ``p_world = pose @ p_sensor`` holds."""
        t = self.trajectory
        level = pose_matrix(float(t.xy[index, 0]), float(t.xy[index, 1]),
                            self.model.mount_height, float(t.yaw[index]))
        if not self.model.tilted:
            return level
        out: npt.NDArray[np.float64] = level @ self._mount
        return out

    def poses(self) -> npt.NDArray[np.float64]:
        """All reference poses, shape (N, 4, 4)."""
        return np.stack([self.pose(i) for i in range(len(self))]) if len(self) else np.zeros(
            (0, 4, 4))

    def scan(self, index: int) -> SimScan:
        """Simulate scan ``index`` (noise seeded by the drive seed and the index)."""
        t = self.trajectory
        if not 0 <= index < len(t):
            raise IndexError(f'scan index {index} outside 0..{len(t) - 1}')
        rng = np.random.default_rng([self.config.seed, index, 0x1D4])
        cloud = cast_scan(self.scene, self.model, float(t.xy[index, 0]), float(t.xy[index, 1]),
                          float(t.yaw[index]), rng)
        return SimScan(index=index, cloud=cloud, pose=self.pose(index),
                       stamp_ns=self.stamp_ns(index), label=str(t.label[index]),
                       revisit_of=int(t.revisit_of[index]))

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
            scene, facade_detail, mount_roll_deg, mount_pitch_deg, ...).

    Yields:
        :class:`SimScan` in driving order.
    """
    drive = Drive(DriveConfig(seed=seed, sensor=sensor, **options))
    n = len(drive)
    total = n if num_scans is None else num_scans
    if total < 0:
        raise ConfigError(f'num_scans: expected >= 0, got {total}')
    period = int(round(drive.trajectory.distance[-1] / drive.config.speed * 1e9)) + 10**9
    for k in range(total):
        lap, i = divmod(k, n)
        if lap == 0:
            yield drive.scan(i)
            continue
        rng = np.random.default_rng([seed, i, lap, 0x1D4])
        t = drive.trajectory
        cloud = cast_scan(drive.scene, drive.model, float(t.xy[i, 0]), float(t.xy[i, 1]),
                          float(t.yaw[i]), rng)
        yield SimScan(index=k, cloud=cloud, pose=drive.pose(i),
                      stamp_ns=drive.stamp_ns(i) + lap * period, label='same', revisit_of=i)
