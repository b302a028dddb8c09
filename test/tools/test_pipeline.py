"""Tests of solid_ros.tools.pipeline: one record per cloud, odometry source -> detector."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from solid_ros.core.config import NodeConfig, SolidConfig
from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.geometry import pose_to_vector
from solid_ros.core.odometry.track import OdomSample
from solid_ros.formats.bags import CloudScan, write_cloud_bag
from solid_ros.tools.options import ReplayOptions
from solid_ros.tools.pipeline import ReplayPipeline, ScanLog, published_best
from solid_ros.tools.progress import Progress

# Places 0..4, then 0..2 again; descriptor only, so no registration is needed.
ROUTE = [0, 1, 2, 3, 4, 0, 1, 2]
CFG = SolidConfig(exclude_recent_frames=3, distance_threshold=0.02, verify=False)
T0 = 10**18


def _place(k: int, n: int = 3000) -> np.ndarray:
    rng = np.random.default_rng(500 + k)
    r = rng.choice(rng.uniform(5.0, 60.0, size=4), size=n) + rng.normal(scale=1.0, size=n)
    az = rng.uniform(-np.pi, np.pi, size=n)
    el = np.radians(rng.uniform(-24.0, 1.5, size=n))
    return np.stack([r * np.cos(az) * np.cos(el), r * np.sin(az) * np.cos(el),
                     r * np.sin(el)], axis=1).astype(np.float32)


def _pose(i: int) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = [2.0 * i, 0.5 * i, 0.0]
    return out


@pytest.fixture(scope='module')
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    scans = [(_place(k), T0 + i * 100_000_000, _pose(i)) for i, k in enumerate(ROUTE)]
    return write_cloud_bag(tmp_path_factory.mktemp('pipeline') / 'bag', scans, 'mcap')


def test_one_record_per_cloud_with_its_odometry(bag: Path) -> None:
    direct = LoopDetector(CFG)
    with ReplayPipeline(bag, LoopClosure(LoopDetector(CFG)), ReplayOptions()) as pipeline:
        assert pipeline.inputs.count == len(ROUTE) and pipeline.inputs.odometry_fed
        assert pipeline.inputs.odom_topic == '/odom'
        records = list(pipeline.run())
    assert [r.seq for r in records] == list(range(len(ROUTE)))
    for i, rec in enumerate(records):
        assert rec.odom is not None and rec.odom.stamp_ns == rec.stamp_ns == T0 + i * 10**8
        np.testing.assert_allclose(rec.odom.pose, _pose(i))
        assert rec.result is not None and not rec.skipped
        # The same as handing the scan and its pose to a detector directly.
        want = direct.process(_place(ROUTE[i]), rec.stamp_ns, pose=_pose(i))
        assert (rec.result.keyframe, rec.result.loops, rec.result.best) == (
            want.keyframe, want.loops, want.best)
    loops = [(c.query_index, c.match_index) for r in records for c in r.result.loops]
    assert loops == [(5, 0), (6, 1), (7, 2)]


class _Shifted:
    """An odometry source of its own: the pose of each cloud's place, shifted, and the clouds
    it was asked about (as one computing odometry from the points would see them)."""

    name = 'shifted'

    def __init__(self) -> None:
        self.sizes: list[int] = []

    def pose_for(self, stamp_ns: int, points: np.ndarray | None = None) -> OdomSample | None:
        assert points is not None
        self.sizes.append(len(points))
        pose = _pose((stamp_ns - T0) // 100_000_000)
        pose[2, 3] = 7.0
        return OdomSample(stamp_ns, pose)


def test_another_odometry_source_plugs_in(bag: Path) -> None:
    source = _Shifted()
    with ReplayPipeline(bag, LoopClosure(LoopDetector(CFG)), ReplayOptions()) as pipeline:
        pipeline.odometry = source
        records = list(pipeline.run())
    assert source.sizes == [3000] * len(ROUTE)
    for rec in records:
        assert rec.odom is not None and rec.result is not None
        np.testing.assert_allclose(rec.result.pose, pose_to_vector(rec.odom.pose))
        assert rec.result.pose[2] == 7.0
    # Without odometry for the detector the scans still go through, with no pose.
    options = ReplayOptions(node_config=NodeConfig(use_odom=False))
    with ReplayPipeline(bag, LoopClosure(LoopDetector(CFG)), options) as pipeline:
        assert pipeline.odometry is None and not pipeline.inputs.odometry_fed
        assert pipeline.inputs.odometry is not None  # still read, as the reference
        plain = list(pipeline.run())
    assert len(plain) == len(ROUTE)
    assert all(r.odom is None and r.result is not None and r.result.pose is None for r in plain)


def test_skipped_clouds_are_records_too(bag: Path) -> None:
    with ReplayPipeline(bag, LoopClosure(LoopDetector(CFG)), ReplayOptions()) as pipeline:
        broken = pipeline.step(CloudScan(3, T0, None, 'truncated data'))
        assert broken.result is None and broken.skipped == 'truncated data'
        undecoded = pipeline.step(CloudScan(4, T0, None))
        assert undecoded.skipped == 'undecodable'
        nan = pipeline.step(CloudScan(5, T0, np.full((50, 3), np.nan, np.float32)))
        assert nan.result is None and nan.skipped.startswith('no usable point')
        assert pipeline.detector.num_keyframes == 0  # nothing reached the database
    log = ScanLog()
    for rec in (broken, undecoded, nan):
        log.add(rec)
    assert (log.messages, log.decoded, log.skipped) == (
        3, 0, [(3, 'truncated data'), (4, 'undecodable'), (5, nan.skipped)])


def test_log_keeps_keyframes_without_descriptors(bag: Path) -> None:
    with ReplayPipeline(bag, LoopClosure(LoopDetector(CFG.replace(keyframe_min_sec=0.15))),
                        ReplayOptions()) as pipeline:
        records = list(pipeline.run())
    assert any(r.result is not None and r.result.descriptor is not None for r in records)
    log = ScanLog()
    for rec in records:
        log.add(rec)
    kept = [r for r in records if r.result is not None and r.result.keyframe]
    assert 0 < len(kept) < len(records)  # every other scan is gated out
    assert [seq for seq, _ in log.keyframes] == [r.seq for r in kept]
    assert all(res.descriptor is None for res in log.results)
    assert log.decoded == log.messages == len(records)
    assert log.candidates == [c for r in kept for c in r.result.loops]
    assert [published_best(res) for res in log.results] == [
        res.best is not None and bool(res.loops) for res in log.results]
    assert len(log.stage_ms('describe')) == len(kept)


# -- KISS-ICP odometry over the clouds (a few real hku1 clouds) --------------------------------

HKU1_CLOUDS = 16


@pytest.fixture(scope='module')
def hku1_bags(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The first hku1 clouds, with the recorded odometry (the reference) and without any."""
    pytest.importorskip('kiss_icp', reason='kiss-icp is not installed')
    from solid_ros.core.odometry.track import nearest_stamp
    from solid_ros.formats.bags import Bag

    with Bag(shared_data / 'hku1' / 'bag') as bag:
        clouds = [(s.points, s.stamp_ns) for s, _ in zip(bag.clouds('/points'),
                                                          range(HKU1_CLOUDS))]
        track = bag.odometry('/odom_slam')
    assert track.stamps_ns is not None
    idx = nearest_stamp(track.stamps_ns, [s for _, s in clouds], 50_000_000)
    root = tmp_path_factory.mktemp('hku1')
    return {'odom': write_cloud_bag(root / 'odom', [(p, s, track.poses[i])
                                                    for (p, s), i in zip(clouds, idx)]),
            'clouds': write_cloud_bag(root / 'clouds', [(p, s, None) for p, s in clouds],
                                      odom_topic=None)}


