"""Paths the tests share: the project root, its config directory, the real data beside it."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = ROOT / 'config'
SHARED_DATA = ROOT.parent / 'shared' / 'data'
