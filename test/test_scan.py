"""stepperctl scan against the simulators, and the params file it writes starting a working node.

Per vendor: the simulator alone on its bus (a pty, a TCP port, the loopback CAN broker), the
scanner run as a subprocess, its YAML read back, then the vendor's node started with nothing but
that YAML: it must connect to every drive found, enable one and move it.
"""

import math
import os
import subprocess
import sys

import pytest
from rosharness import CONFIG, executable, free_port
from std_msgs.msg import Float64
from std_srvs.srv import SetBool
from stepper_drivers_msgs.msg import DriveStatus
from stepper_sim.core.socketcand_broker import SocketcandBroker
import yaml

FAST_DISCOVERY = {'FASTRTPS_DEFAULT_PROFILES_FILE': str(CONFIG / 'fastdds_fast_discovery.xml')}


def ctl(*args, timeout_s=60.0):
    return subprocess.run([executable('stepper_drivers', 'stepperctl'), *args],
                          capture_output=True, text=True, timeout=timeout_s,
                          env={**os.environ, **FAST_DISCOVERY})


def start_sim(procs, vendor, link_param, link):
    sim = procs.start(f'{vendor}_sim', [
        executable('stepper_sim', f'{vendor}_sim'), '--ros-args', '--params-file',
        str(CONFIG / f'{vendor}_sim.yaml'), '-p', f'{link_param}:={link}'], FAST_DISCOVERY)
    sim.wait_line('ready', 30.0)
    return sim


def check_yaml_starts_node(procs, ros, path, vendor, addresses, address_param):
    """The written params file alone starts the node; it connects, enables and moves."""
    params = yaml.safe_load(path.read_text())
    node_name = f'{vendor}_node'
    assert list(params) == [node_name]
    p = params[node_name]['ros__parameters']
    names = [f'axis{a}' for a in addresses]
    assert p['drives'] == names
    assert [p[f'drives.{n}'][address_param] for n in names] == list(addresses)
    node = procs.start(node_name, [executable('stepper_drivers', node_name), '--ros-args',
                                   '--params-file', str(path)], FAST_DISCOVERY)
    for n in names:
        ros.subscribe(DriveStatus, f'/{node_name}/{n}/status')
    for n in names:
        st = ros.wait_msg(f'/{node_name}/{n}/status', lambda m: m.connected, 30.0,
                          f'{node_name}/{n} connected')
        assert not st.fault
    first = f'/{node_name}/{names[0]}'
    r = ros.call(SetBool, first + '/enable', SetBool.Request(data=True))
    assert r.success, r.message
    # pi/4: a whole number of steps at 1024, 2000, 3200 and 12800 steps/rev
    ros.publish(Float64, first + '/position_command', Float64(data=math.pi / 4))
    ros.wait_msg(first + '/status', lambda m: not m.moving and abs(m.position - math.pi / 4)
                 < 1e-3, 20.0, f'{first} at pi/4 rad')
    assert node.proc.poll() is None


def scan_ok(args, expect_addresses, address_word):
    r = ctl('scan', *args)
    assert r.returncode == 0, f'exit {r.returncode}: {r.stderr}{r.stdout}'
    for a in expect_addresses:
        assert f'{address_word} {a:>3}:' in r.stdout, r.stdout
    assert 'found' in r.stderr          # progress
    return r.stdout


def test_xplus_mt(procs, ros, tmp_path):
    port = free_port()
    start_sim(procs, 'xplus_mt', 'port', port)
    out_yaml = tmp_path / 'xplus_mt.yaml'
    out = scan_ok(['xplus_mt', '--host', '127.0.0.1', '--port', str(port), '--ids', '1-8',
                   '--write-yaml', str(out_yaml)], (1, 2), 'unit_id')
    assert 'serial_number=100001' in out and 'word_order=little' in out
    check_yaml_starts_node(procs, ros, out_yaml, 'xplus_mt', (1, 2), 'unit_id')


