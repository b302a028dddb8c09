"""Shared fixtures: the real data set beside the project and small loaders."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / 'shared' / 'data'


@pytest.fixture(scope='session')
def shared_data() -> Path:
    """Path of ../shared/data; skips the test with the reason when it is absent."""
    if not (SHARED_DATA / 'README.md').is_file():
        pytest.skip(f'real data not found at {SHARED_DATA} (CI provides ../shared/data)')
    return SHARED_DATA
