"""Tests of solid_ros.tools.options: one rule per limit, for the API and the command line."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import ConfigError, PoseError
from solid_ros.tools.options import ReplayOptions
from solid_ros.tools.replay import build_parser

# option, its flag, values it refuses, values it takes
LIMITS = [
    ('radius', '--radius', [0.0, -1.0, math.inf, math.nan], [0.1, 5.0, 1e6]),
    ('max_heading_deg', '--max-heading-deg', [0.0, -5.0, 180.5, math.nan], [1.0, 180.0]),
    ('max_pose_error_m', '--max-pose-error-m', [0.0, -1.0, math.inf], [1e-7, 2.0]),
    ('max_pose_error_deg', '--max-pose-error-deg', [0.0, 200.0, math.nan], [1e-5, 180.0]),
    ('target_precision', '--target-precision', [0.0, 1.5, math.nan], [0.5, 1.0]),
]


@pytest.mark.parametrize(('name', 'flag', 'bad', 'good'), LIMITS)
def test_api_and_command_line_share_each_limit(name: str, flag: str, bad: list[float],
                                               good: list[float],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    parser = build_parser()
    for value in bad:
        with pytest.raises(ConfigError, match=f'^{flag} must be'):
            ReplayOptions(**{name: value})  # type: ignore[arg-type]
        with pytest.raises(SystemExit) as exc:
            parser.parse_args(['bag', flag, str(value)])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert f'argument {flag}: must be' in err, err
    for value in good:
        assert getattr(ReplayOptions(**{name: value}), name) == value  # type: ignore[arg-type]
        assert getattr(parser.parse_args(['bag', flag, str(value)]), name) == value


def test_times_need_poses_and_progress_is_a_mode() -> None:
    with pytest.raises(PoseError, match='--times needs --poses'):
        ReplayOptions(times='t.txt')
    assert ReplayOptions(poses='p.txt', times='t.txt').times == 't.txt'
    with pytest.raises(ConfigError, match='progress must be one of'):
        ReplayOptions(progress='loud')


def test_of_applies_changes_and_names_unknown_ones() -> None:
    base = ReplayOptions(radius=3.0)
    opts = ReplayOptions.of(base, out_dir=Path('o'), node_config=None)
    assert (opts.radius, opts.out_dir, opts.node_config) == (3.0, Path('o'), NodeConfig())
    assert ReplayOptions.of() == ReplayOptions()
    with pytest.raises(TypeError, match='unknown replay option'):
        ReplayOptions.of(base, radiuss=2.0)
    with pytest.raises(ConfigError, match='--radius'):
        ReplayOptions.of(base, radius=-2.0)


def test_odometry_settings_follow_the_node_config() -> None:
    node = NodeConfig(use_odom=False, odom_tolerance_sec=0.0125)
    assert not ReplayOptions(node_config=node).feed_odom
    assert ReplayOptions(node_config=node, use_odom=True).feed_odom
    assert ReplayOptions(use_odom=False).feed_odom is False
    assert ReplayOptions(node_config=node).tolerance_ns == 12_500_000


def test_odometry_source_is_the_option_else_the_node_setting() -> None:
    assert ReplayOptions().odometry_mode == 'bag'
    kiss = NodeConfig(odometry_source='kiss_icp')
    assert ReplayOptions(node_config=kiss).odometry_mode == 'kiss-icp'
    assert ReplayOptions(node_config=kiss, odometry='bag').odometry_mode == 'bag'
    assert ReplayOptions(odometry='kiss-icp').odometry_mode == 'kiss-icp'
    with pytest.raises(ConfigError, match='--odometry must be one of bag, kiss-icp'):
        ReplayOptions(odometry='kiss_icp')
    # A fleet feeds each robot the odometry asked for: --odometry is not of one bag only.
    assert ReplayOptions(odometry='kiss-icp', map=True).single_bag() == [('map', '--map')]


def test_single_bag_options_are_named() -> None:
    assert ReplayOptions(radius=2.0, topic='/p', out_dir='o', use_odom=False,
                         max_heading_deg=30.0).single_bag() == []
    opts = ReplayOptions(poses='p', save_db='d', use_odom=False, plots=False)
    assert opts.single_bag() == [('poses', '--poses'), ('save_db', '--save-db')]


def test_for_fleet_drops_the_options_of_one_bag_with_a_line_each() -> None:
    opts = ReplayOptions(poses='p', times='t', load_db='l', save_db='d', plots=False,
                         map=True, radius=2.0, use_odom=False, max_heading_deg=30.0)
    fleet, lines = opts.for_fleet()
    assert fleet == ReplayOptions(radius=2.0, use_odom=False, max_heading_deg=30.0, plots=False)
    flags = ['--poses', '--times', '--load-db', '--save-db', '--map']
    assert [line.split(' (')[0] for line in lines] == [
        f'ignored for a fleet replay: {flag}' for flag in flags]
    assert all(line.endswith(')') and len(line) < 100 for line in lines), lines
    assert ReplayOptions(radius=2.0).for_fleet() == (ReplayOptions(radius=2.0), [])
