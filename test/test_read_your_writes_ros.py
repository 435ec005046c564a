"""A service or action that changes a drive answers after what it changed was published.

A client (a script, MoveIt's start-state check, whose CurrentStateMonitor keeps the latest
joint state it received) that reads /joint_states or a drive's status right after the answer
must see the change: the latest message it has received when the answer comes carries the new
position or state. The RD4 and X-MIND K nodes run with their shipped config
files' poll rates (10 Hz and 5 Hz), where the next periodic publication can be a poll period
after the answer.
"""

import math

from builtin_interfaces.msg import Duration
from control_msgs.action import FollowJointTrajectory
import pytest
from rigs_vendors import Rd4Bench, XmindBench
from rosharness import TrajectoryGoal
from std_srvs.srv import SetBool, Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

RD4_STEPS_PER_RAD = 1024 / (2 * math.pi)


class Rd4Shipped(Rd4Bench):
    node_extra_args = ('-p', 'timeout_s:=0.3')       # config/rd4.yaml's 10 Hz polls


class XmindShipped(XmindBench):
    node_extra_args = ('-p', 'timeout_s:=0.25')      # config/xmind_k.yaml's 5 Hz polls


def latest_at_answer(ros, topic, answer):
    """answer() (a call that returns once answered), and the latest message on topic that the
    client had received by then (its executor takes a message that came before the answer
    first)."""
    result = answer()
    with ros.lock:
        return result, ros.latest[topic]


def joint(msg, name):
    return msg.position[list(msg.name).index(name)]


def test_rd4_joint_states_after_a_move_to_a_home_and_a_trajectory_show_them(procs, ros,
                                                                              tmp_path):
    b = Rd4Shipped(procs, ros, tmp_path)
    js = '/joint_states'
    b.enable('axis1')
    result, msg = latest_at_answer(ros, js, lambda: b.move_to('axis1', 5.0))
    assert result.success, result.message
    assert joint(msg, 'rd4_joint1') == pytest.approx(5.0, abs=1 / RD4_STEPS_PER_RAD)
    # home: the RD4 presets the current position to homing.offset (0 rad)
    r, msg = latest_at_answer(ros, js, lambda: b.call('axis1', 'home', Trigger.Request(), Trigger))
    assert r.success and 'homed at 0' in r.message, r.message
    assert joint(msg, 'rd4_joint1') == pytest.approx(0.0, abs=1 / RD4_STEPS_PER_RAD)
    # a trajectory's result
    traj = JointTrajectory(joint_names=['rd4_joint1'], points=[JointTrajectoryPoint(
        positions=[2.0], time_from_start=Duration(sec=1))])
    g = TrajectoryGoal(b, FollowJointTrajectory.Goal(trajectory=traj))
    result, msg = latest_at_answer(ros, js, lambda: g.result(10.0))
    assert result.error_code == 0, result.error_string
    assert joint(msg, 'rd4_joint1') == pytest.approx(2.0, abs=1 / RD4_STEPS_PER_RAD)


def test_xmind_k_status_after_an_enable_and_a_disable_shows_them(procs, ros, tmp_path):
    b = XmindShipped(procs, ros, tmp_path)
    status = f'{b.node_ns}/axis1/status'      # (the bench keeps every status)
    for on in (True, False, True, False):
        r, msg = latest_at_answer(ros, status, lambda on=on: b.call(
            'axis1', 'enable', SetBool.Request(data=on), SetBool))
        assert r.success, r.message
        assert msg.enabled == on and (msg.state == 'OPERATION ENABLED') == on, (on, msg.state)
