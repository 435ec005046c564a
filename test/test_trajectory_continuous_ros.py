"""Velocity-continuous following and the path bound, through ROS, on the RD4.

rd4_sim (two units on one 19200-baud line with its line timing on, true positions at 100 Hz) and
rd4_node with config/rd4.yaml as separate processes; the client is rclpy's ActionClient of
control_msgs/action/FollowJointTrajectory, sending MoveIt-like goals (a quintic straight line, a
point every 0.1 s with positions, velocities and accelerations, the t=0 start point, no
tolerances). The RD4 takes a new target while it moves (manual §8.1.1 "Position override
function"), so the node follows it without stopping at the points; the line needs about 0.3 s
to send both units a move, so points are merged, and the merged plan is bounded by
constraints.<joint>.path_bound.
"""

import math
import time

from action_msgs.msg import GoalStatus
from control_msgs.action import FollowJointTrajectory
import pytest
from rigs_trajectory import (
    EXECUTION_MARGIN_S,
    EXECUTION_SCALING,
    Rd4Shipped,
    duration,
    log_lines,
    logged,
    quintic,
    rejected,
    set_params,
)
from rosharness import Procs, RosClient, Track
from rosharness import TrajectoryGoal as Client
from trajectory_msgs.msg import JointTrajectoryPoint

JOINTS = ('rd4_joint1', 'rd4_joint2')
STEPS_PER_RAD = 1024 / (2 * math.pi)
SAMPLE_HZ = 100.0
DURATION_S = 3.0
TRAVEL_RAD = (2.0, 1.0)
STALL_FRACTION = 0.25        # slower than a quarter of the planned speed: stalled
SPEED_WINDOW_S = 0.04        # speed from the true positions over this window


class Rd4Sampled(Rd4Shipped):
    """config/rd4.yaml's line (19200 baud, line timing) with true positions at 100 Hz and the
    default path bound (Rd4Shipped leaves it unbounded)."""

    node_extra_args = ('-p', 'timeout_s:=0.3')

    def sim_args(self):
        return super().sim_args() + ['-p', f'publish_rate_hz:={SAMPLE_HZ}']


@pytest.fixture(scope='module')
def bench(tmp_path_factory):
    tmp = tmp_path_factory.mktemp('rd4_continuous')
    procs, ros = Procs(tmp), RosClient('rd4_continuous_test')
    try:
        b = Rd4Sampled(procs, ros, tmp)
        for d in ('axis1', 'axis2'):
            b.enable(d)
        yield b
    finally:
        procs.kill_all()
        ros.close()


def positions(bench):
    js = bench.ros.wait_msg('/joint_states', lambda m: set(JOINTS) <= set(m.name))
    return [js.position[list(js.name).index(j)] for j in JOINTS]


def line_goal(start, dt_s):
    """MoveIt's goal for a quintic line: its start point at t=0, then a point every dt_s."""
    end = [a + (d if a < 1.0 else -d) for a, d in zip(start, TRAVEL_RAD)]
    traj = quintic(JOINTS, start, end, DURATION_S, dt_s)
    traj.points.insert(0, JointTrajectoryPoint(positions=list(start), velocities=[0.0, 0.0],
                                               accelerations=[0.0, 0.0],
                                               time_from_start=duration(0.0)))
    return FollowJointTrajectory.Goal(trajectory=traj), end


