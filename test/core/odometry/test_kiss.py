"""KISS-ICP odometry: a simulated drive is followed, KISS-ICP's poses pass unchanged, and every
cloud it cannot register resets the source into a new segment with a reason, never raising."""

from __future__ import annotations

import subprocess
import sys
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import ConfigError, SolidError
from solid_ros.core.odometry.kiss import KissOdometry, load_kiss_icp
from solid_ros.sim import DEMO_SENSORS, Drive, DriveConfig

ROOT = Path(__file__).resolve().parents[3]
FloatArray = npt.NDArray[np.float64]

needs_kiss = pytest.mark.skipif(
    subprocess.run([sys.executable, '-c', 'import kiss_icp.kiss_icp'],
                   capture_output=True).returncode != 0, reason='kiss-icp is not installed')


@lru_cache(maxsize=1)
def _drive() -> Drive:
    # 64 beams, a scan every metre along the first (straight) street.
    return Drive(DriveConfig(seed=0, sensor=DEMO_SENSORS['hdl64'], block=50.0, spacing=1.0))


@lru_cache(maxsize=80)
def _cloud(index: int) -> FloatArray:
    """Scan ``index`` without its ground points.

    The simulator's ground is an exact plane that every scan samples in the same rings around
    the sensor: point-to-point ICP matches the rings to themselves and stays put (with them
    KISS-ICP moves 0.03 m over these 30 m, without them 30.20 m: test/bench/bench_kiss.py).
    Real ground is not that regular; without it the simulated streets register as real ones
    do.
    """
    points = _drive().scan(index).points.astype(np.float64)
    return points[points[:, 2] > -1.4]


def _corridor(seed: int) -> FloatArray:
    """Two walls, a floor and a ceiling along x, sampled at random: nothing fixes x."""
    rng = np.random.default_rng(seed)
    n = 20000
    side = rng.integers(0, 4, n)
    y = np.where(side == 0, 2.0, np.where(side == 1, -2.0, rng.uniform(-2.0, 2.0, n)))
    z = np.where(side == 2, -1.7, np.where(side == 3, 1.5, rng.uniform(-1.7, 1.5, n)))
    return np.c_[rng.uniform(-40.0, 40.0, n), y, z]


def _relative(poses: list[FloatArray]) -> FloatArray:
    return np.stack([np.linalg.inv(poses[0]) @ p for p in poses])


