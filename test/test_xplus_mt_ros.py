"""X-PLUS MT end to end: xplus_mt_sim and xplus_mt_node as separate processes, driven through ROS.

Every check goes through the node's topics and services (the user's interface); the simulator's
true position topic and fault-injection service play the part of the real world.
"""

import math
import os
import pathlib
import signal
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import pytest
from rigs_vendors import XplusBench
from rosharness import (
    CONFIG,
    MIDDLEWARE_S,
    Track,
    bad_parameter_output,
    executable,
    free_port,
    wait_for,
    watchdog_bound_s,
)
from std_msgs.msg import Float64
from std_srvs.srv import SetBool
from stepper_drivers_msgs.srv import ReadRegister, WriteRegister
from stepper_sim.harness import fifo_allowed

NODE = '/xplus_mt_node'
SIM = '/xplus_mt_sim'
STEPS_PER_RAD = 12800 / (2 * math.pi)


@pytest.fixture
def bench(procs, ros, tmp_path):
    return XplusBench(procs, ros, tmp_path)


def test_start_up_is_safe_and_enable_does_not_move(bench):
    st = bench.status('axis1', lambda m: m.state == 'SWITCH ON DISABLED', what='SOD at start')
    assert not st.enabled and not st.fault
    before = bench.true_steps('axis1')
    r = bench.enable('axis1')
    assert 'OPERATION ENABLED' in r.message
    st = bench.status('axis1', lambda m: m.enabled)
    assert st.state == 'OPERATION ENABLED'
    assert abs(bench.true_steps('axis1') - before) < 1 and not st.moving
    # joint_states: stamped, named after the joints, in rad
    js = bench.ros.wait_msg('/joint_states')
    assert list(js.name) == ['xplus_joint1', 'xplus_joint2']
    assert js.header.stamp.sec > 0


def test_move_to_target_within_tolerance(bench):
    bench.enable('axis1')
    bench.command('axis1', 'position_command', 3.0)
    st = bench.status('axis1', lambda m: not m.moving and abs(m.position - 3.0) < 1e-3,
                      what='axis1 at 3.0 rad')
    assert st.position_steps == round(3.0 * STEPS_PER_RAD)
    # the simulator's own counter agrees (its topic runs at 20 Hz: wait for a fresh sample)
    bench.ros.wait_msg(f'{SIM}/axis1/true_position_steps',
                       lambda m: abs(m.data - 3.0 * STEPS_PER_RAD) <= 1, 5.0, 'true position')
    js = bench.ros.wait_msg('/joint_states', lambda m: abs(m.position[0] - 3.0) < 1e-3)
    assert js.position[1] == pytest.approx(0.0, abs=1e-6)     # axis2 untouched


def test_velocity_stops_by_watchdog(bench):
    bench.enable('axis1')
    track = Track(bench.ros, bench.true_topic('axis1'))
    bench.command('axis1', 'velocity_command', 5.0)
    t_cmd = time.monotonic()
    bench.status('axis1', lambda m: m.moving and m.velocity > 4.0, what='axis1 running')
    # command_timeout_s 0.5, 50 Hz polls, deceleration 200 rad/s^2 (config/xplus_mt.yaml),
    # one Modbus TCP transaction in flight
    bound_s = watchdog_bound_s(0.5, 50.0, 5.0, 200.0, 0.01)
    still_at = track.wait_still(0.3, bound_s + 3.0, 'axis1 stopped')
    assert still_at - t_cmd <= bound_s, (still_at - t_cmd, bound_s)
    st = bench.status('axis1', lambda m: not m.moving, timeout_s=1.0, what='watchdog stop')
    assert st.enabled and abs(st.velocity) < 1e-6
    bench.node.wait_line('velocity watchdog', 1.0)


def test_home_runs_while_joint_states_keep_flowing(bench):
    bench.enable('axis1')
    n_before = len(bench.ros.history['/joint_states'])
    r = bench.call('axis1', 'home')
    assert r.success, r.message
    assert 'homed' in r.message
    st = bench.status('axis1', lambda m: m.homed)
    assert st.homing_state == 'ATTAINED' and st.position == pytest.approx(0.0, abs=1e-3)
    # a homing takes > 0.2 s; at 50 Hz joint_states must not have paused meanwhile
    assert len(bench.ros.history['/joint_states']) - n_before >= 10


