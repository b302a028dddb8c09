"""Style and typing gates run with the suite: ruff on everything, mypy --strict on the core."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _core_modules() -> list[str]:
    """Package modules that do not import ROS: the core must stay mypy --strict clean."""
    out = []
    for path in sorted((ROOT / 'solid_ros').rglob('*.py')):
        text = path.read_text(encoding='utf-8')
        if 'import rclpy' not in text and 'from rclpy' not in text:
            out.append(str(path.relative_to(ROOT)))
    return out


def test_ruff_clean() -> None:
    proc = subprocess.run([str(BIN / 'ruff'), 'check', 'solid_ros', 'test', 'setup.py'],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_mypy_strict_core() -> None:
    modules = _core_modules()
    assert 'solid_ros/core/descriptor/solid.py' in modules
    proc = subprocess.run([str(BIN / 'mypy'), '--strict', '--no-error-summary', *modules],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_no_function_over_80_lines_in_core_ros_and_tools() -> None:
    import ast

    long = []
    for room in ('core', 'ros', 'tools'):
        for path in sorted((ROOT / 'solid_ros' / room).rglob('*.py')):
            for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    lines = (node.end_lineno or node.lineno) - node.lineno + 1
                    if lines > 80:
                        long.append(f'{path.relative_to(ROOT)}:{node.name} {lines} lines')
    assert not long, long