def test_nothing_answers_bad_port_and_usage(tmp_path):
    r = ctl('scan', 'xplus_mt', '--host', '127.0.0.1', '--port', str(free_port()),
            '--ids', '1-3', '--write-yaml', str(tmp_path / 'none.yaml'))
    assert r.returncode == 3, r.stderr
    assert 'no drive answered' in r.stderr and not (tmp_path / 'none.yaml').exists()
    r = ctl('scan', 'xplus_mt', '--ids', '0-300')
    assert r.returncode == 2 and 'allowed: 1..247' in r.stderr
    r = ctl('scan', 'rd4', '--port', str(tmp_path / 'no_such_tty'))
    assert r.returncode == 1 and 'cannot open' in r.stderr and 'no_such_tty' in r.stderr


@pytest.mark.parametrize('argv, loaded', [
    (['list', '--help'], ()), (['--help'], ()), (['move', '--help'], ()),
    (['scan', '--help'], ('xplus_mt', 'rd4', 'xmind_k', 'vector_step')),
    (['scan', 'rd4', '--help'], ('rd4',))])
def test_only_a_scan_command_line_loads_the_vendor_modules(argv, loaded):
    """The scanners are the vendor modules' (VENDOR.scanner), whose imports (canopen, pymodbus)
    take a third of a second: the other commands build their parsers without them."""
    code = ('import contextlib, io, sys\n'
            'from stepper_drivers.cli.main import main\n'
            'with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n'
            '    main(sys.argv[1:])\n'
            "print(sorted(m for m in sys.modules if m.startswith('stepper_drivers.vendors.')))")
    r = subprocess.run([sys.executable, '-c', code, *argv], capture_output=True, text=True,
                       timeout=60.0, check=True)
    modules = r.stdout.strip()
    if loaded:
        assert all(f"'stepper_drivers.vendors.{key}.scan'" in modules for key in loaded), modules
    else:
        assert modules == '[]', modules


def test_rd4_finds_units_and_their_line_settings(procs, ros, tmp_path):
    link = tmp_path / 'rd4_line'
    start_sim(procs, 'rd4', 'port', link)
    # At 9600 baud the units (dip-switch 03h = 19200 8N2) stay silent.
    r = ctl('scan', 'rd4', '--port', str(link), '--ids', '1-3', '--baudrate', '9600',
            '--parity', 'N')
    assert r.returncode == 3 and '--baudrate/--parity' in r.stderr, r.stderr
    out_yaml = tmp_path / 'rd4.yaml'
    out = scan_ok(['rd4', '--port', str(link), '--ids', '1-4', '--baudrate', '9600,19200',
                   '--parity', 'N', '--write-yaml', str(out_yaml)], (1, 2), 'node_id')
    assert 'model=T32' in out and 'model=T48' in out
    p = yaml.safe_load(out_yaml.read_text())['rd4_node']['ros__parameters']
    assert (p['baudrate'], p['parity']) == (19200, 'N')
    assert p['drives.axis2']['max_velocity'] == pytest.approx(6.54, abs=0.01)   # T48, §6.4
    check_yaml_starts_node(procs, ros, out_yaml, 'rd4', (1, 2), 'node_id')


def test_xmind_k(procs, ros, tmp_path):
    link = tmp_path / 'xmind_k_line'
    start_sim(procs, 'xmind_k', 'port', link)
    out_yaml = tmp_path / 'xmind_k.yaml'
    out = scan_ok(['xmind_k', '--port', str(link), '--addresses', '0-5',
                   '--write-yaml', str(out_yaml)], (1, 2, 3), 'address')
    assert 'RS=D2' in out
    p = yaml.safe_load(out_yaml.read_text())['xmind_k_node']['ros__parameters']
    assert p['drives.axis1']['steps_per_rev'] == 2000.0          # RS D2 (§4.2.2.3)
    check_yaml_starts_node(procs, ros, out_yaml, 'xmind_k', (1, 2, 3), 'address')


def test_vector_step(procs, ros, tmp_path):
    broker = SocketcandBroker(port=0)
    broker.start()
    try:
        start_sim(procs, 'vector_step', 'can.port', broker.port)
        out_yaml = tmp_path / 'vector_step.yaml'
        out = scan_ok(['vector_step', '--can-port', str(broker.port), '--write-yaml',
                       str(out_yaml)], (1, 2), 'node_id')
        assert 'vendor_id=0x000000BC (AEC)' in out and 'serial=10001' in out
        check_yaml_starts_node(procs, ros, out_yaml, 'vector_step', (1, 2), 'node_id')
    finally:
        for p in reversed(procs):
            p.kill()
        broker.stop()
