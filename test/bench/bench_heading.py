"""A-SOLiD heading error, 'full' (the paper) vs 'overlap' search, bucketed by |true yaw|.

Run: .venv/bin/python test/bench/bench_heading.py [--positions 150] [--sets NAME,...]

Pair sets (the query and candidate heading signatures are described with the preset named):
- ``hku1_matches``: hku1 (real Livox Avia, ../shared/data/hku1), ``config/avia.yaml``; the
  detector's best match of every query that lies within 5 m of it by the reference poses
  (the replay's "true matches").
- ``hku1_pairs``: hku1, every pair of keyframes within 5 m and more than 50 frames apart.
- ``avia_posed`` / ``hdl64_90_posed``: the simulator's ``avia_like`` sensor with
  ``config/avia.yaml``, and ``hdl64`` clipped to 90 deg with ``config/spinning_fov90.yaml``:
  at ``--positions`` random places of the demo drive (seed 0) a candidate scan, and two
  query scans 0-2 m away turned by a uniform -90..90 deg.
- ``avia_drive`` / ``hdl64_90_drive``: the simulated drives themselves through the detector,
  true matches as for hku1.
- ``kitti_90``: real KITTI scans (313-315 and sequence 00 frames 0-5) turned by -90..90 deg
  and clipped to 90 deg (what the turned sensor would see), against the previous frame
  (about 1 m back), ``config/spinning_fov90.yaml``.

Per |true yaw| bucket: pairs, mean / median error in degrees of ``estimate_yaw`` in each
mode, and of the best of three ``heading_hypotheses`` (what a verifier seeded with three
headings could reach). Errors are |yaw - yaw_ref| wrapped to [0, 180].
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / 'test'))

from solid_ros import LoopDetector, SolidConfig, describe  # noqa: E402
from solid_ros.core.descriptor.matching import estimate_yaw, heading_hypotheses  # noqa: E402
from solid_ros.core.geometry import relative_yaw  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
AVIA = ROOT / 'config' / 'avia.yaml'
FOV90 = ROOT / 'config' / 'spinning_fov90.yaml'
BUCKETS = (0, 10, 20, 30, 40, 50, 60, 90, 180)
MODES = ('full', 'overlap')
SETS = ('hku1_matches', 'hku1_pairs', 'avia_posed', 'avia_drive', 'hdl64_90_posed',
        'hdl64_90_drive', 'kitti_90')

Pairs = tuple[np.ndarray, np.ndarray, np.ndarray]  # query, candidate signatures; true yaw


def _error_deg(a: float, b: float) -> float:
    return abs(math.degrees(math.remainder(a - b, 2 * math.pi)))


def _stack(rows: list[tuple[np.ndarray, np.ndarray, float]]) -> Pairs:
    q, c, y = zip(*rows)
    return np.array(q), np.array(c), np.array(y)


def _detector_matches(scans: Iterable[tuple[np.ndarray, int, np.ndarray]],
                      cfg: SolidConfig, radius: float = 5.0) -> Pairs:
    """Each query's best match within ``radius`` of it (reference poses)."""
    det = LoopDetector(cfg)
    heads: list[np.ndarray] = []
    poses: list[np.ndarray] = []
    rows = []
    for points, stamp, pose in scans:
        desc = describe(points, cfg)
        best = det.process_descriptor(desc, stamp, pose).best
        heads.append(desc.heading)
        poses.append(pose)
        if best is not None:
            j = best.match_index
            if np.linalg.norm(pose[:3, 3] - poses[j][:3, 3]) < radius:
                rows.append((desc.heading, heads[j], relative_yaw(pose, poses[j])))
    return _stack(rows)


def _hku1() -> tuple[list[np.ndarray], list[int], np.ndarray]:
    from hku1_data import hku1_scans

    from solid_ros.formats.poses import read_kitti_poses
    clouds, stamps = hku1_scans(DATA)
    return clouds, stamps, read_kitti_poses(DATA / 'hku1' / 'optimized_poses.txt')


def hku1_matches(_: argparse.Namespace) -> Pairs:
    clouds, stamps, poses = _hku1()
    return _detector_matches(zip(clouds, stamps, poses), SolidConfig.from_yaml(AVIA))


def hku1_pairs(_: argparse.Namespace) -> Pairs:
    clouds, _, poses = _hku1()
    cfg = SolidConfig.from_yaml(AVIA)
    heads = [describe(c, cfg).heading for c in clouds]
    rows = []
    for i in range(len(clouds)):
        for j in range(i - 50):
            if np.linalg.norm(poses[i][:3, 3] - poses[j][:3, 3]) < 5.0:
                rows.append((heads[i], heads[j], relative_yaw(poses[i], poses[j])))
    return _stack(rows)


