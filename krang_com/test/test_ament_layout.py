"""The package as a ROS user gets it: `colcon build` puts every executable where `ros2 run
krang_com <exe>` looks and every configuration and launch file under share/; each
installed executable comes up from install/ with the installed configuration; package.xml names a
rosdep key for every import; the launch files start what `krang bringup` starts."""

import ast
import dataclasses
import os
import subprocess
import sys
import time
import types
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from conftest import REPO
from krang_cli.node_set import file_parameter, node_set, params_files
from krang_ros.entry import NODE_MODULES

NODES = tuple(sorted(NODE_MODULES))
EXECUTABLES = ('krang',) + NODES
COLCON = Path(sys.executable).parent / 'colcon'

#: Import name -> rosdep key of package.xml, for every third-party module the package imports.
ROSDEP_KEYS = {
    'krang_com_interfaces': 'krang_com_interfaces',  # the repository's interface package
    'rclpy': 'rclpy',
    'action_msgs': 'action_msgs',
    'unique_identifier_msgs': 'unique_identifier_msgs',
    'ament_index_python': 'ament_index_python',
    'builtin_interfaces': 'builtin_interfaces',
    'std_msgs': 'std_msgs',
    'sensor_msgs': 'sensor_msgs',
    'geometry_msgs': 'geometry_msgs',
    'std_srvs': 'std_srvs',
    'diagnostic_msgs': 'diagnostic_msgs',
    'rcl_interfaces': 'rcl_interfaces',
    'rosgraph_msgs': 'rosgraph_msgs',
    'launch': 'launch',
    'launch_ros': 'launch_ros',
    'pinocchio': 'pinocchio',
    'coal': 'coal',  # the collision library pinocchio builds on; its own ROS package
    'numpy': 'python3-numpy',
    'numba': 'python3-numba',
    'scipy': 'python3-scipy',
    'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib',
    'tqdm': 'python3-tqdm',
    'can': 'python3-can',
    'msgpack': 'python3-msgpack',
    'canopen': 'python3-canopen',
    'cantools': 'python3-cantools',
    'control': 'python3-control',
    'mcap': 'python3-mcap',
    'mcap_ros2': 'python3-mcap-ros2-support',
    'tf2_msgs': 'tf2_msgs',
    'visualization_msgs': 'visualization_msgs',
    'foxglove': 'python3-foxglove-sdk',
    'mujoco': 'python3-mujoco',
}
OWN_PACKAGES = {p.name for p in REPO.iterdir() if (p / '__init__.py').exists()}


def package_xml():
    return ET.parse(REPO / 'package.xml').getroot()


def test_package_xml_is_format_3_ament_python():
    root = package_xml()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'krang_com'
    assert root.find('export/build_type').text == 'ament_python'
    assert (REPO / 'resource' / 'krang_com').exists()


def imported_modules():
    """Top-level names of every module the installed packages and launch files import."""
    found = {}
    files = [f for pkg in OWN_PACKAGES for f in (REPO / pkg).rglob('*.py')]
    for path in files + list((REPO / 'launch').glob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split('.')[0], path.relative_to(REPO))
    return found


def test_every_import_has_a_rosdep_key():
    keys = {e.text for e in package_xml().findall('exec_depend')}
    stdlib = set(sys.stdlib_module_names)
    missing = []
    for module, where in sorted(imported_modules().items()):
        if module in stdlib or module in OWN_PACKAGES or module == '__future__':
            continue
        key = ROSDEP_KEYS.get(module)
        if key is None or key not in keys:
            missing.append(f'{module} (imported in {where}; key {key})')
    assert not missing, 'imports without an exec_depend in package.xml: ' + ', '.join(missing)


