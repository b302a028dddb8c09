"""Shared fixtures: the real data set beside the project, an rclpy context."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from rclpy.context import Context

from project_paths import SHARED_DATA


@pytest.fixture(scope='session')
def shared_data() -> Path:
    """Path of ../shared/data; skips the test with the reason when it is absent."""
    if not (SHARED_DATA / 'README.md').is_file():
        pytest.skip(f'real data not found at {SHARED_DATA} (CI provides ../shared/data)')
    return SHARED_DATA


@pytest.fixture()
def context() -> Iterator[Context]:
    """A fresh rclpy context for one test (skips when rclpy is absent), shut down after it."""
    rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')
    from rclpy.context import Context

    from solid_ros.tools.runtime import tune_thread_switching

    # In-process nodes get the thread switching solid_node's main() sets for itself.
    interval = sys.getswitchinterval()
    tune_thread_switching()
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)
        sys.setswitchinterval(interval)
