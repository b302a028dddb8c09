"""The launch file and the RViz config: structure, executable, presets, topics, installation.

There is no ``ros2 launch`` here and the launch / launch_yaml packages are not on PyPI for
Jazzy, so the launch file is checked as data and expanded by test/launch_files.py the way
launch_ros would; the expanded command line then goes through solid_node's own argument and
parameter-file checks (test/test_colcon.py also starts the installed node with it).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from launch_files import (
    LAUNCH_FILE,
    NODE_SOURCE,
    PACKAGE,
    RVIZ_FILE,
    enabled,
    launch_entries,
    node_command,
    node_topics,
    publisher_qos,
    resolve_args,
    rviz_displays,
    setup_kwargs,
    share_from_setup,
)
from project_paths import CONFIG_DIR

from solid_ros.core.config import NodeConfig, SolidConfig, load_parameter_file
from solid_ros.ros.cli import NODE_NAME, check_parameter_files, scan_arguments

PRESETS = sorted(p.stem for p in CONFIG_DIR.glob('*.yaml')
                 if 'ros__parameters:' in p.read_text(encoding='utf-8'))
# What launch and launch_ros accept in the entries this file uses (frontend attribute names).
ARG_KEYS = {'name', 'default', 'description', 'choice'}
NODE_KEYS = {'pkg', 'exec', 'name', 'namespace', 'args', 'ros_args', 'output', 'param', 'remap',
             'if', 'unless', 'respawn', 'respawn_delay', 'launch-prefix', 'env'}
EXAMPLE = {'sensor': 'avia', 'points': '/livox/lidar', 'odom': '/Odometry'}


@pytest.fixture(scope='module')
def share(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return share_from_setup(tmp_path_factory.mktemp('install'))


def _entries(kind: str) -> list[dict[str, Any]]:
    return [e[kind] for e in launch_entries() if kind in e]


def _node(exec_name: str) -> dict[str, Any]:
    (node,) = [n for n in _entries('node') if n['exec'] == exec_name]
    return node


def test_launch_file_is_yaml_launch_format() -> None:
    entries = launch_entries()
    assert all(isinstance(e, dict) and len(e) == 1 for e in entries), entries
    assert {k for e in entries for k in e} == {'arg', 'node'}
    names = [a['name'] for a in _entries('arg')]
    assert len(names) == len(set(names))
    for arg in _entries('arg'):
        assert set(arg) <= ARG_KEYS and {'name', 'default', 'description'} <= set(arg), arg
        assert re.fullmatch(r'[a-z_]+', arg['name']) and isinstance(arg['default'], str)
        if 'choice' in arg:
            values = [c['value'] for c in arg['choice']]
            assert all(set(c) == {'value'} and isinstance(c['value'], str)
                       for c in arg['choice']), arg
            assert arg['default'] in values, arg
    for node in _entries('node'):
        assert set(node) <= NODE_KEYS, node
        assert all(set(r) == {'from', 'to'} for r in node.get('remap', []))
        assert all(set(p) in ({'from'}, {'name', 'value'}) for p in node.get('param', []))
    # Every $(var X) names an argument declared before it; only the two substitutions used.
    text = LAUNCH_FILE.read_text(encoding='utf-8')
    kinds = set(re.findall(r'\$\(([a-z-]+)', text))
    assert kinds == {'var', 'find-pkg-share'}
    assert set(re.findall(r'\$\(find-pkg-share ([^)]*)\)', text)) == {PACKAGE}
    assert set(re.findall(r'\$\(var ([^)]*)\)', text)) <= set(names)


def test_node_is_the_installed_solid_node() -> None:
    kwargs = setup_kwargs()
    node = _node('solid_node')
    assert node['pkg'] == kwargs['name'] == PACKAGE
    scripts = dict(s.replace(' ', '').split('=') for s in
                   kwargs['entry_points']['console_scripts'])
    assert scripts[node['exec']] == 'solid_ros.ros.node:main'
    tree = ast.parse(NODE_SOURCE.read_text(encoding='utf-8'))
    assert any(isinstance(d, ast.FunctionDef) and d.name == 'main' for d in tree.body)


def test_sensor_choices_are_the_shipped_presets(share: Path) -> None:
    (sensor,) = [a for a in _entries('arg') if a['name'] == 'sensor']
    assert sorted(c['value'] for c in sensor['choice']) == PRESETS
    assert {'avia', 'hdl64', 'spinning_fov90', 'solid'} <= set(PRESETS)
    entries = launch_entries()
    for name in PRESETS:
        values = resolve_args(entries, {'sensor': name}, share)
        path = Path(values['params_file'])
        assert path == share / 'config' / f'{name}.yaml' and path.resolve().is_file()
    with pytest.raises(ValueError, match='not one of'):
        resolve_args(entries, {'sensor': 'velodyne'}, share)


def test_remaps_target_the_node_subscriptions() -> None:
    topics = node_topics()
    assert topics['sub'] == {'points': 'PointCloud2', 'odom': 'Odometry'}
    for exec_name in ('solid_node', 'rviz2'):
        remaps = {r['from']: r['to'] for r in _node(exec_name)['remap']}
        assert remaps == {name: f'$(var {name})' for name in topics['sub']}, exec_name


@pytest.mark.parametrize('given', [EXAMPLE, {}, {'sensor': 'hdl64', 'use_odom': 'false'},
                                   *({'sensor': s} for s in PRESETS)],
                         ids=lambda g: ' '.join(f'{k}:={v}' for k, v in g.items()) or 'defaults')
def test_expanded_node_command_is_accepted_by_solid_node(
        given: dict[str, str], share: Path, tmp_path: Path) -> None:
    entries = launch_entries()
    values = resolve_args(entries, given, share)
    argv = node_command(_node('solid_node'), values, share, tmp_path)
    args = scan_arguments(argv)
    assert args.fully_qualified_name == f'/{NODE_NAME}'
    check_parameter_files(args)  # the node's own refusal rule: raises ConfigError
    preset, *extra = args.params_files
    assert Path(preset).resolve() == CONFIG_DIR / f'{values["sensor"]}.yaml'
    given_params: dict[str, object] = {}
    for path in extra:
        given_params.update(load_parameter_file(path, args.fully_qualified_name))
    assert given_params == {'use_odom': values['use_odom'] == 'true',
                            'odometry_source': values['odometry_source']}
    want = {'points': given.get('points', '/points'), 'odom': given.get('odom', '/odom')}
    assert [f'{k}:={v}' for k, v in want.items()] == [
        argv[i + 1] for i, a in enumerate(argv) if a == '-r']
    # Every parameter of the expanded files is one the node declares.
    names = {s.name for s in (*SolidConfig.specs(), *NodeConfig.specs())}
    for path in args.params_files:
        assert set(load_parameter_file(path, args.fully_qualified_name)) <= names


def test_rviz_starts_only_when_asked(share: Path, tmp_path: Path) -> None:
    entries = launch_entries()
    (rviz,) = [e for e in entries if e.get('node', {}).get('exec') == 'rviz2']
    assert rviz['node']['pkg'] == 'rviz2'
    assert not enabled(rviz, resolve_args(entries, EXAMPLE, share), share)
    values = resolve_args(entries, {**EXAMPLE, 'rviz': 'true', 'rviz_frame': 'camera_init'},
                          share)
    assert enabled(rviz, values, share)
    assert all(enabled(e, values, share) for e in entries if 'node' in e)
    argv = node_command(rviz['node'], values, share, tmp_path)
    config = Path(argv[argv.index('-d') + 1])
    assert config == share / 'rviz' / 'solid.rviz' and config.resolve() == RVIZ_FILE
    assert argv[argv.index('-f') + 1] == 'camera_init'
    assert '-r' in argv and 'points:=/livox/lidar' in argv and 'odom:=/Odometry' in argv


def test_rviz_config_shows_cloud_odometry_and_latched_loop_markers() -> None:
    doc = yaml.safe_load(RVIZ_FILE.read_text(encoding='utf-8'))
    assert {'Panels', 'Visualization Manager', 'Window Geometry'} <= set(doc)
    manager = doc['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == 'map'
    displays = {d['Name']: d for d in rviz_displays()}
    assert all(d['Class'].startswith(('rviz_default_plugins/', 'rviz_common/'))
               for d in displays.values())
    topics = node_topics()
    markers = displays['Loops']
    private = {name: kind for name, kind in topics['pub'].items() if name.startswith('~/')}
    assert private['~/loop_markers'] == 'MarkerArray'
    assert markers['Topic']['Value'] == f'/{NODE_NAME}/loop_markers'
    # The node latches its markers: a late RViz sees them only as a transient-local reader
    # (and a transient-local reader gets nothing from a volatile writer).
    assert markers['Topic']['Durability Policy'] == 'Transient Local'
    assert markers['Topic']['Reliability Policy'] == 'Reliable'
    qos = publisher_qos('~/loop_markers')
    assert 'DurabilityPolicy.TRANSIENT_LOCAL' in qos and 'ReliabilityPolicy.RELIABLE' in qos
    # Cloud and odometry as the node subscribes to them (remapped together by the launch).
    cloud = displays['LiDAR points']['Topic']
    odom = displays['Odometry']['Topic']
    assert (cloud['Value'], odom['Value']) == ('/points', '/odom')
    assert {topics['sub'][t['Value'][1:]] for t in (cloud, odom)} == {'PointCloud2', 'Odometry'}
    assert cloud['Reliability Policy'] == 'Best Effort'  # drivers publish best effort
    assert all(d['Enabled'] for d in displays.values())
    # The back end's corrected path and map: latched by the node, read as latched.
    for name, topic in (('Corrected path', '~/path'), ('Corrected map', '~/map')):
        shown = displays[name]['Topic']
        assert shown['Value'] == f'/{NODE_NAME}/{topic[2:]}'
        assert shown['Durability Policy'] == 'Transient Local'
    assert displays['Corrected odometry']['Topic']['Value'] == f'/{NODE_NAME}/odometry'


def test_setup_installs_launch_and_rviz_under_share() -> None:
    files = {dest: sorted(names) for dest, names in setup_kwargs()['data_files']}
    assert files['share/solid_ros/launch'] == ['config/launch/solid.launch.yaml']
    assert files['share/solid_ros/rviz'] == ['config/rviz/solid.rviz']
    # Only parameter files among the presets (test_colcon starts the node with each).
    assert sorted(Path(n).stem for n in files['share/solid_ros/config']
                  if n.endswith('.yaml')) == PRESETS
