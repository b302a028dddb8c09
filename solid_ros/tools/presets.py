"""Keep the shipped parameter files in shape: one full reference, short sensor presets.

``python -m solid_ros.tools.presets [--check] [--full] [FILE.yaml ...]`` rewrites each file
(default: the parameter files in ``config/``), keeping its header comment, its values and the
notes after them (``key: value  # why``):

- the reference, ``config/solid.yaml`` (or any file with ``--full``): every setting of the
  schema in declaration order under its group's heading, each with a one-line comment
  (description, range, read-only); new settings come in at their defaults;
- a sensor preset (any other file): only the settings a sensor and its use decide
  (:data:`SENSOR_KEYS`, even at their defaults) and any other the file sets away from its
  default, in declaration order, each with its comment; the rest is left to the defaults.

``--check`` changes nothing and exits 1 when a file is out of date, invalid, or a shipped
preset holds more than :data:`MAX_PRESET_KEYS` settings (the test suite runs it).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from solid_ros.core.config import (
    NodeConfig,
    ParamSpec,
    SolidConfig,
    load_parameter_file,
    param_specs,
)
from solid_ros.core.errors import SolidError

__all__ = ['CONFIG_DIR', 'MAX_PRESET_KEYS', 'REFERENCE', 'SENSOR_KEYS', 'main', 'render',
           'render_values', 'shipped_config', 'value_notes']

CONFIG_DIR = Path(__file__).resolve().parents[2] / 'config'
REFERENCE = 'solid.yaml'  # the file with every setting
MAX_PRESET_KEYS = 40
# What a sensor and its use decide; a preset lists them even where they equal the default,
# so that a user sees every knob of their sensor in one short file.
SENSOR_KEYS = frozenset({
    # What the sensor sees and how the descriptor bins it.
    'fov_width_deg', 'fov_center_deg', 'fov_up_deg', 'fov_down_deg', 'min_range', 'max_range',
    'voxel_size', 'num_range', 'num_angle', 'num_height', 'max_distance', 'heading_weight',
    # How it is mounted.
    'mount_roll_deg', 'mount_pitch_deg', 'mount_yaw_deg',
    # How candidates are ranked, and keyframe spacing (how far the platform moves per scan).
    'num_candidates', 'distance_threshold', 'exclude_recent_frames', 'heading_match',
    'keyframe_min_distance', 'keyframe_min_rotation_deg',
    # Verification clouds (point density) and the back end.
    'verify', 'verify_voxel_size', 'verify_coarse_voxel_size', 'backend',
    # Odometry: the topic or KISS-ICP on the clouds (its ranges and voxel follow the sensor).
    'use_odom', 'odometry_source', 'kiss_max_range', 'kiss_min_range', 'kiss_voxel_size',
})
_NOTE = '  # '


def shipped_config(name: str) -> Path:
    """Path of a YAML file shipped in ``config/`` (source tree or ROS share directory).

    Raises:
        SolidError: not found in either.
    """
    local = CONFIG_DIR / name
    if local.is_file():
        return local
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory('solid_ros')) / 'config' / name
    except (ImportError, LookupError, OSError) as err:  # OSError: no AMENT_PREFIX_PATH
        raise SolidError(f'shipped parameter file {name} not found') from err


def _value(spec: ParamSpec, value: Any) -> str:
    if spec.type is bool:
        return 'true' if value else 'false'
    if spec.type is str:
        return "'" + str(value).replace("'", "''") + "'"
    if spec.type is float:
        text = repr(float(value))
        return text if ('.' in text or 'e' in text or 'inf' in text) else text + '.0'
    return str(int(value))


def value_notes(text: str, values: Mapping[str, Any]) -> dict[str, str]:
    """The notes written after values (``    key: value  # note``), by key."""
    import yaml

    out: dict[str, str] = {}
    for line in text.splitlines():
        key = line.strip().partition(':')[0]
        if not line.startswith('    ') or key not in values or _NOTE not in line:
            continue
        start = 0
        while (cut := line.find(_NOTE, start)) >= 0:
            try:  # the first cut that leaves the value whole (a string may hold '  # ')
                if yaml.safe_load(line[:cut].strip()) == {key: values[key]}:
                    out[key] = line[cut + len(_NOTE):].strip()
                    break
            except yaml.YAMLError:
                pass
            start = cut + 1
    return out


def render_values(header: Sequence[str], values: Mapping[str, Any], *, full: bool,
                  notes: Mapping[str, str] | None = None) -> str:
    """A parameter file's text: ``header`` lines, then the settings (see the module).

    Args:
        header: comment lines, each starting with '#'.
        values: the file's settings (others take their defaults).
        full: every setting (the reference) rather than a sensor preset's.
        notes: a note to write after some values, by key.
    """
    notes = notes or {}
    out = [*header, 'solid_node:', '  ros__parameters:']
    group = ''
    for spec in param_specs():
        value = values.get(spec.name, spec.default)
        if not (full or spec.name in SENSOR_KEYS or value != spec.default):
            continue
        if spec.group != group:
            group = spec.group
            out.append(f'    # ---- {group}')
        flags = ' [read-only]' if spec.read_only else ''
        out.append(f'    # {spec.description}; {spec.range_text()}{flags}')
        note = f'{_NOTE}{notes[spec.name]}' if spec.name in notes else ''
        out.append(f'    {spec.name}: {_value(spec, value)}{note}')
    return '\n'.join(out) + '\n'


def render(path: Path, full: bool | None = None) -> str:
    """The up-to-date text of parameter file ``path`` (``full`` by default for the reference).

    Raises:
        ConfigError: the file is unreadable or holds an unknown or invalid setting.
    """
    text = path.read_text(encoding='utf-8')
    header = []
    for line in text.splitlines():
        if not line.startswith('#'):
            break
        header.append(line)
    values = load_parameter_file(path)
    SolidConfig.from_dict(values, strict=False)  # the rules between settings too
    NodeConfig.from_dict(values, strict=False)
    return render_values(header, values, full=path.name == REFERENCE if full is None else full,
                         notes=value_notes(text, values))


def preset_keys(text: str) -> list[str]:
    """The settings a rendered file lists, in order."""
    return [line.strip().partition(':')[0] for line in text.splitlines()
            if line.startswith('    ') and not line.strip().startswith('#')]


def _shipped(path: Path) -> bool:
    return path.resolve().parent == CONFIG_DIR.resolve()


def main(argv: Sequence[str] | None = None) -> int:
    """Rewrite (or with ``--check`` compare) the parameter files; return the exit status."""
    parser = argparse.ArgumentParser(prog='python -m solid_ros.tools.presets',
                                     description=__doc__.splitlines()[0])
    parser.add_argument('--check', action='store_true', help='only report stale files')
    parser.add_argument('--full', action='store_true',
                        help='write every setting (as config/solid.yaml), not a preset')
    parser.add_argument('files', nargs='*', type=Path)
    args = parser.parse_args(argv)
    files = args.files or [p for p in sorted(CONFIG_DIR.glob('*.yaml'))
                           if 'ros__parameters:' in p.read_text(encoding='utf-8')]
    bad = 0
    for path in files:
        try:
            new = render(path, True if args.full else None)
        except SolidError as err:
            print(f'{path}: {err}', file=sys.stderr)
            return 1
        count = len(preset_keys(new))
        if path.name != REFERENCE and not args.full and count > MAX_PRESET_KEYS:
            print(f'{path}: {count} settings; a preset sets at most {MAX_PRESET_KEYS} (what '
                  'the sensor and its use decide)', file=sys.stderr)
            bad += int(_shipped(path))
        if new == path.read_text(encoding='utf-8'):
            continue
        if args.check:
            bad += 1
            print(f'{path} is out of date: run python -m solid_ros.tools.presets',
                  file=sys.stderr)
        else:
            path.write_text(new, encoding='utf-8')
            print(f'updated {path}')
    return 1 if (args.check and bad) else 0


if __name__ == '__main__':
    sys.exit(main())