def test_fault_shows_code_and_text_and_only_fault_reset_clears_it(bench):
    bench.enable('axis1')
    bench.inject('axis1', 'drive_fault', 0x4310)
    st = bench.status('axis1', lambda m: m.fault, what='fault in status')
    assert st.state == 'FAULT' and st.fault_code == 0x4310
    assert 'temperature' in st.fault_text.lower()
    diag = bench.ros.wait_msg('/diagnostics', lambda a: any(
        s.name.endswith('axis1') and s.level == DiagnosticStatus.ERROR for s in a.status))
    assert any('0x4310' in s.message for s in diag.status)
    # commands are refused, counted and never sent
    refused = st.commands_refused
    bench.command('axis1', 'position_command', 1.0)
    st = bench.status('axis1', lambda m: m.commands_refused > refused)
    assert 'FAULT' in st.last_refusal and 'fault_reset' in st.last_refusal
    # the cause is still there: reset fails and says what remains
    r = bench.call('axis1', 'fault_reset')
    assert not r.success and '0x4310' in r.message
    bench.inject('axis1', 'clear_fault')
    r = bench.call('axis1', 'fault_reset')
    assert r.success, r.message
    st = bench.status('axis1', lambda m: not m.fault)
    assert st.state == 'SWITCH ON DISABLED'


def test_commands_refused_nan_out_of_limits_and_not_enabled(bench):
    bench.command('axis1', 'position_command', 1.0)
    st = bench.status('axis1', lambda m: m.commands_refused >= 1)
    assert 'not enabled' in st.last_refusal
    bench.enable('axis1')
    bench.command('axis1', 'position_command', math.nan)
    st = bench.status('axis1', lambda m: 'finite' in m.last_refusal)
    bench.command('axis1', 'position_command', 1000.0)
    st = bench.status('axis1', lambda m: 'min_position..max_position' in m.last_refusal)
    bench.command('axis1', 'velocity_command', -100.0)
    st = bench.status('axis1', lambda m: 'max_velocity' in m.last_refusal)
    assert st.commands_refused >= 4 and not st.moving
    assert abs(bench.true_steps('axis1')) < 1


def test_a_stream_of_refused_commands_is_logged_once_and_counted_each_time(bench):
    """A controller streaming set points to a drive that is not enabled: each value is another
    command, but one reason. Logged at its first refusal, again only after a command was taken
    (a warning per message flooded the log and /rosout and cut the command thread's rate to a
    third)."""
    def logged():
        return bench.node.output().count('axis1: command refused: ')
    n = 200
    before = bench.status('axis1').commands_refused
    logged_before = logged()
    for i in range(n):
        bench.command('axis1', 'position_command', 0.5 + 0.001 * i)
    st = bench.status('axis1', lambda m: m.commands_refused >= before + n,
                      what=f'{n} refusals counted')
    assert st.last_refusal.startswith(f'position_command {0.5 + 0.001 * (n - 1)}: ') \
        and 'not enabled' in st.last_refusal, st.last_refusal
    assert logged() == logged_before + 1, bench.node.output()[-3000:]
    bench.enable('axis1')
    bench.command('axis1', 'position_command', 0.5)
    bench.status('axis1', lambda m: not m.moving and abs(m.position - 0.5) < 1e-3,
                 what='the command after enable taken')
    bench.enable('axis1', False)
    bench.command('axis1', 'position_command', 0.6)
    bench.status('axis1', lambda m: m.commands_refused >= before + n + 1)
    wait_for(lambda: logged() == logged_before + 2, 5.0, 'the refusal after a taken command '
             'logged again')


def test_a_stream_of_set_points_the_drive_cannot_take_is_logged_once(bench):
    """max_position opened far beyond the drive: set points the node passes but the X-PLUS MT
    cannot hold (its Target Position is 32 bits) fail, each as a job, for one reason: one error
    in the log for the run, the latest in /diagnostics, nothing written."""
    def logged():
        return bench.node.output().count('axis1: position_command ')
    (r,) = bench.set_params(('drives.axis1.max_position', 1e9))
    assert r.successful, r.reason
    bench.enable('axis1')
    logged_before = logged()
    n = 50
    for i in range(n):
        bench.command('axis1', 'position_command', 1e8 + i)
    last = f'position_command {1e8 + n - 1}: '
    bench.ros.wait_msg('/diagnostics', lambda a: any(
        s.name.endswith(': axis1') and s.message.startswith(last) for s in a.status),
        timeout_s=10.0, what='the last failure in /diagnostics')
    assert logged() == logged_before + 1, bench.node.output()[-3000:]
    assert abs(bench.true_steps('axis1')) < 1


def test_a_service_waiting_when_the_node_is_stopped_gets_its_answer(bench):
    """SIGTERM while `home` waits: the caller (ros2 service call, say) gets a refusal naming
    the shutdown, not silence for ever, and the node ends with 0."""
    fut, answered = bench.home_under_way()
    assert bench.node.stop(signal.SIGTERM) == 0
    assert answered.wait(2.0), 'home did not answer before the node ended'
    r = fut.result()
    assert not r.success and r.message == 'axis1: the node is shutting down', r.message


