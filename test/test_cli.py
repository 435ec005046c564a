"""stepperctl against a running node: every subcommand, its output and its exit code.

One X-PLUS MT simulator and node for the module (its services cover every subcommand, and its
simulator can inject a drive fault); the tool runs as a subprocess, as an operator runs it, and a
ROS client in the test checks what the tool claims through the node's own status topic.
Tests run in file order and each leaves the drives without fault.
"""

import json
import os
import subprocess

import pytest
from rosharness import CONFIG, Proc, RosClient, executable, free_port
from stepper_drivers_msgs.msg import DriveStatus
from stepper_drivers_msgs.srv import InjectFault

NODE = '/xplus_mt_node'
AXIS1, AXIS2 = 'xplus_mt_node/axis1', 'xplus_mt_node/axis2'
# Participants announce every 0.3 s (not 3 s): each stepperctl run sees the node at once.
FAST_DISCOVERY = {'FASTRTPS_DEFAULT_PROFILES_FILE': str(CONFIG / 'fastdds_fast_discovery.xml')}


class Rig:
    def __init__(self, log_dir):
        self.log_dir = log_dir
        self.procs = []
        self.ros = RosClient('cli_test')
        port = free_port()
        self.sim = self.start('sim', [executable('stepper_sim', 'xplus_mt_sim'), '--ros-args',
                                      '--params-file', str(CONFIG / 'xplus_mt_sim.yaml'),
                                      '-p', f'port:={port}'])
        self.sim.wait_line('ready', 30.0)
        self.node = self.start('node', [executable('stepper_drivers', 'xplus_mt_node'),
                                        '--ros-args', '--params-file',
                                        str(CONFIG / 'xplus_mt.yaml'), '-p', f'port:={port}',
                                        '-p', 'publish_rate_hz:=20.0',
                                        # the shipped params refuse raw writes
                                        '-p', 'drives.axis1.allow_raw_write:=true'])
        for d in ('axis1', 'axis2'):
            self.ros.subscribe(DriveStatus, f'{NODE}/{d}/status')
            self.status(d, lambda m: m.connected, 30.0)

    def start(self, name, args):
        proc = Proc(args, self.log_dir, name, FAST_DISCOVERY)
        self.procs.append(proc)
        return proc

    def status(self, drive, cond=lambda m: True, timeout_s=10.0, what=''):
        return self.ros.wait_msg(f'{NODE}/{drive}/status', cond, timeout_s, what or drive)

    def inject(self, kind, code=0):
        r = self.ros.call(InjectFault, '/xplus_mt_sim/inject_fault',
                          InjectFault.Request(drive='axis1', kind=kind, code=code))
        assert r.success, r.message

    def close(self):
        self.ros.close()          # first: its executor must not be waiting on vanishing peers
        for p in reversed(self.procs):
            p.kill()


@pytest.fixture(scope='module')
def rig(tmp_path_factory):
    r = Rig(tmp_path_factory.mktemp('cli'))
    yield r
    r.close()


def ctl(*args, timeout_s=60.0):
    """Run stepperctl; returns the CompletedProcess (text output)."""
    return subprocess.run([executable('stepper_drivers', 'stepperctl'), *args],
                          capture_output=True, text=True, timeout=timeout_s,
                          env={**os.environ, **FAST_DISCOVERY})


def ok(r):
    assert r.returncode == 0, f'exit {r.returncode}: {r.stderr}{r.stdout}'
    return r.stdout


def fails(r, code, *words):
    assert r.returncode == code, f'exit {r.returncode}, wanted {code}: {r.stderr}{r.stdout}'
    line = r.stderr.strip()
    assert line.count('\n') == 0, f'error is not one line: {line!r}'
    assert line.startswith('stepperctl')
    for w in words:
        assert w in line, f'{w!r} not in {line!r}'
    return line


def test_list_shows_every_drive_with_its_state(rig):
    out = ok(ctl('list'))
    assert out.splitlines()[0].split()[:3] == ['DRIVE', 'VENDOR', 'ADDR']
    rows = [line for line in out.splitlines() if line.startswith('xplus_mt_node/')]
    assert len(rows) == 2
    for row, joint in zip(rows, ('xplus_joint1', 'xplus_joint2')):
        assert 'X-PLUS MT' in row and joint in row and 'SWITCH ON DISABLED' in row
    data = json.loads(ok(ctl('list', '--json')))
    assert {d['drive'] for d in data} == {AXIS1, AXIS2}
    assert {d['address'] for d in data} == {'1', '2'}