def fake_launch_modules():
    """Stand-ins for launch and launch_ros (not installable here) that record what a launch file
    builds, so the launch files can be compared with `krang bringup`."""
    modules = {
        name: types.ModuleType(name)
        for name in (
            'launch',
            'launch.actions',
            'launch.substitutions',
            'launch_ros',
            'launch_ros.actions',
            'launch_ros.parameter_descriptions',
        )
    }

    class LaunchDescription(list):
        pass

    class Record(dict):
        def __init__(self, *args, **kwargs):
            super().__init__(kwargs, args=args)

    class LaunchConfiguration(str):
        pass

    modules['launch'].LaunchDescription = LaunchDescription
    modules['launch.actions'].DeclareLaunchArgument = type('DeclareLaunchArgument', (Record,), {})
    modules['launch.substitutions'].LaunchConfiguration = LaunchConfiguration
    modules['launch_ros.actions'].Node = type('Node', (Record,), {})
    modules['launch_ros.parameter_descriptions'].ParameterValue = type(
        'ParameterValue', (Record,), {}
    )
    return modules


def launch_actions(launch_file, monkeypatch):
    """What `generate_launch_description()` of `launch_file` builds, split into the declared
    arguments (name -> DeclareLaunchArgument) and the nodes."""
    for name, module in fake_launch_modules().items():
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.delitem(sys.modules, 'krang_ros.launch_set', raising=False)
    namespace = {'__file__': str(REPO / 'launch' / launch_file)}
    exec(compile((REPO / 'launch' / launch_file).read_text(), launch_file, 'exec'), namespace)
    actions = namespace['generate_launch_description']()
    declared = {a['args'][0]: a for a in actions if type(a).__name__ == 'DeclareLaunchArgument'}
    return declared, [a for a in actions if type(a).__name__ == 'Node']


@pytest.mark.parametrize('launch_file, sim', [('robot.launch.py', False), ('sim.launch.py', True)])
def test_launch_files_start_what_bringup_starts(launch_file, sim, monkeypatch):
    declared, nodes = launch_actions(launch_file, monkeypatch)
    files = [
        (a['executable'], tuple(p for p in a['parameters'] if isinstance(p, str))) for a in nodes
    ]
    assert all(a['package'] == 'krang_com' for a in nodes)
    assert files == [(s.executable, s.params_files) for s in node_set(sim)]
    # the parameter files are the ones krang bringup passes, and they exist
    assert all(p == params_files(sim) for _, p in files)
    assert all(Path(f).is_file() for f in params_files(sim))
    expected = {'can_bridge', 'adrc_controller', 'pose_server', 'com_estimator', 'state_publisher'}
    assert {e for e, _ in files} == expected | ({'sim_krang'} if sim else set())
    assert bool(declared) == sim  # the robot's launch file has no simulated robot to choose


