"""X-MIND K end to end: xmind_k_sim and xmind_k_node as separate processes, driven through ROS.

Three drives on one simulated RS-485 line (a pty). Every check goes through the node's topics and
services; the simulator's true position topic and fault injection play the real world. Line
timing is off except where the test is about it (it makes a 9600 baud line 20x slower).
"""

import math
import time

from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from rigs_vendors import XMIND_DRIVES, XmindBench
from rosharness import Track, bad_parameter_output, wait_for, watchdog_bound_s
from stepper_drivers_msgs.srv import ReadRegister, WriteRegister

NODE = '/xmind_k_node'
STEPS_PER_RAD = 2000 / (2 * math.pi)
DRIVES = XMIND_DRIVES


@pytest.fixture
def bench(procs, ros, tmp_path):
    return XmindBench(procs, ros, tmp_path)


def test_three_drives_move_home_with_line_timing_and_busy_silence(procs, ros, tmp_path):
    b = XmindBench(procs, ros, tmp_path, line_timing=True)
    for d in DRIVES:
        st = b.status(d)
        assert st.vendor == 'X-MIND K' and st.address == f'0{DRIVES.index(d) + 1}'
        assert st.state == 'SWITCH ON DISABLED' and not st.enabled and not st.velocity_valid
    b.enable('axis1')
    before = b.true_steps('axis1')
    assert abs(before) < 1
    # A 3 rad move (955 steps) at 20 rad/s: the drive is silent while it runs (§3); the node
    # shows an estimated position, keeps the link up, and corrects it by QA at the end.
    b.command('axis1', 'position_command', 3.0)
    st = b.status('axis1', lambda m: not m.moving and not m.position_estimated
                  and m.position_steps == 955, timeout_s=10.0, what='axis1 at 955 steps')
    during = [m for m in ros.history[f'{NODE}/axis1/status'] if m.moving]
    assert during and all(m.position_estimated and m.connected for m in during)
    assert during[0].mode == 'HIGH RESOLUTION INDEXED RUN WITH RAMP'
    assert abs(b.fresh_true_steps('axis1') - 955) < 0.5
    if st.link_errors:                  # say which kind of error, for the one who reads it
        diag = ros.wait_msg('/diagnostics', lambda a: any(
            s.name.endswith('link') for s in a.status))
        link = {kv.key: kv.value for s in diag.status if s.name.endswith('link')
                for kv in s.values}
        raise AssertionError(f'a busy drive is silent by design, not a link error: {link}')
    history = ros.history[f'{NODE}/axis1/status']
    assert all(m.connected for m in history[-50:])
    assert b.true_steps('axis2') == 0 and b.true_steps('axis3') == 0
    # Zero search on PX (edge at raw 3000 steps, + direction), then counter reset (§7.6)
    r = b.call('axis1', 'home')
    assert r.success, r.message
    assert 'zero search' in r.message and 'homed' in r.message
    st = b.status('axis1', lambda m: m.homed and not m.moving)
    assert st.homing_state == 'ATTAINED' and st.position_steps == 0
    assert b.fresh_true_steps('axis1') == pytest.approx(0.0, abs=0.5)
    # axis3 homes without a switch (method 60: RA); axis2 in - direction; homing needs the
    # drive enabled (a disabled drive must not home and move)
    r = b.call('axis3', 'home')
    assert not r.success and 'not enabled' in r.message, r.message
    b.enable('axis3')
    b.enable('axis2')
    r = b.call('axis3', 'home')
    assert r.success and 'counter reset' in r.message, r.message
    r = b.call('axis2', 'home')
    assert r.success, r.message
    js = ros.wait_msg('/joint_states')
    assert list(js.name) == ['xmind_joint1', 'xmind_joint2', 'xmind_joint3']
    assert all(math.isnan(v) for v in js.velocity), 'X-MIND K has no velocity readback'


