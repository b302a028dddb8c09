"""The launch file and RViz config read as ``ros2 launch`` reads them, without the launch package.

Neither ``ros2 launch`` nor the ``launch`` / ``launch_yaml`` Python packages exist on this
machine (they are not on PyPI for Jazzy), so this module expands the few constructs
``config/launch/solid.launch.yaml`` uses the way launch and launch_ros do: ``arg`` defaults and
choices in order, ``$(var NAME)`` and ``$(find-pkg-share PKG)`` substitutions, ``if``
conditions, and a ``node`` entry's command line (``args``, then ``--ros-args`` with one
``--params-file`` per ``param`` entry, a dict parameter written to a temporary ``/**`` file as
launch_ros does, then ``-r from:=to`` per ``remap``). The share directory is laid out from
setup.py's ``data_files``, as colcon installs it.
"""

from __future__ import annotations

import ast
import os
import re
import runpy
from pathlib import Path
from typing import Any

import yaml
from project_paths import CONFIG_DIR, ROOT

LAUNCH_FILE = CONFIG_DIR / 'launch' / 'solid.launch.yaml'
RVIZ_FILE = CONFIG_DIR / 'rviz' / 'solid.rviz'
NODE_SOURCE = ROOT / 'solid_ros' / 'ros' / 'node.py'
PACKAGE = 'solid_ros'
_SUBSTITUTION = re.compile(r'\$\(([a-z-]+)(?: ([^)]*))?\)')


def launch_entries(path: Path = LAUNCH_FILE) -> list[dict[str, Any]]:
    """The ``launch:`` list of a YAML launch file."""
    doc = yaml.safe_load(path.read_text(encoding='utf-8'))
    if not isinstance(doc, dict) or set(doc) != {'launch'} or not isinstance(doc['launch'], list):
        raise ValueError(f'{path}: a YAML launch file is one mapping "launch:" with a list')
    return doc['launch']


def substitute(text: Any, values: dict[str, str], share: Path) -> str:
    """Expand ``$(var NAME)`` and ``$(find-pkg-share solid_ros)`` in ``text``."""
    def one(match: re.Match[str]) -> str:
        kind, arg = match.group(1), match.group(2)
        if kind == 'var':
            if arg not in values:
                raise KeyError(f'$(var {arg}) before its arg is declared')
            return values[arg]
        if kind == 'find-pkg-share' and arg == PACKAGE:
            return str(share)
        raise ValueError(f'substitution {match.group(0)} is not supported here')
    return _SUBSTITUTION.sub(one, str(text))


def resolve_args(entries: list[dict[str, Any]], given: dict[str, str],
                 share: Path) -> dict[str, str]:
    """Launch argument values: ``given`` (``name:=value``) or the default, checked against
    the choices, in declaration order as launch evaluates them."""
    values: dict[str, str] = {}
    for entry in entries:
        if 'arg' not in entry:
            continue
        arg = entry['arg']
        name = arg['name']
        value = given[name] if name in given else substitute(arg['default'], values, share)
        choices = [c['value'] for c in arg.get('choice', [])]
        if choices and value not in choices:
            raise ValueError(f'argument {name!r}: {value!r} is not one of {choices}')
        values[name] = value
    unknown = set(given) - set(values)
    if unknown:
        raise KeyError(f'no launch argument {sorted(unknown)}')
    return values


def enabled(entry: dict[str, Any], values: dict[str, str], share: Path) -> bool:
    """An entry's ``if`` / ``unless`` condition (launch's IfCondition words)."""
    body = next(iter(entry.values()))
    for key, want in (('if', True), ('unless', False)):
        if key in body:
            word = substitute(body[key], values, share).strip().lower()
            if word not in ('true', 'false', '1', '0'):
                raise ValueError(f'{key}: {word!r} is not a boolean')
            return (word in ('true', '1')) == want
    return True


