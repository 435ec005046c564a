"""AEC Vector Step end to end: vector_step_sim and vector_step_node as separate processes on one
CAN bus (the loopback socketcand broker), driven through ROS only.

The broker runs in the test process; the simulator (two drives, node-IDs 1 and 2; axis2 starts
with its power stage blocked) and the node are started once for the module, because each
process start costs seconds on this machine. Tests leave both drives disabled and without
fault; the last test stops and restarts the simulator and finally the node.
"""

import math
import pathlib
import time

import can
from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from rigs_vendors import VectorRig
from rosharness import (
    MIDDLEWARE_S,
    Track,
    bad_parameter_output,
    wait_for,
    watchdog_bound_s,
)
from std_srvs.srv import SetBool
from stepper_drivers.ros.params import BUS_PARAMS
from stepper_drivers_msgs.msg import DriveStatus
import yaml

STEPS_PER_RAD = 3200 / (2 * math.pi)


@pytest.fixture(scope='module')
def rig(tmp_path_factory):
    r = VectorRig(tmp_path_factory.mktemp('vector_step'))
    yield r
    r.close()


def test_two_drives_start_safe_and_a_blocked_power_stage_is_reported(rig):
    for d, node_id in (('axis1', '1'), ('axis2', '2')):
        st = rig.status(d, lambda m: m.state == 'SWITCH ON DISABLED', what=f'{d} SOD')
        assert st.connected and not st.enabled and not st.fault
        assert st.address == node_id and st.vendor == 'AEC Vector Step'
    diag = rig.ros.wait_msg('/diagnostics', lambda a: any(
        s.name.endswith('axis2') and any(kv.key == 'product_code' for kv in s.values)
        for s in a.status))
    values = {kv.key: kv.value for s in diag.status if s.name.endswith('axis2')
              for kv in s.values}
    assert values['product_code'].endswith('(SMD5006)') and values['node_id'] == '2'
    js = rig.ros.wait_msg('/joint_states')
    assert list(js.name) == ['vector_joint1', 'vector_joint2'] and js.header.stamp.sec > 0
    # axis2's power stage is blocked (STO): start-up worked, enable says why it cannot
    r = rig.call('axis2', 'enable', SetBool.Request(data=True), SetBool)
    assert not r.success
    assert 'SWITCH ON DISABLED' in r.message and 'power stage is blocked' in r.message
    assert 'STO' in r.message
    rig.inject('axis2', 'power_stage_ok')
    rig.enable('axis2')
    rig.status('axis2', lambda m: m.enabled)
    rig.idle('axis2')


def test_enable_does_not_move_and_a_move_reaches_the_target(rig):
    before = rig.true_steps('axis1')
    r = rig.enable('axis1')
    assert 'OPERATION ENABLED' in r.message
    st = rig.status('axis1', lambda m: m.enabled)
    assert not st.moving and rig.true_steps('axis1') == pytest.approx(before)
    start = st.position
    rig.command('axis1', 'position_command', start + 3.0)
    st = rig.status('axis1', lambda m: not m.moving and abs(m.position - start - 3.0) < 1e-3,
                    what='axis1 moved by 3 rad')
    assert st.target_reached and st.mode == 'PROFILE POSITION'
    assert st.position_steps == round((start + 3.0) * STEPS_PER_RAD)
    js = rig.ros.wait_msg('/joint_states', lambda m: abs(m.position[0] - start - 3.0) < 1e-3)
    assert js.position[1] == pytest.approx(rig.status('axis2').position, abs=1e-9)
    rig.idle('axis1')


def test_an_idle_drive_reports_at_the_status_rate_not_at_each_of_its_txpdos(rig):
    """A status goes out at a change and at status_rate_hz otherwise. An idle Vector Step still
    sends TxPDO2 every tpdo_event_timer_ms (100 ms); those frames change nothing, so they send no
    status. (DriveState.measured_at_s, the time of such a frame, once counted as a change: every
    idle drive reported at 20 Hz.)"""
    cfg = yaml.safe_load((pathlib.Path(__file__).parents[1] / 'config' / 'vector_step.yaml')
                         .read_text())['vector_step_node']['ros__parameters']
    rate_hz = cfg.get('status_rate_hz',
                      next(p.default for p in BUS_PARAMS if p.name == 'status_rate_hz'))
    window_s = 3.0 / rate_hz
    rig.status('axis1', lambda m: not m.moving, what='axis1 standing')
    got = []
    sub = rig.ros.node.create_subscription(DriveStatus, '/vector_step_node/axis1/status',
                                           lambda m: got.append(m.position_steps), 50)
    try:
        time.sleep(window_s)                         # the window the messages are counted in
    finally:
        rig.ros.node.destroy_subscription(sub)
    assert len(got) <= window_s * rate_hz + 1, (len(got), window_s)
    assert len(set(got)) == 1, got                   # nothing changed: standing


