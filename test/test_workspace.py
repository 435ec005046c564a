"""The workspace itself: packaging a stock Jazzy install can build, bootstrap, CI, configs."""

import ast
import os
import pathlib
import re
import subprocess
import sys
import sysconfig
import xml.etree.ElementTree as ET

import pytest
from rosharness import INSTALL, ROOT
import yaml

PACKAGES = ('stepper_drivers_msgs', 'stepper_drivers', 'stepper_sim')
# ros_interface.md: the executables every ROS install must find with `ros2 run`
EXECUTABLES = {
    'stepper_drivers': ('xplus_mt_node', 'xmind_k_node', 'vector_step_node', 'rd4_node'),
    'stepper_sim': ('xplus_mt_sim', 'xmind_k_sim', 'vector_step_sim', 'rd4_sim'),
}
# ROS packages a Python import may name, and the package.xml key that provides them
ROS_IMPORTS = {'rclpy', 'std_msgs', 'std_srvs', 'sensor_msgs', 'diagnostic_msgs', 'rcl_interfaces',
               'action_msgs', 'stepper_drivers_msgs', 'ament_index_python', 'launch', 'launch_ros',
               'control_msgs', 'trajectory_msgs'}


def package_xml(pkg):
    return ET.parse(ROOT / 'src' / pkg / 'package.xml').getroot()


@pytest.mark.parametrize('pkg', PACKAGES)
def test_package_xml_is_format_3_and_named_as_its_folder(pkg):
    root = package_xml(pkg)
    assert root.get('format') == '3'
    assert root.findtext('name') == pkg
    build_type = root.find('export/build_type').text
    assert build_type == ('ament_cmake' if pkg.endswith('_msgs') else 'ament_python')


@pytest.mark.parametrize('pkg', ('stepper_drivers', 'stepper_sim'))
def test_every_ros_package_imported_is_declared(pkg):
    declared = {e.text for e in package_xml(pkg) if e.tag.endswith('depend')}
    imported = set()
    for path in (ROOT / 'src' / pkg).rglob('*.py'):
        if '/test/' in str(path):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and node.module
                     and node.level == 0 else [])
            imported |= {n.split('.')[0] for n in names} & ROS_IMPORTS
    missing = imported - declared
    assert not missing, f'{pkg}/package.xml lacks <exec_depend> for {sorted(missing)}'


@pytest.mark.parametrize('pkg, exe', [(p, e) for p, exes in EXECUTABLES.items() for e in exes])
def test_executables_are_where_ros2_run_looks(pkg, exe):
    path = INSTALL / pkg / 'lib' / pkg / exe
    assert path.exists() and path.stat().st_mode & 0o111, path
    assert (INSTALL / pkg / 'share' / 'ament_index' / 'resource_index' / 'packages' / pkg).exists()


@pytest.mark.parametrize('path', sorted((ROOT / 'config').glob('*.yaml')), ids=lambda p: p.name)
def test_params_files_are_keyed_by_their_node_name(path):
    data = yaml.safe_load(path.read_text())
    (node_name,) = data.keys()
    assert 'ros__parameters' in data[node_name]
    exe = node_name if node_name.endswith(('_node', '_sim')) else None
    assert exe, f'{path.name}: top key {node_name!r} is not a node name'
    pkg = 'stepper_sim' if exe.endswith('_sim') else 'stepper_drivers'
    assert (INSTALL / pkg / 'lib' / pkg / exe).exists(), f'{path.name}: no executable {exe}'
    params = data[node_name]['ros__parameters']
    for drive in params.get('drives', []):
        assert f'drives.{drive}' in params, f'{path.name}: no drives.{drive} block'


def test_ci_runs_exactly_the_readme_test_command():
    readme = (ROOT / 'README.md').read_text()
    block = re.search(r'## Quick start\s+```bash\n(.*?)```', readme, re.S).group(1)
    test_cmd = next(line.split('#')[0].strip() for line in block.splitlines() if 'test' in line)
    ci = (ROOT / '.ci' / 'run').read_text()
    assert any(line.strip() == test_cmd for line in ci.splitlines()), (test_cmd, ci)


def test_every_script_keeps_dds_discovery_on_this_machine():
    scripts = [*(ROOT / 'scripts').glob('*.sh'), ROOT / '.ci' / 'run',
               ROOT / 'test' / 'conftest.py']
    for path in scripts:
        assert 'ROS_AUTOMATIC_DISCOVERY_RANGE' in path.read_text(), path
    for path in (ROOT / 'scripts').glob('*.py'):
        text = path.read_text()
        if 'rclpy' in text or 'RosClient' in text:
            assert 'ROS_AUTOMATIC_DISCOVERY_RANGE' in text, path


