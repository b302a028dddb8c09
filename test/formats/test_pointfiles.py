"""Point files: the PCD writer round-trips through the reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from solid_ros.core.errors import SolidError
from solid_ros.formats.pointfiles import read_pcd, read_points, write_pcd


def test_pcd_writer_round_trip(tmp_path: Path) -> None:
    pts = np.random.default_rng(2).uniform(-100.0, 100.0, (1000, 4))
    path = write_pcd(tmp_path / 'map.pcd', pts)
    got = read_pcd(path)
    assert got.dtype == np.float32 and got.shape == (1000, 3)
    np.testing.assert_array_equal(got, pts[:, :3].astype(np.float32))
    np.testing.assert_array_equal(read_points(path), got)
    assert read_pcd(write_pcd(tmp_path / 'empty.pcd', np.zeros((0, 3)))).shape == (0, 3)
    with pytest.raises(SolidError, match=r'\(N, 3\+\)'):
        write_pcd(tmp_path / 'bad.pcd', np.zeros((4, 2)))
    with pytest.raises(SolidError, match='cannot write'):
        write_pcd(tmp_path / 'missing' / 'map.pcd', pts)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['empty.pcd', 'map.pcd']
