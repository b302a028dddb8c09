"""solid_node's command line before ROS starts: --help, bad parameter files, bad ROS arguments."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from bad_inputs import BAD_FILES, write_bad_file

from solid_ros.core.config import param_specs
from solid_ros.ros.cli import scan_arguments, usage
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
        assert f'{spec.name} ({spec.type.__name__}, default' in text
    for name in ('points', 'odom', '~/loop_candidates', '~/loop_markers', '/diagnostics',
                 '~/save_database', '~/reset'):
        assert name in text


# The in-process main() below returns before rclpy.init(), as the executable does.
rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not installed')
from solid_ros.ros.node import main  # noqa: E402


def test_help_prints_usage_and_does_not_start(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['solid_node', '--help']) == 0
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
