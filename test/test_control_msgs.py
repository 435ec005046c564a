"""control_msgs: the released FollowJointTrajectory, or the bootstrap's minimal copy of it.

The nodes serve control_msgs/action/FollowJointTrajectory. A ROS install has the released package
(ros-jazzy-control-msgs); the pip wheels have none, so scripts/bootstrap.sh builds the one of
scripts/control_msgs_min into .venv/control_msgs, only when the environment imports no other.
"""

import ctypes
import json
import os
import pathlib
import shutil
import subprocess
import sys

from rosharness import ROOT

# control_msgs 5.8.0 (jazzy), as ros-jazzy-control-msgs has it: a client built on the released
# package and a node on the minimal one (or the other way round) connect only when these agree.
RELEASED_HASH = 'RIHS01_738ebcb7a2d7cfa42f9f1001cc99ce3a4383d1cfe508015d9be8485e4b1c66f6'
PACKAGES = ['stepper_drivers', 'stepper_drivers_msgs', 'stepper_sim']
MINIMAL = ROOT / '.venv' / 'control_msgs'


class _TypeHash(ctypes.Structure):  # rosidl_runtime_c/type_hash.h: rosidl_type_hash_t
    _fields_ = [('version', ctypes.c_uint8), ('value', ctypes.c_uint8 * 32)]


class _ActionTypeSupport(ctypes.Structure):
    # rosidl_runtime_c/action_type_support_struct.h: five type support pointers (goal, result,
    # cancel services; feedback, status messages), then get_type_hash_func
    _fields_ = [(f'_{i}', ctypes.c_void_p) for i in range(5)] + [
        ('get_type_hash_func', ctypes.CFUNCTYPE(ctypes.POINTER(_TypeHash), ctypes.c_void_p))]


def compiled_type_hash(action_type) -> str:
    """The hash in the C type support that rmw announces for the action (what peers compare)."""
    from rclpy.type_support import check_for_type_support
    check_for_type_support(action_type)
    capsule = action_type._TYPE_SUPPORT
    name_of = ctypes.pythonapi.PyCapsule_GetName
    name_of.restype, name_of.argtypes = ctypes.c_char_p, [ctypes.py_object]
    pointer_of = ctypes.pythonapi.PyCapsule_GetPointer
    pointer_of.restype, pointer_of.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    address = pointer_of(capsule, name_of(capsule))
    digest = _ActionTypeSupport.from_address(address).get_type_hash_func(address).contents
    return f'RIHS{digest.version:02d}_{bytes(digest.value).hex()}'


def test_follow_joint_trajectory_has_the_released_type_hash():
    from control_msgs.action import FollowJointTrajectory
    assert compiled_type_hash(FollowJointTrajectory) == RELEASED_HASH
    # and the type description file rosidl_generator_type_description installed with it
    from ament_index_python.packages import get_package_share_directory
    described = json.loads((pathlib.Path(get_package_share_directory('control_msgs')) / 'action'
                            / 'FollowJointTrajectory.json').read_text())
    hashes = {h['type_name']: h['hash_string'] for h in described['type_hashes']}
    assert hashes['control_msgs/action/FollowJointTrajectory'] == RELEASED_HASH


def test_the_minimal_package_is_the_one_in_use_only_without_another():
    import control_msgs
    system = os.environ.get('STEPPER_SYSTEM_ROS', '/opt/ros/jazzy')
    has_system_ros = (pathlib.Path(system) / 'setup.bash').exists() \
        and os.environ.get('STEPPER_FORCE_PIP_ROS') != '1'
    minimal = pathlib.Path(control_msgs.__file__).resolve().is_relative_to(MINIMAL.resolve())
    if not has_system_ros:
        # the pip wheels have no control_msgs: the bootstrap built the minimal one
        assert minimal, control_msgs.__file__
    elif not minimal:
        assert not MINIMAL.exists(), 'a control_msgs of the system ROS, and the minimal one too'


