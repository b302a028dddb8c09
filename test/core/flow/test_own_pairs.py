"""The partner a keyframe is registered to for the run's calibration: a few metres back along
the odometry, not across a turn or a reset. (The registrations themselves are exercised
through the detector: test_closure.py's calibration, test_detector.py's steps.)"""

from __future__ import annotations

import math

import numpy as np

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import CloudStore
from solid_ros.core.database.descriptors import DescriptorDatabase
from solid_ros.core.descriptor.mount import Mount
from solid_ros.core.flow.own_pairs import OwnKeyframes
from solid_ros.core.geometry import matrix_to_vector, rot_z
from solid_ros.core.odometry.track import OdometryPath
from solid_ros.core.verification.calibration import PAIR_MAX_TURN_DEG, PAIR_PATH_M

SEC = 1_000_000_000


def _own(yaws: dict[int, float] | None = None, reset_at: int | None = None,
         count: int = 11, spacing: float = 0.5) -> tuple[OwnKeyframes, list[np.ndarray]]:
    """Keyframes 0..count-1 along x, ``spacing`` apart, turned by ``yaws`` (deg) where given;
    the odometry announces a reset at ``reset_at``."""
    cfg = SolidConfig()
    db = DescriptorDatabase(cfg)
    path = OdometryPath(100)
    rng = np.random.default_rng(0)
    seqs, poses = {}, []
    for i in range(count):
        T = np.eye(4)
        T[:3, :3] = rot_z(math.radians((yaws or {}).get(i, 0.0)))
        T[0, 3] = i * spacing
        vec = np.asarray(matrix_to_vector(T), dtype=np.float64)
        seqs[i] = db.add(rng.random(40), rng.random(60), i * SEC, vec)
        path.add(i, vec, reset=i == reset_at)
        poses.append(vec)
    own = OwnKeyframes(db, CloudStore(10, 10**6), seqs, path, Mount(cfg), cfg.session_id)
    return own, poses


def test_the_partner_is_the_newest_keyframe_the_pair_path_back() -> None:
    own, poses = _own()
    back = math.ceil(PAIR_PATH_M / 0.5)
    assert own.partner(10, poses[10]) == (back, own.seqs[10 - back], back * 0.5)


def test_a_turn_beyond_the_pair_limit_keeps_the_keyframe_before_it() -> None:
    own, poses = _own(yaws={8: PAIR_MAX_TURN_DEG + 10.0})
    assert own.partner(10, poses[10]) == (1, own.seqs[9], 0.5)
    # Turned right behind it: the turned one all the same (there is none before it).
    own, poses = _own(yaws={9: PAIR_MAX_TURN_DEG + 10.0})
    assert own.partner(10, poses[10]) == (1, own.seqs[9], 0.5)


def test_no_partner_across_a_reset_or_before_the_first_keyframe() -> None:
    own, poses = _own(reset_at=10)
    assert own.partner(10, poses[10]) is None
    own, poses = _own(reset_at=9)
    assert own.partner(10, poses[10]) == (1, own.seqs[9], 0.5)
    assert own.partner(0, poses[0]) is None