def test_status_snapshot_and_live_view(rig):
    out = ok(ctl('status', '--once'))
    assert out.splitlines()[0].split()[:3] == ['DRIVE', 'ADDR', 'STATE']
    assert AXIS1 in out and AXIS2 in out and 'SWITCH ON DISABLED' in out
    # live view of one drive: refreshed tables until --duration
    out = ok(ctl('status', 'axis1', '--period', '0.3', '--duration', '1.0'))
    assert out.count('stepperctl status') >= 3
    assert AXIS1 in out and AXIS2 not in out


def test_unknown_drive_usage_and_ambiguity(rig):
    # 'axis' is no drive name, nor a tail of one ('.../axis1'), nor a joint name
    fails(ctl('enable', 'axis', '--discovery-timeout', '3'), 3, 'not found', AXIS1)
    fails(ctl('move', 'axis1', 'far'), 2, 'invalid float')
    fails(ctl('write', AXIS1, '1063', 'u16', 'x'), 2, 'not an integer')


def test_move_needs_enable_then_reaches_target(rig):
    fails(ctl('move', AXIS1, '1.0'), 1, 'not enabled', 'stepperctl enable')
    assert 'OPERATION ENABLED' in ok(ctl('enable', 'axis1'))
    rig.status('axis1', lambda m: m.enabled, what='axis1 enabled')
    out = ok(ctl('move', AXIS1, '2.5'))
    assert 'at 2.5' in out and '100%' in out
    st = rig.status('axis1', lambda m: not m.moving, what='axis1 still')
    assert st.position == pytest.approx(2.5, abs=1e-3)


def test_move_timeout_stops_the_drive(rig):
    # by joint name; 52 rad at 12 rad/s
    r = ctl('move', 'xplus_joint1', '-50', '--timeout', '0.4')
    fails(r, 4, 'not reached within 0.4 s', 'drive stopped')
    st = rig.status('axis1', lambda m: not m.moving, what='axis1 stopped after the timeout')
    assert -40.0 < st.position < 2.5 and st.enabled


def test_jog_runs_then_stops(rig):
    before = rig.status('axis1').position
    out = ok(ctl('jog', AXIS1, '5', '0.6'))
    assert 'stopped by stop' in out
    st = rig.status('axis1', lambda m: not m.moving)
    assert st.position - before > 2.0          # 5 rad/s for 0.6 s, ramps at 200 rad/s^2
    # --no-stop: the node's velocity watchdog ends the run
    out = ok(ctl('jog', AXIS1, '-5', '0.4', '--no-stop'))
    assert 'watchdog' in out
    rig.node.wait_line('velocity watchdog', 5.0)
    fails(ctl('jog', AXIS1, '100', '0.5'), 1, 'exceeds max_velocity')
    rig.status('axis1', lambda m: not m.moving, what='axis1 still after the refused jog')


def test_stop_and_home(rig):
    assert 'stopping' in ok(ctl('stop', AXIS1))
    out = ok(ctl('home', AXIS1))             # method 19: the home switch at 50000 steps
    assert 'homed at 0' in out
    assert 'homing RUNNING' in out           # progress while the service runs
    st = rig.status('axis1', lambda m: m.homed, what='axis1 homed')
    assert st.position == pytest.approx(0.0, abs=1e-3)


def test_registers_and_save(rig):
    ok(ctl('write', AXIS1, '1063', 'u16', '0x3C'))       # VELOCITY_WINDOW_TIME [ms]
    assert '1063 (u16) = 60 (0x3C)' in ok(ctl('read', AXIS1, '1063'))
    fails(ctl('write', AXIS2, '1063', 'u16', '60'), 1, 'allow_raw_write')
    assert 'parameters saved' in ok(ctl('save', AXIS1))


def test_fault_gives_exit_5_until_reset(rig):
    rig.inject('drive_fault', 0x4310)
    rig.status('axis1', lambda m: m.fault, what='axis1 in fault')
    fails(ctl('status', '--once'), 5, 'in FAULT', AXIS1)
    fails(ctl('jog', AXIS1, '1.0', '0.5'), 5, 'FAULT 0x4310', 'fault-reset')
    fails(ctl('fault-reset', AXIS1), 5, 'fault remains')     # the cause is still there
    rig.inject('clear_fault')
    assert 'fault cleared' in ok(ctl('fault-reset', AXIS1))
    st = rig.status('axis1', lambda m: not m.fault, what='axis1 without fault')
    assert not st.enabled


def test_disable(rig):
    ok(ctl('enable', AXIS2))
    rig.status('axis2', lambda m: m.enabled, what='axis2 enabled')
    assert 'SWITCH ON DISABLED' in ok(ctl('disable', AXIS2))
    st = rig.status('axis2', lambda m: not m.enabled, what='axis2 disabled')
    assert st.state == 'SWITCH ON DISABLED'
