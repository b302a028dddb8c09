"""The README's main command, end to end on the built-in drive and on a user's bag."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from solid_ros.formats.bags import write_cloud_bag
from solid_ros.tools import demo


@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path: Path,
                              capsys: pytest.CaptureFixture[str]) -> None:
    cache, out = tmp_path / 'cache', tmp_path / 'out'
    args = ['--cache-dir', str(cache), '--out', str(out), '-q']
    assert demo.main(args) == 0
    text = capsys.readouterr().out
    assert 'Recall@1' in text and 'yaw error' in text and 'reverse' in text
    report = json.loads((out / 'report.json').read_text())
    # The bars: no false loop, and same-direction revisits found with a correct pose.
    assert report['loops']['published'] > 50 and report['loops']['precision'] == 1.0
    for png in ('pr_curve.png', 'trajectory.png', 'distance_hist.png', 'yaw_error_hist.png',
                'verification.png', 'pose_error_hist.png'):
        assert (out / png).stat().st_size > 1000
    recall, yaw_error = _same_direction(text)
    assert recall >= 0.8 and yaw_error < 1.0
    assert 'reverse' in text  # reported whether found or not
    assert 'descriptor top-1 within 5 m' in text
    # The drive's drifting odometry, closed by the back end: the corrected ATE is lower.
    assert 'ATE odometry' in text and '-> corrected' in text
    traj = report['trajectory']
    assert traj['corrected']['ate_m'] < 0.5 * traj['odometry']['ate_m']
    assert (out / 'trajectory.tum').is_file()
    # One bag in the cache (that a second run reuses it is test_demo_cache's; a second full
    # replay here cost CI 40 s).
    assert len(list(cache.rglob('metadata.yaml'))) == 1


def _same_direction(text: str) -> tuple[float, float]:
    """Recall and mean yaw error of same-direction revisits from the demo's table."""
    line = next(row for row in text.splitlines() if row.strip().startswith('same '))
    words = line.split()
    found, total = int(words[1]), int(words[3])
    return found / total, float(words[words.index('mean') + 1])


def test_demo_with_a_user_bag_is_solid_replay(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(0)
    scans = [(rng.uniform(-30, 30, (2000, 3)).astype(np.float32), 10**9 * (i + 1), None)
             for i in range(5)]
    bag = tmp_path / 'bag'
    write_cloud_bag(bag, scans, fmt='mcap')
    assert demo.main([str(bag), '--out', str(tmp_path / 'out'), '-q']) == 0
    assert (tmp_path / 'out' / 'candidates.csv').is_file()
    assert demo.main([str(tmp_path / 'missing')]) == 1
    assert 'error' in capsys.readouterr().err


def test_keyframes_pair_with_their_scans_by_stamp(tmp_path: Path) -> None:
    """Gated replays skip scans: labels follow the keyframe's stamp, not its index."""
    times = tmp_path / 'times.txt'
    # As the simulator writes them: decimal seconds, float-rounded below the microsecond.
    times.write_text('1700000000.000000000\n1700000000.211311579\n1700000000.418871880\n'
                     '1700000000.630000000\n')
    kept = SimpleNamespace(stamps_ns=np.array([1_700_000_000_000_000_000,
                                               1_700_000_000_418_871_788,
                                               1_700_000_000_630_000_100,
                                               1_700_000_099_000_000_000]))
    got = demo._keyframe_scans(kept, times)  # type: ignore[arg-type]
    assert got.tolist() == [0, 2, 3, -1]
