"""Who may command a drive (docs/security.md): the shipped params files refuse raw register
writes, and a node asked for SROS2 where the middleware cannot provide it ends at start-up with
one line and exit code 2 instead of running unsecured or failing inside the rmw."""

import pathlib

import pytest
from rosharness import CONFIG, DriveBench, executable, free_port
from stepper_drivers import dds_security
from stepper_drivers.params import DRIVE_PARAMS
from stepper_drivers.vendor_table import KEYS
import yaml

EXIT_TIMEOUT_S = 20.0


def raw_write_settings(tree, path=()):
    """(dotted path, value) of every allow_raw_write in a parsed params file."""
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from raw_write_settings(value, (*path, str(key)))
    elif path and path[-1].split('.')[-1] == 'allow_raw_write':
        yield '.'.join(path), tree


def test_no_shipped_params_file_allows_raw_writes():
    files = sorted(CONFIG.rglob('*.yaml'))
    assert {f'{v}.yaml' for v in KEYS} <= {f.name for f in files}
    allowed = [(f.name, name) for f in files
               for name, value in raw_write_settings(yaml.safe_load(f.read_text()))
               if value is not False]
    assert not allowed, f'allow_raw_write not false in {allowed}'
    # a drive without the parameter gets the declared default: refused as well
    (default,) = [p.default for p in DRIVE_PARAMS if p.name == 'allow_raw_write']
    assert default is False


class ShippedParams(DriveBench):
    """X-PLUS MT simulator and node with config/xplus_mt.yaml as shipped (a free port only)."""

    vendor = 'xplus_mt'

    def __init__(self, procs, ros):
        self.port = free_port()
        super().__init__(procs, ros)

    def link_args(self):
        return ['-p', f'port:={self.port}']


def test_a_node_with_the_shipped_params_refuses_write_register(procs, ros):
    from stepper_drivers_msgs.srv import ReadRegister, WriteRegister
    bench = ShippedParams(procs, ros)
    read = ReadRegister.Request(address='1063', data_type='u16')    # VELOCITY_WINDOW_TIME
    before = bench.call('axis1', 'read_register', read, ReadRegister)
    assert before.success, before.message
    r = bench.call('axis1', 'write_register',
                   WriteRegister.Request(address='1063', data_type='u16',
                                         value=before.value + 1), WriteRegister)
    assert not r.success
    assert 'raw writes are disabled' in r.message
    assert 'drives.axis1.allow_raw_write' in r.message
    after = bench.call('axis1', 'read_register', read, ReadRegister)
    assert after.success and after.value == before.value


# ------------------------------------------------------------------------------ SROS2
def _fake_library(tmp_path: pathlib.Path, name: str, content: bytes) -> str:
    path = tmp_path / name
    path.write_bytes(b'\x7fELF' + b'\0' * 64 + content + b'\0' * 64)
    return str(path)


def test_security_plugins_are_found_by_their_namespace(tmp_path):
    with_plugins = _fake_library(
        tmp_path, 'libfastrtps.so.2.14',
        b'_ZN8eprosima8fastrtps4rtps8security15SecurityManager4initEv')
    fast_dds_3 = _fake_library(tmp_path, 'libfastdds.so.3.1',
                               b'N8eprosima7fastdds4rtps8security5PKIDHE')
    without = _fake_library(tmp_path, 'libfastrtps.so.2.13',
                            b'_ZN8eprosima8fastrtps4rtps15MessageReceiver')
    assert dds_security.problem('rmw_fastrtps_cpp', [with_plugins]) == ''
    assert dds_security.problem('rmw_fastrtps_dynamic_cpp', [fast_dds_3]) == ''
    line = dds_security.problem('rmw_fastrtps_cpp', [without])
    assert line.startswith('ROS_SECURITY_ENABLE=true, but the Fast DDS of rmw_fastrtps_cpp '
                           f'({without}) has no DDS-Security plugins')
    assert 'docs/security.md' in line and '\n' not in line
    # what it cannot tell, the rmw decides: another rmw, no library, an unreadable one
    assert dds_security.problem('rmw_cyclonedds_cpp', [without]) == ''
    assert dds_security.problem('rmw_fastrtps_cpp', []) == ''
    assert dds_security.problem('rmw_fastrtps_cpp', [str(tmp_path / 'gone.so')]) == ''
    # rcl/security.c: only the exact string 'true' turns security on
    assert dds_security.security_requested({'ROS_SECURITY_ENABLE': 'true'})
    for value in ('', 'True', '1', 'false'):
        assert not dds_security.security_requested({'ROS_SECURITY_ENABLE': value})


def test_the_fast_dds_library_of_this_process_is_found():
    from rclpy.utilities import get_rmw_implementation_identifier
    if not get_rmw_implementation_identifier().startswith('rmw_fastrtps'):
        pytest.skip('the rmw here is not rmw_fastrtps')
    libraries = dds_security.mapped_fast_dds_libraries()
    assert libraries and all(pathlib.Path(p).is_file() for p in libraries), libraries


NO_PLUGINS = dds_security.startup_problem({'ROS_SECURITY_ENABLE': 'true'})


@pytest.mark.skipif(not NO_PLUGINS, reason="this ROS install's middleware has the security "
                    'plugins (or cannot be asked): nodes start secured there')
@pytest.mark.parametrize('exe, env', [
    (f'{v}_node', {'ROS_SECURITY_ENABLE': 'true'}) for v in KEYS] + [
    ('rd4_lifecycle_node', {'ROS_SECURITY_ENABLE': 'true'}),
    # as docs/security.md sets it up: a keystore with the node's enclave, Enforce
    ('rd4_node', {'ROS_SECURITY_ENABLE': 'true', 'ROS_SECURITY_STRATEGY': 'Enforce',
                  'ROS_SECURITY_KEYSTORE': '{keystore}'}),
])
def test_a_node_asked_for_sros2_without_security_plugins_ends_with_one_line(
        procs, tmp_path, exe, env):
    keystore = tmp_path / 'keystore'
    (keystore / 'enclaves' / 'rd4_node').mkdir(parents=True)
    env = {k: v.format(keystore=keystore) for k, v in env.items()}
    vendor = exe.removesuffix('_node').removesuffix('_lifecycle')
    args = [executable('stepper_drivers', exe), '--ros-args',
            '--params-file', str(CONFIG / f'{vendor}.yaml')]
    if 'ROS_SECURITY_KEYSTORE' in env:
        args += ['--enclave', '/rd4_node']
    p = procs.start(exe, args, env)
    code = p.proc.wait(timeout=EXIT_TIMEOUT_S)
    lines = p.output().strip().splitlines()
    assert code == 2, f'{exe} exited with {code}:\n{p.output()}'
    assert lines == [f'{exe}: {NO_PLUGINS}'], lines