def test_velocity_change_and_watchdog_stop(bench):
    bench.enable('axis1')
    track = Track(bench.ros, bench.true_topic('axis1'))
    last_command = [0.0]

    def commanding(velocity, cond, what):
        """Keep commanding (as a client does, faster than command_timeout_s) until cond."""
        def check():
            bench.command('axis1', 'velocity_command', velocity)
            last_command[0] = time.monotonic()
            return cond()
        wait_for(check, 10.0, what, period_s=0.1)

    # 6 rad/s = 1909 Hz: an unramped free run (22) on the Table 4 grid (1900 Hz)
    commanding(6.0, lambda: bench.status('axis1').velocity > 5.0, 'axis1 running')
    p0 = bench.fresh_true_steps('axis1')
    commanding(6.0, lambda: bench.fresh_true_steps('axis1') > p0 + 50, 'true position rising')
    # a new direction: ES, wait until the drive answers again, rewrite cell 229, PS again
    commanding(-6.0, lambda: bench.status('axis1').velocity < -5.0, 'running backwards')
    p1 = bench.fresh_true_steps('axis1')
    commanding(-6.0, lambda: bench.fresh_true_steps('axis1') < p1 - 50, 'true position falling')
    # no more commands: the watchdog stops it (ES). command_timeout_s 0.5 (config), 20 Hz polls
    # (this bench), 400 rad/s^2, and at 9600 baud one string in flight (up to ~61 ms) plus the
    # ES itself (~26 ms)
    bound_s = watchdog_bound_s(0.5, 20.0, 6.0, 400.0, 0.1)
    still_at = track.wait_still(0.3, bound_s + 3.0, 'axis1 stopped')
    assert still_at - last_command[0] <= bound_s, (still_at - last_command[0], bound_s)
    st = bench.status('axis1', lambda m: not m.moving, timeout_s=1.0, what='watchdog stop')
    bench.node.wait_line('velocity watchdog', 1.0)
    still = bench.fresh_true_steps('axis1')
    assert bench.fresh_true_steps('axis1') == still
    st = bench.status('axis1', lambda m: not m.position_estimated)
    assert st.position_steps == pytest.approx(still, abs=0.5) and st.enabled


def test_commands_refused_nan_limits_not_enabled_and_drive_range(bench):
    bench.command('axis1', 'position_command', 1.0)
    st = bench.status('axis1', lambda m: 'not enabled' in m.last_refusal)
    assert st.commands_refused >= 1
    bench.enable('axis1')
    bench.command('axis1', 'position_command', math.nan)
    bench.status('axis1', lambda m: 'finite' in m.last_refusal)
    bench.command('axis1', 'position_command', 1000.0)
    bench.status('axis1', lambda m: 'min_position..max_position' in m.last_refusal)
    bench.command('axis1', 'velocity_command', -100.0)
    st = bench.status('axis1', lambda m: 'max_velocity' in m.last_refusal)
    assert st.commands_refused >= 4 and not st.moving
    # what the drive itself cannot do: 80 rad/s = 25465 Hz > 24000 Hz (§4.1.2)
    bench.set_param('drives.axis1.max_velocity', 100.0)
    bench.set_param('drives.axis1.profile_velocity', 80.0)
    bench.command('axis1', 'position_command', 2.0)
    bench.node.wait_line('exceeds the X-MIND K maximum of 24000 Hz', 5.0)
    assert abs(bench.fresh_true_steps('axis1')) < 1


def test_pty_cut_and_restored_reconnects_and_stays_stopped(bench):
    bench.enable('axis1')
    bench.command('axis1', 'position_command', 1.0)
    bench.status('axis1', lambda m: not m.moving and m.position_steps == 318,
                 what='axis1 at 1 rad')
    bench.inject('', 'cut')
    st = bench.status('axis1', lambda m: m.state == 'DISCONNECTED', what='DISCONNECTED')
    assert not st.connected
    bench.ros.wait_msg('/diagnostics', lambda a: any(
        s.name.endswith('link') and s.level == DiagnosticStatus.ERROR for s in a.status))
    bench.command('axis1', 'position_command', 2.0)
    bench.status('axis1', lambda m: 'DISCONNECTED' in m.last_refusal)
    bench.inject('', 'link_ok')
    st = bench.status('axis1', lambda m: m.connected, timeout_s=15.0, what='reconnected')
    assert not st.moving and st.position_steps == 318
    assert st.enabled, 'no power cycle (flag F7 kept): the drive stayed enabled'
    assert bench.fresh_true_steps('axis1') == pytest.approx(318, abs=0.5)
    bench.command('axis1', 'position_command', 0.5)
    bench.status('axis1', lambda m: not m.moving and m.position_steps == 159, what='moves again')