def test_a_stop_during_homing_ends_the_home_call_at_once(bench):
    """A stop halts the homing: the `home` call ends at the next polls with the reason, not
    homing.timeout_s (20 s in config/xplus_mt.yaml) later as a time-out."""
    # the halt's ramp (homing.speed_search 8 rad/s at homing.acceleration 200 rad/s^2), a
    # transaction, the simulator's tick, three polls at 50 Hz (two that agree, and the phase),
    # the answer's way back
    bench.stop_during_homing('axis1', 8.0 / 200.0 + 0.01 + 0.02 + 3 / 50.0 + MIDDLEWARE_S)
    assert not bench.status('axis1', lambda m: not m.moving).homed


def test_save_params_is_verified_by_the_stored_copy(bench):
    import json
    # 1093 Brake Delay Lock is storable (App.1 '**'); change it, save, read the simulated EEPROM
    reg = ReadRegister.Request(address='1093', data_type='u16')
    r = bench.call('axis1', 'read_register', reg, ReadRegister)
    assert r.success, r.message
    new = r.value + 7
    r = bench.call('axis1', 'write_register',
                   WriteRegister.Request(address='1093', data_type='u16', value=new),
                   WriteRegister)
    assert r.success, r.message
    assert not list(bench.storage.glob('*unit1*.json'))
    r = bench.call('axis1', 'save_params')
    assert r.success, r.message
    stored = wait_for(lambda: list(bench.storage.glob('*unit1*.json')), 10.0, 'stored copy')
    data = json.loads(stored[0].read_text())
    flat = json.dumps(data)
    assert f'"1093": {new}' in flat, flat[:800]


def test_raw_write_refused_unless_allowed(bench):
    r = bench.call('axis2', 'write_register',
                   WriteRegister.Request(address='1044', data_type='i32', value=1), WriteRegister)
    assert not r.success and 'allow_raw_write' in r.message
    r = bench.call('axis1', 'read_register', ReadRegister.Request(address='1001', data_type='u16'),
                   ReadRegister)
    assert r.success and r.value == bench.status('axis1').status_word
    r = bench.call('axis1', 'read_register', ReadRegister.Request(address='1003', data_type='u16'),
                   ReadRegister)
    assert not r.success and '1003' in r.message


def test_simulator_restart_reconnects_and_stays_stopped(bench):
    bench.enable('axis1')
    bench.command('axis1', 'velocity_command', 3.0)
    bench.status('axis1', lambda m: m.moving, what='running')
    bench.sim.kill()
    st = bench.status('axis1', lambda m: m.state == 'DISCONNECTED', what='DISCONNECTED')
    assert not st.connected
    bench.ros.wait_msg('/diagnostics', lambda a: any(
        s.name.endswith('link') and s.level == DiagnosticStatus.ERROR for s in a.status))
    bench.start_sim()
    st = bench.status('axis1', lambda m: m.connected, timeout_s=15.0, what='reconnected')
    assert st.state == 'SWITCH ON DISABLED' and not st.moving
    # nothing resumed: the position stays where the (power-cycled) simulator put it
    before = bench.true_steps('axis1')
    bench.status('axis1', lambda m: m.link_reconnects >= 1)
    assert bench.status('axis1').position_steps == pytest.approx(before, abs=1)
    assert not bench.status('axis1').enabled


def test_sigterm_stops_and_disables(bench):
    bench.sigterm_while_running(3.0)
    # the drive is left stopped and disabled: ask it over Modbus directly
    from pymodbus.client import ModbusTcpClient
    c = ModbusTcpClient('127.0.0.1', port=bench.port, timeout=2)
    assert c.connect()
    try:
        sw = c.read_holding_registers(1001, count=1, device_id=1).registers[0]
        assert sw & 0x004F == 0x0040 or sw & 0x006F == 0x0021, hex(sw)   # SOD or RTSO
        p1 = bench.true_steps('axis1')
        wait_for(lambda: bench.true_steps('axis1') == p1, 2.0, 'standstill')
    finally:
        c.close()


def test_bad_parameter_fails_start_up_with_one_line(procs, tmp_path):
    out = bad_parameter_output(procs, tmp_path, 'xplus_mt', 'unit_id: 2', 'unit_id: 300')
    assert out[-1] == ('xplus_mt_node: parameter drives.axis2.unit_id: 300 is out of range '
                       '(allowed: an integer from 0 to 255)'), out


