"""The shipped parameter files: config/solid.yaml holds every setting, a sensor preset only what
its sensor and use decide, and loading a trimmed preset gives what the full one gave."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from project_paths import CONFIG_DIR

from solid_ros.core.config import NodeConfig, SolidConfig, load_yaml_parameters, param_specs
from solid_ros.tools import presets

# The full files before they were trimmed (see its 'about').
BEFORE = json.loads((Path(__file__).parent / 'preset_values_7f254e1.json').read_text())
# Defaults changed on purpose since then (issue 35: KISS-ICP's max range, voxel and jump limit
# from the data, its overlap bar calibrated on the run, deskew wherever clouds carry times).
REDEFINED = {'kiss_max_range', 'kiss_voxel_size', 'kiss_deskew', 'kiss_max_step_m',
             'kiss_min_overlap'}
SHIPPED = sorted(p for p in CONFIG_DIR.glob('*.yaml')
                 if 'ros__parameters:' in p.read_text(encoding='utf-8'))
SENSOR_PRESETS = [p for p in SHIPPED if p.name != presets.REFERENCE]


def _loaded(path: Path) -> dict[str, Any]:
    return SolidConfig.from_yaml(path).to_dict() | NodeConfig.from_yaml(path).to_dict()


def test_shipped_files_are_up_to_date() -> None:
    assert presets.main(['--check']) == 0


@pytest.mark.parametrize('name', sorted(BEFORE['presets']))
def test_trimmed_preset_loads_as_the_full_file_did(name: str) -> None:
    want = {k: v for k, v in (BEFORE['defaults'] | BEFORE['presets'][name]).items()
            if k not in REDEFINED}
    got = _loaded(CONFIG_DIR / name)
    assert {k: got[k] for k in want} == want
    # What differs from a default is written out, never left to the default.
    assert set(BEFORE['presets'][name]) <= set(load_yaml_parameters(CONFIG_DIR / name))


def test_reference_lists_every_setting_in_order() -> None:
    keys = presets.preset_keys((CONFIG_DIR / presets.REFERENCE).read_text())
    assert keys == [s.name for s in param_specs()]
    assert _loaded(CONFIG_DIR / presets.REFERENCE) == (SolidConfig().to_dict()
                                                       | NodeConfig().to_dict())


@pytest.mark.parametrize('path', SENSOR_PRESETS, ids=[p.name for p in SENSOR_PRESETS])
def test_sensor_preset_is_short_and_commented(path: Path) -> None:
    lines = path.read_text().splitlines()
    keys = presets.preset_keys('\n'.join(lines))
    assert len(keys) <= presets.MAX_PRESET_KEYS
    assert set(presets.SENSOR_KEYS) <= set(keys)
    for i, line in enumerate(lines):
        if line.startswith('    ') and not line.strip().startswith('#'):
            assert lines[i - 1].strip().startswith('# '), (path.name, line)
    assert lines[0].startswith('# solid_ros preset: ')


def test_render_trims_a_preset_and_keeps_values_and_notes(tmp_path: Path) -> None:
    path = tmp_path / 'mine.yaml'
    path.write_text('# my robot\nsolid_node:\n  ros__parameters:\n    num_range: 20  # finer\n'
                    "    verify: false\n    capacity: 100000\n    map_frame: 'a  # b'\n")
    assert presets.main([str(path)]) == 0
    text = path.read_text()
    assert text.startswith('# my robot\nsolid_node:\n')
    values = load_yaml_parameters(path)
    assert 'capacity' not in values  # at its default, and no sensor decides it
    assert values['num_range'] == 20 and values['verify'] is False
    assert values['map_frame'] == 'a  # b'
    assert '    num_range: 20  # finer\n' in text
    assert set(values) == set(presets.SENSOR_KEYS) | {'map_frame'}
    assert presets.main(['--check', str(path)]) == 0
    path.write_text(text.replace('    # N_r', '    # changed'))
    assert presets.main(['--check', str(path)]) == 1


def test_full_render_lists_everything(tmp_path: Path) -> None:
    path = tmp_path / 'mine.yaml'
    path.write_text('solid_node:\n  ros__parameters:\n    num_range: 20\n')
    assert presets.main(['--full', str(path)]) == 0
    values = load_yaml_parameters(path)
    assert set(values) == {s.name for s in param_specs()} and values['num_range'] == 20


def test_check_refuses_invalid_and_oversized_files(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / 'bad.yaml'
    bad.write_text('solid_node:\n  ros__parameters:\n    fov_up_deg: -30.0\n')
    assert presets.main(['--check', str(bad)]) == 1
    assert 'fov_up_deg' in capsys.readouterr().err
    big = tmp_path / 'big.yaml'
    settings = {s.name: s for s in param_specs()}
    changed = {'min_margin': 0.1, 'margin_neighbourhood': 3, 'max_candidates': 2,
               'min_loop_gap': 1, 'keyframe_min_sec': 1.0, 'verify_hypotheses': 4,
               'verify_max_rmse': 0.2, 'verify_max_drift': 0.3, 'graph_candidates': 2,
               'backend_extra_iterations': 3, 'queue_size': 3}
    body = ''.join(f'    {k}: {v!r}\n' for k, v in changed.items() if k in settings)
    big.write_text('solid_node:\n  ros__parameters:\n' + body)
    assert presets.main([str(big)]) == 0  # a user's file: rewritten, with a note
    assert 'at most 40' in capsys.readouterr().err
    assert len(presets.preset_keys(big.read_text())) > presets.MAX_PRESET_KEYS