def planned_speed(travel_rad, t_s):
    """|velocity| of the quintic line at trajectory time t_s [rad/s]."""
    s = min(max(t_s / DURATION_S, 0.0), 1.0)
    return abs(travel_rad) * (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / DURATION_S


def speeds(samples, t0, t_from, t_to):
    """[(trajectory time, |speed| rad/s)] from true positions [(arrival time, steps)], each the
    difference over SPEED_WINDOW_S centred on a sample in t_from..t_to."""
    out = []
    for t, _x in samples:
        tau = t - t0
        if not t_from <= tau <= t_to:
            continue
        near = [(ts, x) for ts, x in samples if abs(ts - t) <= SPEED_WINDOW_S / 2 + 1e-9]
        (ta, xa), (tb, xb) = near[0], near[-1]
        if tb - ta >= SPEED_WINDOW_S / 2:
            out.append((tau, abs(xb - xa) / STEPS_PER_RAD / (tb - ta)))
    return out


def test_an_axis_passes_the_middle_points_of_a_dense_trajectory_at_speed(bench):
    """Around its middle point (1.5 s, the top speed: 1 rad/s and 0.5 rad/s) and the points on
    either side (1.0 .. 2.0 s) each joint runs at least a quarter of its planned speed. With a
    rest-to-rest move per merged segment (0.4 s) each joint stopped at every segment's end:
    18-39 % of the middle of the move below a quarter of the planned speed
    (docs/benchmarks.md)."""
    for d in ('axis1', 'axis2'):
        bench.status(d, lambda m: not m.moving, 10.0, f'{d} at rest')
    tracks = {d: Track(bench.ros, bench.true_topic(d)) for d in ('axis1', 'axis2')}
    goal, end = line_goal(positions(bench), 0.1)
    c = Client(bench, goal)
    result = c.result(EXECUTION_SCALING * DURATION_S + EXECUTION_MARGIN_S + 5.0)
    assert c.status == GoalStatus.STATUS_SUCCEEDED, result.error_string
    assert c.result_t - c.sent_t <= EXECUTION_SCALING * DURATION_S + EXECUTION_MARGIN_S
    for k, d in enumerate(('axis1', 'axis2')):
        with tracks[d].lock:
            samples = list(tracks[d].samples)
        seen = speeds(samples, c.sent_t, 1.0, 2.0)
        assert len(seen) >= 0.5 * SAMPLE_HZ, f'{d}: {len(seen)} speeds (samples missing)'
        slow = [(round(t, 3), round(v, 3)) for t, v in seen
                if v < STALL_FRACTION * planned_speed(TRAVEL_RAD[k], t)]
        assert not slow, f'{d} below a quarter of its planned speed at (s, rad/s): {slow}'
        assert samples[-1][1] / STEPS_PER_RAD == pytest.approx(end[k], abs=1.5 / STEPS_PER_RAD)


def test_a_path_bound_the_merged_segments_would_break_rejects_the_goal(bench):
    """The line needs about 0.3 s to send both units a move, so 0.05 s points are merged; the
    merged plan passes more than 2 mrad from the points in between. With
    constraints.rd4_joint1.path_bound 0.002 rad (MoveIt sends no path tolerance) the goal is
    REJECTED in the goal callback, the log naming the joint, the point, the bound and what to
    change, and nothing moves; with the default bound (0.05 rad) the same goal is followed."""
    for d in ('axis1', 'axis2'):
        bench.status(d, lambda m: not m.moving, 10.0, f'{d} at rest')
    before = {d: bench.fresh_true_steps(d) for d in ('axis1', 'axis2')}
    set_params(bench, ('constraints.rd4_joint1.path_bound', 0.002))
    try:
        since = len(log_lines(bench))
        goal, _ = line_goal(positions(bench), 0.05)
        assert rejected(bench, goal)
        line = logged(bench, since, 'goal rejected', 'rd4_joint1: point',
                      'path bound 0.002 rad')
        for what in ("MoveIt's resample_dt", 'baud rate', 'constraints.rd4_joint1.path_bound'):
            assert what in line, line
        time.sleep(0.3)                     # anything sent would have moved by now
        assert {d: bench.fresh_true_steps(d) for d in ('axis1', 'axis2')} == before
    finally:
        set_params(bench, ('constraints.rd4_joint1.path_bound', 0.05))
    goal, end = line_goal(positions(bench), 0.05)
    c = Client(bench, goal)
    result = c.result(EXECUTION_SCALING * DURATION_S + EXECUTION_MARGIN_S + 5.0)
    assert c.status == GoalStatus.STATUS_SUCCEEDED, result.error_string