@needs_kiss
def test_follows_a_simulated_drive_with_kiss_icps_own_poses() -> None:
    odo = KissOdometry()
    samples = [odo.pose_for(_drive().stamp_ns(i), _cloud(i)) for i in range(30)]
    assert all(s is not None and s.segment == 0 and s.reason is None for s in samples)
    got = np.stack([s.pose for s in samples if s is not None])
    truth = _relative([_drive().pose(i) for i in range(30)])
    errors = np.linalg.norm(got[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert errors[-1] < 0.5 and errors.max() < 0.6, errors  # 29 m driven
    assert odo.registered == 30 and odo.resets == 0
    assert all(s is not None and s.covariance is None for s in samples)
    # KISS-ICP's own poses: the adapter adds nothing to a cloud it registers. (KISS-ICP
    # itself differs from run to run in the last bits, about 1e-15 per cloud.)
    KissICP, KISSConfig, _ = load_kiss_icp()
    # Its settings came from the first cloud, as KISS-ICP's pipeline takes its voxel from the
    # range: the 99th percentile of the ranges, and a hundredth of it.
    ranges = np.linalg.norm(_cloud(0), axis=1)
    assert odo.config.kiss_max_range == np.ceil(np.percentile(ranges, 99))
    assert odo.config.kiss_voxel_size == odo.config.kiss_max_range / 100.0
    kc = KISSConfig()
    kc.data.max_range, kc.data.deskew = odo.config.kiss_max_range, False
    kc.mapping.voxel_size = odo.config.kiss_voxel_size
    kiss = KissICP(kc)
    for i, sample in enumerate(samples):
        kiss.register_frame(_cloud(i), np.zeros(0))
        assert sample is not None
        np.testing.assert_allclose(sample.pose, kiss.last_pose, rtol=0.0, atol=1e-9)


@needs_kiss
def test_clouds_it_cannot_register_reset_it_into_new_segments() -> None:
    odo = KissOdometry()
    seen: list[tuple[int, str | None]] = []

    def feed(points: Any) -> FloatArray:
        sample = odo.pose_for(0, points)
        assert sample is not None
        seen.append((sample.segment, sample.reason))
        return sample.pose

    for i in range(6):
        last = feed(_cloud(i))
    assert seen[-1] == (0, None)
    # Empty, all NaN, malformed: dropped; the pose stays, a new segment starts once.
    np.testing.assert_array_equal(feed(np.zeros((0, 3))), last)
    assert seen[-1][0] == 1 and 'finite points' in str(seen[-1][1])
    feed(np.full((5000, 3), np.nan))
    feed(np.arange(5.0))
    assert [s for s, _ in seen[-2:]] == [1, 1] and all(r for _, r in seen[-2:])
    assert odo.reset_counts['points'] == 3 and odo.resets == 1
    # The next good cloud starts segment 1 where segment 0 ended; NaN rows are dropped.
    with_nan = np.r_[_cloud(6), np.full((50, 3), np.nan)]
    np.testing.assert_array_equal(feed(with_nan), last)
    feed(_cloud(7))
    assert seen[-2:] == [(1, None), (1, None)]
    # A teleport 50 m ahead: KISS-ICP follows a metre of it; the clouds do not overlap.
    feed(_cloud(57))
    assert seen[-1][0] == 2 and 'overlap' in str(seen[-1][1]) and odo.reset_counts['overlap']
    feed(_cloud(58))
    assert seen[-1] == (2, None)
    # The same place turned by 90 degrees (a jump KISS-ICP cannot follow).
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    feed(_cloud(59) @ turn.T)
    assert seen[-1][0] == 3 and 'overlap' in str(seen[-1][1]), seen[-1]
    feed(_cloud(60) @ turn.T)
    assert seen[-1] == (3, None)
    # A corridor: its motion along the walls is unknown.
    feed(_corridor(0))
    assert seen[-1][0] == 4 and 'degenerate' in str(seen[-1][1])
    assert odo.resets == 4 and odo.segment == 4
    # NaN rows were dropped from two clouds: the all-NaN one and the one with 50 of them.
    assert sum(odo.reset_counts.values()) == 6 and odo.input_counts['nan'] == 2
    odo.reset('relocalised')  # the caller's reset
    feed(_cloud(61))
    assert seen[-1][0] == 5 and 'relocalised' in str(seen[-1][1])


@needs_kiss
def test_a_gap_in_the_clouds_is_registered_from_the_time_scaled_guess() -> None:
    # 1 m steps, then 6 m (five clouds missing, as keyframes of a fast car): KISS-ICP's
    # constant velocity guesses 1 m and its alignment does not overlap; six times the last
    # motion does, and no reset is needed.
    odo = KissOdometry()
    indices = [0, 1, 2, 3, 9, 10]
    samples = [odo.pose_for(_drive().stamp_ns(i), _cloud(i)) for i in indices]
    assert all(s is not None and s.reason is None for s in samples), samples
    assert odo.resets == 0 and odo.recovered == {'time-scaled': 1}
    truth = np.linalg.inv(_drive().pose(0)) @ _drive().pose(10)
    assert samples[-1] is not None
    assert np.linalg.norm(samples[-1].pose[:3, 3] - truth[:3, 3]) < 0.1


@needs_kiss
@pytest.mark.parametrize('gap', [False, True])
def test_a_cloud_kept_from_the_standstill_guess_after_a_gap_leaves_kiss_icps_motion(
        gap: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    # Along a road a standstill alignment passes the checks while the car drives on (riv281,
    # cloud 110, 2.6 s after the last): it gives the cloud's pose, but a motion taken from it
    # held the odometry still. Only the standstill guess is let through for the fifth cloud,
    # three steps' time after the fourth (a gap: the time-scaled guess is tried) or one.
    odo = KissOdometry()
    for i in range(4):
        assert odo.pose_for(_drive().stamp_ns(i), _cloud(i)).reason is None  # type: ignore
    motion = np.array(odo._kiss.last_delta)
    assert np.linalg.norm(motion[:3, 3]) > 0.9  # the drive's 1 m steps
    check = KissOdometry._check
    labels: list[str] = []

    def standstill_only(self: KissOdometry, kiss: Any, step: Any, frame: Any) -> Any:
        labels.append('standstill' if np.array_equal(step.guess, np.asarray(kiss.last_pose))
                      else 'other')
        if labels[-1] != 'standstill':
            return ('overlap', 'refused for the test'), None
        return check(self, kiss, step, frame)

    monkeypatch.setattr(KissOdometry, '_check', standstill_only)
    kept = odo.pose_for(_drive().stamp_ns(6 if gap else 4), _cloud(4))
    assert kept is not None and kept.reason is None and odo.recovered == {'standstill': 1}
    assert labels == ['other'] * (2 if gap else 1) + ['standstill']
    np.testing.assert_array_equal(odo._kiss.last_pose, np.linalg.inv(odo._origin) @ kept.pose)
    if gap:
        np.testing.assert_array_equal(odo._kiss.last_delta, motion)
    else:  # at the usual spacing a standstill is taken for one: the motion is its step
        assert not np.array_equal(odo._kiss.last_delta, motion)


@needs_kiss
def test_a_stamp_that_jumps_back_starts_a_new_segment() -> None:
    odo = KissOdometry()
    for i in range(4):
        assert odo.pose_for(_drive().stamp_ns(i), _cloud(i)).reason is None  # type: ignore
    back = odo.pose_for(_drive().stamp_ns(1), _cloud(4))
    assert back is not None and back.segment == 1 and 'older than the last' in str(back.reason)
    assert odo.reset_counts == {'stamp': 1}
    after = odo.pose_for(_drive().stamp_ns(2), _cloud(5))
    assert after is not None and after.segment == 1 and after.reason is None


@needs_kiss
def test_a_jump_and_a_failure_reset_it() -> None:
    # 1 m steps against a 0.5 m limit: every step after the first of a segment is a jump.
    odo = KissOdometry(NodeConfig(kiss_max_step_m=0.5))
    assert KissOdometry().max_step_m == 0.0  # half the max range, once there is one
    first = odo.pose_for(1, _cloud(0))
    jumped = odo.pose_for(2, _cloud(1))
    assert first is not None and jumped is not None
    assert jumped.segment == 1 and 'jumped 1.' in str(jumped.reason)
    np.testing.assert_array_equal(jumped.pose, first.pose)  # no pose that jumps unlogged

    class Broken:
        """A KISS-ICP whose every step raises, as the binding may (out of memory)."""

        last_pose = np.eye(4)
        last_delta = np.eye(4)

        def __init__(self, config: Any) -> None:
            self.preprocessor = self

        def preprocess(self, frame: Any, times: Any, delta: Any) -> None:
            raise RuntimeError('std::bad_alloc')

    odo = KissOdometry()
    odo.pose_for(1, _cloud(0))
    odo._KissICP = Broken
    odo._kiss = Broken(None)
    sample = odo.pose_for(2, _cloud(1))
    assert sample is not None and sample.segment == 1 and 'bad_alloc' in str(sample.reason)
    again = odo.pose_for(3, _cloud(2))  # still failing: counted, no further segment
    assert again is not None and again.segment == 1 and odo.reset_counts['failed'] == 2
    assert odo.pose_for(4, None) is None  # no cloud, no pose


def test_missing_kiss_icp_says_how_to_install_it(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in [m for m in sys.modules if m == 'kiss_icp' or m.startswith('kiss_icp.')]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, 'kiss_icp', None)  # import fails
    with pytest.raises(SolidError, match='pip install kiss-icp'):
        KissOdometry()


def test_missing_small_gicp_is_said_at_start_not_as_resets(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # The overlap check takes its neighbours from small_gicp's kd-tree.
    monkeypatch.setitem(sys.modules, 'small_gicp', None)  # import fails
    with pytest.raises(SolidError, match='pip install small-gicp'):
        KissOdometry()


def test_kiss_icp_is_imported_only_when_chosen() -> None:
    code = ('import sys, solid_ros.core.odometry.kiss, solid_ros.core.config; '
            'print(any(m.startswith("kiss_icp") for m in sys.modules))')
    out = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout
    assert out.strip() == 'False'


def test_settings_are_checked() -> None:
    default = NodeConfig()
    assert default.odometry_source == 'topic' and default.kiss_deskew is True
    # Range, voxel and jump come from the data unless set.
    assert default.kiss_max_range == default.kiss_voxel_size == default.kiss_max_step_m == 0.0
    with pytest.raises(ConfigError, match='kiss_max_range'):
        NodeConfig(kiss_min_range=10.0, kiss_max_range=5.0)
    with pytest.raises(ConfigError, match='odometry_source'):
        NodeConfig(odometry_source='wheels')


def test_the_input_checks_give_numpys_ranges_and_finite_rows_to_the_bit() -> None:
    """The cheaper range and finite-row code keeps what the gate and the checks see exactly."""
    from solid_ros.core.odometry.kiss import _finite_xyz, _norms

    rng = np.random.default_rng(5)
    pts = rng.normal(scale=30.0, size=(20_000, 4)).astype(np.float32)
    pts[::3] *= np.float32(1e-3)
    pts[::97, 1] = np.nan
    pts[::89, 2] = np.inf
    xyz, keep = _finite_xyz(pts)
    want = pts[:, :3].astype(np.float64)
    want_keep = np.all(np.isfinite(want), axis=1)
    assert np.array_equal(keep, want_keep) and not keep.all()
    assert np.array_equal(xyz, want[want_keep]) and xyz.flags['C_CONTIGUOUS']
    assert np.array_equal(_norms(xyz), np.linalg.norm(xyz, axis=1))
    clean, every = _finite_xyz(pts[want_keep])
    assert every.all() and np.array_equal(clean, xyz) and clean.dtype == np.float64