def test_link_cut_during_velocity_run_ends_stopped_not_resumed(procs, ros, tmp_path):
    # the drive's own watchdog (1097) off: this is about the node's watchdog after a reconnect
    bench = XplusBench(procs, ros, tmp_path, node_args=('-p', 'drives.axis1.watchdog_ms:=0'))
    bench.enable('axis1')
    bench.command('axis1', 'velocity_command', 3.0)
    bench.status('axis1', lambda m: m.moving, what='running')
    bench.inject('axis1', 'cut')
    bench.status('axis1', lambda m: m.state == 'DISCONNECTED', what='DISCONNECTED')
    bench.inject('axis1', 'link_ok')
    # the drive kept running on its own while the link was down; once back, the node's watchdog
    # (the last velocity_command is long past command_timeout_s) stops it, and nothing restarts it
    st = bench.status('axis1', lambda m: m.connected and not m.moving, timeout_s=15.0,
                      what='reconnected and stopped')
    assert st.state == 'OPERATION ENABLED' and abs(st.velocity) < 1e-6
    bench.node.wait_line('velocity watchdog', 5.0)
    p1 = bench.true_steps('axis1')
    wait_for(lambda: abs(bench.ros.wait_msg(f'{SIM}/axis1/true_position_steps').data - p1) < 1
             and bench.status('axis1').link_reconnects >= 1, 5.0, 'standstill after reconnect')


def test_runtime_parameters_take_effect_and_are_checked(bench):
    bench.enable('axis1')
    # cross-field rule: max_velocity below profile_velocity (12 rad/s) is refused with the reason
    (r,) = bench.set_params(('drives.axis1.max_velocity', 5.0))
    assert not r.successful and 'drives.axis1.profile_velocity' in r.reason
    # range of the descriptor
    (r,) = bench.set_params(('drives.axis1.max_velocity', -1.0))
    assert not r.successful
    # bus settings are read-only after start
    (r,) = bench.set_params(('port', 1))
    assert not r.successful and 'read-only' in r.reason
    (r,) = bench.set_params(('drives.axis1.max_velocity', 20.0))
    assert r.successful, r.reason
    bench.command('axis1', 'velocity_command', 25.0)
    st = bench.status('axis1', lambda m: 'exceeds max_velocity (20)' in m.last_refusal)
    assert not st.moving
    # a slower profile makes the same move take longer: profile_velocity 1 rad/s, 0.5 rad
    (r,) = bench.set_params(('drives.axis1.profile_velocity', 1.0))
    assert r.successful, r.reason
    bench.command('axis1', 'position_command', 0.5)
    st = bench.status('axis1', lambda m: m.moving and m.velocity > 0.5, what='moving')
    assert st.velocity == pytest.approx(1.0, abs=0.05)


def test_joint_command_moves_several_drives_by_joint_name(bench):
    from sensor_msgs.msg import JointState
    bench.enable('axis1')
    bench.enable('axis2')
    # one jump of 2 rad, not a stream: the start guard (0.1 rad by default) widened
    assert all(r.successful for r in bench.set_params(
        *[(f'drives.{d}.joint_command_max_start_offset', 5.0) for d in ('axis1', 'axis2')]))
    js = JointState(name=['xplus_joint2', 'xplus_joint1', 'unknown'],
                    position=[-1.0, 2.0, 0.0])
    bench.ros.publish(JointState, '/joint_command', js)
    bench.status('axis1', lambda m: not m.moving and abs(m.position - 2.0) < 1e-3,
                 what='xplus_joint1')
    bench.status('axis2', lambda m: not m.moving and abs(m.position + 1.0) < 1e-3,
                 what='xplus_joint2')
    # velocity field where position is NaN
    js = JointState(name=['xplus_joint1'], position=[math.nan], velocity=[2.0])
    bench.ros.publish(JointState, '/joint_command', js)
    bench.status('axis1', lambda m: m.moving and m.velocity > 1.5,
                 what='xplus_joint1 velocity')
    bench.status('axis1', lambda m: not m.moving, what='watchdog stop')


def test_move_to_and_homing_actions_give_feedback_and_result(bench):
    import threading

    from rclpy.action import ActionClient
    from stepper_drivers_msgs.action import Home, MoveTo
    bench.enable('axis1')
    feedback = []
    client = ActionClient(bench.ros.node, MoveTo, NODE + '/axis1/move_to')
    assert client.wait_for_server(timeout_sec=10)
    done = threading.Event()
    # in_spin: rclpy's ActionClient races its own executor when called from another thread
    goal_future = bench.ros.in_spin(client.send_goal_async, MoveTo.Goal(position=4.0),
                                    feedback_callback=lambda f: feedback.append(f.feedback))
    goal_future.add_done_callback(lambda _f: done.set())
    assert done.wait(10) and goal_future.result().accepted
    result_future = bench.ros.in_spin(goal_future.result().get_result_async)
    got = threading.Event()
    result_future.add_done_callback(lambda _f: got.set())
    assert got.wait(20)
    result = result_future.result().result
    assert result.success, result.message
    assert result.final_position == pytest.approx(4.0, abs=1e-3)
    # the last feedback may come from a snapshot at the target (within the 2-step tolerance,
    # 1e-3 rad), before the result is decided
    assert feedback and all(-1e-3 <= f.distance_remaining <= 4.0 for f in feedback[1:])
    home = ActionClient(bench.ros.node, Home, NODE + '/axis1/homing')
    assert home.wait_for_server(timeout_sec=10)
    done.clear()
    goal_future = bench.ros.in_spin(home.send_goal_async, Home.Goal())
    goal_future.add_done_callback(lambda _f: done.set())
    assert done.wait(10) and goal_future.result().accepted
    result_future = bench.ros.in_spin(goal_future.result().get_result_async)
    got.clear()
    result_future.add_done_callback(lambda _f: got.set())
    assert got.wait(30)
    result = result_future.result().result
    assert result.success and 'homed' in result.message
    assert bench.status('axis1', lambda m: m.homed).homing_state == 'ATTAINED'
    client.destroy()   # before the test's ROS client goes: its executor waits on them
    home.destroy()


