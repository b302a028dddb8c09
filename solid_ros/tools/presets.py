"""Keep the shipped parameter files complete: every setting, its comment, the file's values.

``python -m solid_ros.tools.presets [--check] [FILE.yaml ...]`` rewrites each file (default:
``config/*.yaml``) with its header comment, then every setting of the schema in declaration
order with a one-line comment (description, range, read-only), keeping the file's own values
and filling new settings with their defaults. ``--check`` changes nothing and exits 1 when a
file is out of date (the test suite runs it).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from solid_ros.core.config import ParamSpec, load_yaml_parameters, param_specs
from solid_ros.core.errors import SolidError

__all__ = ['main', 'render']

CONFIG_DIR = Path(__file__).resolve().parents[2] / 'config'


def _value(spec: ParamSpec, value: Any) -> str:
    if spec.type is bool:
        return 'true' if value else 'false'
    if spec.type is str:
        return "'" + str(value).replace("'", "''") + "'"
    if spec.type is float:
        text = repr(float(value))
        return text if ('.' in text or 'e' in text or 'inf' in text) else text + '.0'
    return str(int(value))


def render(path: Path) -> str:
    """The up-to-date text of parameter file ``path``."""
    text = path.read_text(encoding='utf-8')
    header = []
    for line in text.splitlines():
        if not line.startswith('#'):
            break
        header.append(line)
    values = load_yaml_parameters(path)
    out = header + ['solid_node:', '  ros__parameters:']
    for spec in param_specs():
        flags = ' [read-only]' if spec.read_only else ''
        out.append(f'    # {spec.description}; {spec.range_text()}{flags}')
        out.append(f'    {spec.name}: {_value(spec, values.get(spec.name, spec.default))}')
    return '\n'.join(out) + '\n'


def main(argv: Sequence[str] | None = None) -> int:
    """Rewrite (or with ``--check`` compare) the parameter files; return the exit status."""
    parser = argparse.ArgumentParser(prog='python -m solid_ros.tools.presets',
                                     description=__doc__.splitlines()[0])
    parser.add_argument('--check', action='store_true', help='only report stale files')
    parser.add_argument('files', nargs='*', type=Path)
    args = parser.parse_args(argv)
    files = args.files or [p for p in sorted(CONFIG_DIR.glob('*.yaml'))
                           if 'ros__parameters:' in p.read_text(encoding='utf-8')]
    stale = 0
    for path in files:
        try:
            new = render(path)
        except SolidError as err:
            print(f'{path}: {err}', file=sys.stderr)
            return 1
        if new == path.read_text(encoding='utf-8'):
            continue
        stale += 1
        if args.check:
            print(f'{path} is out of date: run python -m solid_ros.tools.presets',
                  file=sys.stderr)
        else:
            path.write_text(new, encoding='utf-8')
            print(f'updated {path}')
    return 1 if (args.check and stale) else 0


if __name__ == '__main__':
    sys.exit(main())
