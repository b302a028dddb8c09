"""Shared fixtures (the real data set beside the project, an rclpy context) and the rule that
``./run.sh test`` may skip only for missing real data.

``./run.sh test`` installs rclpy, small-gicp, colcon and the console scripts and sets
``SOLID_ROS_FULL_SUITE=1``; a test skipped there for anything but absent ``../shared/data``
(say, rclpy failing to import without its middleware) would hide a broken install, so it
fails instead. Plain ``pytest`` in another environment still skips.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from rclpy.context import Context

from project_paths import SHARED_DATA

_NO_DATA = 'real data not found at'
_FULL_SUITE = os.environ.get('SOLID_ROS_FULL_SUITE') == '1'


def _no_tool_skips(report: pytest.CollectReport | pytest.TestReport) -> None:
    if _FULL_SUITE and report.skipped and _NO_DATA not in str(report.longrepr):
        report.outcome = 'failed'
        report.longrepr = (f'skipped under ./run.sh test, which installs everything the suite '
                           f'needs: {report.longrepr}')


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector: pytest.Collector) -> Iterator[None]:
    outcome = yield
    _no_tool_skips(outcome.get_result())  # type: ignore[attr-defined]


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    outcome = yield
    _no_tool_skips(outcome.get_result())  # type: ignore[attr-defined]


_ROS_FILES = ('test_colcon.py', 'test_launch.py')
# What a test file contains when it starts a ROS participant without being marked ros (a node
# in-process or its executable); README and doc blocks may do so too.
_PARTICIPANT_SIGNS = ('rclpy.init', 'SolidNode(', 'lib/solid_ros', 'solid_ros.ros.node')
_PARTICIPANT_FILES = ('test_docs.py',)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark what a test needs, so ``-m 'not ros and not data and not slow'`` is the fast part:
    ``data`` when it uses the real data set, ``ros`` when it runs rclpy (everything under
    test/ros, the colcon and launch tests, and any test on an rclpy ``context``); ``slow`` is
    set by the tests themselves."""
    for item in items:
        path = Path(str(item.fspath))
        names = set(getattr(item, 'fixturenames', ()))
        if 'shared_data' in names or 'hku1' in names:
            item.add_marker(pytest.mark.data)
        if 'ros' in path.parts or path.name in _ROS_FILES or 'context' in names:
            item.add_marker(pytest.mark.ros)


@functools.cache
def _starts_participants(path: Path) -> bool:
    """Whether the tests of this file start ROS participants (nodes, executables)."""
    if 'ros' in path.parts or path.name in _ROS_FILES + _PARTICIPANT_FILES:
        return True
    try:
        text = path.read_text(encoding='utf-8', errors='replace')
    except OSError:
        return False
    return 'context: Context' in text or any(sign in text for sign in _PARTICIPANT_SIGNS)


if importlib.util.find_spec('xdist') is not None:
    def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
        """``./run.sh test`` runs two workers (pytest-xdist): each file's tests go to one
        worker together (its module fixtures are built once), and every file that starts a
        ROS participant to the same worker, one after another as without workers: several
        use the default domain and the same topic names, and two at once hear each other.
        (pytest-xdist's own ``--dist loadgroup`` does not group under pytest 9, which gtsam
        4.3 requires.)"""
        from xdist.scheduler import LoadFileScheduling

        root = Path(str(config.rootpath))

        class RosTogether(LoadFileScheduling):  # type: ignore[misc]
            def _split_scope(self, nodeid: str) -> str:
                file = nodeid.split('::', 1)[0]
                return 'ros' if _starts_participants(root / file) else file

        return RosTogether(config, log)


@pytest.fixture(scope='session')
def shared_data() -> Path:
    """Path of ../shared/data; skips the test with the reason when it is absent."""
    if not (SHARED_DATA / 'README.md').is_file():
        pytest.skip(f'{_NO_DATA} {SHARED_DATA} (CI provides ../shared/data)')
    return SHARED_DATA


@pytest.fixture()
def context() -> Iterator[Context]:
    """A fresh rclpy context for one test (skips when rclpy is absent), shut down after it."""
    rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')
    from rclpy.context import Context

    from solid_ros.runtime import tune_thread_switching

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