def test_a_move_to_goal_running_when_the_node_is_stopped_gets_its_result(bench):
    """SIGTERM during a move_to goal: the result (ABORTED, the reason) reaches the client
    before the node ends with exit code 0."""
    import threading

    from action_msgs.msg import GoalStatus
    from rclpy.action import ActionClient
    from stepper_drivers_msgs.action import MoveTo
    bench.enable('axis1')
    client = ActionClient(bench.ros.node, MoveTo, NODE + '/axis1/move_to')
    assert client.wait_for_server(timeout_sec=10)
    sent = threading.Event()
    goal_future = bench.ros.in_spin(client.send_goal_async, MoveTo.Goal(position=50.0))
    goal_future.add_done_callback(lambda _f: sent.set())
    assert sent.wait(10) and goal_future.result().accepted
    result_future = bench.ros.in_spin(goal_future.result().get_result_async)
    got = threading.Event()
    result_future.add_done_callback(lambda _f: got.set())
    bench.status('axis1', lambda m: m.moving, what='moving to 50 rad')   # 4 s at 12 rad/s
    assert bench.node.stop(signal.SIGTERM) == 0
    assert got.wait(2.0), 'no move_to result before the node ended'
    assert result_future.result().status == GoalStatus.STATUS_ABORTED
    result = result_future.result().result
    assert not result.success and result.message == 'axis1: the node is shutting down', result
    bench.ros.in_spin(client.destroy)


def test_status_carries_address_and_diagnostics_identity(bench):
    st = bench.status('axis2')
    assert (st.vendor, st.address, st.joint_name) == ('X-PLUS MT', '2', 'xplus_joint2')
    diag = bench.ros.wait_msg('/diagnostics',
                              lambda a: any(s.name.endswith('axis2') for s in a.status))
    (d,) = [s for s in diag.status if s.name.endswith('axis2')]
    keys = {kv.key: kv.value for kv in d.values}
    assert keys['state'] == 'SWITCH ON DISABLED' and keys['joint'] == 'xplus_joint2'
    assert d.level == DiagnosticStatus.OK


def test_diagnostics_go_out_at_their_rate_from_the_poll_cycles(bench):
    # config/xplus_mt.yaml: publish_rate_hz 50, diagnostics_rate_hz 1 (the default). The
    # owner thread publishes /diagnostics at the first poll cycle at or after it is due (the
    # executor has no timer): every interval is the period give or take a poll period (the stamp
    # is read when the message is built, after the cycle's joint_states and statuses).
    period_s, poll_s = 1.0, 1.0 / 50.0
    bench.ros.subscribe(DiagnosticArray, '/diagnostics', keep=True)

    def stamps():
        with bench.ros.lock:
            msgs = list(bench.ros.history.get('/diagnostics', []))
        return [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in msgs]
    wait_for(lambda: len(stamps()) >= 4, 4 * period_s + 2.0, '4 /diagnostics messages')
    got = stamps()
    gaps = [b - a for a, b in zip(got, got[1:])]
    assert all(period_s - poll_s <= g <= period_s + 3 * poll_s for g in gaps), gaps


def test_homing_that_does_not_finish_times_out_and_stops(bench):
    # method 21 searches the home switch in the negative direction; axis1's switch is on the
    # positive side, so the search runs on until homing.timeout_s
    (a, b) = bench.set_params(('drives.axis1.homing.method', 21),
                              ('drives.axis1.homing.timeout_s', 1.0))
    assert a.successful and b.successful, (a.reason, b.reason)
    bench.enable('axis1')
    r = bench.call('axis1', 'home')
    assert not r.success and 'timed out after 1 s (homing.timeout_s)' in r.message, r.message
    st = bench.status('axis1', lambda m: not m.moving, timeout_s=5.0, what='stopped')
    assert not st.homed and st.position < 0
    # axis2's I0 is a general-purpose input (1088 bit 0 = 1): a switch method is refused up front
    (r,) = bench.set_params(('drives.axis2.homing.method', 19))
    assert r.successful, r.reason
    bench.enable('axis2')
    r = bench.call('axis2', 'home')
    assert not r.success and 'INPUT_CONFIG (1088)' in r.message, r.message