def test_a_refusal_to_an_idle_drive_shows_in_its_status_at_once(rig):
    """Idle drives make cycles with nothing new, whose statuses are not looked at again; a
    refused command is still in the next status, not only in the one status_rate_hz brings."""
    rate_hz = next(p.default for p in BUS_PARAMS if p.name == 'status_rate_hz')
    st = rig.status('axis1', lambda m: not m.enabled and not m.moving, what='axis1 idle')
    got = []
    sub = rig.ros.node.create_subscription(
        DriveStatus, '/vector_step_node/axis1/status',
        lambda m: got.append((time.monotonic(), m.commands_refused, m.last_refusal)), 50)
    try:
        time.sleep(1.0 / rate_hz)                   # idle cycles, a status at the rate
        t0 = time.monotonic()
        rig.command('axis1', 'position_command', 0.25)
        wait_for(lambda: any(n > st.commands_refused for _, n, _ in got), 2.0 / rate_hz,
                 'the refusal in a status')
    finally:
        rig.ros.node.destroy_subscription(sub)
    t, n, why = next(m for m in got if m[1] > st.commands_refused)
    assert 'not enabled' in why, why
    assert t - t0 < 0.5 / rate_hz, f'the refusal came {t - t0:.3f} s later ({rate_hz:g} Hz)'


def test_jog_runs_in_aec_velocity_mode_and_the_watchdog_stops_it(rig):
    rig.enable('axis1')
    track = Track(rig.ros, rig.true_topic('axis1'))
    rig.command('axis1', 'velocity_command', 4.0)
    t_cmd = time.monotonic()
    st = rig.status('axis1', lambda m: m.moving and m.velocity > 3.5, what='axis1 jogging')
    assert st.mode == 'AEC VELOCITY (JOG)'
    # command_timeout_s 0.5, 50 Hz polls, deceleration 200 rad/s^2 (config/vector_step.yaml),
    # one SDO/PDO exchange in flight
    bound_s = watchdog_bound_s(0.5, 50.0, 4.0, 200.0, 0.02)
    still_at = track.wait_still(0.3, bound_s + 3.0, 'axis1 stopped')
    assert still_at - t_cmd <= bound_s, (still_at - t_cmd, bound_s)
    st = rig.status('axis1', lambda m: not m.moving, 1.0, 'watchdog stop')
    assert st.enabled and st.velocity == 0.0
    rig.node.wait_line('velocity watchdog', 1.0)
    rig.idle('axis1')


def test_home_on_the_bls_switch_while_joint_states_keep_flowing(rig):
    rig.enable('axis1')
    n_before = len(rig.ros.history['/joint_states'])
    t0 = time.monotonic()
    r = rig.call('axis1', 'home')
    assert r.success, r.message
    assert 'homed' in r.message and 'BLS, negative direction' in r.message
    elapsed = time.monotonic() - t0
    st = rig.status('axis1', lambda m: m.homed and m.homing_state == 'ATTAINED')
    assert st.mode == 'HOMING'
    assert st.position == pytest.approx(-13.0, abs=0.1)     # 0x607C forced at the BLS edge
    assert len(rig.ros.history['/joint_states']) - n_before >= 0.5 * elapsed * 50
    rig.command('axis1', 'position_command', 0.0)           # away from the switch
    rig.status('axis1', lambda m: not m.moving and abs(m.position) < 1e-3, what='at 0')
    rig.idle('axis1')


