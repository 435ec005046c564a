"""Trajectories end to end: ~/joint_trajectory and ~/follow_joint_trajectory of the
vendor nodes against the simulators, as separate processes.

Arrival is measured on the simulators' own axes (their true position topics, 20 Hz): the first
sample of the final standstill. Bounds come from the settings: the node's poll period, one line
transaction, one true-position sample and the middleware hops of the measurement.
"""

import math
import re
import signal
import sys
import threading
import time

from action_msgs.msg import GoalStatus
from builtin_interfaces.msg import Duration
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTolerance
from lifecycle_msgs.msg import Transition
import pytest
from rigs_lifecycle import XplusLifecycle
from rigs_trajectory import log_lines, logged, rejected
from rigs_vendors import Rd4Bench, VectorRig, XmindBench, XplusBench
from rosharness import MIDDLEWARE_S, ROOT, Track, wait_for
from rosharness import TrajectoryGoal as Goal
from stepper_drivers_msgs.msg import DriveStatus
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

RD4_STEPS_PER_RAD = 1024 / (2 * math.pi)
XPLUS_STEPS_PER_RAD = 12800 / (2 * math.pi)
VECTOR_STEPS_PER_RAD = 3200 / (2 * math.pi)
XMIND_STEPS_PER_RAD = 2000 / (2 * math.pi)


def trajectory(joints, points):
    """points: [(time_from_start_s, [positions])]"""
    msg = JointTrajectory(joint_names=list(joints))
    for t, positions in points:
        sec = int(t)
        msg.points.append(JointTrajectoryPoint(
            positions=[float(p) for p in positions],
            time_from_start=Duration(sec=sec, nanosec=int(round((t - sec) * 1e9)))))
    return msg


class Rd4LineBench(Rd4Bench):
    """Two RD4 units on one line with the simulator's 19200-baud line timing, polled at 10 Hz
    (config/rd4.yaml)."""

    node_extra_args = ('-p', 'timeout_s:=0.3')

    def sim_args(self):
        return super().sim_args() + ['-p', 'line_timing:=true']


@pytest.fixture
def rd4(procs, ros, tmp_path):
    return Rd4LineBench(procs, ros, tmp_path)


@pytest.fixture
def xplus(procs, ros, tmp_path):
    return XplusBench(procs, ros, tmp_path)


def test_rd4_axes_on_one_line_arrive_together(rd4):
    """Both units start from 0; their moves go out one after the other on the line, yet they
    arrive together: the second one's profile is computed for the time left."""
    rate_hz = 10.0                                 # config/rd4.yaml publish_rate_hz
    transaction_s = 0.025                          # an FC16 of 4 registers at 19200, with t3.5
    for d in rd4.drives:
        rd4.enable(d)
    tracks = {d: Track(rd4.ros, rd4.true_topic(d)) for d in rd4.drives}
    t0 = time.monotonic()
    rd4.ros.publish(JointTrajectory, '/rd4_node/joint_trajectory',
                    trajectory(['rd4_joint1', 'rd4_joint2'], [(1.5, [3.0, 1.0])]))
    arrived = {d: tracks[d].wait_still(0.3, 10.0, f'{d} at rest') for d in rd4.drives}
    for d, rad in (('axis1', 3.0), ('axis2', 1.0)):
        assert rd4.true_steps(d) == pytest.approx(rad * RD4_STEPS_PER_RAD, abs=1)
    spread = abs(arrived['axis1'] - arrived['axis2'])
    assert spread <= 1 / rate_hz + transaction_s + Track.SAMPLE_S, spread
    for d in rd4.drives:     # not early, and late by no more than the moves' own transactions
        late = arrived[d] - t0 - 1.5
        assert -Track.SAMPLE_S <= late <= 1 / rate_hz + 4 * transaction_s + Track.SAMPLE_S \
            + MIDDLEWARE_S, (d, late)