def _avia() -> tuple[SolidConfig, NodeConfig]:
    from project_paths import CONFIG_DIR

    from solid_ros.tools.replay import load_config

    return load_config(CONFIG_DIR / 'avia.yaml')


def test_kiss_icp_gives_a_pose_per_cloud_and_the_bag_odometry_is_the_reference(
        hku1_bags: dict[str, Path]) -> None:
    from solid_ros.tools.replay import replay, summary_lines

    cfg, ncfg = _avia()
    r = replay(hku1_bags['odom'], cfg, node_config=ncfg, odometry='kiss-icp', progress='quiet')
    assert r.inputs.odometry_source == 'kiss-icp' and r.report['reference'] == '/odom'
    assert r.log.posed == r.log.decoded == HKU1_CLOUDS
    assert r.report['odometry'] == {'source': 'kiss-icp', 'topic': '/odom',
                                    'posed_scans': HKU1_CLOUDS, 'resets': 0}
    assert r.report['timings']['odometry_ms']['p50'] > 0
    # KISS-ICP's poses are its own (start at the identity), not the recorded ones.
    first = r.trajectory.odometry[0]
    np.testing.assert_allclose(first, np.eye(4), atol=1e-9)
    t = r.report['trajectory']
    assert t is not None and t['odometry']['ate_m'] < 0.2  # a short stretch, tracked
    text = '\n'.join(summary_lines(r))
    assert 'KISS-ICP over the clouds, 0 resets' in text and 'ATE odometry' in text