def test_a_stop_during_homing_ends_the_home_call_at_once(rig):
    """The Vector Step reports a halted homing as IDLE: the `home` call ends at the next polls
    with the reason, not homing.timeout_s (20 s) later as a time-out."""
    # the halt's ramp (homing.speed_search 12 rad/s at homing.acceleration 200 rad/s^2), the
    # statusword's TxPDO (inhibit 10 ms), the simulator's tick, three polls at 50 Hz, the
    # answer's way back
    rig.stop_during_homing('axis1', 12.0 / 200.0 + 0.01 + 0.02 + 3 / 50.0 + MIDDLEWARE_S)
    rig.idle('axis1')


def test_drive_fault_emcy_text_and_fault_reset(rig):
    rig.enable('axis1')
    rig.inject('axis1', 'drive_fault', code=1 << 6)          # Ralarm bit 6 over-temperature
    st = rig.status('axis1', lambda m: m.fault, what='fault in status')
    assert st.state == 'FAULT' and st.fault_code == 0x5400
    assert 'power stage' in st.fault_text and 'over-temperature' in st.fault_text
    rig.ros.wait_msg('/diagnostics', lambda a: any(
        s.name.endswith('axis1') and s.level == DiagnosticStatus.ERROR and '0x5400' in s.message
        for s in a.status))
    refused = st.commands_refused
    rig.command('axis1', 'position_command', 1.0)
    st = rig.status('axis1', lambda m: m.commands_refused > refused)
    assert 'fault_reset' in st.last_refusal
    r = rig.call('axis1', 'fault_reset')
    assert not r.success and '0x5400' in r.message and 'over-temperature' in r.message
    rig.inject('axis1', 'clear_fault')
    r = rig.call('axis1', 'fault_reset')
    assert r.success, r.message
    st = rig.status('axis1', lambda m: not m.fault)
    assert st.state == 'SWITCH ON DISABLED'


def test_typed_sdo_read_and_write(rig):
    for address, data_type, value in (('0x1001:0', 'u8', 0), ('0x6061:0', 'i8', 1),
                                      ('0x605A:0', 'i16', 2), ('0x1000:0', 'u32', 0x00040192),
                                      ('0x202A:1', 'u32', 1234567890)):
        r = rig.read('axis2', address, data_type)
        assert r.success and r.value == value, (address, r.message)
    r = rig.read('axis2', '0x6505:0', 'string')                 # segmented upload
    assert r.success and r.text == 'www.aec-smd.it'
    st = rig.status('axis1')
    r = rig.read('axis1', '0x6064:0', 'i32')
    assert r.success and r.value == st.position_steps
    r = rig.write('axis1', '0x6504:0', 'string', text='stepper_drivers rig')
    assert r.success, r.message
    assert rig.read('axis1', '0x6504:0', 'string').text == 'stepper_drivers rig'
    r = rig.write('axis1', '0x6098:0', 'i8', -3)
    assert r.success and rig.read('axis1', '0x2052:1', 'i16').value == -3
    r = rig.write('axis1', '0x1000:0', 'u32', 5)
    assert not r.success and '0x06010002' in r.message
    r = rig.read('axis1', '0x6064:0', 'i16')
    assert not r.success and 'answered 4 byte' in r.message
    r = rig.write('axis2', '0x2020:1', 'u32', 5)
    assert not r.success and 'allow_raw_write' in r.message


def test_save_params_is_verified_by_rloadsav(rig):
    r = rig.write('axis1', '0x2020:1', 'u32', 170000)           # Rhmaxspc (SAVE)
    assert r.success, r.message
    r = rig.call('axis1', 'save_params')
    assert r.success, r.message
    assert 'Reepsts 0' in r.message
    stored = wait_for(lambda: list(rig.storage.glob('vector_step_node1.json')), 5.0, 'EEPROM')
    assert '170000' in stored[0].read_text()


def test_can_error_frames_show_in_the_status_alarms_and_the_link_diagnostics(rig):
    """An error frame the CAN interface reports (socketcand forwards the controller's): every
    drive's status names it among its alarms, and the link entry of /diagnostics goes to WARN
    with it, its count in the link's values."""
    rig.broker.error_frame(0x004)                   # CAN_ERR_CRTL: controller problems
    want = 'CAN error frames within 10 s, last: controller'
    for drive in ('axis1', 'axis2'):
        rig.status(drive, lambda m: want in m.alarms, what=f'{drive}: the error frame alarm')

    def link_warns(arr):
        return any(s.name.endswith('link') and s.level == DiagnosticStatus.WARN
                   and s.message == want
                   and {kv.key: kv.value for kv in s.values}.get('error_frames') == '1'
                   for s in arr.status)
    rig.ros.wait_msg('/diagnostics', link_warns, 10.0, 'link WARN with the error frame')