def _posed(sensor: str, preset: Path, positions: int) -> Pairs:
    from solid_ros.sim.drive import Drive, DriveConfig
    from solid_ros.sim.lidar import cast_scan
    drive = Drive(DriveConfig(seed=0, sensor=sensor))
    traj = drive.trajectory
    cfg = SolidConfig.from_yaml(preset)
    rng = np.random.default_rng(123)
    rows = []
    for k in rng.choice(len(traj), min(positions, len(traj)), replace=False):
        x, y, heading = float(traj.xy[k, 0]), float(traj.xy[k, 1]), float(traj.yaw[k])
        cand = describe(cast_scan(drive.scene, drive.model, x, y, heading, rng), cfg).heading
        for _ in range(2):
            turn = math.radians(rng.uniform(-90.0, 90.0))
            r, a = rng.uniform(0.0, 2.0), rng.uniform(-math.pi, math.pi)
            cloud = cast_scan(drive.scene, drive.model, x + r * math.cos(a),
                              y + r * math.sin(a), heading + turn, rng)
            rows.append((describe(cloud, cfg).heading, cand, turn))
    return _stack(rows)


def avia_posed(args: argparse.Namespace) -> Pairs:
    return _posed('avia_like', AVIA, args.positions)


def hdl64_90_posed(args: argparse.Namespace) -> Pairs:
    return _posed('hdl64', FOV90, args.positions)


def _drive(sensor: str) -> Iterator[tuple[np.ndarray, int, np.ndarray]]:
    from solid_ros.sim import simulate
    for scan in simulate(seed=0, sensor=sensor):
        yield scan.points, scan.stamp_ns, scan.pose


def avia_drive(_: argparse.Namespace) -> Pairs:
    return _detector_matches(_drive('avia_like'), SolidConfig.from_yaml(AVIA))


def hdl64_90_drive(_: argparse.Namespace) -> Pairs:
    return _detector_matches(_drive('hdl64'), SolidConfig.from_yaml(FOV90))


def kitti_90(_: argparse.Namespace) -> Pairs:
    from solid_ros.formats.pointfiles import read_kitti_bin, read_pcd
    cfg = SolidConfig.from_yaml(FOV90)
    rng = np.random.default_rng(5)
    groups = [[read_pcd(DATA / 'kitti' / 'pcd' / f'000{f}.pcd') for f in (313, 314, 315)],
              [read_kitti_bin(DATA / 'kitti' / 'seq00_frames' / f'00000{i}.bin')[:, :3]
               for i in range(6)]]
    rows = []
    for frames in groups:
        for prev, cur in zip(frames, frames[1:]):
            cand = describe(prev, cfg).heading
            for _ in range(50):
                turn = math.radians(rng.uniform(-90.0, 90.0))
                c, s = math.cos(-turn), math.sin(-turn)  # the sensor turned by +turn
                pts = cur.copy()
                pts[:, 0] = c * cur[:, 0] - s * cur[:, 1]
                pts[:, 1] = s * cur[:, 0] + c * cur[:, 1]
                rows.append((describe(pts, cfg).heading, cand, turn))
    return _stack(rows)


def _table(name: str, pairs: Pairs) -> None:
    q, c, yaw = pairs
    err: dict[str, np.ndarray] = {}
    for mode in MODES:
        err[mode] = np.array([_error_deg(estimate_yaw(a, b, mode), t)
                              for a, b, t in zip(q, c, yaw)])
        err[mode + ' top3'] = np.array([
            min((_error_deg(h, t) for h, _ in heading_hypotheses(a, b, 3, mode)),
                default=180.0) for a, b, t in zip(q, c, yaw)])
    cols = list(err)
    print(f'\n{name}: {len(yaw)} pairs; mean / median error, degrees')
    print(f'{"|true yaw|":>10s} {"pairs":>6s} ' + ' '.join(f'{c:>15s}' for c in cols))
    true = np.degrees(np.abs(yaw))
    for lo, hi in zip(BUCKETS[:-1], BUCKETS[1:]):
        sel = (true >= lo) & (true < hi)
        if sel.any():
            print(f'{f"{lo}-{hi}":>10s} {int(sel.sum()):6d} ' + ' '.join(
                f'{err[k][sel].mean():7.1f}/{np.median(err[k][sel]):6.1f}' for k in cols))
    print(f'{"all":>10s} {len(yaw):6d} ' + ' '.join(
        f'{err[k].mean():7.1f}/{np.median(err[k]):6.1f}' for k in cols))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--positions', type=int, default=150,
                        help='places of the simulated posed pairs (two queries each)')
    parser.add_argument('--sets', default=','.join(SETS), help='comma-separated pair sets')
    args = parser.parse_args()
    for name in args.sets.split(','):
        if name not in SETS:
            parser.error(f'unknown set {name!r}; choose from {", ".join(SETS)}')
        if name.startswith(('hku1', 'kitti')) and not DATA.is_dir():
            print(f'\n{name}: skipped, {DATA} not found')
            continue
        _table(name, globals()[name](args))
    return 0


if __name__ == '__main__':
    sys.exit(main())
