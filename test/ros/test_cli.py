"""solid_node's command line before ROS starts: --help, bad parameter files, bad ROS arguments."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from bad_inputs import BAD_FILES, write_bad_file

from solid_ros.core.config import GROUPS, param_specs
from solid_ros.ros.cli import check_parameter_files, scan_arguments, usage
from solid_ros.tools import replay

EXE = Path(sys.executable).parent / 'solid_node'


def test_scan_finds_files_and_remapped_name() -> None:
    args = scan_arguments(['solid_node', '--ros-args', '--params-file', 'a.yaml', '-r',
                           '__node:=loops', '-r', 'other:__ns:=/x', '-r', '__ns:=/robot',
                           '-p', 'x:=1', '--', '--help', '--ros-args', '--params-file', 'b.yaml'])
    assert args.params_files == ['a.yaml', 'b.yaml']
    assert args.fully_qualified_name == '/robot/loops'
    assert args.help  # after '--' it is the program's own argument
    assert not scan_arguments(['solid_node', '--ros-args', '-p', '--help:=1']).help


def test_usage_lists_parameters_topics_and_services() -> None:
    text = usage()
    for spec in param_specs():
        ro = ', read-only' if spec.read_only else ''
        assert (f'{spec.name} ({spec.type.__name__}, default {spec.default!r}, allowed '
                f'{spec.range_text()}{ro})') in text
        assert spec.description.split()[0] in text
    # Grouped, in schema order, after the synopsis of files and remapping.
    heads = [text.index(f'\n  {g}\n') for g in GROUPS.values()]
    assert heads == sorted(heads)
    assert text.index('parameter files') < text.index('remapping') < heads[0]
    for name in ('points', 'odom', '~/loop_candidates', '~/loop_markers', '/diagnostics',
                 '~/save_database', '~/reset'):
        assert name in text


# The in-process main() below returns before rclpy.init(), as the executable does.
rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')
from solid_ros.ros.node import main  # noqa: E402


@pytest.mark.parametrize('flag', ['--help', '-h'])
def test_help_prints_usage_and_does_not_start(flag: str,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['solid_node', flag]) == 0
    out, err = capsys.readouterr()
    assert out.startswith('usage: solid_node') and 'database_save_path' in out and not err


@pytest.mark.parametrize('name', sorted(BAD_FILES))
def test_bad_parameter_file_one_line_exit_2_like_replay(
        tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_bad_file(tmp_path, name)
    assert main(['solid_node', '--ros-args', '--params-file', str(path)]) == 2
    _, err = capsys.readouterr()
    assert err.startswith(f'solid_node: error: {path}: ') and err.count('\n') == 1, err
    # One rule: solid_replay refuses the same file with the same words.
    assert replay.main([str(tmp_path / 'no_bag'), '--params', str(path)]) == 1
    _, rerr = capsys.readouterr()
    assert rerr.replace('solid_replay', 'solid_node') == err


def test_every_file_is_checked_and_missing_value_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = tmp_path / 'good.yaml'
    good.write_text('solid_node:\n  ros__parameters:\n    num_range: 20\n')
    bad = write_bad_file(tmp_path, 'other node only')
    assert main(['solid_node', '--ros-args', '--params-file', str(good), '--params-file',
                 str(bad)]) == 2
    assert str(bad) in capsys.readouterr().err
    assert main(['solid_node', '--ros-args', '--params-file']) == 2
    assert '--params-file needs a value' in capsys.readouterr().err


def test_frames_that_make_a_self_transform_exit_2_with_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def write(name: str, body: str) -> Path:
        path = tmp_path / name
        path.write_text('solid_node:\n  ros__parameters:\n' + body)
        return path

    # odom_frame 'map' beside the default map_frame 'map': map -> map on /tf.
    same = write('same.yaml', "    odom_frame: 'map'\n")
    assert main(['solid_node', '--ros-args', '--params-file', str(same)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'solid_node: error: {same}: map_frame and odom_frame') and (
        'map -> map' in err and 'map_frame: solid_map' in err and err.count('\n') == 1), err
    # Two files: the second sets the frame the first named the map.
    first = write('first.yaml', "    map_frame: 'world'\n")
    second = write('second.yaml', "    odom_frame: 'world'\n")
    assert main(['solid_node', '--ros-args', '--params-file', str(first), '--params-file',
                 str(second)]) == 2
    assert capsys.readouterr().err.startswith(f'solid_node: error: {second}: map_frame')
    # KISS-ICP broadcasts odom_frame -> sensor_frame too.
    kiss = write('kiss.yaml', "    odometry_source: 'kiss_icp'\n    sensor_frame: 'odom'\n")
    assert main(['solid_node', '--ros-args', '--params-file', str(kiss)]) == 2
    assert 'odom_frame and sensor_frame' in capsys.readouterr().err
    # Distinct frames pass the check (checked alone: the node is not started here).
    ok = write('ok.yaml', "    map_frame: 'solid_map'\n    odom_frame: 'map'\n")
    check_parameter_files(scan_arguments(['solid_node', '--ros-args', '--params-file',
                                          str(ok)]))


def test_rcl_errors_are_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['solid_node', '--ros-args', '--log-level', 'nonsense']) == 2
    err = capsys.readouterr().err
    assert err.startswith('solid_node: error: invalid ROS arguments: ') and 'log level' in err
    assert err.count('\n') == 1


def test_executable_help_and_bad_file(tmp_path: Path) -> None:
    if not EXE.is_file():
        pytest.skip(f'{EXE} is not installed')
    out = subprocess.run([str(EXE), '--help'], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.startswith('usage: solid_node'), out.stderr
    bad = write_bad_file(tmp_path, 'binary')
    run = subprocess.run([str(EXE), '--ros-args', '--params-file', str(bad)],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    assert run.stderr == (f'solid_node: error: {bad}: not a parameter file: byte 0x80 at '
                          'offset 128 is not UTF-8 text\n')
