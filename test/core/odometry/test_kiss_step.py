"""The guesses a registration is aligned from: KISS-ICP's own first, then time-scaled, then
standstill (the split step itself is checked against ``register_frame`` in test_kiss.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from solid_ros.core.odometry.kiss_step import guesses


def _pose(yaw_deg: float, xyz: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('z', yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = xyz
    return T


def test_kiss_icps_guess_first_then_time_scaled_then_standstill() -> None:
    kiss = SimpleNamespace(last_pose=_pose(30.0, (5.0, 2.0, 0.0)),
                           last_delta=_pose(4.0, (1.0, 0.1, 0.0)))
    got = guesses(kiss, 3.0)
    assert [name for name, _ in got] == ['constant velocity', 'time-scaled', 'standstill']
    np.testing.assert_allclose(got[0][1], kiss.last_pose @ kiss.last_delta)
    step = np.linalg.inv(kiss.last_pose) @ got[1][1]  # three times the last motion
    np.testing.assert_allclose(step[:3, 3], [3.0, 0.3, 0.0], atol=1e-12)
    yaw = Rotation.from_matrix(step[:3, :3]).as_euler('xyz', degrees=True)[2]
    assert abs(yaw - 12.0) < 1e-9
    np.testing.assert_allclose(got[2][1], kiss.last_pose)
    # Evenly spaced clouds, or no spacing known: no time-scaled guess.
    assert [n for n, _ in guesses(kiss, 1.1)] == ['constant velocity', 'standstill']
    assert [n for n, _ in guesses(kiss, None)] == ['constant velocity', 'standstill']
    assert [n for n, _ in guesses(kiss, float('nan'))] == ['constant velocity', 'standstill']
