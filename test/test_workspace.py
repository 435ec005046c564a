"""The workspace itself: packaging a stock Jazzy install can build, bootstrap, CI, configs."""

import ast
import re
import subprocess
import xml.etree.ElementTree as ET

import pytest
import yaml
from rosharness import INSTALL, ROOT

PACKAGES = ('stepper_drivers_msgs', 'stepper_drivers', 'stepper_sim')
# ros_interface.md: the executables every ROS install must find with `ros2 run`
EXECUTABLES = {
    'stepper_drivers': ('xplus_mt_node', 'xmind_k_node', 'vector_step_node', 'rd4_node'),
    'stepper_sim': ('xplus_mt_sim', 'xmind_k_sim', 'vector_step_sim', 'rd4_sim'),
}
# ROS packages a Python import may name, and the package.xml key that provides them
ROS_IMPORTS = {'rclpy', 'std_msgs', 'std_srvs', 'sensor_msgs', 'diagnostic_msgs', 'rcl_interfaces',
               'action_msgs', 'stepper_drivers_msgs', 'ament_index_python', 'launch', 'launch_ros'}


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
    out = subprocess.run(['bash', str(ROOT / 'scripts' / 'bootstrap.sh')], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stderr.strip().splitlines()[-1] == '[bootstrap] ready'
    assert 'colcon build' not in out.stderr and 'installing' not in out.stderr, out.stderr
