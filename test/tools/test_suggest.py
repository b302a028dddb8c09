"""solid_replay BAG --suggest-params: a preset for a bag's sensor from its first clouds."""

from __future__ import annotations

from pathlib import Path

import pytest
from project_paths import CONFIG_DIR

from solid_ros.core.config import SolidConfig, load_parameter_file
from solid_ros.formats.bags import write_cloud_bag
from solid_ros.tools import presets
from solid_ros.tools.replay import main
from solid_ros.tools.suggest import SENSOR_CLASSES, suggest_parameters

# Each simulated sensor and the preset it must be given.
SIMULATED = {'avia_like': 'avia.yaml', 'ouster_like': 'ouster.yaml', 'vlp16_like': 'vlp16.yaml',
             'hesai_like': 'hesai.yaml', 'mid360_like': 'mid360.yaml', 'hdl64': 'hdl64.yaml'}


def _sim_bag(root: Path, sensor: str, scans: int = 10) -> Path:
    from solid_ros.sim import DEMO_SENSORS, simulate

    items = [(s.points.copy(), 10**18 + i * 100_000_000, s.pose)
             for i, s in enumerate(simulate(seed=1, sensor=DEMO_SENSORS[sensor],
                                            num_scans=scans))]
    return write_cloud_bag(root / sensor, items, 'mcap')


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / 'suggested.yaml'
    path.write_text(text)
    return path


def test_every_sensor_class_is_a_shipped_preset() -> None:
    for name, sensor in SENSOR_CLASSES.items():
        cfg = SolidConfig.from_yaml(CONFIG_DIR / name)
        assert (cfg.fov_down_deg, cfg.fov_up_deg) == (sensor.down, sensor.up), name


@pytest.mark.parametrize('sensor', sorted(SIMULATED))
def test_simulated_sensor_gets_its_preset_unchanged(tmp_path: Path, sensor: str) -> None:
    text = suggest_parameters(_sim_bag(tmp_path, sensor))
    preset = SIMULATED[sensor]
    assert f'# Starting point: {preset} (' in text and 'contradict none of it' in text
    path = _write(tmp_path, text)
    assert SolidConfig.from_yaml(path) == SolidConfig.from_yaml(CONFIG_DIR / preset)
    assert len(presets.preset_keys(text)) <= presets.MAX_PRESET_KEYS


def test_a_file_that_does_not_fit_is_changed_with_what_was_measured(tmp_path: Path) -> None:
    bag = _sim_bag(tmp_path, 'vlp16_like')
    text = suggest_parameters(bag, params=CONFIG_DIR / 'hdl64.yaml')
    header = ' '.join(line[2:] for line in text.splitlines() if line.startswith('# '))
    assert 'changed where the clouds contradict it: fov_up_deg, fov_down_deg.' in header
    assert '    fov_up_deg: 15.0  # measured: 99.5% of the returns at or below +15.0 deg ' \
           '(hdl64.yaml: 2.0)' in text.replace(str(CONFIG_DIR) + '/', '')
    cfg = SolidConfig.from_yaml(_write(tmp_path, text))
    assert (cfg.fov_up_deg, cfg.fov_down_deg) == (15.0, -15.0)
    assert cfg.replace(fov_up_deg=2.0, fov_down_deg=-24.8) == SolidConfig.from_yaml(
        CONFIG_DIR / 'hdl64.yaml')


def test_command_line_prints_a_loadable_file_and_exits_0(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = _sim_bag(tmp_path, 'mid360_like')
    assert main([str(bag), '--suggest-params']) == 0
    out, err = capsys.readouterr()
    assert out.startswith('# solid_ros preset suggested by solid_replay --suggest-params')
    assert 'no rings (non-repetitive pattern)' in out and not err
    assert load_parameter_file(_write(tmp_path, out))['fov_up_deg'] == 52.0
    assert main([str(tmp_path / 'missing'), '--suggest-params']) == 1
    assert capsys.readouterr().err.startswith('solid_replay: error: ')
    with pytest.raises(SystemExit) as exc:
        main([str(bag), str(bag), '--suggest-params'])
    assert exc.value.code == 2


@pytest.mark.parametrize('name, preset, up, down', [
    ('hku1', 'avia.yaml', 38.6, -38.6),  # Livox Avia
    ('quickshack', 'avia.yaml', 38.6, -38.6),
    ('riv281', 'ouster.yaml', 22.5, -22.5),  # Ouster OS1-64 (Gen 1: 64 rings over 33 deg)
])
def test_real_bags(shared_data: Path, tmp_path: Path, name: str, preset: str, up: float,
                   down: float) -> None:
    text = suggest_parameters(shared_data / name / 'bag')
    assert f'# Starting point: {preset} (' in text
    cfg = SolidConfig.from_yaml(_write(tmp_path, text))
    assert (cfg.fov_up_deg, cfg.fov_down_deg) == (up, down)
    assert ('64 rings' in text) is (name == 'riv281')
