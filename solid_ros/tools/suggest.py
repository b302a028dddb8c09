"""``solid_replay BAG --suggest-params``: a parameter file for a bag's sensor, from its first
clouds, without replaying the bag.

It measures the first clouds (:mod:`solid_ros.core.descriptor.sensor`), picks the shipped
preset nearest the sensor (:data:`SENSOR_CLASSES`: a full turn or a sector, the vertical field
of view, the rings), changes in it only what the clouds contradict
(:func:`~solid_ros.core.descriptor.sensor_check.suggest_settings`, the rule of the node's
warning) and prints it as a preset with comments saying what was measured.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from solid_ros.core.config import SolidConfig, load_parameter_file
from solid_ros.core.descriptor.sensor import CloudSample, SensorView, measure
from solid_ros.core.descriptor.sensor_check import suggest_settings
from solid_ros.core.errors import BagError
from solid_ros.formats.bags import Bag, select_cloud_topic
from solid_ros.tools.presets import render_values, shipped_config, value_notes

__all__ = ['SENSOR_CLASSES', 'SensorClass', 'nearest_preset', 'read_first_clouds',
           'suggest_parameters']


@dataclass(frozen=True)
class SensorClass:
    """The sensor a shipped preset is for.

    Attributes:
        name: the sensor in words.
        full_turn: whether it sees all around.
        down: lowest elevation, degrees.
        up: highest elevation, degrees.
        rings: its rings (0: a non-repetitive pattern).
    """

    name: str
    full_turn: bool
    down: float
    up: float
    rings: int

    def distance(self, view: SensorView) -> float:
        """How far the measured view is from this class (degrees of vertical field of view,
        plus penalties for another coverage or scan pattern)."""
        out = abs(view.elevation_low_deg - self.down) + abs(view.elevation_high_deg - self.up)
        if view.full_turn != self.full_turn:
            out += 1000.0
        if view.rings and not self.rings:
            out += 50.0  # rings never come from a non-repetitive pattern
        elif view.rings and self.rings:
            out += 20.0 * abs(math.log2(view.rings / self.rings))
        return out  # no rings seen: voxel-downsampled clouds may hide them


SENSOR_CLASSES = {
    'avia.yaml': SensorClass('Livox Avia-class 70-degree solid-state LiDAR', False, -38.6,
                             38.6, 0),
    'mid360.yaml': SensorClass('Livox Mid-360', True, -7.0, 52.0, 0),
    'ouster.yaml': SensorClass('Ouster OS1', True, -22.5, 22.5, 64),
    'vlp16.yaml': SensorClass('Velodyne VLP-16', True, -15.0, 15.0, 16),
    'hesai.yaml': SensorClass('Hesai PandarXT32', True, -16.0, 15.0, 32),
    'hdl64.yaml': SensorClass('Velodyne HDL-64E', True, -24.8, 2.0, 64),
}


def nearest_preset(view: SensorView) -> str:
    """The shipped preset (file name) whose sensor is nearest the measured view."""
    return min(SENSOR_CLASSES, key=lambda name: SENSOR_CLASSES[name].distance(view))


def read_first_clouds(bag: str | Path, topic: str | None = None,
                      sample: CloudSample | None = None) -> tuple[CloudSample, str]:
    """The first clouds of a bag's cloud topic (undecodable ones skipped).

    Raises:
        BagError: the bag cannot be read, lacks the topic or holds no usable cloud.
    """
    sample = sample if sample is not None else CloudSample()
    with Bag(bag) as reader:
        name = select_cloud_topic(reader, topic)
        for scan in reader.clouds(name):
            if scan.points is not None and sample.add(scan.points):
                break
    if sample.clouds == 0:
        raise BagError(f'{bag}: no usable cloud on {name}')
    return sample, name


def _notes(view: SensorView, base: dict[str, Any], changed: dict[str, Any],
           preset: str) -> dict[str, str]:
    """What was measured, after each changed value."""
    said = {
        'fov_up_deg': f'measured: 99.5% of the returns at or below '
                      f'{view.elevation_high_deg:+.1f} deg',
        'fov_down_deg': f'measured: 99.5% at or above {view.elevation_low_deg:+.1f} deg',
        'max_range': f'measured: 99% of the returns within {view.range_high_m:.1f} m',
        'min_range': f'measured: 1% of the returns within {view.range_low_m:.1f} m',
    }
    return {key: f'{said.get(key, "measured")} ({preset}: {base[key]!r})' for key in changed}


def suggest_parameters(bag: str | Path, topic: str | None = None,
                       params: str | Path | None = None) -> str:
    """The text of a parameter file for the bag's sensor.

    Args:
        bag: the bag.
        topic: its PointCloud2 topic (default: the only one).
        params: a parameter file to fit instead of the nearest shipped preset.

    Raises:
        SolidError: the bag or the parameter file cannot be read.
    """
    sample, name = read_first_clouds(bag, topic)
    view = measure(sample)
    if view is None:
        raise BagError(f'{bag}: the first {sample.clouds} clouds on {name} hold too few '
                       'points to measure the sensor')
    source = Path(params) if params is not None else shipped_config(nearest_preset(view))
    label = source.name if params is None else str(source)
    values = load_parameter_file(source)
    base = SolidConfig.from_dict(values, strict=False)
    changed = suggest_settings(sample, base)
    full = base.to_dict()
    sensor = SENSOR_CLASSES.get(source.name) if params is None else None
    what = f' ({sensor.name})' if sensor is not None else ''
    said = [
        f'solid_ros preset suggested by solid_replay --suggest-params for {bag} ({name}).',
        f'Measured on its first {view.clouds} clouds: {view.summary()}.',
        f'Starting point: {label}{what}; '
        + (f'changed where the clouds contradict it: {", ".join(changed)}.' if changed else
           'the clouds contradict none of it.'),
        'Sky and far space return nothing: a field of view measured in the open can be '
        "narrower than the sensor's; check it against the datasheet.",
        'Load with: solid_node --ros-args --params-file FILE, or solid_replay BAG --params '
        'FILE',
    ]
    header = ['# ' + line for text in said for line in textwrap.wrap(
        text, 94, break_long_words=False, break_on_hyphens=False)]
    notes = value_notes(source.read_text(encoding='utf-8'), values)
    notes.update(_notes(view, full, changed, label))
    return render_values(header, {**values, **changed}, full=False, notes=notes)
