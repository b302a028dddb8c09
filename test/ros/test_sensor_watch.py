"""The node's one line after its first clouds: what they show, and what to set when the
settings contradict them; never a failure of the node."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from solid_ros.core.config import SolidConfig
from solid_ros.ros import sensor_watch
from solid_ros.ros.sensor_watch import SensorWatch

VLP16 = SolidConfig(fov_up_deg=15.0, fov_down_deg=-15.0)


class Log:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, message: str, **kwargs: Any) -> None:
        self.lines.append(('info', message))

    def warning(self, message: str, **kwargs: Any) -> None:
        self.lines.append(('warning', message))


def rings(seed: int) -> np.ndarray:
    """A VLP-16-like cloud: 16 rings over +-15 deg, ranges 2-60 m."""
    rng = np.random.default_rng(seed)
    el = np.radians(np.repeat(np.linspace(-15.0, 15.0, 16), 900))
    az = np.radians(np.tile(np.linspace(-180.0, 180.0, 900, endpoint=False), 16))
    r = rng.uniform(2.0, 60.0, len(el))
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                     r * np.sin(el)], axis=1).astype(np.float32)


def test_contradiction_is_one_warning_after_the_first_clouds() -> None:
    log = Log()
    watch = SensorWatch(SolidConfig(), log)
    for i in range(9):
        watch.add(rings(i))
    assert log.lines == [] and not watch.done
    watch.add(rings(9))
    for i in range(10, 30):
        watch.add(rings(i))
    assert watch.done and len(log.lines) == 1
    level, line = log.lines[0]
    assert level == 'warning' and '\n' not in line
    assert line.startswith('the first 10 clouds contradict the parameters: ')
    assert 'set fov_up_deg: 15.0, fov_down_deg: -15.0' in line and '16 rings' in line


def test_fitting_settings_give_one_info_line() -> None:
    log = Log()
    watch = SensorWatch(VLP16, log, clouds=3)
    for i in range(5):
        watch.add(rings(i))
    assert [level for level, _ in log.lines] == ['info']
    assert log.lines[0][1].startswith('sensor: 360-degree, 16 rings')


def test_bad_clouds_and_failures_never_reach_the_node(monkeypatch: pytest.MonkeyPatch) -> None:
    log = Log()
    watch = SensorWatch(VLP16, log, clouds=2)
    for bad in (None, np.zeros((0, 3)), np.full((50, 3), np.nan), 'x', np.zeros((3, 2))):
        watch.add(bad)
    assert log.lines == [] and not watch.done

    def broken(*args: Any) -> str:
        raise RuntimeError('boom')

    monkeypatch.setattr(sensor_watch, 'check_line', broken)
    watch.add(rings(0))
    watch.add(rings(1))
    assert watch.done and log.lines == [('warning', 'sensor check skipped: RuntimeError: boom')]
    watch.add(rings(2))  # nothing more
    assert len(log.lines) == 1