def test_sim_launch_arguments_choose_the_plant(monkeypatch):
    """`ros2 launch krang_com sim.launch.py plant:=mujoco plant_model:=F`: the arguments default
    to what the parameter files give, reach sim_krang only, after its files (so they win), and
    are sim_krang's own parameters (`krang bringup --sim --plant --plant-model`)."""
    from krang_sim.node import SimNodeParams

    declared, nodes = launch_actions('sim.launch.py', monkeypatch)
    assert set(declared) == {'plant', 'plant_model'}
    assert declared['plant']['default_value'] == file_parameter('sim_krang', 'plant', sim=True)
    assert declared['plant_model']['default_value'] == ''
    assert all(d['description'] for d in declared.values())
    assert set(declared) <= {f.name for f in dataclasses.fields(SimNodeParams)}
    for node in nodes:
        chosen = [p for p in node['parameters'] if isinstance(p, dict)]
        if node['executable'] != 'sim_krang':
            assert not chosen
            continue
        assert isinstance(node['parameters'][-1], dict)  # last: wins over the files
        values = chosen[0]
        assert set(values) == set(declared)
        for name, value in values.items():  # a string even when empty (no YAML guess)
            assert value['args'] == (name,) and value['value_type'] is str


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory):
    if not COLCON.exists():
        pytest.skip('colcon is not installed in this environment (pip: colcon-common-extensions)')
    work = tmp_path_factory.mktemp('colcon')
    result = subprocess.run(
        [
            str(COLCON),
            'build',
            '--base-paths',
            str(REPO),
            '--build-base',
            str(work / 'build'),
            '--install-base',
            str(work / 'install'),
            '--event-handlers',
            'console_direct-',
        ],
        cwd=work,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    return work / 'install' / 'krang_com'


def test_colcon_install_layout(colcon_install):
    prefix = colcon_install
    for exe in EXECUTABLES:
        assert (prefix / 'lib' / 'krang_com' / exe).is_file(), exe
    assert (
        prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'krang_com'
    ).exists()
    share = prefix / 'share' / 'krang_com'
    assert (share / 'package.xml').exists()
    for source in sorted((REPO / 'config').iterdir()):
        assert (share / 'config' / source.name).is_file(), f'config/{source.name} is not installed'
    for source in sorted((REPO / 'launch').glob('*.launch.py')):
        assert (share / 'launch' / source.name).is_file(), f'launch/{source.name} is not installed'


def installed_env(prefix):
    """The environment `source install/setup.bash` gives: the installed packages first, the
    installed share/ found through AMENT_PREFIX_PATH, and the source tree nowhere on the path."""
    site = next((prefix / 'lib').glob('python3*/site-packages'))
    env = dict(os.environ)
    env['PYTHONPATH'] = str(site)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(
        [str(prefix)] + [p for p in env.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    )
    return env


@pytest.mark.ros
def test_installed_executables_come_up(colcon_install, tmp_path):
    """Every installed node starts from install/ with the installed configuration (the simulated
    robot's, as no SocketCAN is here) and joins the ROS graph; `krang --help` answers."""
    import rclpy
    from rclpy.node import Node

    prefix = colcon_install
    env = installed_env(prefix)
    lib, share = prefix / 'lib' / 'krang_com', prefix / 'share' / 'krang_com' / 'config'
    out = subprocess.run(
        [str(lib / 'krang'), '--help'],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0 and 'demo' in out.stdout, out.stderr[-2000:]
    probe = (
        'import krang_model.config as c, krang_cli; '
        'print(c.config_dir()); print(krang_cli.__file__)'
    )
    where = subprocess.run(
        [sys.executable, '-c', probe],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout.split()
    assert Path(where[0]).resolve() == share.resolve()
    assert Path(where[1]).resolve().is_relative_to(prefix.resolve())

    from krang_sim.session_config import session_devices_file

    devices = session_devices_file(tmp_path)
    files = [share / n for n in ('controller.yaml', 'krang_params.yaml', 'sim_params.yaml')]
    extra = {
        'can_bridge': {'devices_file': devices},
        'sim_krang': {'devices_file': devices},
        'mcap_recorder': {'output': tmp_path / 'x.mcap'},
        'com_estimator': {'output': tmp_path / 'beta.yaml'},
    }
    procs = {}
    rclpy.init()
    probe_node = Node('layout_probe')
    try:
        for exe in NODES:
            cmd = [str(lib / exe), '--ros-args'] + [
                a for f in files for a in ('--params-file', str(f))
            ]
            for key, value in extra.get(exe, {}).items():
                cmd += ['-p', f'{key}:={value}']
            log = open(tmp_path / f'{exe}.log', 'w')
            procs[exe] = (
                subprocess.Popen(cmd, env=env, cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT),
                log,
            )
        deadline = time.monotonic() + 60.0
        seen = set()
        while time.monotonic() < deadline and seen != set(NODES):
            rclpy.spin_once(probe_node, timeout_sec=0.2)
            seen = set(probe_node.get_node_names()) & set(NODES)
            dead = {e: p.poll() for e, (p, _) in procs.items() if p.poll() is not None}
            assert not dead, f'installed nodes exited: {dead}: ' + ' | '.join(
                (tmp_path / f'{e}.log').read_text()[-800:] for e in dead
            )
        assert seen == set(NODES), f'not in the graph after 60 s: {set(NODES) - seen}'
    finally:
        probe_node.destroy_node()
        rclpy.shutdown()
        for proc, log in procs.values():
            proc.send_signal(2)
        for proc, log in procs.values():
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
            log.close()
