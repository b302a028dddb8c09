"""ROS parameters of solid_node: descriptors from the schema, start-up and runtime validation."""

from __future__ import annotations

from pathlib import Path

import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')

from project_paths import CONFIG_DIR  # noqa: E402
from rcl_interfaces.msg import ParameterType  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from solid_ros.core.config import NodeConfig, SolidConfig, param_specs  # noqa: E402
from solid_ros.core.errors import ConfigError  # noqa: E402
from solid_ros.ros.params import (  # noqa: E402
    WEAKENS,
    apply_changes,
    declare_all,
    make_descriptor,
    unknown_overrides,
    weakening,
)

PRESETS = sorted(CONFIG_DIR.glob('*.yaml'))


def _node(ctx: Context, *, overrides: list[Parameter] | None = None,
          params_file: Path | None = None) -> Node:
    cli = ['--ros-args', '--params-file', str(params_file)] if params_file else None
    return Node('solid_node', context=ctx, parameter_overrides=overrides or [], cli_args=cli)


def test_descriptors_carry_type_range_and_read_only() -> None:
    for spec in param_specs():
        d = make_descriptor(spec)
        assert d.name == spec.name
        assert d.description == spec.description
        assert d.read_only == spec.read_only
        if spec.type is float:
            assert d.type == ParameterType.PARAMETER_DOUBLE
            assert d.floating_point_range[0].from_value == spec.low
            assert d.floating_point_range[0].to_value == spec.high
        elif spec.type is int:
            assert d.type == ParameterType.PARAMETER_INTEGER
            assert d.integer_range[0].from_value == spec.low
            assert d.integer_range[0].to_value == spec.high
        elif spec.choices is not None:
            assert all(c in d.additional_constraints for c in spec.choices)
    by_name = {s.name: make_descriptor(s) for s in param_specs()}
    assert by_name['num_range'].read_only
    assert not by_name['distance_threshold'].read_only


def test_defaults_without_overrides(context: Context) -> None:
    node = _node(context)
    try:
        solid, node_cfg = declare_all(node)
        assert solid == SolidConfig()
        assert node_cfg == NodeConfig()
        assert node.get_parameter('distance_threshold').value == SolidConfig().distance_threshold
    finally:
        node.destroy_node()


@pytest.mark.parametrize('path', PRESETS, ids=[p.name for p in PRESETS])
def test_shipped_yaml_matches_offline_loader(context: Context, path: Path) -> None:
    node = _node(context, params_file=path)
    try:
        solid, node_cfg = declare_all(node)
    finally:
        node.destroy_node()
    assert solid == SolidConfig.from_yaml(path)
    assert node_cfg == NodeConfig.from_yaml(path)


def test_presets_exist_and_differ() -> None:
    names = {p.name for p in PRESETS}
    assert {'solid.yaml', 'hdl64.yaml', 'avia.yaml', 'spinning_fov90.yaml'} <= names
    assert SolidConfig.from_yaml(CONFIG_DIR / 'spinning_fov90.yaml').fov_width_deg == 90.0
    avia = SolidConfig.from_yaml(CONFIG_DIR / 'avia.yaml')
    assert avia.fov_up_deg > 30.0 and avia.fov_down_deg < -30.0


def test_every_preset_has_one_comment_per_parameter() -> None:
    for path in PRESETS:
        lines = path.read_text().splitlines()
        keys = [i for i, ln in enumerate(lines) if ln.startswith('    ') and ':' in ln
                and not ln.strip().startswith('#')]
        # The reference lists every setting; a sensor preset what its sensor decides.
        assert (len(keys) == len(param_specs()) if path.name == 'solid.yaml'
                else 0 < len(keys) <= 40), path
        for i in keys:
            assert lines[i - 1].strip().startswith('#'), (path, lines[i])


def test_integer_for_double_is_reported_clearly(context: Context) -> None:
    node = _node(context, overrides=[Parameter('fov_width_deg', value=360)])
    try:
        with pytest.raises(ConfigError, match=r'fov_width_deg.*360\.0'):
            declare_all(node)
    finally:
        node.destroy_node()


def test_out_of_range_names_parameter_and_range(context: Context) -> None:
    node = _node(context, overrides=[Parameter('distance_threshold', value=3.0)])
    try:
        with pytest.raises(ConfigError, match=r'distance_threshold.*\[0\.0, 2\.0\]'):
            declare_all(node)
    finally:
        node.destroy_node()