def test_xplus_follow_action_gives_feedback_and_reaches_the_goal(xplus):
    for d in xplus.drives:
        xplus.enable(d)
    goal = FollowJointTrajectory.Goal(trajectory=trajectory(
        ['xplus_joint1', 'xplus_joint2'], [(0.6, [2.0, -1.0]), (1.2, [1.0, 1.0])]))
    goal.goal_tolerance = [JointTolerance(name='xplus_joint1', position=0.001),
                           JointTolerance(name='xplus_joint2', position=0.001)]
    g = Goal(xplus, goal)
    result = g.result(10.0)
    assert result.error_code == FollowJointTrajectory.Result.SUCCESSFUL, result.error_string
    for d, rad in (('axis1', 1.0), ('axis2', 1.0)):
        assert xplus.fresh_true_steps(d) == pytest.approx(rad * XPLUS_STEPS_PER_RAD, abs=2)
    assert len(g.feedback) >= 5
    mid = g.feedback[len(g.feedback) // 2]
    assert list(mid.joint_names) == ['xplus_joint1', 'xplus_joint2']
    for k in range(2):
        assert mid.error.positions[k] == pytest.approx(
            mid.desired.positions[k] - mid.actual.positions[k], abs=1e-9)


def test_xplus_a_goal_running_when_the_node_is_stopped_gets_its_result(xplus):
    """SIGTERM during a trajectory: the goal is aborted with the reason, the client's result
    request is answered before the node ends (exit code 0), and the axes stopped."""
    for d in xplus.drives:
        xplus.enable(d)
    g = Goal(xplus, FollowJointTrajectory.Goal(trajectory=trajectory(
        ['xplus_joint1', 'xplus_joint2'], [(3.0, [20.0, -20.0])])))
    xplus.status('axis1', lambda m: m.moving, what='following')
    assert xplus.node.stop(signal.SIGTERM) == 0
    result = g.result(2.0)                   # 'no result within 2 s': not before the node ended
    assert g.status == GoalStatus.STATUS_ABORTED, g.status
    # not SUCCESSFUL, which MoveIt logs as "successfully finished" (JointTrajectoryController
    # ends a goal at its deactivation with INVALID_GOAL too)
    assert result.error_code == FollowJointTrajectory.Result.INVALID_GOAL, result
    assert result.error_string == 'the node is shutting down', result


def test_xplus_impossible_segment_is_rejected_before_anything_moves(xplus):
    xplus.enable('axis1')
    before = xplus.fresh_true_steps('axis1')
    # 40 rad in 0.1 s: 400 rad/s on average; max_velocity is 40 (config/xplus_mt.yaml; the
    # X-PLUS MT's joints follow velocity-continuously, bounded by their max_velocity)
    since = len(log_lines(xplus))
    assert rejected(xplus, FollowJointTrajectory.Goal(trajectory=trajectory(
        ['xplus_joint1'], [(0.1, [40.0])])))
    logged(xplus, since, 'goal rejected (INVALID_GOAL): xplus_joint1: segment to point 0',
           'max_velocity')
    assert not xplus.status('axis1').moving
    assert xplus.fresh_true_steps('axis1') == before


def test_xplus_unknown_joint_is_rejected_as_invalid_joints(xplus):
    since = len(log_lines(xplus))
    assert rejected(xplus, FollowJointTrajectory.Goal(trajectory=trajectory(
        ['elbow'], [(1.0, [1.0])])))
    logged(xplus, since, "goal rejected (INVALID_JOINTS): joints ['elbow'] are not driven by "
                         'this node')


def test_xplus_goals_for_an_inactive_node_or_a_drive_in_fault_are_rejected(procs, ros, tmp_path):
    managed = XplusLifecycle(procs, ros, tmp_path)
    goal = FollowJointTrajectory.Goal(trajectory=trajectory(['xplus_joint1'], [(1.0, [1.0])]))
    assert managed.change(Transition.TRANSITION_CONFIGURE)
    since = len(log_lines(managed))
    assert rejected(managed, goal)
    logged(managed, since, 'goal rejected (INVALID_GOAL): the node is not active (lifecycle '
                           'state inactive)')
    assert managed.change(Transition.TRANSITION_ACTIVATE)
    managed.enable('axis1')
    managed.inject('axis1', 'drive_fault', 0x4310)
    managed.status('axis1', lambda m: m.fault, what='fault in status')
    since = len(log_lines(managed))
    assert rejected(managed, goal)
    logged(managed, since, 'goal rejected (INVALID_GOAL): xplus_joint1: drive axis1 is in '
                           'FAULT 0x4310')
    assert not managed.status('axis1').moving


RELAY = ROOT / 'scripts' / 'bench_cp_relays.py'


class XplusRelayed(XplusBench):
    """The node's Modbus TCP link through scripts/bench_cp_relays.py's relay, a process that
    prints every request with the time its first byte came from the node (time.monotonic(),
    one clock for every process of the machine): the node's frames on the wire."""

    def start_sim(self, *extra_args):
        super().start_sim(*extra_args)
        if not hasattr(self, 'relay'):
            self.relay = self.procs.start('relay', [sys.executable, str(RELAY), 'tcp',
                                                    str(self.port)])
            self.relay.wait_line('port ', 10.0)
            port = re.search(r'port (\d+)', self.relay.output())[1]
            self.node_extra_args = (*type(self).node_extra_args, '-p', f'port:={port}')

    def writes(self, address, after_t):
        """(time, unit) of each write request (FC06, FC16) from `address` on after after_t."""
        out = []
        for line in self.relay.output().splitlines():
            parts = line.split()
            if len(parts) == 7 and parts[0] == 'Q':
                t, unit, fc, start = float(parts[1]), int(parts[3]), int(parts[4]), int(parts[5])
                if fc in (6, 16) and start == address and t > after_t:
                    out.append((t, unit))
        return out


def timed_cancel(bench, goal):
    """Cancel `goal` (a TrajectoryGoal); (when the cancel was sent, when its answer arrived)."""
    answered, got = [], threading.Event()
    sent_t = time.monotonic()
    fut = bench.ros.in_spin(goal.handle.cancel_goal_async)
    fut.add_done_callback(lambda _f: (answered.append(time.monotonic()), got.set()))
    assert got.wait(5.0), 'no answer to the cancel'
    return sent_t, answered[0]


def test_xplus_a_cancel_stop_reaches_the_wire_within_a_transaction_of_the_cancel(
        procs, ros, tmp_path):
    """The cancel callback hands the joints' stops to the bus owner as urgent jobs: each axis's
    Halt write (controlword 1040) goes out behind the transaction in flight and the stops
    before it, two transactions each (statusword, controlword), counted from the cancel's
    answer reaching the client; the joints' stops waited for the next feedback tick before
    (up to 0.1 s plus the executor's time). Three cancels at random points of a tick."""
    transaction_s = 0.005            # one Modbus TCP transaction on loopback, with margin
    xplus = XplusRelayed(procs, ros, tmp_path)
    for d in xplus.drives:
        xplus.enable(d)
    for k in range(3):
        before = xplus.status('axis1', lambda m: not m.moving, 10.0, 'at rest').position
        sign = 1.0 if before < 10.0 else -1.0
        g = Goal(xplus, FollowJointTrajectory.Goal(trajectory=trajectory(
            ['xplus_joint1', 'xplus_joint2'], [(4.0, [before + 12.0 * sign, 6.0 * sign])])))
        xplus.status('axis1', lambda m: m.moving, 5.0, 'following')
        time.sleep(0.3 + 0.1 * k / 3)             # a different phase of the 10 Hz feedback
        sent_t, answered_t = timed_cancel(xplus, g)
        g.result(5.0)
        assert g.status == GoalStatus.STATUS_CANCELED
        halts = {}
        wait_for(lambda t0=sent_t: len({u for _t, u in xplus.writes(1040, t0)}) == 2, 2.0,
                 'both Halt writes')
        for t, unit in xplus.writes(1040, sent_t):
            halts.setdefault(unit, t - answered_t)
        assert halts[1] <= 2 * transaction_s, (k, halts)
        assert halts[2] <= 4 * transaction_s, (k, halts)
        for d in xplus.drives:
            xplus.status(d, lambda m: not m.moving, 2.0, f'{d} stopped by the cancel')


def test_xplus_a_new_trajectory_replaces_the_old_and_an_empty_one_stops(xplus):
    xplus.enable('axis1')
    topic = '/xplus_mt_node/joint_trajectory'
    xplus.ros.publish(JointTrajectory, topic, trajectory(['xplus_joint1'], [(3.0, [30.0])]))
    xplus.status('axis1', lambda m: m.moving, what='moving to 30 rad')
    xplus.ros.publish(JointTrajectory, topic, trajectory(['xplus_joint1'], [(1.0, [-1.0])]))
    xplus.status('axis1', lambda m: not m.moving and abs(m.position + 1.0) < 1e-3, 5.0,
                 'at -1 rad: the newer trajectory replaced the rest of the old one')
    xplus.ros.publish(JointTrajectory, topic, trajectory(['xplus_joint1'], [(3.0, [30.0])]))
    xplus.status('axis1', lambda m: m.moving and m.position > 0, what='moving to 30 rad again')
    xplus.ros.publish(JointTrajectory, topic, JointTrajectory(joint_names=['xplus_joint1']))
    st = xplus.status('axis1', lambda m: not m.moving, 3.0, 'stopped by the empty trajectory')
    assert st.position < 20.0
    wait_for(lambda: not xplus.status('axis1').moving, 2.0, 'still stopped')


class VectorIpRig(VectorRig):
    """Two Vector Steps, the node's SYNC every 10 ms: trajectories stream in interpolated
    position mode (0x60C2 = 10 ms, the longest the manual allows)."""

    first_sim_args = ()
    node_extra_args = ('-p', 'timeout_s:=1.5', '-p', 'can.sync_period_s:=0.01')


@pytest.fixture
def vector_ip(tmp_path):
    r = VectorIpRig(tmp_path)
    yield r
    r.close()


def test_vector_step_follows_in_interpolated_mode_within_2_percent(vector_ip):
    rig = vector_ip
    for d in rig.drives:
        rig.enable(d)
    modes = []
    rig.ros.node.create_subscription(
        DriveStatus, '/vector_step_node/axis1/status', lambda m: modes.append(m.mode), 50)
    points = [(1.0, [2.0, 1.0]), (2.0, [0.5, 2.5])]
    goal = FollowJointTrajectory.Goal(trajectory=trajectory(
        ['vector_joint1', 'vector_joint2'], points))
    g = Goal(rig, goal)
    result = g.result(15.0)
    assert result.error_code == FollowJointTrajectory.Result.SUCCESSFUL, result.error_string
    assert any('INTERPOLATED POSITION' in m for m in modes), set(modes)
    for d, rad in (('axis1', 0.5), ('axis2', 2.5)):      # (the true position topic lags)
        rig.ros.wait_msg(rig.true_topic(d), lambda m, s=rad * VECTOR_STEPS_PER_RAD:
                         abs(m.data - s) <= 2, 2.0, f'{d} at {rad} rad')
    # following error against the planned profile (the action's feedback, 10 Hz): under 2 %
    # of the longest segment, 2.0 rad (the Vector Step's goal, docs/benchmarks.md)
    worst = max(abs(e) for f in g.feedback for e in f.error.positions)
    assert len(g.feedback) >= 10 and worst < 0.02 * 2.0, worst
    # the stream ended: the periodic SYNC is back (the drives' 0x1006 watchdog) and no alarm
    st = rig.status('axis1', lambda m: not m.moving)
    assert not st.fault and not st.alarms


class VectorP2PRig(VectorRig):
    first_sim_args = ()           # both power stages work


def test_vector_step_point_to_point_with_the_default_sync_period(tmp_path):
    rig = VectorP2PRig(tmp_path)
    try:
        for d in rig.drives:
            rig.enable(d)
        tracks = {d: Track(rig.ros, rig.true_topic(d)) for d in rig.drives}
        t0 = time.monotonic()
        g = Goal(rig, FollowJointTrajectory.Goal(trajectory=trajectory(
            ['vector_joint1', 'vector_joint2'], [(1.0, [2.0, -1.0])])))
        assert g.result(10.0).error_code == FollowJointTrajectory.Result.SUCCESSFUL
        arrived = {d: tracks[d].wait_still(0.2, 5.0, f'{d} at rest') for d in rig.drives}
        spread = abs(arrived['axis1'] - arrived['axis2'])
        assert spread <= 1 / 50.0 + 0.005 + Track.SAMPLE_S, spread    # poll + one SDO/PDO
        for d in rig.drives:
            assert arrived[d] - t0 >= 1.0 - Track.SAMPLE_S
    finally:
        rig.close()


class XmindLineBench(XmindBench):
    """Three X-MIND K on one 9600-baud line with the simulator's line timing, polled at 5 Hz
    (config/xmind_k.yaml): moves go out one after the other, some 130 ms each."""

    node_extra_args = ('-p', 'timeout_s:=0.25')

    def __init__(self, procs, ros, tmp_path):
        super().__init__(procs, ros, tmp_path, line_timing=True)


def test_xmind_k_axes_on_one_slow_line_arrive_together(procs, ros, tmp_path):
    bench = XmindLineBench(procs, ros, tmp_path)
    rate_hz, transaction_s = 5.0, 0.06       # config publish_rate_hz; a status string at 9600
    for d in ('axis1', 'axis2'):
        bench.enable(d)
    tracks = {d: Track(ros, bench.true_topic(d)) for d in ('axis1', 'axis2')}
    t0 = time.monotonic()
    # 4775 and 6366 steps in 1.5 s: above 3000 Hz, where the drive's frequency steps are 100 Hz
    ros.publish(JointTrajectory, '/xmind_k_node/joint_trajectory',
                trajectory(['xmind_joint1', 'xmind_joint2'], [(1.5, [15.0, 20.0])]))
    arrived = {d: tracks[d].wait_still(0.4, 10.0, f'{d} at rest') for d in tracks}
    for d, rad in (('axis1', 15.0), ('axis2', 20.0)):
        assert bench.fresh_true_steps(d) == pytest.approx(rad * XMIND_STEPS_PER_RAD, abs=1)
    spread = abs(arrived['axis1'] - arrived['axis2'])
    assert spread <= 1 / rate_hz + transaction_s + Track.SAMPLE_S, spread
    for d in tracks:
        assert arrived[d] - t0 >= 1.5 - Track.SAMPLE_S, (d, arrived[d] - t0)
