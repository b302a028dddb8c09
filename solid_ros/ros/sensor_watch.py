"""The node's check of its first clouds against its settings: one line, once.

After :data:`~solid_ros.core.descriptor.sensor.FIRST_CLOUDS` clouds, :class:`SensorWatch`
logs what they show and, when they contradict the settings, one WARN line saying what to set
(:func:`~solid_ros.core.descriptor.sensor_check.check_line`, the replay's rule too). Runs on
the describe thread; it never stops the node: a failure ends the check with a line.
"""

from __future__ import annotations

from typing import Any, Protocol

from solid_ros.core.config import SolidConfig
from solid_ros.core.descriptor.sensor import CloudSample, measure
from solid_ros.core.descriptor.sensor_check import check_line

__all__ = ['SensorWatch']


class _Log(Protocol):
    def info(self, message: str, **kwargs: Any) -> object: ...
    def warning(self, message: str, **kwargs: Any) -> object: ...


class SensorWatch:
    """Samples the first clouds, then checks them against ``config`` once.

    Args:
        config: the node's detector settings (those checked are read-only at runtime).
        log: where the lines go.
        clouds: how many clouds to sample first.
    """

    def __init__(self, config: SolidConfig, log: _Log, clouds: int | None = None) -> None:
        self._config = config
        self._log = log
        self._sample: CloudSample | None = (CloudSample() if clouds is None
                                            else CloudSample(clouds))

    @property
    def done(self) -> bool:
        """Whether the check has run (or given up)."""
        return self._sample is None

    def add(self, points: Any) -> None:
        """Take one decoded cloud; after the last one, log the result."""
        sample = self._sample
        if sample is None:
            return
        try:
            if not sample.add(points):
                return
            self._sample = None
            view = measure(sample)
            if view is None:
                return
            line = check_line(sample, self._config)
            if line is None:
                self._log.info(f'sensor: {view.summary()}; the parameters fit it')
            else:
                self._log.warning(f'{line} (sensor: {view.summary()})')
        except Exception as err:  # noqa: BLE001 - a check must never take the node down
            self._sample = None
            self._log.warning(f'sensor check skipped: {type(err).__name__}: {err}')