def sdo_statusword(port: int, node_id: int) -> int:
    """Ask a drive directly (expedited upload of 0x6041) with a raw python-can client."""
    bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel='can0',
                  tcp_tune=True)
    try:
        bus.send(can.Message(arbitration_id=0x600 + node_id, is_extended_id=False,
                             data=bytes.fromhex('4041600000000000')))
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            msg = bus.recv(0.5)
            if msg is not None and msg.arbitration_id == 0x580 + node_id:
                return int.from_bytes(msg.data[4:6], 'little')
        raise AssertionError(f'node {node_id} did not answer')
    finally:
        bus.shutdown()


def test_heartbeat_loss_restart_recovery_and_shutdown(rig):
    assert rig.write('axis1', '0x2020:1', 'u32', 170001).success     # saved: survives the
    assert rig.call('axis1', 'save_params').success                  # power cycle below
    rig.enable('axis1')
    rig.command('axis1', 'velocity_command', 2.0)
    rig.status('axis1', lambda m: m.moving, what='axis1 jogging')
    rig.sim.kill()                                               # the drives vanish
    st = rig.status('axis1', lambda m: m.state == 'DISCONNECTED', 5.0, 'DISCONNECTED')
    assert not st.connected
    rig.ros.wait_msg('/diagnostics', lambda a: any(
        s.name.endswith('link') and s.level == DiagnosticStatus.ERROR for s in a.status))
    rig.node.wait_line('heartbeat lost', 5.0)
    rig.start_sim()                                              # power on again
    st = rig.status('axis1', lambda m: m.connected, 20.0, 'reconnected')
    assert st.state == 'SWITCH ON DISABLED' and not st.moving and not st.enabled
    st = rig.status('axis1', lambda m: m.link_reconnects >= 1)
    rig.status('axis2', lambda m: m.connected, what='axis2 reconnected')
    before = rig.true_steps('axis1')
    time.sleep(0.3)                                              # nothing resumes by itself
    assert rig.true_steps('axis1') == pytest.approx(before)
    assert rig.read('axis1', '0x2020:1', 'u32').value == 170001  # saved before the restart
    # SIGTERM: stop, disable, close; the drive stays disabled
    rig.sigterm_while_running(2.0)
    assert sdo_statusword(rig.broker.port, 1) & 0x4F == 0x40     # SWITCH ON DISABLED


def test_bad_parameter_fails_start_up_with_one_line(procs, tmp_path):
    out = bad_parameter_output(procs, tmp_path, 'vector_step', 'node_id: 2', 'node_id: 300',
                               timeout_s=30.0)
    assert out[-1] == ('vector_step_node: parameter drives.axis2.node_id: 300 is out of range '
                       '(allowed: an integer from 1 to 127)'), out


class SlowTpdoRig(VectorRig):
    """TxPDO2..4 50 ms behind TxPDO1, as on a slow or busy bus (at 10-20 kbit/s one TPDO takes
    about 10 ms, and the frames of drives with lower COB-IDs go first)."""

    first_sim_args = ('-p', 'tpdo_lag_s:=0.05')


def test_move_to_decides_on_the_position_after_the_statusword_on_a_slow_bus(tmp_path):
    """A "target reached" statusword (TxPDO1) before the TxPDO2 with the final position: the
    move_to result is decided on the drive's real final position, every time."""
    rig = SlowTpdoRig(tmp_path)
    try:
        rig.enable('axis1')
        start = rig.status('axis1', lambda m: m.enabled).position
        for k in range(16):
            target = start + (1.0 if k % 2 == 0 else 0.0) + 0.25 * k
            r = rig.move_to('axis1', target)
            assert r.success, (k, r.message)
            assert r.final_position == pytest.approx(target, abs=1 / STEPS_PER_RAD)
    finally:
        rig.close()