def test_a_second_bootstrap_has_nothing_to_do():
    """Also after Python wrote its bytecode next to the sources (no PYTHONDONTWRITEBYTECODE: the
    symlinked packages' __pycache__ lands in src/, and a new one moves its directory's time)."""
    os.utime(ROOT / 'src' / 'stepper_drivers' / 'stepper_drivers' / 'cli')
    out = subprocess.run(['bash', str(ROOT / 'scripts' / 'bootstrap.sh')], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stderr.strip().splitlines()[-1] == '[bootstrap] ready'
    assert 'colcon build' not in out.stderr and 'installing' not in out.stderr, out.stderr


# What /opt/ros/jazzy/setup.bash does, pointed at this workspace's pip ROS (.venv): so the
# bootstrap's system-ROS branch runs here although this machine has no apt ROS.
FAKE_SYSTEM_ROS_SETUP = """\
_v={venv}
export ROS_DISTRO=jazzy ROS_VERSION=2 ROS_PYTHON_VERSION=3
export AMENT_PREFIX_PATH=$_v${{AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}}
export CMAKE_PREFIX_PATH=$_v${{CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}}
export PYTHONPATH={site}${{PYTHONPATH:+:$PYTHONPATH}}
_ld=$_v/lib
for _d in {site}/ros_*.libs; do _ld=$_ld:$_d; done
export LD_LIBRARY_PATH=$_ld${{LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}}
export PATH={bin}:$PATH
unset _v _ld _d
"""


def test_bootstrap_takes_the_system_ros_when_there_is_one(tmp_path):
    system = pathlib.Path('/opt/ros/jazzy')
    if not (system / 'setup.bash').exists():
        # the pip ROS as a system install (apt's colcon lives outside the workspace's venv)
        venv = ROOT / '.venv'
        system = tmp_path / 'ros'
        (system / 'bin').mkdir(parents=True)
        (system / 'bin' / 'colcon').symlink_to(venv / 'bin' / 'colcon')
        site = sysconfig.get_paths(vars={'base': str(venv), 'platbase': str(venv)})['purelib']
        (system / 'setup.bash').write_text(FAKE_SYSTEM_ROS_SETUP.format(
            venv=venv, site=site, bin=system / 'bin'))
    ws = tmp_path / 'ws'
    files = subprocess.run(['git', 'ls-files', '-z'], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split('\0')
    for name in filter(None, files):
        if (ROOT / name).is_file():
            (ws / name).parent.mkdir(parents=True, exist_ok=True)
            (ws / name).write_bytes((ROOT / name).read_bytes())
    env = {k: v for k, v in os.environ.items() if k not in (
        'VIRTUAL_ENV', 'AMENT_PREFIX_PATH', 'CMAKE_PREFIX_PATH', 'PYTHONPATH', 'LD_LIBRARY_PATH',
        'COLCON_PREFIX_PATH')}
    env['STEPPER_SYSTEM_ROS'] = str(system)
    env['PATH'] = os.pathsep.join(p for p in env['PATH'].split(os.pathsep)
                                  if not p.startswith(str(ROOT)))
    out = subprocess.run(['bash', str(ws / 'scripts' / 'bootstrap.sh')], capture_output=True,
                         text=True, timeout=900, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    assert f'using the system ROS in {system}' in out.stderr
    assert 'PyPI wheels' not in out.stderr and 'colcon build' in out.stderr
    assert 'include-system-site-packages = true' in (ws / '.venv' / 'pyvenv.cfg').read_text()
    node = ws / 'install' / 'stepper_drivers' / 'lib' / 'stepper_drivers' / 'xplus_mt_node'
    # the executables run on the venv's python (pymodbus & co.), not on colcon's own
    assert node.read_text().splitlines()[0] == f'#!{ws}/.venv/bin/python'
    # the node starts in that environment: rclpy, the built messages, pymodbus, parameters
    run = subprocess.run(['bash', '-c', f'source {ws}/scripts/env.sh && exec {node} --ros-args '
                          f'--params-file {ws}/config/xplus_mt.yaml -p no_such_parameter:=1'],
                         capture_output=True, text=True, timeout=60, env=env)
    assert run.returncode == 2, run.stdout + run.stderr
    assert 'no_such_parameter' in run.stdout + run.stderr
    again = subprocess.run(['bash', str(ws / 'scripts' / 'bootstrap.sh')], capture_output=True,
                           text=True, timeout=600, env=env)
    assert again.returncode == 0 and 'colcon build' not in again.stderr, again.stderr


def test_the_fast_dds_profile_lets_services_wait_for_a_new_client():
    # rmw_fastrtps applies the publisher profile named "service" to every response writer and
    # waits max_blocking_time for the client's reader (default 100 ms: answers lost under load)
    ns = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ET.parse(ROOT / 'config' / 'fastdds_fast_discovery.xml').getroot()
    (service,) = [p for p in root.findall('p:publisher', ns) if p.get('profile_name') == 'service']
    wait = service.find('p:qos/p:reliability/p:max_blocking_time', ns)
    seconds = int(wait.findtext('p:sec', '0', ns)) + int(wait.findtext('p:nanosec', '0', ns)) / 1e9
    assert seconds >= 1.0
    (participant,) = root.findall('p:participant', ns)
    assert participant.get('is_default_profile') == 'true'
    # and Fast DDS itself accepts the file (it prints XMLPARSER errors and goes on without it)
    code = ('import rclpy; from std_srvs.srv import Trigger; rclpy.init(); '
            'n = rclpy.create_node("profile_check"); '
            'n.create_service(Trigger, "profile_check", lambda q, r: r); print("created")')
    env = dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=str(ROOT / 'config' /
                                                              'fastdds_fast_discovery.xml'))
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=60, env=env)
    assert out.returncode == 0 and 'created' in out.stdout, out.stderr
    assert 'XMLPARSER' not in out.stdout + out.stderr, out.stdout + out.stderr