def test_bad_choice_and_cross_rule_are_rejected(context: Context) -> None:
    node = _node(context, overrides=[Parameter('search', value='linear')])
    try:
        with pytest.raises(ConfigError, match='search'):
            declare_all(node)
    finally:
        node.destroy_node()
    node = _node(context, overrides=[Parameter('fov_up_deg', value=-30.0)])
    try:
        with pytest.raises(ConfigError, match='fov_up_deg'):
            declare_all(node)
    finally:
        node.destroy_node()


def test_frames_that_make_a_self_transform_are_rejected(context: Context) -> None:
    # -p overrides and in-process nodes do not pass the command-line check of the files.
    node = _node(context, overrides=[Parameter('odom_frame', value='map')])
    try:
        with pytest.raises(ConfigError, match=r"map_frame and odom_frame .* both 'map'"):
            declare_all(node)
    finally:
        node.destroy_node()


def test_unknown_parameter_in_file_is_rejected(context: Context, tmp_path: Path) -> None:
    path = tmp_path / 'typo.yaml'
    path.write_text('solid_node:\n  ros__parameters:\n    distance_treshold: 0.1\n')
    node = _node(context, params_file=path)
    try:
        with pytest.raises(ConfigError, match='distance_treshold'):
            declare_all(node)
    finally:
        node.destroy_node()
    assert unknown_overrides(['use_sim_time', 'qos_overrides./points.subscription.depth']) == []


def test_runtime_changes_validated_by_the_schema() -> None:
    solid, node_cfg = SolidConfig(), NodeConfig()
    new_solid, new_node = apply_changes(solid, node_cfg, [
        Parameter('distance_threshold', value=0.12), Parameter('odom_tolerance_sec', value=0.2)],
        allow_weakening=True)
    assert new_solid.distance_threshold == 0.12
    assert new_node.odom_tolerance_sec == 0.2
    assert solid.distance_threshold == SolidConfig().distance_threshold
    with pytest.raises(ConfigError, match=r'distance_threshold.*\[0\.0, 2\.0\]'):
        apply_changes(solid, node_cfg, [Parameter('distance_threshold', value=5.0)])
    with pytest.raises(ConfigError, match='num_range.*read-only'):
        apply_changes(solid, node_cfg, [Parameter('num_range', value=20)])
    with pytest.raises(ConfigError, match='unknown'):
        apply_changes(solid, node_cfg, [Parameter('nonsense', value=1)])
    with pytest.raises(ConfigError, match='database_save_path.*read-only'):
        apply_changes(solid, node_cfg, [Parameter('database_save_path', value='/etc/passwd')])


def test_every_runtime_setting_has_a_direction_and_weakening_is_refused() -> None:
    tunable = {s.name for s in param_specs() if not s.read_only}
    assert tunable == set(WEAKENS), tunable ^ set(WEAKENS)
    solid, node_cfg = SolidConfig(), NodeConfig()
    with pytest.raises(ConfigError, match=r'distance_threshold: 0\.03 -> 0\.5 would weaken'):
        apply_changes(solid, node_cfg, [Parameter('distance_threshold', value=0.5)])
    with pytest.raises(ConfigError, match='verify_min_overlap.*allow_runtime_weakening'):
        apply_changes(solid, node_cfg, [Parameter('verify_min_overlap', value=0.1)])
    # Several at once: one weakening change refuses them all.
    with pytest.raises(ConfigError, match='verify_max_conflict'):
        apply_changes(solid, node_cfg, [Parameter('distance_threshold', value=0.01),
                                        Parameter('verify_max_conflict', value=0.5)])
    tighter, _ = apply_changes(solid, node_cfg, [Parameter('distance_threshold', value=0.01),
                                                 Parameter('verify_min_spread', value=0.01)])
    assert (tighter.distance_threshold, tighter.verify_min_spread) == (0.01, 0.01)
    assert weakening('odom_check_drift', 0.1, 0.0) and not weakening('odom_check_drift', 0.0,
                                                                      0.05)
    assert weakening('heading_match', 'full', 'overlap') and weakening('min_margin', 0.1, 0.0)
    assert not weakening('exclude_recent_frames', 50, 60)
    assert weakening('verify_covariance_scale', 1.0, 0.5) and weakening('backend_loop_refuse',
                                                                        12.0, 0.0)
    assert not weakening('map_voxel_size', 0.5, 0.1) and weakening('map_max_points', 10, 11)
    assert NodeConfig().allow_runtime_weakening is False
