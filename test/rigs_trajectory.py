"""Trajectories as MoveIt sends them, and what the trajectory tests check a node with.

- `quintic`: a MoveIt-like trajectory (a straight line in joint space with quintic timing, a
  point every dt_s with positions, velocities and accelerations); `duration`: a time_from_start;
- `rejected`: whether a node rejects a goal in its goal callback; `log_lines`, `logged`: the
  node's log, and the line in it that says why;
- EXECUTION_SCALING, EXECUTION_MARGIN_S: MoveIt's bound for a goal's execution;
- `set_params`: node parameters set, each one taken;
- `Rd4Shipped`: two RD4 on config/rd4.yaml's line with line timing, their plans unbounded.
"""

import math
import threading

from builtin_interfaces.msg import Duration
from control_msgs.action import FollowJointTrajectory
from rigs_vendors import Rd4Bench
from rosharness import wait_for
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

# MoveIt's trajectory_execution defaults
EXECUTION_SCALING = 1.2
EXECUTION_MARGIN_S = 0.5


def duration(t):
    sec = int(math.floor(t))
    return Duration(sec=sec, nanosec=int(round((t - sec) * 1e9)))


def quintic(joints, start, end, duration_s, dt_s):
    """MoveIt-like: a straight line from `start` to `end` (rad) with quintic timing, a point
    every dt_s with positions, velocities and accelerations."""
    n = int(round(duration_s / dt_s))
    msg = JointTrajectory(joint_names=list(joints))
    for k in range(1, n + 1):
        s, T = k / n, duration_s
        f = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
        df = (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / T
        ddf = (60 * s - 180 * s ** 2 + 120 * s ** 3) / T ** 2
        msg.points.append(JointTrajectoryPoint(
            positions=[a + f * (b - a) for a, b in zip(start, end)],
            velocities=[df * (b - a) for a, b in zip(start, end)],
            accelerations=[ddf * (b - a) for a, b in zip(start, end)],
            time_from_start=duration(k * dt_s)))
    return msg


def rejected(bench, goal):
    """Whether the node rejects `goal` in its goal callback (rclpy's ActionClient as MoveIt's
    controller handle uses it: the goal response only)."""
    from rclpy.action import ActionClient
    client = ActionClient(bench.ros.node, FollowJointTrajectory,
                          f'{bench.node_ns}/follow_joint_trajectory')
    try:
        assert client.wait_for_server(timeout_sec=10)
        answered = threading.Event()
        fut = bench.ros.in_spin(client.send_goal_async, goal)
        fut.add_done_callback(lambda _f: answered.set())
        assert answered.wait(10), 'no goal response'
        return not fut.result().accepted
    finally:
        bench.ros.in_spin(client.destroy)


def log_lines(bench):
    return bench.node.output().splitlines()


def logged(bench, since, *parts, timeout_s=2.0):
    """The first line of the node's log after line `since` (a len(log_lines())) holding every
    one of `parts`."""
    def find():
        return next((line for line in log_lines(bench)[since:]
                     if all(p in line for p in parts)), None)
    return wait_for(find, timeout_s, f'a log line with {parts}')


def set_params(bench, *params):
    results = bench.set_params(*params)
    assert all(r.successful for r in results), [r.reason for r in results]


# ----------------------------------------------------------------------------- benches
def unbounded(*joints):
    """Node arguments that leave the plans of `joints` unbounded (constraints.<joint>.path_bound
    0): the serial lines' tests of test_follow_joint_trajectory_ros.py send short fast
    trajectories (1 rad in 1 s) whose merged segments pass farther than the default bound from
    the points; the bound has tests of its own (test_trajectory_continuous_ros.py,
    src/stepper_drivers/test/motion/test_trajectory.py)."""
    return tuple(x for j in joints for x in ('-p', f'constraints.{j}.path_bound:=0.0'))


class Rd4Shipped(Rd4Bench):
    """Two RD4 on one 19200-baud line with line timing, polled at config/rd4.yaml's 10 Hz."""

    # the simulator shares 2 busy cores
    node_extra_args = ('-p', 'timeout_s:=0.3', *unbounded('rd4_joint1', 'rd4_joint2'))

    def sim_args(self):
        return super().sim_args() + ['-p', 'line_timing:=true']
