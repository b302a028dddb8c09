"""The rooms of the package and the one direction of their imports.

Inside core, the base modules (``solid_ros/core/*.py``: errors, configuration, geometry, stamps,
reasons, the result records) sit below the subpackages, which rank descriptor < database <
odometry < verification < backend < candidates < flow: a module imports only its own room, the
base and the rooms below (:data:`CORE_ROOMS`). No module imports another that imports it back,
however indirectly, not even for type checking.

core (pure numpy: no ROS, no bag or plot library, nothing of the rooms above) <- formats
(message and file formats) <- sim (the simulator) ; ros (the node) and tools (offline tools)
are sibling adapters over core and formats (tools also drive the simulator); nothing imports
ros or tools from below, and neither imports the other. ``solid_ros.runtime`` is a leaf that
imports nothing of the package, so every room may use it.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest
from project_paths import ROOT

PKG = ROOT / 'solid_ros'
ROOMS = ('core', 'formats', 'sim', 'ros', 'tools')
# What each room may import of the package (besides itself and the runtime leaf).
ALLOWED = {
    'core': set(),
    'formats': {'core'},
    'sim': {'core', 'formats'},
    'ros': {'core', 'formats'},
    'tools': {'core', 'formats', 'sim'},
}
CORE_FORBIDDEN = ('rclpy', 'rosbags', 'mcap', 'matplotlib')
# The core's rooms, lowest first; the base modules (core/*.py) rank below all of them.
CORE_ROOMS = ('descriptor', 'database', 'odometry', 'verification', 'backend', 'candidates',
              'flow')


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding='utf-8'))
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.append(node.module)
    return names


def _room_of(module: str) -> str | None:
    """The room (or top-level module) of a solid_ros module; None outside the package."""
    parts = module.split('.')
    return parts[1] if parts[0] == 'solid_ros' and len(parts) > 1 else None


def test_every_module_lives_in_a_room_or_is_a_leaf() -> None:
    top = sorted(p.stem for p in PKG.glob('*.py'))
    assert top == ['__init__', 'runtime'], top
    for path in PKG.rglob('*.py'):
        assert path.relative_to(PKG).parts[0] in (*ROOMS, '__init__.py', 'runtime.py'), path


@pytest.mark.parametrize('room', ROOMS)
def test_imports_run_one_way(room: str) -> None:
    modules = sorted((PKG / room).rglob('*.py'))
    assert modules
    for path in modules:
        for name in _imports(path):
            other = _room_of(name)
            if other is None or other == room or other == 'runtime':
                continue
            assert other in ALLOWED[room], f'{room}/{path.name} imports {name}'


def test_the_runtime_leaf_imports_nothing_of_the_package() -> None:
    assert not [n for n in _imports(PKG / 'runtime.py') if n.startswith('solid_ros')]


def test_core_imports_no_ros_bag_or_plot_library() -> None:
    paths = sorted((PKG / 'core').rglob('*.py'))
    assert len(paths) > 40  # every room's modules, not only the base ones
    for path in paths:
        bad = [n for n in _imports(path)
               if any(n == f or n.startswith(f + '.') for f in CORE_FORBIDDEN)]
        assert not bad, f'{path.relative_to(PKG)} imports {bad}'


def test_importing_the_package_loads_no_adapter() -> None:
    # A fresh interpreter: what `import solid_ros` and the core pull in, transitively.
    code = ('import sys, solid_ros, solid_ros.core.database.persistence, '
            'solid_ros.core.flow.detector; '
            'print("\\n".join(sorted(sys.modules)))')
    out = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout.split()
    adapters = (*CORE_FORBIDDEN, *(f'solid_ros.{r}' for r in ROOMS if r != 'core'))
    loaded = [m for m in out if any(m == f or m.startswith(f + '.') for f in adapters)]
    assert loaded == []


def _core_rank(module: str) -> int:
    """Rank of a core module: 0 for the base modules, else 1 + its room's place."""
    parts = module.split('.')
    return CORE_ROOMS.index(parts[2]) + 1 if len(parts) > 3 else 0


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix('')
    parts = rel.parts[:-1] if rel.name == '__init__' else rel.parts
    return '.'.join(parts)


def test_core_rooms_import_down_only() -> None:
    rooms = sorted(p.name for p in (PKG / 'core').iterdir()
                   if p.is_dir() and (p / '__init__.py').exists())
    assert rooms == sorted(CORE_ROOMS)
    for path in sorted((PKG / 'core').rglob('*.py')):
        own = _module_name(path)
        for name in _imports(path):
            if not name.startswith('solid_ros.core.'):
                continue
            assert _core_rank(name) <= _core_rank(own), f'{own} imports {name} (a higher room)'


def test_no_import_cycle() -> None:
    modules = {_module_name(p): p for p in PKG.rglob('*.py')}
    graph = {m: {n for n in _imports(p) if n in modules and n != m} for m, p in modules.items()}
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            assert state.get(n) != 1, 'import cycle: ' + ' -> '.join([*path, m, n])
            if n not in state:
                visit(n, [*path, m])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])
