"""The shipped parameter files list every setting with its comment (tools.presets keeps them)."""

from __future__ import annotations

from pathlib import Path

from solid_ros.core.config import load_yaml_parameters, param_specs
from solid_ros.tools import presets


def test_shipped_files_are_up_to_date() -> None:
    assert presets.main(['--check']) == 0


def test_render_adds_missing_settings_and_keeps_values(tmp_path: Path) -> None:
    path = tmp_path / 'mine.yaml'
    path.write_text('# my robot\nsolid_node:\n  ros__parameters:\n    num_range: 20\n'
                    '    verify: false\n')
    assert presets.main([str(path)]) == 0
    text = path.read_text()
    assert text.startswith('# my robot\nsolid_node:\n')
    values = load_yaml_parameters(path)
    assert set(values) == {s.name for s in param_specs()}
    assert values['num_range'] == 20 and values['verify'] is False
    assert presets.main(['--check', str(path)]) == 0
    path.write_text(text.replace('    # N_r', '    # changed'))
    assert presets.main(['--check', str(path)]) == 1
