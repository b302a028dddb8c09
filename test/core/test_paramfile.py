"""The parameter-file layout: node blocks, wildcards and namespaces, as rcl applies them."""

from __future__ import annotations

from pathlib import Path

import pytest

from solid_ros import ConfigError
from solid_ros.core.paramfile import load_yaml_parameters


@pytest.mark.parametrize('key, applies', [
    ('solid_node', True), ('/solid_node', True), ('/**', True), ('/**/solid_node', True),
    ('/*', True), ('/solid_*', True), ('other', False), ('/ns/solid_node', False),
    ('/*/solid_node', False),
])
def test_blocks_match_node_names_as_rcl_does(tmp_path: Path, key: str, applies: bool) -> None:
    f = tmp_path / 'p.yaml'
    f.write_text(f'{key}:\n  ros__parameters:\n    num_range: 20\n')
    if applies:
        assert load_yaml_parameters(f) == {'num_range': 20}
    else:
        with pytest.raises(ConfigError, match='no ros__parameters block'):
            load_yaml_parameters(f)


def test_nested_namespace_blocks(tmp_path: Path) -> None:
    f = tmp_path / 'p.yaml'
    f.write_text('robot:\n  solid_node:\n    ros__parameters:\n      num_range: 20\n')
    assert load_yaml_parameters(f, '/robot/solid_node') == {'num_range': 20}
    with pytest.raises(ConfigError, match='blocks: /robot/solid_node'):
        load_yaml_parameters(f)
