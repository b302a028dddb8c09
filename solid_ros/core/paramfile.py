"""The ROS 2 parameter-file layout, read as rcl reads it: YAML in, one node's flat parameters out.

Knows nothing of the settings themselves: :func:`solid_ros.core.config.check_parameters`
validates what this returns against the schema.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from solid_ros.core.errors import ConfigError

__all__ = ['load_yaml_parameters']


def load_yaml_parameters(path: str | Path, node_name: str = 'solid_node') -> dict[str, Any]:
    """Read the merged ``ros__parameters`` of ``node_name`` (and ``/**``) from a YAML file.

    Blocks apply as rcl applies them: a key names a node relative to the root namespace
    (``solid_node``, ``/solid_node``, nested ``ns: solid_node:``) or matches it with the
    wildcards ``*`` (one name) and ``**`` (any names), e.g. ``/**``. Values are returned
    as written; :func:`check_parameters` validates them.

    Args:
        path: the parameter file.
        node_name: node name or fully qualified name (``/ns/name``).

    Raises:
        ConfigError: one line naming the file: missing or unreadable, not UTF-8 text, not
            YAML, not in ROS 2 parameter layout, or without a block for the node.
    """
    import yaml

    try:
        blob = Path(path).read_bytes()
    except OSError as err:
        raise ConfigError(f'{path}: cannot read parameter file: {err.strerror or err}') from err
    try:
        text = blob.decode('utf-8')
    except UnicodeDecodeError as err:
        raise ConfigError(f'{path}: not a parameter file: byte 0x{blob[err.start]:02x} at '
                          f'offset {err.start} is not UTF-8 text') from err
    # libyaml's loader where PyYAML has it: the pure-Python scanner is quadratic in the
    # nesting of flow collections (seconds for a few hundred '{').
    loader = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
    try:
        doc = yaml.load(text, Loader=loader)  # noqa: S506 (a safe loader)
    except RecursionError as err:
        raise ConfigError(f'{path}: not valid YAML: nested too deeply') from err
    except (yaml.YAMLError, ValueError, TypeError, OverflowError) as err:
        # PyYAML raises more than YAMLError for odd scalars (dates) and deep nesting.
        where = ' '.join(str(err).replace(' in "<unicode string>",', '').split())
        raise ConfigError(f'{path}: not valid YAML: {_shorten(where)}') from err
    if not isinstance(doc, dict):
        kind = 'empty' if doc is None else f'a YAML {type(doc).__name__}'
        raise ConfigError(f'{path}: expected "<node>: ros__parameters:" at the top level, '
                          f'the file is {kind}')
    fqn = '/' + node_name.strip('/')
    params: dict[str, Any] = {}
    found = False
    names = []
    for name, block in _node_blocks(doc):
        names.append(name)
        if not _name_matches(name, fqn):
            continue
        if not isinstance(block, dict) or not isinstance(block.get('ros__parameters'), dict):
            raise ConfigError(f'{path}: block {name!r} has no ros__parameters mapping')
        params.update(_flatten(block['ros__parameters']))
        found = True
    if not found:
        raise ConfigError(f'{path}: no ros__parameters block for node {fqn!r} '
                          f'(blocks: {", ".join(names[:10]) or "none"})')
    return params


def _shorten(text: str) -> str:
    return text if len(text) <= 300 else text[:297] + '...'


def _node_blocks(doc: Mapping[Any, Any], prefix: str = '') -> list[tuple[str, Any]]:
    """``(name, block)`` for every node block; nested namespace mappings are joined by '/'."""
    out: list[tuple[str, Any]] = []
    for key, value in doc.items():
        name = f'{prefix}/{str(key).strip("/")}'
        if isinstance(value, dict) and 'ros__parameters' not in value and value and all(
                isinstance(v, dict) for v in value.values()):
            out.extend(_node_blocks(value, name))  # a namespace level
        else:
            out.append((name, value))
    return out


def _name_matches(pattern: str, fqn: str) -> bool:
    """rcl's node-name wildcards: ``**`` spans any names (also none), ``*`` one name."""
    if '*' not in pattern:
        return pattern == fqn
    rx = ''
    for token in pattern.strip('/').split('/'):
        if token == '**':
            rx += '(?:/[^/]+)*'
        else:
            rx += '/' + '[^/]*'.join(re.escape(t) for t in token.split('*'))
    return re.fullmatch(rx, fqn) is not None


def _flatten(block: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in block.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict):
            out.update(_flatten(value, name + '.'))
        else:
            out[name] = value
    return out