def test_joint_command_with_arrays_that_do_not_match_the_names_is_refused(bench):
    from sensor_msgs.msg import JointState
    bench.enable('axis1')
    bench.enable('axis2')
    before = (bench.fresh_true_steps('axis1'), bench.fresh_true_steps('axis2'))
    # two names, one position: executed index by index, joint2's value would go to joint1
    bench.ros.publish(JointState, '/joint_command',
                      JointState(name=['xplus_joint2', 'xplus_joint1'], position=[1.0]))
    for d in ('axis1', 'axis2'):
        st = bench.status(d, lambda m: '1 position values for 2 names' in m.last_refusal,
                          what=f'{d} refusal')
        assert st.commands_refused >= 1 and not st.moving
    # the next message is a good one (within the start guard's 0.1 rad): had the bad one moved
    # anything, this one shows it
    bench.ros.publish(JointState, '/joint_command',
                      JointState(name=['xplus_joint1'], position=[0.05]))
    bench.status('axis1', lambda m: not m.moving and abs(m.position - 0.05) < 1e-3,
                 what='the good command done')
    assert bench.fresh_true_steps('axis2') == before[1]


def test_two_drives_answering_with_one_identity_are_not_driven(procs, ros, tmp_path):
    """Both unit ids reach one drive (axis2 configured with axis1's unit id): enabling one
    would enable the other, so neither is driven and the status names the parameters."""
    class Unconnected(XplusBench):
        wait_connected = False
    bench = Unconnected(procs, ros, tmp_path, node_args=('-p', 'drives.axis2.unit_id:=1'))
    for d in ('axis1', 'axis2'):
        st = bench.status(d, lambda m: m.not_driven, timeout_s=30.0, what=f'{d} not driven')
        assert 'one identity' in st.not_driven and 'drives.<name>.unit_id' in st.not_driven
        assert not st.connected and st.state == 'DISCONNECTED'
    r = bench.call('axis1', 'enable', SetBool.Request(data=True), SetBool)
    assert not r.success and 'not driven' in r.message, r.message
    assert bench.fresh_true_steps('axis1') == 0
    bench.node.wait_line('answer with one identity', 1.0)


def test_one_node_serves_drives_on_several_hosts(procs, ros, tmp_path):
    """A real X-PLUS MT is its own Modbus TCP server: one node, one connection per drive host
    (drives.<name>.port here; .host the same), each with its own owner thread, so a host that
    drops out does not stall the other."""
    from stepper_drivers_msgs.msg import DriveStatus

    ports = (free_port(), free_port())
    # the simulator's params for any node name: two simulators, two names
    sim_yaml = tmp_path / 'sim.yaml'
    sim_yaml.write_text((CONFIG / 'xplus_mt_sim.yaml').read_text().replace(
        'xplus_mt_sim:', "'/**':", 1))
    sims = []
    for i, port in enumerate(ports):
        storage = tmp_path / f'eeprom{i}'
        storage.mkdir()
        sims.append(procs.start(f'sim{i}', [
            executable('stepper_sim', 'xplus_mt_sim'), '--ros-args', '--params-file',
            str(sim_yaml), '-r', f'__node:=xplus_mt_sim{i}',
            '-p', f'port:={port}', '-p', f'storage_dir:={storage}']))
    for s in sims:
        s.wait_line('ready', 30.0)
    # axis1 on the first host's unit 1, axis2 on the second host's unit 2
    node = procs.start('node', [
        executable('stepper_drivers', 'xplus_mt_node'), '--ros-args', '--params-file',
        str(CONFIG / 'xplus_mt.yaml'), '-p', f'port:={ports[0]}', '-p',
        f'drives.axis2.port:={ports[1]}', '-p', 'reconnect_period_s:=0.2'])
    ros.subscribe(DiagnosticArray, '/diagnostics')
    for d in ('axis1', 'axis2'):
        ros.subscribe(DriveStatus, f'{NODE}/{d}/status')
        ros.wait_msg(f'{NODE}/{d}/status', lambda m: m.connected, 30.0, f'{d} connected')
    ros.subscribe(Float64, '/xplus_mt_sim1/axis2/true_position_steps')
    diag = ros.wait_msg('/diagnostics', lambda a: sum(
        s.name.startswith('xplus_mt_node: link') for s in a.status) == 2, what='two links')
    links = sorted(s.hardware_id for s in diag.status if s.name.startswith('xplus_mt_node: link'))
    assert links == sorted(f'modbus tcp 127.0.0.1:{p}' for p in ports)
    # one joint_states for the node, not one per link
    from sensor_msgs.msg import JointState
    ros.subscribe(JointState, '/joint_states')
    js = ros.wait_msg('/joint_states')
    assert list(js.name) == ['xplus_joint1', 'xplus_joint2']
    r = ros.call(SetBool, f'{NODE}/axis2/enable', SetBool.Request(data=True))
    assert r.success, r.message
    ros.publish(Float64, f'{NODE}/axis2/position_command', Float64(data=1.0))
    ros.wait_msg('/xplus_mt_sim1/axis2/true_position_steps',
                 lambda m: abs(m.data - 12800 / (2 * math.pi)) < 1, what='second host moved')
    # the first host goes away: only axis1 is lost, axis2 keeps being polled
    sims[0].stop()
    ros.wait_msg(f'{NODE}/axis1/status', lambda m: m.state == 'DISCONNECTED', 10.0)
    # /diagnostics goes on (the owner threads publish it) and says so
    ros.wait_msg('/diagnostics', lambda a: any(
        s.name == 'xplus_mt_node: axis1' and s.message == 'DISCONNECTED' for s in a.status),
        5.0, 'axis1 DISCONNECTED in /diagnostics')
    a = ros.wait_msg(f'{NODE}/axis2/status', lambda m: m.connected)
    b = ros.wait_msg(f'{NODE}/axis2/status', lambda m: m.header.stamp.sec > a.header.stamp.sec
                     + 1, 5.0, 'axis2 status going on')
    assert b.connected and b.link_reconnects == 0
    assert node.stop() == 0


