"""Tests of solid_ros.tools.scoring: the reference pose of each keyframe."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.errors import PoseError
from solid_ros.formats.poses import PoseTrack
from solid_ros.tools.scoring import reference_poses


def _poses(n: int) -> np.ndarray:
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, 0, 3] = np.arange(n)
    return out


def test_unstamped_poses_pair_by_message_order() -> None:
    track = PoseTrack(_poses(6), None, 'poses.txt')
    ref = reference_poses(track, [0, 2, 5], [10, 20, 30], 5, 5e-9)
    assert ref[:, 0, 3].tolist() == [0.0, 2.0, 5.0]


def test_stamped_poses_pair_by_nearest_stamp_within_the_tolerance() -> None:
    track = PoseTrack(_poses(4), np.array([100, 200, 300, 400], dtype=np.int64), '/odom')
    ref = reference_poses(track, [0, 1, 2], [149, 251, 700], 50, 5e-8)
    assert ref[0, 0, 3] == 0.0 and ref[1, 0, 3] == 2.0
    assert np.isnan(ref[2]).all()  # nothing within 50 ns
    with pytest.raises(PoseError, match=r'no reference pose of /odom lies within 5e-08 s'):
        reference_poses(track, [0], [10_000], 50, 5e-8)
    assert reference_poses(track, [], [], 50, 5e-8).shape == (0, 4, 4)
