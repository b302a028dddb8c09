"""One typed, validated configuration schema for the core, the node and the offline tools.

Every setting is a dataclass field whose metadata carries its description, allowed range or
choices and whether it is read-only at runtime (it changes descriptor shape or values). The ROS
node declares its parameters from this metadata, the YAML file holds the same keys under
``<node>: ros__parameters:``, and the offline tools load that YAML with :meth:`from_yaml`
(:mod:`solid_ros.core.paramfile` reads the file's layout; this module checks the values).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from solid_ros.core.errors import ConfigError
from solid_ros.core.paramfile import load_yaml_parameters

__all__ = ['GROUPS', 'ParamSpec', 'SolidConfig', 'NodeConfig', 'check_parameters',
           'is_standard_ros_parameter', 'load_parameter_file', 'load_yaml_parameters',
           'param_specs', 'type_message', 'unknown_parameters']

_C = TypeVar('_C', bound='_Schema')

# Parameters every rclpy node accepts besides its own (qos_overrides.<topic>... nests).
_ROS_STANDARD = frozenset({'use_sim_time', 'start_type_description_service'})

# The settings come in groups, in declaration order: the first setting of each, its heading.
GROUPS = {
    'fov_width_deg': 'Descriptor: field of view, ranges, voxel, bins (saved with databases)',
    'capacity': 'Database',
    'distance_threshold': 'Query and acceptance',
    'keyframe_min_sec': 'Keyframes (0 turns a criterion off; all off keeps every scan)',
    'mount_roll_deg': 'Sensor mounting: R = Rz(yaw) Ry(pitch) Rx(roll) levels the points',
    'verify': 'Verification by registration',
    'odom_check_drift': 'Odometry check of loops',
    'graph_candidates': 'Candidates from the pose graph',
    'cloud_capacity': 'Keyframe clouds',
    'backend': 'Back end: pose graph (gtsam iSAM2)',
    'qos_reliability': 'Node: input, files, diagnostics, markers, map',
    'map_frame': 'Back end outputs: frames, rates, files',
    'odometry_source': 'Odometry source and KISS-ICP',
    'max_points_per_cloud': 'Bounds on the inputs and on peers',
}


@dataclass(frozen=True)
class ParamSpec:
    """Description of one setting, as used for validation and ROS parameter declaration."""

    name: str
    type: type
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = False
    # Whether changing it changes descriptor values (saved databases record these).
    shape: bool = False
    # Heading of the settings it is declared among (--help and config/solid.yaml use it).
    group: str = ''

    def range_text(self) -> str:
        """Return the allowed values as text for error messages."""
        if self.choices is not None:
            return 'one of ' + ', '.join(repr(c) for c in self.choices)
        if self.low is not None and self.high is not None:
            return f'[{self.low}, {self.high}]'
        if self.low is not None:
            return f'>= {self.low}'
        if self.high is not None:
            return f'<= {self.high}'
        return f'any {self.type.__name__}'


def _p(default: Any, description: str, *, low: float | None = None,
       high: float | None = None, choices: tuple[str, ...] | None = None,
       read_only: bool = False, shape: bool = False) -> Any:
    meta = {'description': description, 'low': low, 'high': high, 'choices': choices,
            'read_only': read_only or shape, 'shape': shape}
    return field(default=default, metadata=meta)


class _Schema:
    """Shared behaviour of the configuration dataclasses."""

    _cross_checks: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def specs(cls) -> tuple[ParamSpec, ...]:
        """Return one :class:`ParamSpec` per setting, in declaration order."""
        out = []
        group = ''
        for f in dataclasses.fields(cls):  # type: ignore[arg-type]
            m = f.metadata
            typ = {'float': float, 'int': int, 'str': str, 'bool': bool}[str(f.type)]
            group = GROUPS.get(f.name, group)
            out.append(ParamSpec(f.name, typ, f.default, m['description'], m['low'], m['high'],
                                 m['choices'], m['read_only'], m['shape'], group))
        return tuple(out)

    def __post_init__(self) -> None:
        for spec in self.specs():
            value = _coerce(spec, getattr(self, spec.name))
            object.__setattr__(self, spec.name, value)
        self._validate_cross()

    def _validate_cross(self) -> None:
        """Check rules that involve several keys."""

    def to_dict(self) -> dict[str, Any]:
        """Return the settings as a plain dict (YAML/JSON ready)."""
        out: dict[str, Any] = dataclasses.asdict(self)  # type: ignore[call-overload]
        return out

    def replace(self: _C, **changes: Any) -> _C:
        """Return a validated copy with some settings changed."""
        unknown = sorted(set(changes) - {s.name for s in self.specs()})
        if unknown:
            raise ConfigError(f'unknown parameter {unknown[0]!r}')
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]

    @classmethod
    def from_dict(cls: type[_C], values: Mapping[str, Any], *, strict: bool = True) -> _C:
        """Build from a mapping; with ``strict`` unknown keys raise :class:`ConfigError`."""
        names = {s.name for s in cls.specs()}
        unknown = unknown_parameters(values) if strict else []
        if unknown:
            raise ConfigError(f'unknown parameter {unknown[0]!r}')
        return cls(**{k: v for k, v in values.items() if k in names})

    @classmethod
    def from_yaml(cls: type[_C], path: str | Path, node_name: str = 'solid_node') -> _C:
        """Load the ``ros__parameters`` block of ``node_name`` from a ROS 2 parameter file.

        Args:
            path: YAML parameter file, as given to ``--ros-args --params-file``.
            node_name: node whose block is read; ``/**`` wildcard blocks also apply.

        Raises:
            ConfigError: the file is unreadable, malformed, or holds an invalid value (the
                node's rule: see :func:`load_parameter_file`).
        """
        return cls.from_dict(load_parameter_file(path, node_name))


def _coerce(spec: ParamSpec, value: Any) -> Any:
    """Check one value against its spec and return it with the exact declared type."""
    name = spec.name
    if spec.type is bool:
        if not isinstance(value, bool):
            raise ConfigError(f'{name}: expected true or false, got {value!r}')
        return value
    if spec.type is str:
        if not isinstance(value, str):
            raise ConfigError(f'{name}: expected a string, got {value!r}')
        if spec.choices is not None and value not in spec.choices:
            raise ConfigError(f'{name}: {value!r} is not allowed; use {spec.range_text()}')
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f'{name}: expected a number in {spec.range_text()}, got {value!r}')
    if spec.type is int:
        if isinstance(value, float) and not value.is_integer():
            raise ConfigError(f'{name}: expected an integer in {spec.range_text()}, '
                              f'got {value!r}')
        value = int(value)
    else:
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f'{name}: {value!r} is not finite; allowed {spec.range_text()}')
    if (spec.low is not None and value < spec.low) or (
            spec.high is not None and value > spec.high):
        raise ConfigError(f'{name}: {value!r} is out of range; allowed {spec.range_text()}')
    return value


@dataclass(frozen=True)
class SolidConfig(_Schema):
    """Descriptor and loop-detector settings.

    ``SolidConfig()`` equals the SOLiD authors' C++ defaults (360 deg, +2/-24.8 deg,
    3-80 m, voxel 0.4 m, 40/60/32 bins, L_max 80 m) and reproduces their descriptors.

    Raises:
        ConfigError: a value is of the wrong type or out of range; the message names the key.
    """

    # Field of view and preprocessing (change descriptor values: read-only at runtime).
    fov_width_deg: float = _p(360.0, 'Horizontal field of view kept, degrees', low=1.0,
                              high=360.0, shape=True)
    fov_center_deg: float = _p(0.0, 'Centre heading of the horizontal FOV, degrees CCW from +x',
                               low=-180.0, high=180.0, shape=True)
    fov_up_deg: float = _p(2.0, 'Sensor vertical FOV upper limit, degrees', low=-90.0,
                           high=90.0, shape=True)
    fov_down_deg: float = _p(-24.8, 'Sensor vertical FOV lower limit, degrees', low=-90.0,
                             high=90.0, shape=True)
    min_range: float = _p(3.0, 'Points closer than this (3-D, metres) are dropped', low=0.0,
                          high=1000.0, shape=True)
    max_range: float = _p(80.0, 'Points at or beyond this (3-D, metres) are dropped', low=0.1,
                          high=1000.0, shape=True)
    voxel_size: float = _p(0.4, 'Voxel grid leaf in metres (0 turns it off)', low=0.0,
                           high=100.0, shape=True)
    num_range: int = _p(40, 'N_r: range bins over [0, max_distance)', low=1, high=1024,
                        shape=True)
    num_angle: int = _p(60, 'N_a: azimuth bins over [0, 360) degrees', low=4, high=3600,
                        shape=True)
    num_height: int = _p(32, 'N_e: elevation bins over [fov_down_deg, fov_up_deg]', low=1,
                         high=1024, shape=True)
    max_distance: float = _p(80.0, 'L_max: horizontal extent of the range bins, metres',
                             low=0.1, high=1000.0, shape=True)
    heading_weight: str = _p('count', "Heading signature: 'count' is the paper's A-SOLiD; "
                             "'range' weights points by squared range (less parallax)",
                             choices=('count', 'range'), shape=True)

    # Database (fixed once running).
    capacity: int = _p(100000, 'Stored scans; the oldest is evicted beyond this', low=1,
                       high=10_000_000, read_only=True)
    search: str = _p('brute', 'Search mode: exact vectorised brute force (faster for 40-bin '
                     'descriptors) or kd-tree',
                     choices=('kdtree', 'brute'), read_only=True)
    kdtree_rebuild_every: int = _p(64, 'Rebuild the kd-tree after at least this many '
                                   'insertions (and 1/16 of its size)',
                                   low=1, high=1_000_000, read_only=True)
    num_candidates: int = _p(10, 'Top-k candidates re-ranked by exact cosine distance',
                             low=1, high=1000)
    session_id: int = _p(0, 'Session id stored with every scan of this run', low=0,
                         high=2**31 - 1, read_only=True)
    peer_capacity: int = _p(50000, "Stored scans of peer robots, in a ring of their own (the "
                            "oldest peer scan is evicted beyond this; a peer never evicts this "
                            "robot's scans; 0 stores none)", low=0, high=10_000_000,
                            read_only=True)

    # Query and acceptance (tunable at runtime).
    distance_threshold: float = _p(0.03, 'Accept a loop when cosine distance is below this',
                                   low=0.0, high=2.0)
    exclude_recent_frames: int = _p(50, 'Never match the most recent N stored scans', low=0,
                                    high=10_000_000)
    exclude_recent_sec: float = _p(0.0, 'Never match scans newer than this many seconds',
                                   low=0.0, high=1e9)
    min_margin: float = _p(0.0, 'Required distance gap to the next-best distinct place '
                           '(0 = off)', low=0.0, high=2.0)
    margin_neighbourhood: int = _p(10, 'Scans within this index distance of the best match '
                                   'count as the same place for the margin test', low=0,
                                   high=1_000_000)
    max_candidates: int = _p(1, 'Most loops reported per query to this session, and as many '
                             'to a loaded map and to peers', low=1, high=100)
    min_loop_gap: int = _p(0, 'Queries between two accepted loops (0 = off)', low=0,
                           high=1_000_000)
    heading_match: str = _p('full', "Heading search: 'full' compares whole heading signatures "
                            "(the paper); 'overlap' only the bins both scans see, for narrow "
                            'fields of view', choices=('full', 'overlap'))

    # Keyframe gating (0 turns a criterion off; all off keeps every scan).
    keyframe_min_sec: float = _p(0.0, 'Keyframe when this many seconds passed', low=0.0,
                                 high=1e6)
    keyframe_min_distance: float = _p(0.0, 'Keyframe when the sensor moved this far, metres '
                                      '(needs poses)', low=0.0, high=1e6)
    keyframe_min_rotation_deg: float = _p(0.0, 'Keyframe when the sensor turned this much, '
                                          'degrees (needs poses)', low=0.0, high=360.0)

    # Sensor mounting: the sensor's orientation in a level body frame (x forward, z up), as
    # R = Rz(yaw) Ry(pitch) Rx(roll); points are levelled with it before anything else.
    mount_roll_deg: float = _p(0.0, 'Sensor roll in the level body frame, degrees (points are '
                               'levelled before describing and verifying)', low=-180.0,
                               high=180.0, shape=True)
    mount_pitch_deg: float = _p(0.0, 'Sensor pitch in the level body frame, degrees', low=-90.0,
                                high=90.0, shape=True)
    mount_yaw_deg: float = _p(0.0, 'Sensor yaw in the level body frame, degrees', low=-180.0,
                              high=180.0, shape=True)

    # Geometric verification (registration with small_gicp; see
    # solid_ros.core.verification.verifier).
    verify: bool = _p(True, 'Verify candidates by registration and publish only verified loops '
                      'with a 6-DoF pose (false: descriptor-only candidates, yaw only)',
                      read_only=True)
    verify_voxel_size: float = _p(0.5, 'Voxel of the stored keyframe clouds and of the fine '
                                  'registration, metres', low=0.05, high=5.0, read_only=True)
    verify_coarse_voxel_size: float = _p(1.5, 'Voxel of the coarse registration of structure '
                                         'points, metres', low=0.1, high=10.0, read_only=True)
    verify_tight_range: float = _p(8.0, 'A keyframe whose 90th percentile horizontal range is '
                                   'below this (a room, a tight space) keeps its cloud on half '
                                   'the voxels; two such keyframes register on half of both '
                                   'voxels (0 = off), metres', low=0.0, high=1000.0,
                                   read_only=True)
    verify_coarse_max_points: int = _p(250, 'Most coarse structure points of a candidate '
                                       'registered per heading hypothesis; a denser place is '
                                       'evenly thinned (bounds the coarse cost)', low=10,
                                       high=1_000_000, read_only=True)
    verify_max_iterations: int = _p(30, 'Iteration limit of each registration', low=1,
                                    high=1000, read_only=True)
    verify_inlier_distance: float = _p(0.15, 'A point supports an alignment within this distance '
                                       "of the other cloud's surface, metres", low=0.005,
                                       high=5.0, read_only=True)
    verify_hypotheses: int = _p(3, 'Heading hypotheses (best A-SOLiD shifts) tried per '
                                'candidate', low=1, high=16)
    verify_min_coarse_overlap: float = _p(0.25, 'Coarse screen: least fraction of coarse '
                                          'structure points that must align', low=0.0, high=1.0)
    verify_min_overlap: float = _p(0.35, 'Least fraction of structure points supporting the '
                                   'alignment, in both directions', low=0.0, high=1.0)
    verify_max_rmse: float = _p(0.1, 'Largest RMS point-to-plane distance of supporting points, '
                                'metres', low=0.001, high=10.0)
    verify_min_constraint: float = _p(0.0075, 'Least horizontal constraint (information on x, '
                                      'y, yaw per structure point; 0 in a corridor)', low=0.0,
                                      high=1.0)
    verify_max_conflict: float = _p(0.03, 'Largest fraction of points lying in space the other '
                                    'scan saw through (free-space conflict)', low=0.0, high=1.0)
    verify_min_spread: float = _p(0.002, 'Constraint left without the strongest object; below '
                                  'this the pose rests on one object and must pass the '
                                  'single-object bar', low=0.0, high=1.0)
    verify_single_object_overlap: float = _p(0.45, 'Single-object bar: least structure overlap '
                                             '(and at most half of verify_max_conflict)',
                                             low=0.0, high=1.0)
    verify_max_drift: float = _p(0.2, 'Consistency: restarts one voxel off must return within '
                                 'this, metres', low=0.0, high=100.0)
    verify_max_drift_deg: float = _p(1.0, 'Consistency: restarts turned 2 deg (less where the '
                                     'far points would move over a voxel) must return within '
                                     'this per 2 deg of turn, degrees', low=0.0, high=180.0)
    verify_covariance_scale: float = _p(1.0, 'Factor on the published loop covariance (1 = the '
                                        'calibrated model; raise it for errors the loops do '
                                        'not see, e.g. a reference or odometry frame that is '
                                        'itself off)', low=0.01, high=1e4)
    odom_check_drift: float = _p(0.1, 'Loops within this session must agree with its odometry: '
                                 "the loop's translation may differ from the odometry's by "
                                 'this fraction of the path driven between the two keyframes, '
                                 'plus odom_check_slack_m, until the run has measured its '
                                 "odometry's drift, which then replaces it (0 turns the check "
                                 'off)', low=0.0, high=100.0)
    odom_check_slack_m: float = _p(10.0, 'Odometry check: disagreement always allowed, metres '
                                   '(sensor offset from the odometry frame, descriptor-only '
                                   "loops); 1 m for verified loops once most of the run's "
                                   'calibration pairs agreed with the odometry', low=0.0,
                                   high=1e6)
    graph_candidates: int = _p(3, 'Besides the descriptor candidates, verify up to this many '
                               'earlier keyframes of this session lying near the query in the '
                               "back end's corrected estimate, nearest first, and when none of "
                               "them saw the query's place as many whose view centre lies near "
                               "the query's (needs verify and the back end with odometry; "
                               '0 = off)', low=0, high=100)
    graph_candidate_radius_m: float = _p(5.0, 'Graph candidates: search radius around the '
                                         "query's predicted pose when the back end is certain "
                                         'of it (the floor), metres', low=0.0, high=1000.0)
    graph_candidate_sigmas: float = _p(3.0, 'Graph candidates: the radius grows by this many '
                                       "standard deviations of the newest pose's marginal "
                                       'position covariance', low=0.0, high=100.0)
    graph_candidate_max_radius_m: float = _p(15.0, 'Graph candidates: largest search radius '
                                             '(the cap), metres', low=0.0, high=10000.0)
    graph_candidate_min_path_m: float = _p(10.0, 'Graph candidates: least odometry path driven '
                                           'between a candidate and the query, metres (besides '
                                           'exclude_recent_frames / _sec)', low=0.0, high=1e6)
    cloud_capacity: int = _p(20000, 'Keyframe clouds kept for verification; the oldest cloud is '
                             'dropped beyond this (its scan stays, unverifiable)', low=0,
                             high=10_000_000, read_only=True)
    cloud_memory_mb: float = _p(1024.0, 'Memory limit of the keyframe clouds, MB; the oldest is '
                                'dropped beyond it', low=0.0, high=1e6, read_only=True)

    # Back end: a pose graph on gtsam iSAM2 (solid_ros.core.backend.posegraph); not shape settings.
    backend: bool = _p(False, 'Close the loop in a pose graph (gtsam iSAM2): corrected keyframe '
                       'poses, map->odom, relocalisation in a loaded map (needs pip install '
                       'gtsam)', read_only=True)
    backend_odom_trans_sigma: float = _p(0.05, 'Odometry model (used when the odometry gives no '
                                         'usable covariance): translation sigma after 1 m '
                                         'driven, metres; variance grows with the distance',
                                         low=0.0, high=10.0, read_only=True)
    backend_odom_rot_sigma_deg: float = _p(0.1, 'Odometry model: rotation sigma after 1 m '
                                           'driven, degrees; variance grows with the distance',
                                           low=0.0, high=90.0, read_only=True)
    backend_odom_rot_per_rad: float = _p(0.05, 'Odometry model: rotation sigma after 1 rad '
                                         'turned, radians; variance grows with the angle',
                                         low=0.0, high=10.0, read_only=True)
    backend_odom_floor_m: float = _p(0.01, 'Least translation sigma of an odometry step, metres '
                                     '(added in quadrature)', low=1e-4, high=100.0,
                                     read_only=True)
    backend_odom_floor_deg: float = _p(0.05, 'Least rotation sigma of an odometry step, degrees '
                                       '(added in quadrature)', low=1e-4, high=90.0,
                                       read_only=True)
    backend_loop_floor_m: float = _p(0.02, 'Least translation sigma of a loop, metres (added in '
                                     'quadrature: registration covariances are optimistic)',
                                     low=1e-4, high=100.0, read_only=True)
    backend_loop_floor_deg: float = _p(0.1, 'Least rotation sigma of a loop, degrees (added in '
                                       'quadrature)', low=1e-4, high=90.0, read_only=True)
    backend_loop_kernel: str = _p('huber', "Robust kernel of the loop factors: 'huber' keeps "
                                  "far-off true loops (drifted odometry) pulling; 'cauchy' "
                                  "discounts them; 'none' is least squares",
                                  choices=('huber', 'cauchy', 'none'), read_only=True)
    backend_loop_kernel_width: float = _p(1.345, 'Width of the loop kernel, in sigmas of the '
                                          "loop's covariance", low=0.01, high=1000.0,
                                          read_only=True)
    backend_loop_gate: float = _p(3.0, 'A loop farther than this many sigmas from the current '
                                  'estimate (Mahalanobis distance with the loop covariance and '
                                  'the relative marginal covariance of its keyframes) waits for '
                                  'loops of other keyframes that agree with it (0 = take every '
                                  'loop)',
                                  low=0.0, high=1e6)
    backend_loop_refuse: float = _p(12.0, 'A loop farther than this many sigmas from the current '
                                    'estimate is refused (0 = never refuse)', low=0.0,
                                    high=1e6)
    backend_segment_jump_m: float = _p(10.0, 'An odometry step longer than this between two '
                                       'keyframes (a jump or reset) starts a new graph segment, '
                                       'metres', low=0.01, high=1e6)
    backend_extra_iterations: int = _p(2, 'Extra iSAM2 iterations after a keyframe with loops',
                                       low=0, high=100)
    backend_step_registration: str = _p(
        'auto', 'Register each keyframe to the previous one (seeded by the odometry step, the '
        "loops' tests and covariance) and add it beside the odometry step as a second between "
        "factor: 'on', 'off', or 'auto': on when the odometry is KISS-ICP run here on the same "
        'clouds (a scan-only odometry that can run away in a weak scene), off with an external '
        'odometry (an IMU-aided one is better between two keyframes; without loops the graph '
        'then stays the odometry)', choices=('auto', 'on', 'off'), read_only=True)

    def _validate_cross(self) -> None:
        if self.fov_up_deg <= self.fov_down_deg:
            raise ConfigError(f'fov_up_deg: {self.fov_up_deg} must be greater than '
                              f'fov_down_deg ({self.fov_down_deg})')
        if self.max_range <= self.min_range:
            raise ConfigError(f'max_range: {self.max_range} must be greater than '
                              f'min_range ({self.min_range})')

    def shape_params(self) -> dict[str, Any]:
        """Return the settings that change descriptor values (saved with databases)."""
        return {s.name: getattr(self, s.name) for s in self.specs() if s.shape}

    def fingerprint(self) -> str:
        """Return a short hash of :meth:`shape_params`."""
        blob = json.dumps(self.shape_params(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def for_odometry(self, scan_only: bool) -> SolidConfig:
        """These settings with ``'auto'`` resolved for the odometry in use: ``scan_only``
        when it is KISS-ICP run here on the same clouds (``backend_step_registration``)."""
        if self.backend_step_registration != 'auto':
            return self
        return self.replace(backend_step_registration='on' if scan_only else 'off')


@dataclass(frozen=True)
class NodeConfig(_Schema):
    """Settings of the ROS node only (topics, QoS, files); see :class:`SolidConfig`."""

    qos_reliability: str = _p('best_effort', 'QoS reliability of the points subscription',
                              choices=('best_effort', 'reliable'), read_only=True)
    qos_depth: int = _p(5, 'QoS history depth of the points subscription', low=1, high=1000,
                        read_only=True)
    use_odom: bool = _p(True, 'Subscribe to odom for keyframe gating and markers',
                        read_only=True)
    odom_tolerance_sec: float = _p(0.05, 'Max stamp difference when pairing cloud and odom',
                                   low=0.0, high=10.0)
    queue_size: int = _p(2, 'Clouds waiting for processing; the oldest is dropped beyond '
                         'this', low=1, high=1000, read_only=True)
    database_save_path: str = _p('', 'File written by ~/save_database (empty = disabled; never '
                                 'replaces a non-database)', read_only=True)
    database_load_path: str = _p('', 'Saved database loaded at start (empty = none)',
                                 read_only=True)
    diagnostics_period_sec: float = _p(1.0, 'Period of /diagnostics messages', low=0.05,
                                       high=3600.0, read_only=True)
    marker_max_loops: int = _p(1000, 'Newest loops drawn on ~/loop_markers (latched); older '
                               'edges are dropped, so memory stays bounded (0 = no markers, '
                               'the topic is not advertised)', low=0, high=100_000,
                               read_only=True)
    peers: bool = _p(False, 'Exchange keyframe descriptors with other robots (robot id = '
                     'session_id) and publish verified inter-robot loops', read_only=True)
    peer_timeout_sec: float = _p(1.0, 'Wait this long for a peer keyframe cloud before the '
                                 'candidate is dropped', low=0.01, high=60.0)
    peer_catchup: int = _p(2000, 'Most stored descriptors sent to a robot that joins late '
                           '(and asked for at start)', low=0, high=1_000_000, read_only=True)
    map_voxel_size: float = _p(0.5, 'Voxel of the map of keyframe clouds at their corrected poses '
                               '(~/map, saved maps), metres', low=0.01, high=100.0)
    map_max_points: int = _p(1_000_000, 'Most points of the map; beyond it the voxel grows by '
                             'half until it fits', low=1, high=100_000_000)

    # The back end's outputs (with backend on): frames, rates, files.
    map_frame: str = _p('map', 'Frame of the corrected poses, path and map (parent of the '
                        'map -> odom TF)', read_only=True)
    odom_frame: str = _p('', "Odometry frame (child of the map -> odom TF); empty = the "
                         "Odometry messages' header.frame_id ('odom' with kiss_icp)",
                         read_only=True)
    sensor_frame: str = _p('', "LiDAR frame, child of KISS-ICP's odom -> sensor TF; empty = "
                           "the PointCloud2's header.frame_id", read_only=True)
    tf_rate_hz: float = _p(20.0, 'Rate of the map -> odom TF broadcast (0 = none)', low=0.0,
                           high=1000.0, read_only=True)
    path_period_sec: float = _p(1.0, 'Least time between two ~/path messages (latched; only '
                                'after a change)', low=0.05, high=3600.0)
    map_period_sec: float = _p(10.0, 'Least time between two ~/map builds (latched; only after '
                               'a change; 0 = no ~/map)', low=0.0, high=86400.0)
    output_directory: str = _p('', 'Directory of ~/save_map (map.pcd) and ~/save_trajectory '
                               '(trajectory.tum, trajectory.kitti); empty = both services '
                               'refuse', read_only=True)
    lio_sam_loop_topic: str = _p('', 'Also publish each loop as LIO-SAM takes external loops '
                                 '(std_msgs/Float64MultiArray [query stamp, match stamp] in '
                                 's; e.g. lio_loop/loop_closure_detection); empty = off',
                                 read_only=True)

    # Odometry source; KISS-ICP's settings (solid_ros.core.odometry.kiss).
    odometry_source: str = _p('topic', "Pose of each cloud: 'topic' (the odom subscription, a "
                              "bag's Odometry or a poses file) or 'kiss_icp' (KISS-ICP "
                              'registers the clouds; pip install kiss-icp)',
                              choices=('topic', 'kiss_icp'), read_only=True)
    kiss_max_range: float = _p(0.0, 'KISS-ICP: points beyond this range are not registered, '
                               'metres; 0 = from the data (99th percentile of the first '
                               "cloud's ranges)", low=0.0, high=1000.0, read_only=True)
    kiss_min_range: float = _p(0.0, 'KISS-ICP: points within this range are not registered '
                               '(the vehicle itself), metres', low=0.0, high=100.0,
                               read_only=True)
    kiss_voxel_size: float = _p(0.0, "KISS-ICP: voxel of its local map, metres; 0 = KISS-ICP's "
                                'own rule, max range / 100', low=0.0, high=10.0,
                                read_only=True)
    kiss_deskew: bool = _p(True, 'KISS-ICP: motion compensation within a sweep, for clouds '
                           "that carry per-point times (Ouster 't', Livox 'offset_time' or "
                           "'timestamp', Velodyne 'time', or kiss_time_field); clouds without "
                           'them are registered as they are', read_only=True)
    kiss_time_field: str = _p('', 'KISS-ICP: name of the per-point time field of the clouds '
                              '(any numeric type, normalised over each sweep); empty = the '
                              'first of t, offset_time, timestamp, time', read_only=True)
    kiss_max_step_m: float = _p(0.0, 'KISS-ICP: a registration that moves the sensor farther '
                                'than this from its last pose or from the constant-velocity '
                                'prediction is a jump: reset, new odometry segment, metres; '
                                '0 = half the max range', low=0.0, high=10000.0,
                                read_only=True)
    kiss_min_overlap: float = _p(0.5, 'KISS-ICP: a registered cloud whose overlap with the '
                                 'previous cloud (its structure points within two voxels) is '
                                 "below this times the run's median overlap did not register "
                                 '(a jump in the input): reset, new segment (0 = off)',
                                 low=0.0, high=1.0, read_only=True)
    kiss_min_constraint: float = _p(0.01, 'KISS-ICP: least horizontal constraint of a cloud '
                                    '(smallest eigenvalue of the mean n n^T over its points of '
                                    'the x-y part of planar normals; about 0 in a corridor); '
                                    'below it the motion along some direction is unknown: '
                                    'reset, new segment (0 = off)', low=0.0, high=1.0,
                                    read_only=True)

    # Bounds on the inputs and on peers: what a participant of the ROS domain can send.
    max_points_per_cloud: int = _p(500_000, 'PointCloud2 with more points are thinned to '
                                   'this by keeping every k-th point (counted as downsampled): '
                                   'bounds time and memory of a huge cloud', low=1000,
                                   high=100_000_000, read_only=True)
    allow_runtime_weakening: bool = _p(False, 'Accept runtime parameter changes that weaken '
                                       'loop acceptance or gating (any participant on the ROS '
                                       'domain can send them); changes that make the node '
                                       'stricter are always accepted', read_only=True)
    peer_key_file: str = _p('', 'File holding the fleet key (16+ bytes, shared by the robots, '
                            'never sent or logged): every peer message is authenticated with '
                            'HMAC-SHA256 and others are refused (empty = unauthenticated, for '
                            'a trusted ROS domain)', read_only=True)
    peer_allowlist: str = _p('', "Robot ids accepted as peers, e.g. '1,2,3' (empty = any)",
                             read_only=True)
    peer_max_robots: int = _p(32, 'Peer robots tracked; the least recently heard is dropped '
                              'for a new one', low=1, high=100_000, read_only=True)
    peer_replay_window_sec: float = _p(60.0, 'With a fleet key: largest difference between a '
                                       "peer message's stamp and this clock (replays and "
                                       'unsynchronised clocks are refused)', low=1.0,
                                       high=86400.0, read_only=True)
    peer_descriptor_rate: float = _p(50.0, 'Descriptors a second accepted from one robot '
                                     '(beyond a burst of peer_catchup + 100)', low=0.1,
                                     high=1e6, read_only=True)
    peer_request_rate: float = _p(100.0, 'Cloud requests a second answered for one robot '
                                  '(burst 500; 200 a second for all together)', low=0.1,
                                  high=1e6, read_only=True)
    peer_max_cloud_points: int = _p(100_000, 'Largest peer keyframe cloud accepted, points '
                                    '(bigger replies are refused unread)', low=100,
                                    high=2_000_000, read_only=True)
    peer_backoff_sec: float = _p(30.0, 'A peer that lets 3 cloud requests in a row time out is '
                                 'not asked for this long (doubling while it stays silent)',
                                 low=1.0, high=3600.0, read_only=True)

    def _validate_cross(self) -> None:
        if 0 < self.kiss_max_range <= self.kiss_min_range:
            raise ConfigError(f'kiss_max_range: {self.kiss_max_range} must be greater than '
                              f'kiss_min_range ({self.kiss_min_range})')


def param_specs() -> tuple[ParamSpec, ...]:
    """Return the specs of every setting of the node: core first, then node-only."""
    return SolidConfig.specs() + NodeConfig.specs()


def is_standard_ros_parameter(name: str) -> bool:
    """Whether ``name`` is a parameter every rclpy node accepts (``use_sim_time``,
    ``qos_overrides.*``, ...), which a shared parameter file may carry."""
    return name in _ROS_STANDARD or name == 'qos_overrides' or name.startswith('qos_overrides.')


def unknown_parameters(names: Iterable[str]) -> list[str]:
    """The names, sorted, that are neither a setting of the node nor a standard ROS parameter
    (typos in a parameter file or a ``-p`` override)."""
    known = {s.name for s in param_specs()}
    return sorted(n for n in names if n not in known and not is_standard_ros_parameter(n))


def check_parameters(values: Mapping[str, Any], source: str | Path | None = None) -> None:
    """Check parameter values as the node receives them from a file or the command line.

    Stricter than keyword construction: like ROS 2, an integer is refused for a
    floating-point setting (``90`` for ``fov_width_deg``) and a float for an integer one.
    Cross-setting rules are left to the configuration classes (other files may complete them).

    Raises:
        ConfigError: unknown key, wrong type or value out of range; prefixed with ``source``.
    """
    specs = {s.name: s for s in param_specs()}
    prefix = f'{source}: ' if source is not None else ''
    for key, value in values.items():
        spec = specs.get(key)
        if spec is None:
            if is_standard_ros_parameter(key):
                continue
            raise ConfigError(f'{prefix}unknown parameter {key!r} (see config/solid.yaml for '
                              'the valid names)')
        wrong_number = (spec.type is float and isinstance(value, int)
                        and not isinstance(value, bool)) or (
            spec.type is int and isinstance(value, float))
        try:
            if wrong_number:
                raise ConfigError(type_message(spec, value))
            _coerce(spec, value)
        except ConfigError as err:
            raise ConfigError(f'{prefix}{err}') from err


def load_parameter_file(path: str | Path, node_name: str = 'solid_node') -> dict[str, Any]:
    """:func:`load_yaml_parameters` then :func:`check_parameters`: the node's and the offline
    tools' one rule for a parameter file.

    Raises:
        ConfigError: one line naming the file and the problem.
    """
    values = load_yaml_parameters(path, node_name)
    check_parameters(values, path)
    return values


_TYPE_WORDS = {bool: 'true or false', int: 'an integer', float: 'a floating-point number',
               str: 'a string'}


def type_message(spec: ParamSpec, value: Any) -> str:
    """The message for a value of the wrong type (same words for node, files and tools)."""
    msg = (f'{spec.name}: expected {_TYPE_WORDS[spec.type]} in {spec.range_text()}, '
           f'got {value!r}')
    if spec.type is float and isinstance(value, int) and not isinstance(value, bool):
        msg += f' (write {float(value)!r}: ROS 2 rejects an integer for a double parameter)'
    return msg