def node_command(node: dict[str, Any], values: dict[str, str], share: Path,
                 tmp: Path) -> list[str]:
    """The argv launch_ros runs for a ``node`` entry (executable name first)."""
    argv = [node['exec'], *substitute(node.get('args', ''), values, share).split()]
    ros = ['--ros-args']
    if 'name' in node:
        ros += ['-r', f'__node:={substitute(node["name"], values, share)}']
    if 'namespace' in node:
        ros += ['-r', f'__ns:={substitute(node["namespace"], values, share)}']
    for i, param in enumerate(node.get('param', [])):
        if 'from' in param:
            ros += ['--params-file', substitute(param['from'], values, share)]
            continue
        # launch_ros types the substituted text by YAML rules and writes a '/**' file.
        value = yaml.safe_load(substitute(param['value'], values, share))
        path = tmp / f'launch_params_{i}.yaml'
        path.write_text(yaml.safe_dump({'/**': {'ros__parameters': {param['name']: value}}}))
        ros += ['--params-file', str(path)]
    for remap in node.get('remap', []):
        ros += ['-r', f'{substitute(remap["from"], values, share)}:='
                      f'{substitute(remap["to"], values, share)}']
    return argv + ros


def setup_kwargs() -> dict[str, Any]:
    """The keyword arguments setup.py passes to setuptools.setup (globs run in the root)."""
    import setuptools

    captured: dict[str, Any] = {}
    real = setuptools.setup
    cwd = os.getcwd()
    setuptools.setup = lambda **kw: captured.update(kw)  # type: ignore[assignment]
    try:
        os.chdir(ROOT)
        runpy.run_path(str(ROOT / 'setup.py'), run_name='__main__')
    finally:
        setuptools.setup = real
        os.chdir(cwd)
    return captured


def share_from_setup(dest: Path) -> Path:
    """Lay out ``share/solid_ros`` under ``dest`` from setup.py's data_files (symlinks)."""
    prefix = Path('share') / PACKAGE
    for target, files in setup_kwargs()['data_files']:
        folder = Path(target)
        if folder != prefix and prefix not in folder.parents:
            continue
        (dest / folder).mkdir(parents=True, exist_ok=True)
        for name in files:
            (dest / folder / Path(name).name).symlink_to(ROOT / name)
    return dest / prefix


def node_topics() -> dict[str, dict[str, str]]:
    """``{'sub' | 'pub': {topic name: message type}}`` of solid_node, read from its source."""
    out: dict[str, dict[str, str]] = {'sub': {}, 'pub': {}}
    for call in ast.walk(ast.parse(NODE_SOURCE.read_text(encoding='utf-8'))):
        if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute)
                and call.func.attr in ('create_subscription', 'create_publisher')
                and len(call.args) >= 2 and isinstance(call.args[0], ast.Name)
                and isinstance(call.args[1], ast.Constant)):
            continue
        kind = 'sub' if call.func.attr == 'create_subscription' else 'pub'
        out[kind][str(call.args[1].value)] = call.args[0].id
    return out


def publisher_qos(topic: str) -> str:
    """Source text of the QoS argument solid_node creates the publisher of ``topic`` with."""
    source = NODE_SOURCE.read_text(encoding='utf-8')
    for call in ast.walk(ast.parse(source)):
        if (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute)
                and call.func.attr == 'create_publisher' and len(call.args) >= 3
                and isinstance(call.args[1], ast.Constant) and call.args[1].value == topic):
            return ast.get_source_segment(source, call.args[2]) or ''
    raise KeyError(f'solid_node creates no publisher {topic!r}')


def rviz_displays(path: Path = RVIZ_FILE) -> list[dict[str, Any]]:
    """The displays of an RViz2 config (groups flattened)."""
    doc = yaml.safe_load(path.read_text(encoding='utf-8'))
    out: list[dict[str, Any]] = []
    todo = list(doc['Visualization Manager']['Displays'])
    while todo:
        display = todo.pop(0)
        out.append(display)
        todo.extend(display.get('Displays', []))
    return out
