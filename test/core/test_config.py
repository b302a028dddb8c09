"""SolidConfig and NodeConfig: defaults, validation messages, checked parameter files."""

from __future__ import annotations

from pathlib import Path

import pytest
from bad_inputs import BAD_FILES, write_bad_file
from project_paths import CONFIG_DIR  # noqa: E402

from solid_ros import ConfigError, NodeConfig, SolidConfig
from solid_ros.core.config import load_parameter_file, load_yaml_parameters, param_specs


def test_defaults_are_the_authors_cpp_defaults() -> None:
    cfg = SolidConfig()
    assert (cfg.fov_width_deg, cfg.fov_up_deg, cfg.fov_down_deg) == (360.0, 2.0, -24.8)
    assert (cfg.min_range, cfg.max_range, cfg.voxel_size) == (3.0, 80.0, 0.4)
    assert (cfg.num_range, cfg.num_angle, cfg.num_height, cfg.max_distance) == (40, 60, 32, 80.0)


def test_keyword_construction_and_type_coercion() -> None:
    cfg = SolidConfig(fov_width_deg=90, num_angle=72.0)
    assert cfg.fov_width_deg == 90.0 and isinstance(cfg.fov_width_deg, float)
    assert cfg.num_angle == 72 and isinstance(cfg.num_angle, int)


@pytest.mark.parametrize('key, value, words', [
    ('fov_width_deg', 400.0, ['fov_width_deg', '[1.0, 360.0]']),
    ('num_range', 0, ['num_range', '[1, 1024]']),
    ('num_angle', 6.5, ['num_angle', 'integer']),
    ('voxel_size', float('nan'), ['voxel_size', 'not finite']),
    ('search', 'octree', ['search', "'kdtree'", "'brute'"]),
    ('min_range', 'far', ['min_range', 'number']),
    ('fov_down_deg', 5.0, ['fov_up_deg', 'fov_down_deg']),
    ('min_range', 90.0, ['max_range', 'min_range']),
])
def test_invalid_values_name_key_and_range(key: str, value: object, words: list[str]) -> None:
    with pytest.raises(ConfigError) as info:
        SolidConfig(**{key: value})
    for word in words:
        assert word in str(info.value)


def test_marker_bound_is_a_bounded_integer() -> None:
    assert NodeConfig().marker_max_loops == 1000
    assert NodeConfig(marker_max_loops=0).marker_max_loops == 0  # markers off
    for bad in (-1, 100_001, 2.5):
        with pytest.raises(ConfigError, match=r'marker_max_loops.*\[0, 100000\]'):
            NodeConfig(marker_max_loops=bad)


def test_replace_validates_and_rejects_unknown_keys() -> None:
    cfg = SolidConfig()
    assert cfg.replace(distance_threshold=0.2).distance_threshold == 0.2
    with pytest.raises(ConfigError, match='distance_threshold'):
        cfg.replace(distance_threshold=3.0)
    with pytest.raises(ConfigError, match="unknown parameter 'typo'"):
        cfg.replace(typo=1)


def test_fingerprint_tracks_only_descriptor_settings() -> None:
    cfg = SolidConfig()
    assert cfg.fingerprint() == cfg.replace(distance_threshold=0.3).fingerprint()
    assert cfg.fingerprint() != cfg.replace(voxel_size=0.5).fingerprint()
    assert set(cfg.shape_params()) >= {'num_range', 'num_angle', 'num_height', 'voxel_size'}


def test_shipped_default_yaml_equals_defaults() -> None:
    assert SolidConfig.from_yaml(CONFIG_DIR / 'solid.yaml') == SolidConfig()
    assert NodeConfig.from_yaml(CONFIG_DIR / 'solid.yaml') == NodeConfig()


@pytest.mark.parametrize('path', sorted(CONFIG_DIR.glob('*.yaml')), ids=lambda p: p.name)
def test_every_shipped_yaml_is_valid_and_commented(path: Path) -> None:
    SolidConfig.from_yaml(path)
    NodeConfig.from_yaml(path)
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        stripped = line.strip()
        if stripped and not stripped.startswith('#') and stripped.count(':') == 1 \
                and not stripped.endswith(':'):
            assert lines[i - 1].strip().startswith('#'), f'{path.name}: no comment for {line}'


def test_default_yaml_lists_every_parameter() -> None:
    params = load_yaml_parameters(CONFIG_DIR / 'solid.yaml')
    assert set(params) == {s.name for s in param_specs()}


def test_yaml_layout_errors_are_clear(tmp_path: Path) -> None:
    bad = tmp_path / 'bad.yaml'
    bad.write_text('solid_node:\n  ros__parameters:\n    num_range: -3\n')
    with pytest.raises(ConfigError, match='num_range'):
        SolidConfig.from_yaml(bad)
    bad.write_text('other_node:\n  ros__parameters:\n    num_range: 3\n')
    with pytest.raises(ConfigError, match="no ros__parameters block for node '/solid_node'"):
        SolidConfig.from_yaml(bad)
    bad.write_text('solid_node:\n  ros__parameters:\n    nmu_range: 3\n')
    with pytest.raises(ConfigError, match="unknown parameter 'nmu_range'"):
        SolidConfig.from_yaml(bad)
    bad.write_text('solid_node: [\n')
    with pytest.raises(ConfigError, match='not valid YAML'):
        SolidConfig.from_yaml(bad)
    with pytest.raises(ConfigError, match='cannot read'):
        SolidConfig.from_yaml(tmp_path / 'missing.yaml')


def test_wildcard_block_and_node_block_merge(tmp_path: Path) -> None:
    f = tmp_path / 'p.yaml'
    f.write_text('/**:\n  ros__parameters:\n    use_sim_time: true\n    num_angle: 90\n'
                 'solid_node:\n  ros__parameters:\n    num_range: 20\n')
    cfg = SolidConfig.from_yaml(f)
    assert (cfg.num_angle, cfg.num_range) == (90, 20)


@pytest.mark.parametrize('name', sorted(BAD_FILES))
def test_bad_parameter_files_give_one_line_naming_the_file(tmp_path: Path, name: str) -> None:
    path = write_bad_file(tmp_path, name)
    with pytest.raises(ConfigError) as info:
        SolidConfig.from_yaml(path)
    text = str(info.value)
    assert text.startswith(f'{path}: ') and '\n' not in text and len(text) < 400, text


def test_integer_for_float_names_the_fix(tmp_path: Path) -> None:
    path = write_bad_file(tmp_path, 'integer for float')
    with pytest.raises(ConfigError, match=r'got 90 \(write 90.0: ROS 2 rejects an integer'):
        load_parameter_file(path)
    # Keyword construction in Python stays lenient.
    assert SolidConfig(fov_width_deg=90).fov_width_deg == 90.0


def test_auto_step_registration_is_resolved_for_the_odometry_in_use() -> None:
    cfg = SolidConfig()
    assert cfg.backend_step_registration == 'auto'
    assert cfg.for_odometry(scan_only=True).backend_step_registration == 'on'
    assert cfg.for_odometry(scan_only=False).backend_step_registration == 'off'
    for mode in ('on', 'off'):  # a setting given stays
        fixed = cfg.replace(backend_step_registration=mode)
        assert fixed.for_odometry(scan_only=True) is fixed
        assert fixed.for_odometry(scan_only=False) is fixed
    with pytest.raises(ConfigError, match='backend_step_registration'):
        SolidConfig(backend_step_registration='maybe')
