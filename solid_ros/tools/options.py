"""What a replay reads, how it scores and where it writes: :class:`ReplayOptions`.

Each limit is checked once, here: :class:`ReplayOptions` refuses a bad value with
:class:`~solid_ros.core.errors.ConfigError`, and the command line parses its numbers through
the same checks (:func:`cli_number`), so ``--radius -1`` is a bad command line (exit 2) and
``replay(..., radius=-1)`` a bad input, for one rule.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, TextIO

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import ConfigError, PoseError

__all__ = ['ODOMETRY_CHOICES', 'PROGRESS_MODES', 'ReplayOptions', 'check_degrees',
           'check_fraction', 'check_metres', 'cli_number', 'fleet_note']

PROGRESS_MODES = ('auto', 'bar', 'lines', 'quiet')
# Where a replay's odometry comes from: the bag's Odometry topic, or KISS-ICP over the clouds.
ODOMETRY_CHOICES = ('bag', 'kiss-icp')


def check_metres(value: float) -> str | None:
    """What is wrong with a distance in metres (None: nothing)."""
    return None if 0.0 < value < math.inf else 'must be a positive number of metres'


def check_degrees(value: float) -> str | None:
    """What is wrong with an angle limit in degrees (None: nothing)."""
    return None if 0.0 < value <= 180.0 else 'must be in (0, 180] degrees'


def check_fraction(value: float) -> str | None:
    """What is wrong with a precision (None: nothing)."""
    return None if 0.0 < value <= 1.0 else 'must be in (0, 1]'


def cli_number(check: Callable[[float], str | None], name: str) -> Callable[[str], float]:
    """An argparse ``type`` that parses a float and applies ``check`` (exit 2 when it fails)."""
    def parse(text: str) -> float:
        value = float(text)  # argparse reports a ValueError as an invalid value
        problem = check(value)
        if problem is not None:
            raise argparse.ArgumentTypeError(f'{problem}, got {text!r}')
        return value

    parse.__name__ = name  # argparse names it in 'invalid <name> value'
    return parse


# Option, its command-line name and its check, in the order they are checked.
_CHECKS: tuple[tuple[str, str, Callable[[float], str | None]], ...] = (
    ('radius', '--radius', check_metres),
    ('max_heading_deg', '--max-heading-deg', check_degrees),
    ('max_pose_error_m', '--max-pose-error-m', check_metres),
    ('max_pose_error_deg', '--max-pose-error-deg', check_degrees),
    ('target_precision', '--target-precision', check_fraction),
)

# Options that mean nothing to a fleet replay, with their flags and why: the command line
# ignores them with one line each (for_fleet), replay_fleet refuses them.
_SINGLE_BAG = (
    ('poses', '--poses', "a fleet is scored against each bag's odometry"),
    ('times', '--times', 'it goes with --poses'),
    ('load_db', '--load-db', 'each robot starts a database of its own'),
    ('save_db', '--save-db', 'each robot has a database of its own; none is saved'),
    ('map', '--map', 'a fleet replay writes no map of clouds'),
)


def fleet_note(flag: str) -> str:
    """The line for an option of one bag only given to a fleet replay: ignored, and why."""
    why = {f: w for _, f, w in _SINGLE_BAG}[flag]
    return f'ignored for a fleet replay: {flag} ({why})'


@dataclass(frozen=True)
class ReplayOptions:
    """Everything a replay takes besides the bag and the detector settings.

    Attributes:
        node_config: node settings (odometry use and pairing tolerance).
        topic: PointCloud2 topic (default: the bag's only one).
        odom_topic: Odometry topic fed to the detector as the node's ``odom`` (default: the
            bag's only one, if any) and used as reference when ``poses`` is not given.
        use_odom: feed odometry to the detector (default ``node_config.use_odom``).
        odometry: ``'bag'`` (the bag's Odometry topic) or ``'kiss-icp'`` (KISS-ICP registers
            the clouds, with ``node_config``'s ``kiss_*`` settings); default: the node's
            ``odometry_source`` (``'topic'`` is the bag's).
        poses: reference poses file (KITTI 3x4 or TUM); KITTI files pair with scans by order
            unless ``times`` gives their stamps.
        times: stamps of a KITTI poses file.
        radius: true-loop distance in metres.
        max_heading_deg: also require headings within this many degrees for a true loop.
        max_pose_error_m: a published loop is correct within this translation error.
        max_pose_error_deg: ... and this rotation error of the reference relative pose.
        target_precision: the sweep recommends the setting reaching this precision.
        out_dir: where to write candidates.csv, report.json and plots (None: nothing).
        plots: also write PNG plots to ``out_dir`` when poses are available (off by
            default: matplotlib and the six figures cost more than the replay of a short
            bag; the demo turns them on).
        map: write the map of the keyframe clouds at their corrected poses (``map.pcd``).
        load_db: database file to load before the run (its scans are searched too).
        save_db: where to save the database after the run.
        params_file: recorded in the report.
        progress: 'auto', 'bar', 'lines' or 'quiet'.
        stream: progress stream (default stderr).

    Raises:
        ConfigError: a limit out of range or an unknown progress mode (the option named).
        PoseError: ``times`` without ``poses``.
    """

    node_config: NodeConfig = NodeConfig()
    topic: str | None = None
    odom_topic: str | None = None
    use_odom: bool | None = None
    odometry: str | None = None
    poses: str | Path | None = None
    times: str | Path | None = None
    radius: float = 5.0
    max_heading_deg: float | None = None
    max_pose_error_m: float = 1.0
    max_pose_error_deg: float = 3.0
    target_precision: float = 1.0
    out_dir: str | Path | None = None
    plots: bool = False
    map: bool = False
    load_db: str | Path | None = None
    save_db: str | Path | None = None
    params_file: str | Path | None = None
    progress: str = 'auto'
    stream: TextIO | None = None

    def __post_init__(self) -> None:
        if self.times is not None and self.poses is None:
            raise PoseError('--times needs --poses')
        for name, flag, check in _CHECKS:
            value = getattr(self, name)
            problem = None if value is None else check(value)
            if problem is not None:
                raise ConfigError(f'{flag} {problem}, got {value}')
        if self.odometry is not None and self.odometry not in ODOMETRY_CHOICES:
            raise ConfigError(f'--odometry must be one of {", ".join(ODOMETRY_CHOICES)}, got '
                              f'{self.odometry!r}')
        if self.progress not in PROGRESS_MODES:
            raise ConfigError(f'progress must be one of {", ".join(PROGRESS_MODES)}, got '
                              f'{self.progress!r}')

    @classmethod
    def of(cls, options: ReplayOptions | None = None, **changes: Any) -> ReplayOptions:
        """``options`` (default: all defaults) with ``changes``, checked.

        Raises:
            TypeError: a change names no option.
        """
        unknown = set(changes) - {f.name for f in fields(cls)}
        if unknown:
            raise TypeError(f'unknown replay option(s): {", ".join(sorted(unknown))}')
        if 'node_config' in changes and changes['node_config'] is None:
            changes['node_config'] = NodeConfig()  # None: the node's defaults
        return replace(options if options is not None else cls(), **changes)

    def single_bag(self) -> list[tuple[str, str]]:
        """``(option, flag)`` of each option set here that only a one-bag replay takes."""
        default = ReplayOptions()
        return [(name, flag) for name, flag, _ in _SINGLE_BAG
                if getattr(self, name) != getattr(default, name)]

    def for_fleet(self) -> tuple[ReplayOptions, list[str]]:
        """These options for a fleet replay: those of one bag only back at their defaults,
        and one line for each of them that was set, saying it is ignored and why
        (:func:`fleet_note`)."""
        default = ReplayOptions()
        set_here = dict(self.single_bag())
        lines = [fleet_note(flag) for flag in set_here.values()]
        return replace(self, **{name: getattr(default, name) for name in set_here}), lines

    @property
    def feed_odom(self) -> bool:
        """Whether the detector gets the odometry (``use_odom``, else the node's setting)."""
        return self.node_config.use_odom if self.use_odom is None else self.use_odom

    @property
    def odometry_mode(self) -> str:
        """``'bag'`` or ``'kiss-icp'``: ``odometry``, else the node's ``odometry_source``."""
        if self.odometry is not None:
            return self.odometry
        return 'kiss-icp' if self.node_config.odometry_source == 'kiss_icp' else 'bag'

    @property
    def tolerance_ns(self) -> int:
        """The odometry pairing tolerance in integer nanoseconds."""
        return int(round(self.node_config.odom_tolerance_sec * 1e9))