def test_a_clouds_only_bag_gets_keyframes_and_the_back_end_with_kiss_icp(
        hku1_bags: dict[str, Path]) -> None:
    from solid_ros.tools.replay import replay, summary_lines

    cfg, ncfg = _avia()
    plain = replay(hku1_bags['clouds'], cfg, node_config=ncfg, progress='quiet')
    assert plain.inputs.odometry_source == 'none' and plain.report['backend']['loops'] == {}
    assert not plain.trajectory.posed.any()  # no pose: nothing in the graph
    r = replay(hku1_bags['clouds'], cfg, node_config=ncfg, odometry='kiss-icp',
               progress='quiet')
    assert r.report['reference'] is None and r.report['trajectory'] is None
    assert r.log.posed == HKU1_CLOUDS
    # Keyframes every 0.5 m or 10 deg of KISS-ICP's motion: fewer than the clouds, all posed.
    assert 2 <= r.keyframes < HKU1_CLOUDS and r.trajectory.posed.all()
    assert [kf['segment'] for kf in r.report['keyframes']] == [0] * r.keyframes
    # A scan-only odometry: 'auto' registers each keyframe to the previous one as well.
    assert plain.config.backend_step_registration == 'off'
    assert r.config.backend_step_registration == 'on'
    assert 0 < r.report['backend']['steps'] <= r.keyframes - 1
    assert 'registered steps' in '\n'.join(summary_lines(r))


@pytest.fixture(scope='module')
def vlp16_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Twelve scans of the simulator's VLP-16 (+-15 deg), written as a bag."""
    from solid_ros.sim import simulate

    items = [(s.points.copy(), T0 + i * 100_000_000, s.pose)
             for i, s in enumerate(simulate(seed=0, sensor='vlp16_like', num_scans=12))]
    return write_cloud_bag(tmp_path_factory.mktemp('vlp16') / 'bag', items, 'mcap')


@pytest.mark.parametrize('config, contradicts', [
    (SolidConfig(verify=False), True),  # the authors' +2 / -24.8 deg on a +-15 deg sensor
    (SolidConfig(verify=False, fov_up_deg=15.0, fov_down_deg=-15.0), False)])
def test_first_clouds_are_checked_against_the_settings(vlp16_bag: Path, config: SolidConfig,
                                                       contradicts: bool) -> None:
    with ReplayPipeline(vlp16_bag, LoopClosure(LoopDetector(config)),
                        ReplayOptions()) as pipeline:
        log = pipeline.collect(Progress(12, 'quiet'))
    assert log.sensor.startswith('360-degree, 16 rings, elevations -15.0 to +15.0 deg')
    assert bool(log.sensor_check) is contradicts
    if contradicts:
        assert log.sensor_check.startswith('the first 10 clouds contradict the parameters: ')
        assert log.sensor_check.endswith('set fov_up_deg: 15.0, fov_down_deg: -15.0')


def test_a_bag_shorter_than_the_sample_is_checked_at_its_end(bag: Path) -> None:
    with ReplayPipeline(bag, LoopClosure(LoopDetector(CFG)), ReplayOptions()) as pipeline:
        log = pipeline.collect(Progress(len(ROUTE), 'quiet'))
    assert log.messages == len(ROUTE) < 10
    assert f'over {len(ROUTE)} clouds' in log.sensor