def colcon(*args: str, cwd: pathlib.Path = ROOT) -> subprocess.CompletedProcess:
    code = ('import sys; from colcon_core.command import main; sys.argv[0] = "colcon"; '
            'sys.exit(main())')
    return subprocess.run([sys.executable, '-c', code, '--log-base', os.devnull, *args], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def test_the_workspace_build_does_not_find_the_minimal_package(tmp_path):
    out = colcon('list', '--names-only')
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == PACKAGES
    # the bootstrap's copy of it, which has no marker of its own, is under one
    staged = ROOT / 'build' / 'control_msgs_min'
    if staged.exists():
        out = colcon('list', '--names-only', '--base-paths', str(staged))
        assert out.returncode == 0 and out.stdout.split() == [], out.stdout + out.stderr
    # the sources are a package that only their COLCON_IGNORE keeps out of the crawl
    copy = tmp_path / 'scripts' / 'control_msgs_min'
    shutil.copytree(ROOT / 'scripts' / 'control_msgs_min', copy)
    out = colcon('list', '--names-only', '--base-paths', str(tmp_path))
    assert out.stdout.split() == [], out.stdout + out.stderr
    (copy / 'COLCON_IGNORE').unlink()
    out = colcon('list', '--names-only', '--base-paths', str(tmp_path))
    assert out.stdout.split() == ['control_msgs'], out.stdout + out.stderr


def test_the_minimal_package_has_exactly_the_three_interfaces():
    src = ROOT / 'scripts' / 'control_msgs_min'
    files = sorted(str(p.relative_to(src)) for p in src.rglob('*') if p.is_file())
    assert files == ['CMakeLists.txt', 'COLCON_IGNORE', 'action/FollowJointTrajectory.action',
                     'msg/JointComponentTolerance.msg', 'msg/JointTolerance.msg', 'package.xml']


def clean_env(**extra: str) -> dict:
    """This process's environment without the workspace's (env.sh) paths."""
    env = {k: v for k, v in os.environ.items() if k not in (
        'VIRTUAL_ENV', 'AMENT_PREFIX_PATH', 'CMAKE_PREFIX_PATH', 'PYTHONPATH', 'LD_LIBRARY_PATH',
        'COLCON_PREFIX_PATH', 'STEPPER_SYSTEM_ROS', 'STEPPER_FORCE_PIP_ROS')}
    env['PATH'] = os.pathsep.join(p for p in env['PATH'].split(os.pathsep)
                                  if not p.startswith(str(ROOT)))
    return {**env, **extra}


def fake_system_ros(root: pathlib.Path, with_control_msgs: bool) -> pathlib.Path:
    """A ROS install (a setup.bash) that has a control_msgs, or one that has none."""
    site = root / 'lib' / 'python3.11' / 'site-packages'
    site.mkdir(parents=True)
    if with_control_msgs:
        (site / 'control_msgs').mkdir()
        (site / 'control_msgs' / '__init__.py').write_text('RELEASED = True\n')
        index = root / 'share' / 'ament_index' / 'resource_index' / 'packages'
        index.mkdir(parents=True)
        (index / 'control_msgs').write_text('')
    (root / 'setup.bash').write_text(
        f'export ROS_DISTRO=jazzy\n'
        f'export AMENT_PREFIX_PATH={root}${{AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}}\n'
        f'export PYTHONPATH={site}${{PYTHONPATH:+:$PYTHONPATH}}\n')
    return root


def workspace_copy(ws: pathlib.Path) -> pathlib.Path:
    """The bootstrap, env.sh and the minimal package in ws, on this workspace's prepared .venv
    (every entry linked but the stamps), with a minimal control_msgs built before."""
    for name in ('scripts/bootstrap.sh', 'scripts/env.sh', 'requirements/python.txt',
                 'requirements/ros-pip.txt', 'requirements/constraints.txt',
                 *(str(p.relative_to(ROOT)) for p in (ROOT / 'scripts' / 'control_msgs_min')
                   .rglob('*') if p.is_file())):
        (ws / name).parent.mkdir(parents=True, exist_ok=True)
        (ws / name).write_bytes((ROOT / name).read_bytes())
    venv = ws / '.venv'
    venv.mkdir()
    for entry in (ROOT / '.venv').iterdir():
        if entry.name not in ('.stamps', 'control_msgs'):
            (venv / entry.name).symlink_to(entry)
    (venv / '.stamps').mkdir()
    (venv / '.stamps' / 'control_msgs').write_text('built before\n')
    (venv / 'control_msgs').mkdir()
    (venv / 'control_msgs' / 'local_setup.bash').write_text('export MINIMAL_CONTROL_MSGS=1\n')
    (ws / 'build' / 'control_msgs_min').mkdir(parents=True)
    return ws


def test_the_bootstrap_never_builds_the_minimal_package_beside_a_control_msgs(tmp_path):
    ws = workspace_copy(tmp_path / 'ws')
    system = fake_system_ros(tmp_path / 'ros', with_control_msgs=True)
    env = clean_env(STEPPER_SYSTEM_ROS=str(system))
    out = subprocess.run(['bash', str(ws / 'scripts' / 'bootstrap.sh'), '--control-msgs'],
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    origin = system / 'lib' / 'python3.11' / 'site-packages' / 'control_msgs' / '__init__.py'
    assert f'control_msgs comes from {origin}: removing the minimal one' in out.stderr
    assert 'building' not in out.stderr and 'Starting' not in out.stderr, out.stderr
    assert not (ws / '.venv' / 'control_msgs').exists()
    assert not (ws / 'build' / 'control_msgs_min').exists()
    assert not (ws / '.venv' / '.stamps' / 'control_msgs').exists()
    # the environment imports the system's and has no path into the workspace's prefix
    run = subprocess.run(
        ['bash', '-c', f'source {ws}/scripts/env.sh && echo "$AMENT_PREFIX_PATH:$PYTHONPATH" '
         '&& python -c "import control_msgs; print(control_msgs.__file__)"'],
        capture_output=True, text=True, timeout=60, env=env)
    assert run.returncode == 0, run.stderr
    paths, imported = run.stdout.splitlines()
    assert 'control_msgs' not in paths.replace(str(system), ''), paths
    assert imported == str(origin)


def sourced_minimal(ws: pathlib.Path, env: dict) -> bool:
    run = subprocess.run(['bash', '-c', f'source {ws}/scripts/env.sh && '
                          'echo "${MINIMAL_CONTROL_MSGS:-0}"'],
                         capture_output=True, text=True, timeout=60, env=env)
    assert run.returncode == 0, run.stderr
    return run.stdout.split()[-1] == '1'


def test_env_sh_takes_the_minimal_package_only_when_no_prefix_has_control_msgs(tmp_path):
    ws = workspace_copy(tmp_path / 'ws')  # as though built before a control_msgs came
    with_it = fake_system_ros(tmp_path / 'with', with_control_msgs=True)
    without = fake_system_ros(tmp_path / 'without', with_control_msgs=False)
    assert not sourced_minimal(ws, clean_env(STEPPER_SYSTEM_ROS=str(with_it)))
    assert sourced_minimal(ws, clean_env(STEPPER_SYSTEM_ROS=str(without)))
    assert sourced_minimal(ws, clean_env(STEPPER_FORCE_PIP_ROS='1'))


def test_a_second_control_msgs_step_has_nothing_to_do():
    # this process's environment has the minimal package on its paths (env.sh): the bootstrap
    # must not take it for another control_msgs and remove it
    out = subprocess.run(['bash', str(ROOT / 'scripts' / 'bootstrap.sh'), '--control-msgs'],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stderr == '', out.stderr