def test_power_cycle_behind_a_lost_link_raises_the_alarm(bench):
    """A real power cycle silences the drive first (a lost link); after the
    reconnect the alarm must be there, in status and diagnostics, until the next homing."""
    def diag(drive, cond):
        return bench.ros.wait_msg('/diagnostics', lambda a: any(
            s.name.endswith(f': {drive}') and cond(s) for s in a.status), 10.0,
            f'{drive} diagnostics')

    bench.enable('axis3')
    r = bench.call('axis3', 'home')                 # method 60: the counter is reset here
    assert r.success, r.message
    bench.command('axis3', 'position_command', 1.0)
    bench.status('axis3', lambda m: m.homed and not m.moving and m.position_steps == 318,
                 what='axis3 homed at 1 rad')
    diag('axis3', lambda s: s.level == DiagnosticStatus.OK)
    bench.inject('', 'cut')
    bench.status('axis3', lambda m: m.state == 'DISCONNECTED', what='DISCONNECTED')
    bench.inject('axis3', 'power_cycle')            # the drive restarts while the line is down
    bench.inject('', 'link_ok')
    st = bench.status('axis3', lambda m: m.connected, timeout_s=15.0, what='reconnected')
    assert st.position_steps == 0 and not st.homed and not st.enabled
    assert [a for a in st.alarms if a.startswith('power cycle detected')], st.alarms
    d = diag('axis3', lambda s: s.level == DiagnosticStatus.WARN)
    (status,) = [s for s in d.status if s.name.endswith(': axis3')]
    assert 'power cycle detected' in status.message and 'home again' in status.message
    assert not bench.status('axis1', lambda m: m.connected).alarms, 'axis1 kept its power'
    r = bench.call('axis3', 'home')
    assert not r.success and 'not enabled' in r.message, r.message
    bench.enable('axis3')
    r = bench.call('axis3', 'home')
    assert r.success, r.message
    bench.status('axis3', lambda m: m.homed and not m.alarms, what='alarm cleared by homing')
    diag('axis3', lambda s: s.level == DiagnosticStatus.OK)


def test_garbled_and_lost_replies_are_survived(bench):
    bench.enable('axis2')
    before = bench.status('axis2')
    # One fault at a time (the simulated line holds one), injected while the drives are idle so
    # that every poll expects an answer: garbled answers count as link errors, a lost answer as
    # a silence (a busy drive is silent too, so silence alone is no error).
    bench.inject('', 'corrupt_reply', code=3)
    bench.status('axis2', lambda m: m.link_errors >= before.link_errors + 3, timeout_s=15.0,
                 what='3 garbled replies counted')

    def silences():
        diag = bench.ros.wait_msg('/diagnostics', lambda a: any(
            s.name.endswith('link') for s in a.status))
        (link,) = [s for s in diag.status if s.name.endswith('link')]
        return int({kv.key: kv.value for kv in link.values}['silences'])
    silent = silences()
    bench.inject('', 'no_reply', code=1)
    wait_for(lambda: silences() > silent, 15.0, 'the lost reply counted as a silence')
    bench.command('axis2', 'position_command', -2.0)
    bench.status('axis2', lambda m: not m.moving and m.position_steps == -637,
                 timeout_s=15.0, what='axis2 at -2 rad')
    history = bench.ros.history[f'{NODE}/axis2/status']
    # the statuses since the enable, by the whole stamp: the start-up's DISCONNECTED may share
    # the enable's second
    since = (before.header.stamp.sec, before.header.stamp.nanosec)
    lost = [m for m in history
            if (m.header.stamp.sec, m.header.stamp.nanosec) >= since and not m.connected]
    assert not lost, f'{lost[0]}\n{bench.node.output()[-3000:]}'
    assert bench.fresh_true_steps('axis2') == pytest.approx(-637, abs=0.5)


def test_fault_reset_refused_power_cycle_and_save_params(bench):
    bench.enable('axis1')
    bench.inject('axis1', 'drive_fault')
    st = bench.status('axis1', lambda m: m.fault, what='FA off in status')
    assert st.state == 'FAULT' and 'protection' in st.fault_text
    r = bench.call('axis1', 'fault_reset')
    assert not r.success
    assert 'X-MIND K has no fault reset command; clear the cause and power-cycle' in r.message
    bench.command('axis1', 'position_command', 1.0)
    bench.status('axis1', lambda m: 'FAULT' in m.last_refusal)
    bench.inject('axis1', 'clear_fault')            # the cause is gone and the drive restarted
    st = bench.status('axis1', lambda m: not m.fault, timeout_s=5.0, what='FA back')
    assert not st.enabled and not st.homed and 'power cycle' in ' '.join(st.alarms)
    r = bench.call('axis1', 'save_params')
    assert r.success and 'no save command' in r.message and 'RS D2' in r.message, r.message
    r = bench.call('axis1', 'read_register', ReadRegister.Request(address='QS,RD', data_type='u8'),
                   ReadRegister)
    assert r.success and r.value == 10, r.message
    req = ReadRegister.Request(address='QM,228', data_type='string')
    r = bench.call('axis1', 'read_register', req, ReadRegister)
    assert r.success and r.text == '01QM,228,00,000', r.text
    r = bench.call('axis1', 'write_register',
                   WriteRegister.Request(address='SO,O2', data_type='u8', value=1), WriteRegister)
    assert r.success, r.message
    r = bench.call('axis1', 'read_register', ReadRegister.Request(address='QO,O2', data_type='u8'),
                   ReadRegister)
    assert r.success and r.value == 1
    r = bench.call('axis2', 'write_register', WriteRegister.Request(address='SA', data_type='i32',
                                                                    value=5), WriteRegister)
    assert not r.success and 'allow_raw_write' in r.message


