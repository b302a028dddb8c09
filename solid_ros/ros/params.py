"""ROS parameters of ``solid_node``: declared from the config schema, validated by it.

Every setting of :class:`~solid_ros.config.SolidConfig` and :class:`~solid_ros.config.NodeConfig`
becomes a parameter whose :class:`ParameterDescriptor` carries the description, the range (or
the allowed strings) and ``read_only`` for settings that change descriptor shape or node
wiring. Start-up errors become :class:`~solid_ros.errors.ConfigError` naming the parameter and
its range; runtime changes are checked by the same dataclass validation as the core.

Runtime changes come from any participant of the ROS domain (``~/set_parameters``), so unless
the parameter file sets ``allow_runtime_weakening: true`` a change is accepted only when it
makes the node stricter: each runtime-tunable setting has a direction in :data:`WEAKENS`
(raising a maximum or lowering a minimum weakens the tests that decide whether a loop is true;
``'any'`` marks a setting without such an order, which is locked; ``'free'`` one whose change is
harmless). Tightening stays open.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Mapping
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
)
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from solid_ros.core.config import (
    NodeConfig,
    ParamSpec,
    SolidConfig,
    is_standard_ros_parameter,
    param_specs,
    type_message,
    unknown_parameters,
)
from solid_ros.core.errors import ConfigError
from solid_ros.core.stamps import INT64
from solid_ros.ros.frames import frame_conflict

__all__ = ['WEAKENS', 'apply_changes', 'changed', 'declare_all', 'make_descriptor',
           'unknown_overrides', 'weakening']

_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
          float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}
# Which runtime change of a tunable setting weakens the node: 'up' (raising it: a maximum,
# a count of chances, a tolerance), 'down' (lowering it: a minimum, an exclusion; 0 often
# turns it off) or 'any' (no order: any change may). A tunable setting missing here counts as
# 'any'. Keyframe gating decides no loop, but a remote change could starve the node of
# keyframes: locked too. The back end's gates and the loops' covariance scale decide how hard
# a loop pulls; its rates and sizes decide its load. 'free': any change is harmless.
WEAKENS: dict[str, str] = {
    'distance_threshold': 'up', 'num_candidates': 'up', 'max_candidates': 'up',
    'exclude_recent_frames': 'down', 'exclude_recent_sec': 'down', 'min_margin': 'down',
    'margin_neighbourhood': 'any', 'min_loop_gap': 'down', 'heading_match': 'any',
    'keyframe_min_sec': 'any', 'keyframe_min_distance': 'any',
    'keyframe_min_rotation_deg': 'any', 'verify_hypotheses': 'up',
    'verify_min_coarse_overlap': 'down', 'verify_min_overlap': 'down', 'verify_max_rmse': 'up',
    'verify_min_constraint': 'down', 'verify_max_conflict': 'up', 'verify_min_spread': 'down',
    'verify_single_object_overlap': 'down', 'verify_max_drift': 'up',
    'verify_max_drift_deg': 'up', 'odom_check_drift': 'up0', 'odom_check_slack_m': 'up',
    'odom_tolerance_sec': 'up', 'peer_timeout_sec': 'up',
    'verify_covariance_scale': 'down', 'graph_candidates': 'up',
    'graph_candidate_radius_m': 'up', 'graph_candidate_sigmas': 'up',
    'graph_candidate_max_radius_m': 'up', 'graph_candidate_min_path_m': 'down',
    'backend_loop_gate': 'up0', 'backend_loop_refuse': 'up0', 'backend_segment_jump_m': 'up',
    'backend_extra_iterations': 'up', 'map_voxel_size': 'free', 'map_max_points': 'up',
    'path_period_sec': 'down', 'map_period_sec': 'down',
}


def make_descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """Return the ROS descriptor of one setting (type, description, range, read-only)."""
    desc = ParameterDescriptor(name=spec.name, type=_TYPES[spec.type],
                               description=spec.description, read_only=spec.read_only)
    if spec.choices is not None:
        desc.additional_constraints = spec.range_text()
    elif spec.type is float and (spec.low is not None or spec.high is not None):
        low = -sys.float_info.max if spec.low is None else float(spec.low)
        high = sys.float_info.max if spec.high is None else float(spec.high)
        desc.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
    elif spec.type is int and (spec.low is not None or spec.high is not None):
        low_i = INT64[0] if spec.low is None else int(spec.low)
        high_i = INT64[1] if spec.high is None else int(spec.high)
        desc.integer_range = [IntegerRange(from_value=low_i, to_value=high_i, step=0)]
    return desc


def unknown_overrides(names: Iterable[str]) -> list[str]:
    """Return the override names that are not settings of the node (typos in a YAML file)."""
    return unknown_parameters(names)


def declare_all(node: Node) -> tuple[SolidConfig, NodeConfig]:
    """Declare every setting on ``node`` and build the validated configurations.

    Values come from the node's overrides (``--params-file``, ``-p``) or the schema defaults.

    Raises:
        ConfigError: an override is unknown, of the wrong type, out of range, or fails a
            cross-parameter rule (among them frames that would make a transform from a frame
            to itself); the message names the parameter and the allowed values.
    """
    # rclpy silently ignores overrides that are never declared; a typo must not be ignored.
    overrides: Mapping[str, Any] = getattr(node, '_parameter_overrides', {}) or {}
    unknown = unknown_overrides(overrides)
    if unknown:
        raise ConfigError(f'{unknown[0]}: unknown parameter of solid_node (see '
                          'config/solid.yaml for the valid names)')
    values: dict[str, Any] = {}
    for spec in param_specs():
        try:
            param = node.declare_parameter(spec.name, spec.default, make_descriptor(spec))
        except InvalidParameterTypeException as err:
            raise ConfigError(_type_message(spec, overrides.get(spec.name))) from err
        except InvalidParameterValueException as err:
            value = _override_value(overrides.get(spec.name))
            raise ConfigError(f'{spec.name}: {value!r} is out of range; allowed '
                              f'{spec.range_text()}') from err
        except ParameterException as err:
            raise ConfigError(f'{spec.name}: {err}') from err
        values[spec.name] = param.value
    solid = SolidConfig.from_dict(values, strict=False)
    node_cfg = NodeConfig.from_dict(values, strict=False)
    problem = frame_conflict(node_cfg)
    if problem is not None:
        raise ConfigError(problem)
    return solid, node_cfg


def weakening(name: str, old: Any, new: Any) -> bool:
    """Whether changing setting ``name`` from ``old`` to ``new`` weakens the node (see
    :data:`WEAKENS`; 'up0': raising weakens, and 0 turns the check off)."""
    if old == new:
        return False
    way = WEAKENS.get(name, 'any')
    if way == 'up0':
        return new == 0 or (old != 0 and new > old)
    if way == 'up':
        return bool(new > old)
    if way == 'down':
        return bool(new < old)
    return way != 'free'


def changed(solid: SolidConfig, node_cfg: NodeConfig, new_solid: SolidConfig,
            new_node: NodeConfig) -> list[tuple[str, Any, Any]]:
    """``(name, old, new)`` of every setting that differs, in schema order."""
    old = {**solid.to_dict(), **node_cfg.to_dict()}
    new = {**new_solid.to_dict(), **new_node.to_dict()}
    return [(s.name, old[s.name], new[s.name]) for s in param_specs()
            if old[s.name] != new[s.name]]


def apply_changes(solid: SolidConfig, node_cfg: NodeConfig, params: Iterable[Parameter],
                  allow_weakening: bool = False) -> tuple[SolidConfig, NodeConfig]:
    """Return the configurations with runtime parameter changes applied and validated.

    Args:
        solid, node_cfg: the settings in force.
        params: the changes asked for.
        allow_weakening: accept changes that weaken the node (see :data:`WEAKENS`); the
            node passes ``allow_runtime_weakening`` from its parameter file.

    Raises:
        ConfigError: a value is invalid, the setting is read-only, or (unless
            ``allow_weakening``) the change would weaken the node; the message says why.
    """
    specs = {s.name: s for s in param_specs()}
    solid_changes: dict[str, Any] = {}
    node_changes: dict[str, Any] = {}
    solid_names = {s.name for s in SolidConfig.specs()}
    for p in params:
        spec = specs.get(p.name)
        if spec is None:
            if is_standard_ros_parameter(p.name):
                continue
            raise ConfigError(f'{p.name}: unknown parameter')
        if spec.read_only:
            raise ConfigError(f'{p.name}: read-only at runtime (changes descriptor shape or '
                              'node wiring); restart the node with the new value')
        target = solid_changes if p.name in solid_names else node_changes
        target[p.name] = p.value
    new_solid = solid.replace(**solid_changes) if solid_changes else solid
    new_node = node_cfg.replace(**node_changes) if node_changes else node_cfg
    if not allow_weakening:
        for name, old, new in changed(solid, node_cfg, new_solid, new_node):
            if weakening(name, old, new):
                raise ConfigError(
                    f'{name}: {old!r} -> {new!r} would weaken the node; refused at runtime '
                    '(set allow_runtime_weakening: true in the parameter file to allow it; '
                    'changes that make it stricter are accepted)')
    return new_solid, new_node


def _override_value(param: Any) -> Any:
    return getattr(param, 'value', param)


def _type_message(spec: ParamSpec, override: Any) -> str:
    return type_message(spec, _override_value(override))
