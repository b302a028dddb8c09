"""The core stays ROS-free: it imports no rclpy and nothing from the adapter subpackages."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

from project_paths import ROOT

CORE = ROOT / 'solid_ros' / 'core'
ADAPTERS = ('solid_ros.formats', 'solid_ros.ros', 'solid_ros.tools', 'solid_ros.sim')
FORBIDDEN = ('rclpy', 'rosbags', 'mcap', 'matplotlib', *ADAPTERS)


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding='utf-8'))
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.append(node.module)
    return names


def test_core_sources_import_no_adapter() -> None:
    modules = sorted(CORE.glob('*.py'))
    assert len(modules) >= 8
    for path in modules:
        bad = [n for n in _imports(path)
               if any(n == f or n.startswith(f + '.') for f in FORBIDDEN)]
        assert not bad, f'{path.name} imports {bad}'


def test_importing_the_package_loads_no_adapter() -> None:
    # A fresh interpreter: what `import solid_ros` and the core pull in, transitively.
    code = ('import sys, solid_ros, solid_ros.core.persistence, solid_ros.core.detector; '
            'print("\\n".join(sorted(sys.modules)))')
    out = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout.split()
    loaded = [m for m in out if any(m == f or m.startswith(f + '.') for f in FORBIDDEN)]
    assert loaded == []