def test_a_velocity_write_whose_reply_is_lost_is_still_watched(procs, ros, tmp_path):
    """The velocity write reaches the drive but its reply is lost: the node must assume it ran
    (the watchdog was armed before the write) and stop it once the drive answers again."""
    bench = XplusBench(procs, ros, tmp_path, node_args=(
        '-p', 'drives.axis1.watchdog_ms:=0'))     # the node's watchdog, not the drive's
    bench.enable('axis1')
    track = Track(bench.ros, bench.true_topic('axis1'))
    # the controlword write with New Set Point (bit 4) starts the run (PV, A10): its reply is
    # lost; the write itself takes effect
    bench.inject('axis1', 'lose_write_reply', code=1040, value=0x0010)
    bench.command('axis1', 'velocity_command', 3.0)
    t_cmd = time.monotonic()
    p0 = bench.fresh_true_steps('axis1')
    wait_for(lambda: bench.fresh_true_steps('axis1') > p0 + 100, 5.0, 'the drive runs')
    # the node loses the link on that write (timeout_s 0.5, config/xplus_mt.yaml) and
    # reconnects; by then command_timeout_s (0.5 s) is past, and the watchdog, armed before the
    # write, stops the drive as soon as it answers again: the one transaction, the stop ramp,
    # the simulator's tick and one true-position sample after the reconnect
    still_at = track.wait_still(0.3, 10.0, 'axis1 stopped')
    bench.node.wait_line('velocity watchdog', 1.0)
    wall_minus_mono = time.time() - time.monotonic()
    (line,) = [ln for ln in bench.node.output().splitlines()
               if 'axis1: connected' in ln][1:2]          # the reconnect
    reconnected_at = float(line.split('[')[2].split(']')[0]) - wall_minus_mono
    bound_s = 0.01 + 3.0 / 200.0 + 0.02 + Track.SAMPLE_S + MIDDLEWARE_S
    assert 0.5 <= reconnected_at - t_cmd          # the write's timeout, then the reconnect
    assert still_at - reconnected_at <= bound_s, (still_at - reconnected_at, bound_s)


@pytest.mark.parametrize('args, priority', [((), 10), (('-p', 'owner_thread_priority:=0'), 0)])
def test_owner_thread_priority_runs_the_bus_owner_on_sched_fifo(procs, ros, tmp_path, args,
                                                                 priority):
    """By default (owner_thread_priority 10, as ros2_control's controller_manager asks for
    real-time) one thread of the node, its bus owner (one bus), is on SCHED_FIFO at priority 10,
    and the node moves a drive as before; 0 turns it off. Where the machine refuses (no
    CAP_SYS_NICE, no rtprio limit), the node says so in one line naming the parameter and the
    limits file, and no thread is."""
    class DefaultPriority(XplusBench):
        owner_priority_args = ()                  # the shipped default

    bench = DefaultPriority(procs, ros, tmp_path, node_args=args)
    fifo = {}
    for task in (pathlib.Path('/proc') / str(bench.node.pid) / 'task').iterdir():
        fields = (task / 'stat').read_text().rsplit(')', 1)[1].split()   # from field 3 on
        policy, rt_priority = int(fields[41 - 3]), int(fields[40 - 3])
        if policy == os.SCHED_FIFO:
            fifo[task.name] = rt_priority
    if priority and fifo_allowed(priority):
        assert list(fifo.values()) == [priority], fifo
    else:
        assert not fifo
    if priority and not fifo_allowed(priority):
        bench.node.wait_line('owner_thread_priority 10: SCHED_FIFO refused', 5.0)
        assert '/etc/security/limits.conf' in bench.node.output()
    bench.enable('axis1')
    bench.command('axis1', 'position_command', 1.0)
    bench.status('axis1', lambda m: not m.moving and abs(m.position - 1.0) < 1e-3,
                 what='axis1 at 1.0 rad')


