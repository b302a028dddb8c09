"""Command line of ``solid_node`` before ROS starts: ``--help`` and the parameter-file check.

rcl parses ``--ros-args`` itself inside ``rclpy.init()``, where a bad parameter file ends in an
``RCLError`` traceback. :func:`scan_arguments` finds the parameter files and the node's name in
the arguments first, so that :func:`check_parameter_files` can refuse a bad file with one line
by the rule ``solid_replay --params`` uses too
(:func:`~solid_ros.core.config.load_parameter_file`). Nothing here imports rclpy.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from solid_ros.core.config import NodeConfig, SolidConfig, load_parameter_file
from solid_ros.core.errors import ConfigError
from solid_ros.ros.frames import FRAME_KEYS, frame_conflict

__all__ = ['NODE_NAME', 'NodeArguments', 'check_parameter_files', 'scan_arguments', 'usage']

NODE_NAME = 'solid_node'
# rcl's ROS arguments that take a value (rcl/arguments.h); the others are flags.
_WITH_VALUE = frozenset({'-r', '--remap', '-p', '--param', '--params-file', '-e', '--enclave',
                         '--log-level', '--log-file-name', '--log-config-file'})


@dataclass
class NodeArguments:
    """What :func:`scan_arguments` found.

    Attributes:
        help: ``-h`` or ``--help`` outside the ROS arguments.
        params_files: every ``--params-file``, in order.
        node_name: the node's name after ``__node:=`` remapping.
        namespace: the node's namespace after ``__ns:=`` remapping.
    """

    help: bool = False
    params_files: list[str] = field(default_factory=list)
    node_name: str = NODE_NAME
    namespace: str = '/'

    @property
    def fully_qualified_name(self) -> str:
        """``/namespace/name`` as rcl matches it against parameter-file blocks."""
        ns = self.namespace.strip('/')
        return f'/{ns}/{self.node_name}' if ns else f'/{self.node_name}'


def scan_arguments(argv: Sequence[str]) -> NodeArguments:
    """Find ``--help``, ``--params-file`` and name remapping in a full ``argv``.

    Args:
        argv: the process arguments, program name first (as ``sys.argv``).

    Raises:
        ConfigError: a ROS option that needs a value is the last argument.
    """
    out = NodeArguments()
    ros = False
    args = list(argv[1:])
    i = 0
    while i < len(args):
        arg = args[i]
        if arg == '--ros-args':
            ros = True
        elif ros and arg == '--':
            ros = False
        elif not ros and arg in ('-h', '--help'):
            out.help = True
        elif ros and arg in _WITH_VALUE:
            if i + 1 >= len(args) or args[i + 1] in ('--', '--ros-args'):
                raise ConfigError(f'{arg} needs a value (e.g. {arg} FILE after --ros-args)')
            value = args[i + 1]
            if arg == '--params-file':
                out.params_files.append(value)
            elif arg in ('-r', '--remap'):
                _remap(out, value)
            i += 1
        i += 1
    return out


def _remap(out: NodeArguments, rule: str) -> None:
    target, sep, value = rule.partition(':=')
    if not sep:
        return
    node, colon, name = target.rpartition(':')
    if colon and node not in (NODE_NAME, out.node_name):
        return  # a rule for another node
    if name == '__node' and value:
        out.node_name = value
    elif name == '__ns' and value:
        out.namespace = value


def check_parameter_files(args: NodeArguments) -> None:
    """Refuse any parameter file the node should not start with.

    Every file must be UTF-8 YAML in the ROS 2 layout with a block for this node (an empty
    file, or one whose blocks are all for other nodes, is refused as ``solid_replay`` refuses
    it), and every value must be a setting of the node, of the right type and in range. The
    frames the files set, later files over earlier ones as rcl reads them, must not make a
    transform from a frame to itself (:func:`~solid_ros.ros.frames.frame_conflict`).

    Raises:
        ConfigError: one line naming the file and the problem (for the frames, the last file
            that set one of them).
    """
    frames: dict[str, Any] = {}
    last = ''
    for path in args.params_files:
        values = load_parameter_file(path, args.fully_qualified_name)
        if any(key in values for key in FRAME_KEYS):
            frames.update({key: values[key] for key in FRAME_KEYS if key in values})
            last = path
    problem = frame_conflict(NodeConfig(**frames)) if frames else None
    if problem is not None:
        raise ConfigError(f'{last}: {problem}')


_SYNOPSIS = """\
usage: solid_node [-h] [--ros-args [--params-file FILE.yaml ...] [-p NAME:=VALUE ...]
                  [-r points:=TOPIC] [-r odom:=TOPIC] [-r __node:=NAME] [-r __ns:=/NS]]

SOLiD LiDAR loop-closure node: PointCloud2 (and odometry) in, verified loops with a 6-DoF pose
out. -h, --help prints this and exits without starting ROS.
Exit status: 0 after SIGINT or shutdown, 1 database cannot be loaded, 2 bad parameter file,
parameter value or ROS argument.

parameter files (--params-file, several allowed, later ones and -p override earlier ones):
  ROS 2 layout: "solid_node: ros__parameters: {NAME: VALUE}" ("/**:" blocks apply too).
  A sensor preset (config/avia.yaml, hdl64.yaml, ...) sets only what the sensor and its use
  decide; every other parameter takes the default below. config/solid.yaml lists them all.
  Floats keep a decimal point: ROS 2 rejects 360 for a double parameter (write 360.0).
  solid_replay BAG --suggest-params prints a preset measured from a bag's first clouds.

remapping (-r FROM:=TO):
  points:=TOPIC, odom:=TOPIC      the subscriptions below
  __node:=NAME, __ns:=/NS         the node's name and namespace (the file's block must match)

topics:
  points (sub)            sensor_msgs/PointCloud2
  odom (sub, use_odom)    nav_msgs/Odometry
  ~/loop_candidates (pub) std_msgs/Float64MultiArray, one row per loop
  ~/loop_markers (pub)    visualization_msgs/MarkerArray, latched (transient local):
                          the newest marker_max_loops loops
  /diagnostics (pub)      diagnostic_msgs/DiagnosticArray
  with backend: ~/path, ~/odometry, ~/map and the map -> odom TF on /tf
  with odometry_source kiss_icp: ~/kiss/odometry

services:
  ~/save_database         std_srvs/Trigger: write database_save_path
  ~/reset                 std_srvs/Trigger: clear the database and the queue
  with backend: ~/save_map, ~/save_trajectory (into output_directory)

parameters by group: NAME (type, default DEFAULT, allowed RANGE[, read-only]); read-only ones
are fixed when the node starts, the others may change at runtime (only stricter unless
allow_runtime_weakening is true):"""


def usage() -> str:
    """The ``solid_node --help`` text: how to run it, parameter files and remapping, topics
    and services, then every parameter by group with its type, default, range, whether it is
    read-only and its description (all from the schema)."""
    lines = [_SYNOPSIS]
    group = ''
    for spec in SolidConfig.specs() + NodeConfig.specs():
        if spec.group != group:
            group = spec.group
            lines += ['', f'  {group}']
        ro = ', read-only' if spec.read_only else ''
        lines.append(f'    {spec.name} ({spec.type.__name__}, default {spec.default!r}, '
                     f'allowed {spec.range_text()}{ro})')
        lines += textwrap.wrap(spec.description, 94, initial_indent=' ' * 8,
                               subsequent_indent=' ' * 8)
    return '\n'.join(lines)