def test_sigterm_stops_and_disables_every_drive(bench):
    bench.sigterm_while_running(20.0, ('axis1', 'axis2'))      # ramped free runs (32)
    p = {d: bench.fresh_true_steps(d) for d in ('axis1', 'axis2')}
    assert all(bench.fresh_true_steps(d) == p[d] for d in p), 'still moving after shutdown'
    # CY/CN cannot be read back over the line: the simulator logs the current
    for d in DRIVES:
        bench.sim.wait_line(f'{d}: motor current OFF (CN)', 5.0)
    assert 'shutdown:' not in bench.node.output(), bench.node.output()[-2000:]


def test_bad_parameter_fails_start_up_with_one_line(procs, tmp_path):
    last = bad_parameter_output(procs, tmp_path, 'xmind_k', 'method: -3 ', 'method: 35 ')[-1]
    assert last.startswith('xmind_k_node: parameter drives.axis2.homing.method: 35 is not an '
                           'X-MIND K method (allowed: 3 = zero search'), last


def test_line_noise_during_reconnects_is_a_link_error_not_another_device(bench):
    """The field's fault soak: for seconds every answer has one character garbled
    ('02?S,RS,D2' for '02QS,RS,D2'), then the line is clean. The drives are DISCONNECTED
    meanwhile and reconnected on the normal back-off, never "not driven", and they are back
    without a restart."""
    histories = {d: bench.ros.history[f'{NODE}/{d}/status'] for d in DRIVES}
    bench.inject('', 'corrupt_reply')                         # every answer, until link_ok
    for d in DRIVES:
        bench.status(d, lambda m: not m.connected, timeout_s=15.0,
                     what=f'{d}: the link lost to the noise')
    start = {d: len(h) for d, h in histories.items()}
    time.sleep(4.0)        # reconnects every 0.2 s, doubling to 1.6 s: several attempts
    bench.inject('', 'link_ok')
    for d in DRIVES:
        st = bench.status(d, lambda m: m.connected, timeout_s=15.0,
                          what=f'{d} back without a restart')
        assert st.not_driven == '' and st.link_reconnects >= 1
        noisy = histories[d][start[d]:]
        assert noisy and all(m.not_driven == '' for m in noisy), [m.not_driven for m in noisy]
    log = bench.node.output()
    assert '02?S,RS,D2' in log and 'not driven' not in log, log[-3000:]


def test_a_trajectory_with_broadcast_start_starts_its_joints_by_one_broadcast(
        procs, ros, tmp_path):
    """broadcast_start true (the line holds these three drives only): once the node's line probe
    found no other address answering, a follow_joint_trajectory goal of the three joints runs
    as one chain per drive (two runs each, through both points), stored in every drive and
    started by one broadcast 99PS (the simulator logs each broadcast string it heard), and they
    end where the goal says."""
    from builtin_interfaces.msg import Duration
    from control_msgs.action import FollowJointTrajectory
    from rosharness import TrajectoryGoal
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    b = XmindBench(procs, ros, tmp_path, line_timing=True, node_args=(
        '-p', 'broadcast_start:=true', '-p', 'broadcast_probe_wait_ms:=10',
        '-p', 'timeout_s:=0.06'))       # the probe: 45 silent addresses of 10 ms + this each
    wait_for(lambda: 'line probe: no answer' in b.node.output(), 15.0, 'the line probe')
    for d in DRIVES:
        b.enable(d)
    joints = [f'xmind_joint{i}' for i in (1, 2, 3)]
    points = [(1.6, [1.0, -0.8, 0.6]), (3.2, [0.3, 0.2, -0.4])]     # 1.27 s at least (3 axes)
    goal = FollowJointTrajectory.Goal(trajectory=JointTrajectory(joint_names=joints, points=[
        JointTrajectoryPoint(positions=p, time_from_start=Duration(
            sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))) for t, p in points]))
    c = TrajectoryGoal(b, goal)
    result = c.result(10.0)
    assert result.error_code == 0, result.error_string
    assert b.sim.output().count('broadcast 99PS,228') == 1, b.sim.output()[-2000:]
    assert 'points followed as one chain of 2 runs per joint' in b.node.output()
    for d, want in zip(DRIVES, points[-1][1]):
        assert b.fresh_true_steps(d) == pytest.approx(want * STEPS_PER_RAD, abs=1.0)