class LateControlword:
    """An X-PLUS MT that takes a controlword a while after it acknowledged it: a TCP relay
    between the node and the simulator that, once armed, answers the next write of the
    controlword (1040) with bit 4 set as the drive does (FC06: the echo of the request) and hands
    that write to the simulator `lag_s` later, over a connection of its own (pymodbus); every
    other request and reply passes unchanged. The node sees a drive whose statusword shows the
    previous homing for lag_s after the homing's start edge."""

    def __init__(self, upstream_port, lag_s):
        import socket
        import threading
        self.upstream_port, self.lag_s = upstream_port, lag_s
        self.armed = threading.Event()
        self.taken_at = None               # time.monotonic() the simulator got the late write
        self._listener = socket.create_server(('127.0.0.1', 0))
        self.port = self._listener.getsockname()[1]
        self._threading, self._socket = threading, socket
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return                     # closed
            try:
                upstream = self._socket.create_connection(('127.0.0.1', self.upstream_port()))
            except OSError:
                client.close()
                continue
            for pump in (self._requests, self._replies):
                self._threading.Thread(target=pump, args=(client, upstream), daemon=True).start()

    def _requests(self, client, upstream):
        buf = b''
        try:
            while chunk := client.recv(260):
                buf += chunk
                while len(buf) >= 7 and len(buf) >= 6 + int.from_bytes(buf[4:6], 'big'):
                    end = 6 + int.from_bytes(buf[4:6], 'big')
                    frame, buf = buf[:end], buf[end:]
                    function, address, value = frame[7], frame[8:10], frame[10:12]
                    if self.armed.is_set() and function == 6 and \
                            int.from_bytes(address, 'big') == 1040 and value[1] & 0x10:
                        self.armed.clear()
                        client.sendall(frame)                   # FC06's reply: the echo
                        self._threading.Timer(self.lag_s, self._write, (
                            frame[6], int.from_bytes(value, 'big'))).start()
                    else:
                        upstream.sendall(frame)
        except OSError:
            pass
        finally:
            client.close()
            upstream.close()

    @staticmethod
    def _replies(client, upstream):
        try:
            while chunk := upstream.recv(260):
                client.sendall(chunk)
        except OSError:
            pass

    def _write(self, unit, value):
        from pymodbus.client import ModbusTcpClient
        mb = ModbusTcpClient('127.0.0.1', port=self.upstream_port(), timeout=1.0, retries=0)
        try:
            assert mb.connect()
            assert not mb.write_register(1040, value, device_id=unit).isError()
            self.taken_at = time.monotonic()
        finally:
            mb.close()

    def close(self):
        self._listener.close()


def test_a_homing_the_drive_shows_late_is_answered_by_its_own_end(procs, ros, tmp_path):
    """A homing after another one and a move: the drive still shows the first homing's result
    (ATTAINED, homing mode) when the start edge is written, and acknowledges that write, but
    runs the new homing only a moment later (here 0.6 of the driver's start check's time:
    still in it). `home` answers once this homing ended (at the home position), from
    snapshots after its start, and not with the position the axis was leaving ("homed at -1"),
    which would let a caller move an axis that is still homing."""
    from stepper_drivers.vendors.xplus_mt import XplusMtDrive

    class Lagging(XplusBench):
        def __init__(self, procs, ros, tmp_path):
            self.relay = LateControlword(lambda: self.port,
                                         0.6 * XplusMtDrive.HANDSHAKE_TIMEOUT_S)
            super().__init__(procs, ros, tmp_path, node_args=('-p', f'port:={self.relay.port}'))

    bench = Lagging(procs, ros, tmp_path)
    try:
        bench.enable('axis1')
        r = bench.call('axis1', 'home')
        assert r.success and r.message.startswith('axis1: homed at 0 '), r.message
        r = bench.move_to('axis1', -1.0)
        assert r.success, r.message
        status = f'{bench.node_ns}/axis1/status'
        bench.relay.armed.set()
        r = bench.call('axis1', 'home')
        answered_at = time.monotonic()
        with bench.ros.lock:
            st = bench.ros.latest[status]           # what the client had by the answer
        assert not bench.relay.armed.is_set(), 'the start edge did not go through the relay'
        assert r.success and r.message.startswith('axis1: homed at 0 '), r.message
        assert bench.relay.taken_at is not None and bench.relay.taken_at < answered_at
        assert st.homing_state == 'ATTAINED' and st.position == pytest.approx(0.0, abs=1e-3), st
        assert abs(bench.fresh_true_steps('axis1')) < 1
    finally:
        bench.relay.close()
