"""control_msgs/action/FollowJointTrajectory on every vendor node, as MoveIt sends it.

Each vendor's simulator and node run as separate processes with the shipped config files (RD4
at 19200 baud and X-MIND K at 9600 with the simulators' line timing on, the Vector Step at its
default SYNC of 0.1 s, so in profile position); the client is rclpy's ActionClient of the
control_msgs type, as moveit_simple_controller_manager uses it. Trajectories are MoveIt-like: a
straight line in the joint space of two joints with quintic timing (rest to rest), a point every
0.1 s or 0.05 s with positions, velocities and accelerations, header.stamp zero (start now).
MoveIt cancels a goal not done within 1.2 x its duration + 0.5 s (its defaults): that is the
bound here. A goal the node cannot take is REJECTED in its goal callback, as
JointTrajectoryController does, the reason in the node's log.
"""

import math
import time
from types import SimpleNamespace

from action_msgs.msg import GoalStatus
from builtin_interfaces.msg import Duration, Time
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointComponentTolerance, JointTolerance
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
    unbounded,
)
from rigs_vendors import VectorRig, XmindBench, XplusBench
from rosharness import MIDDLEWARE_S, Procs, RosClient, Track
from rosharness import TrajectoryGoal as Client
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint, MultiDOFJointTrajectory

Result = FollowJointTrajectory.Result


def get_param(bench, name):
    """A node parameter's value (double parameters only)."""
    from rcl_interfaces.srv import GetParameters
    r = bench.ros.call(GetParameters, f'{bench.node_ns}/get_parameters',
                       GetParameters.Request(names=[name]))
    return r.values[0].double_value


def single_point(joints, positions, t_s):
    return JointTrajectory(joint_names=list(joints), points=[JointTrajectoryPoint(
        positions=[float(p) for p in positions], time_from_start=duration(t_s))])


# ------------------------------------------------------------------------- the four benches
# (the RD4's, Rd4Shipped, is in rigs_trajectory.py)
class XplusShipped(XplusBench):
    pass


class XmindShipped(XmindBench):
    """Three X-MIND K on one 9600-baud line with line timing, config/xmind_k.yaml's 5 Hz."""

    node_extra_args = ('-p', 'timeout_s:=0.25',
                       *unbounded('xmind_joint1', 'xmind_joint2', 'xmind_joint3'))

    def __init__(self, procs, ros, tmp_path):
        super().__init__(procs, ros, tmp_path, line_timing=True)


class VectorShipped(VectorRig):
    """Two Vector Steps at config/vector_step.yaml's SYNC of 0.1 s: profile position."""

    first_sim_args = ()


# vendor: (bench, joints, steps per rad, poll period [s], one transaction [s])
VENDORS = {
    'xplus_mt': (XplusShipped, ('xplus_joint1', 'xplus_joint2'), 12800 / (2 * math.pi),
                 1 / 50.0, 0.005),
    'rd4': (Rd4Shipped, ('rd4_joint1', 'rd4_joint2'), 1024 / (2 * math.pi), 1 / 10.0, 0.025),
    'xmind_k': (XmindShipped, ('xmind_joint1', 'xmind_joint2'), 2000 / (2 * math.pi),
                1 / 5.0, 0.06),
    'vector_step': (VectorShipped, ('vector_joint1', 'vector_joint2'), 3200 / (2 * math.pi),
                    1 / 50.0, 0.005),
}


class Setup:
    def __init__(self, vendor, tmp_path):
        cls, self.joints, self.steps_per_rad, self.poll_s, self.transaction_s = VENDORS[vendor]
        self.vendor = vendor
        if vendor == 'vector_step':
            self.bench = cls(tmp_path)
            self._close = self.bench.close
        else:
            self.procs, self.ros = Procs(tmp_path), RosClient(f'{vendor}_fjt_test')
            try:
                self.bench = cls(self.procs, self.ros, tmp_path)
            except BaseException:
                self.close_procs()
                raise
            self._close = self.close_procs
        for d in ('axis1', 'axis2'):
            self.bench.enable(d)

    def close_procs(self):
        self.procs.kill_all()
        self.ros.close()

    def close(self):
        self._close()

    def positions(self):
        """The joints' positions from a fresh /joint_states [rad]."""
        js = self.bench.ros.wait_msg('/joint_states', lambda m: set(self.joints) <= set(m.name))
        return [js.position[list(js.name).index(j)] for j in self.joints]

    def true_rad(self, drive):
        return self.bench.fresh_true_steps(drive) / self.steps_per_rad


@pytest.fixture(scope='module', params=list(VENDORS))
def setup(request, tmp_path_factory):
    s = Setup(request.param, tmp_path_factory.mktemp(request.param))
    yield s
    s.close()


def still(setup):
    for d in ('axis1', 'axis2'):
        setup.bench.status(d, lambda m: not m.moving, 10.0, f'{d} at rest')


@pytest.mark.parametrize('dt_s', [0.1, 0.05])
def test_a_dense_trajectory_finishes_within_moveits_limit_and_the_path_tolerance(setup, dt_s):
    still(setup)
    start = setup.positions()
    end = [start[0] + (2.0 if start[0] < 1.0 else -2.0),
           start[1] + (1.0 if start[1] < 0.5 else -1.0)]            # 2.24 rad in joint space
    duration_s = 3.0
    goal = FollowJointTrajectory.Goal(trajectory=quintic(setup.joints, start, end, duration_s,
                                                         dt_s))
    # The path tolerance from the settings: the node checks each polled position against its
    # plan at the time the position was true; what it cannot know is when a move really
    # reached its drive on a shared line (a poll or another drive's transactions may go
    # first): up to a poll period and a transaction, at the plan's top speed (point-to-point
    # segments, at most twice the trajectory's 1.875 x 2 rad / 3 s).
    # The X-PLUS MT and Vector Step drivers have no estimate of a move's time (Drive.move_time_s,
    # a fast link): until the node has timed one, a move's own transactions (about four) are
    # lag on top.
    top_rad_s = 2 * 1.875 * 2.0 / duration_s
    untimed_s = 0.0 if setup.vendor in ('rd4', 'xmind_k') else 4 * setup.transaction_s
    path_rad = top_rad_s * (setup.poll_s + setup.transaction_s + untimed_s)
    goal.path_tolerance = [JointTolerance(name=j, position=path_rad) for j in setup.joints]
    c = Client(setup.bench, goal)
    result = c.result(EXECUTION_SCALING * duration_s + EXECUTION_MARGIN_S + 5.0)
    took = c.result_t - c.sent_t
    assert c.status == GoalStatus.STATUS_SUCCEEDED and result.error_code == Result.SUCCESSFUL, \
        result.error_string
    assert took <= EXECUTION_SCALING * duration_s + EXECUTION_MARGIN_S, took
    for d, want in zip(('axis1', 'axis2'), end):
        assert setup.true_rad(d) == pytest.approx(want, abs=1.5 / setup.steps_per_rad)
    # the feedback: every joint named, desired - actual = error, within the path tolerance
    assert c.feedback and list(c.feedback[-1].joint_names) == list(setup.joints)
    for f in c.feedback:
        for k in range(2):
            assert f.error.positions[k] == pytest.approx(
                f.desired.positions[k] - f.actual.positions[k], abs=1e-9)
            assert abs(f.error.positions[k]) <= path_rad
        assert not f.multi_dof_joint_names


def test_goals_that_cannot_be_taken_are_rejected_naming_why_and_nothing_moves(setup):
    """Rejected in the goal callback (MoveIt then cancels the parts of the plan it sent to
    other controllers), each with its reason and the result code it stands for in the log."""
    still(setup)
    before = setup.positions()
    j1, j2 = setup.joints
    one = quintic(setup.joints, before, [before[0] + 1.0, before[1]], 1.0, 0.1)
    cases = []
    g = FollowJointTrajectory.Goal(trajectory=quintic(['elbow', j2], [0, 0], [1, 1], 1.0, 0.1))
    cases.append((g, 'INVALID_JOINTS', "joints ['elbow'] are not driven by this node"))
    g = FollowJointTrajectory.Goal(trajectory=one, multi_dof_trajectory=MultiDOFJointTrajectory(
        joint_names=['base']))
    cases.append((g, 'INVALID_GOAL', 'multi_dof_trajectory'))
    g = FollowJointTrajectory.Goal(trajectory=one, component_path_tolerance=[
        JointComponentTolerance(joint_name='base', component=4, position=0.1)])
    cases.append((g, 'INVALID_GOAL', 'component_path_tolerance'))
    g = FollowJointTrajectory.Goal(trajectory=one, path_tolerance=[
        JointTolerance(name=j1, acceleration=1.0)])
    cases.append((g, 'INVALID_GOAL', f'path_tolerance of {j1}: acceleration 1'))
    g = FollowJointTrajectory.Goal(trajectory=one, goal_tolerance=[
        JointTolerance(name=j1, position=-0.5)])
    cases.append((g, 'INVALID_GOAL', f'goal_tolerance of {j1}: position -0.5 is not a '
                                     'tolerance'))
    g = FollowJointTrajectory.Goal(trajectory=one, goal_tolerance=[
        JointTolerance(name='wrist', position=0.1)])
    cases.append((g, 'INVALID_JOINTS', "goal_tolerance: joint 'wrist' is not driven"))
    old = FollowJointTrajectory.Goal(trajectory=quintic(setup.joints, before, before, 1.0, 0.1))
    old.trajectory.header.stamp = Time(sec=1)                       # 1970: ended long ago
    cases.append((old, 'OLD_HEADER_TIMESTAMP', 'the trajectory ended'))
    g = FollowJointTrajectory.Goal(trajectory=JointTrajectory(joint_names=list(setup.joints)))
    cases.append((g, 'INVALID_GOAL', 'empty trajectory (no points)'))
    g = FollowJointTrajectory.Goal(trajectory=single_point([j1], [1e4], 100.0))
    cases.append((g, 'INVALID_GOAL', f'{j1}: point 0 at 10000 rad is outside '
                                     'min_position..max_position'))
    # 40 rad in 0.1 s: 16000 rad/s^2, beyond every shipped max_acceleration (the plan, made in
    # the goal callback too)
    far = before[0] + (40.0 if before[0] < 10.0 else -40.0)
    g = FollowJointTrajectory.Goal(trajectory=single_point([j1], [far], 0.1))
    cases.append((g, 'INVALID_GOAL', f'{j1}: segment to point 0'))
    for goal, code, text in cases:
        since = len(log_lines(setup.bench))
        assert rejected(setup.bench, goal), text
        logged(setup.bench, since, f'goal rejected ({code}): ', text)
    setup.bench.enable('axis2', False)
    try:
        since = len(log_lines(setup.bench))
        assert rejected(setup.bench, FollowJointTrajectory.Goal(trajectory=one))
        logged(setup.bench, since, 'goal rejected (INVALID_GOAL): ',
               f'{j2}: drive axis2 is not enabled')
    finally:
        setup.bench.enable('axis2')
    for d in ('axis1', 'axis2'):
        assert not setup.bench.status(d).moving
    assert setup.positions() == pytest.approx(before, abs=1.5 / setup.steps_per_rad)


def test_a_plan_at_the_joint_limits_is_followed(setup):
    """MoveIt interpolates as from + (to - from) * t (RevoluteJointModel::interpolate), which
    can end an ulp beyond `to`: a plan to a joint's max_position can end an ulp beyond it. A
    joint standing at the step nearest its min_position reports a position up to half a step
    beyond it, which every point of a plan that does not move it keeps. Both are followed, at
    the limit; a point a step beyond a limit is rejected."""
    still(setup)
    j1, j2 = setup.joints
    bench, spu = setup.bench, setup.steps_per_rad
    start = setup.positions()
    names = [f'drives.{d}.{k}' for d in ('axis1', 'axis2') for k in ('min_position',
                                                                      'max_position')]
    saved = [(n, get_param(bench, n)) for n in names]
    # j1 to an ulp beyond its max_position, 1 rad ahead (beyond in steps too); j2's
    # min_position a quarter step above where it stands
    upper = next(u for u in (start[0] + 1.0 + k * 1e-7 for k in range(1000))
                 if math.nextafter(u, math.inf) * spu > u * spu)
    lower = start[1] + 0.25 / spu
    try:
        set_params(bench, ('drives.axis1.max_position', upper),
                   ('drives.axis2.min_position', lower))
        plan = quintic(setup.joints, start, [math.nextafter(upper, math.inf), start[1]], 1.0,
                       0.1)
        assert plan.points[-1].positions[0] > upper and plan.points[-1].positions[1] < lower
        c = Client(bench, FollowJointTrajectory.Goal(trajectory=plan))
        result = c.result(10.0)
        assert c.status == GoalStatus.STATUS_SUCCEEDED, result.error_string
        assert setup.true_rad('axis1') == pytest.approx(upper, abs=0.5 / spu)
        assert setup.true_rad('axis2') == pytest.approx(start[1], abs=0.5 / spu)
        since = len(log_lines(bench))
        assert rejected(bench, FollowJointTrajectory.Goal(trajectory=single_point(
            [j1], [upper + 1.0 / spu], 1.0)))
        logged(bench, since, 'goal rejected (INVALID_GOAL): ', f'{j1}: point 0 at',
               'is outside min_position..max_position')
    finally:
        set_params(bench, *saved)


def test_a_newer_goal_replaces_the_running_one_which_ends_aborted_with_a_code(setup):
    """As JointTrajectoryController preempts a goal: ABORTED with a nonzero code (INVALID_GOAL;
    MoveIt logs a result of SUCCESSFUL as "successfully finished") and a text saying why."""
    still(setup)
    start = setup.positions()
    sign = 1 if start[0] < 1.0 else -1
    old = Client(setup.bench, FollowJointTrajectory.Goal(trajectory=quintic(
        setup.joints, start, [start[0] + 4.0 * sign, start[1] + 2.0 * sign], 4.0, 0.1)))
    setup.bench.status('axis1', lambda m: abs(m.position - start[0]) > 0.3, 5.0,
                       'axis1 well under way')
    new = Client(setup.bench, FollowJointTrajectory.Goal(trajectory=single_point(
        setup.joints, start, 2.0)))
    replaced = old.result(5.0)
    assert old.status == GoalStatus.STATUS_ABORTED
    assert replaced.error_code == Result.INVALID_GOAL, replaced
    assert 'replaced by a newer goal' in replaced.error_string
    result = new.result(10.0)
    assert new.status == GoalStatus.STATUS_SUCCEEDED, result.error_string
    assert setup.positions() == pytest.approx(start, abs=1.5 / setup.steps_per_rad)


def test_the_constraints_parameters_are_the_defaults_of_a_goal(setup):
    """JointTrajectoryController's constraints.<joint>.goal and .trajectory (per joint, in rad):
    a goal with no tolerances of its own is checked against them; a goal's own -1 lifts one."""
    still(setup)
    bench, (j1, _) = setup.bench, setup.joints
    goal_param, path_param = f'constraints.{j1}.goal', f'constraints.{j1}.trajectory'
    assert get_param(bench, goal_param) == pytest.approx(1.0 / setup.steps_per_rad, rel=1e-9)
    assert get_param(bench, path_param) == 0.0
    saved = [(goal_param, get_param(bench, goal_param)), (path_param, 0.0)]
    try:
        # stopped short: within a goal tolerance of 100 rad (with one step, the default, it is
        # GOAL_TOLERANCE_VIOLATED: test_a_tolerance_of_minus_one_is_not_checked)
        set_params(bench, (goal_param, 100.0))
        start = setup.positions()
        c = Client(bench, FollowJointTrajectory.Goal(trajectory=single_point(
            [j1], [start[0] + (3.0 if start[0] < 1.0 else -3.0)], 2.0)))
        bench.status('axis1', lambda m: m.moving, 5.0, 'axis1 following')
        assert bench.call('axis1', 'stop').success
        result = c.result(10.0)
        assert c.status == GoalStatus.STATUS_SUCCEEDED, result.error_string
        bench.status('axis1', lambda m: not m.moving, 5.0, 'axis1 stopped')
        assert abs(setup.positions()[0] - start[0]) < 2.9          # it did stop short
        # a path tolerance of 1e-9 rad: any following error ends the goal, and stops the joint
        set_params(bench, (path_param, 1e-9))
        start = setup.positions()
        c = Client(bench, FollowJointTrajectory.Goal(trajectory=single_point(
            [j1], [start[0] + (1.0 if start[0] < 1.0 else -1.0)], 1.0)))
        result = c.result(10.0)
        assert c.status == GoalStatus.STATUS_ABORTED
        assert result.error_code == Result.PATH_TOLERANCE_VIOLATED, result.error_string
        assert result.error_string.startswith(f'{j1}: ')
        # the goal's own path tolerance of -1: not checked
        bench.status('axis1', lambda m: not m.moving, 5.0, 'axis1 stopped')
        start = setup.positions()
        target = start[0] + (1.0 if start[0] < 1.0 else -1.0)
        goal = FollowJointTrajectory.Goal(trajectory=single_point([j1], [target], 1.0),
                                          path_tolerance=[JointTolerance(name=j1, position=-1.0)])
        c = Client(bench, goal)
        result = c.result(10.0)
        assert c.status == GoalStatus.STATUS_SUCCEEDED, result.error_string
        assert setup.true_rad('axis1') == pytest.approx(target, abs=1.5 / setup.steps_per_rad)
    finally:
        set_params(bench, *saved)


def test_a_goals_tolerances_resolve_over_the_constraints_parameters_as_jtcs():
    """The node's resolution (node_trajectory, no process): > 0 the goal's bound, 0 the
    constraints.* parameter (0 there: not checked), -1 not checked; goal_time_tolerance 0 is
    constraints.goal_time, -1 no limit."""
    from stepper_drivers.contract.units import UnitConversion
    from stepper_drivers.ros.trajectory_interface import TrajectoryInterface
    conv = UnitConversion(12800.0)
    spu = conv.steps_per_unit
    params = {'constraints.goal_time': 0.5, 'constraints.stopped_velocity_tolerance': 0.02,
              'constraints.a.trajectory': 0.1, 'constraints.a.goal': 0.0,
              'constraints.b.trajectory': 0.0, 'constraints.b.goal': 0.01,
              'constraints.a.path_bound': 0.05, 'constraints.b.path_bound': 0.05}
    handle = SimpleNamespace(name='axis', conv=conv, cfg=SimpleNamespace(params={'unit': 'rad'}),
                             state=SimpleNamespace(velocity_valid=True))
    trajectories = TrajectoryInterface.__new__(TrajectoryInterface)     # no node: its parts
    trajectories.node = SimpleNamespace(
        by_joint={'a': handle, 'b': handle},
        get_parameter=lambda name: SimpleNamespace(value=params[name]))
    tol = trajectories._tolerances(FollowJointTrajectory.Goal(), ['a', 'b'])
    assert tol.path_steps == {'a': pytest.approx(0.1 * spu)}
    assert tol.goal_steps == {'a': None, 'b': pytest.approx(0.01 * spu)}
    assert tol.goal_velocity_steps_s == {'a': pytest.approx(0.02 * spu),
                                         'b': pytest.approx(0.02 * spu)}
    assert tol.goal_time_s == 0.5
    # the plan's bound: the path tolerance where there is one, else constraints.*.path_bound
    assert tol.path_bound_steps == {'a': pytest.approx(0.1 * spu), 'b': pytest.approx(0.05 * spu)}
    goal = FollowJointTrajectory.Goal(
        path_tolerance=[JointTolerance(name='a', position=-1.0),
                        JointTolerance(name='b', position=0.3)],
        goal_tolerance=[JointTolerance(name='a', position=0.2, velocity=-1.0),
                        JointTolerance(name='b', position=0.0, velocity=0.5)],
        goal_time_tolerance=duration(1.5))
    tol = trajectories._tolerances(goal, ['a', 'b'])
    assert tol.path_steps == {'b': pytest.approx(0.3 * spu)}
    assert tol.path_bound_steps == {'a': pytest.approx(0.05 * spu), 'b': pytest.approx(0.3 * spu)}
    assert tol.goal_steps == {'a': pytest.approx(0.2 * spu), 'b': pytest.approx(0.01 * spu)}
    assert tol.goal_velocity_steps_s == {'a': None, 'b': pytest.approx(0.5 * spu)}
    assert tol.goal_time_s == 1.5
    tol = trajectories._tolerances(FollowJointTrajectory.Goal(
        goal_time_tolerance=Duration(sec=-1)), ['a'])
    assert tol.goal_time_s == 0.0                             # -1: no limit
    params['constraints.stopped_velocity_tolerance'] = 0.0
    assert trajectories._tolerances(FollowJointTrajectory.Goal(), ['a']) \
        .goal_velocity_steps_s == {'a': None}                 # 0: not checked


def test_a_tolerance_of_minus_one_is_not_checked(setup):
    """A stop on one axis leaves it short of the goal: with the default goal tolerance the
    goal fails, with -1 it succeeds once the joints stand (goal velocity still checked)."""
    still(setup)
    start = setup.positions()
    j1, _ = setup.joints
    outcomes = []
    for position_tol in (0.0, -1.0):
        target = [start[0] + 3.0 * (1 if not outcomes else -1), start[1]]
        goal = FollowJointTrajectory.Goal(trajectory=JointTrajectory(
            joint_names=[j1], points=[JointTrajectoryPoint(positions=[target[0]],
                                                           time_from_start=duration(2.0))]))
        goal.goal_tolerance = [JointTolerance(name=j1, position=position_tol)]
        c = Client(setup.bench, goal)
        setup.bench.status('axis1', lambda m: m.moving, 5.0, 'axis1 following')
        r = setup.bench.call('axis1', 'stop', Trigger.Request(), Trigger)
        assert r.success, r.message
        outcomes.append((c.result(10.0), c.status))
        setup.bench.status('axis1', lambda m: not m.moving, 5.0, 'axis1 stopped')
        start = setup.positions()
        assert abs(start[0] - target[0]) > 0.1         # it did stop short
    (r0, s0), (r1, s1) = outcomes
    assert s0 == GoalStatus.STATUS_ABORTED and r0.error_code == Result.GOAL_TOLERANCE_VIOLATED
    assert f'{j1}: ' in r0.error_string and 'from the goal' in r0.error_string
    assert s1 == GoalStatus.STATUS_SUCCEEDED and r1.error_code == Result.SUCCESSFUL, \
        r1.error_string


def test_cancel_stops_the_joints(setup):
    still(setup)
    start = setup.positions()
    target = [start[0] + 6.0 * (1 if start[0] < 1.0 else -1), start[1] + 3.0 * (
        1 if start[1] < 0.5 else -1)]
    c = Client(setup.bench, FollowJointTrajectory.Goal(trajectory=quintic(
        setup.joints, start, target, 4.0, 0.1)))
    for d in ('axis1', 'axis2'):
        setup.bench.status(d, lambda m: m.moving, 5.0, f'{d} following')
    time.sleep(0.5)                                    # well into the motion
    c.cancel()
    c.result(5.0)
    assert c.status == GoalStatus.STATUS_CANCELED
    # stopped: within two polls, a transaction in flight and the ramp from at most max speed
    for d in ('axis1', 'axis2'):
        setup.bench.status(d, lambda m: not m.moving, 2.0, f'{d} stopped by the cancel')
    time.sleep(2 * setup.poll_s)
    now = setup.positions()
    assert all(abs(n - t) > 0.5 for n, t in zip(now, target)), (now, target)


# ------------------------------------------------------------------ one trajectory, two nodes
def crossing(track, after_t, target):
    """When the true position reached or passed `target` (a whole step: linear between the two
    samples around it), the first time after `after_t`; None if it never did."""
    with track.lock:
        samples = [(t, x) for t, x in track.samples if t >= after_t]
    for (t0, x0), (t1, x1) in zip(samples, samples[1:]):
        if abs(x0 - target) <= 0.5:
            return t0
        if (x0 - target) * (x1 - target) <= 0:
            return t0 + (t1 - t0) * (target - x0) / (x1 - x0)
    return None


def test_two_nodes_given_the_parts_of_one_trajectory_start_and_arrive_together(
        procs, ros, tmp_path, request):
    """As MoveIt splits a planning group over two controllers: an X-PLUS MT node (Modbus TCP)
    and an RD4 node (19200-baud line with line timing), each sent its joints' part with the
    same header.stamp. Every axis arrives at every point within one poll period of each node
    plus one line transaction of the other axes (and the measurement's 20 Hz sample)."""
    (xplus_dir := tmp_path / 'xplus').mkdir()
    (rd4_dir := tmp_path / 'rd4').mkdir()
    xplus = XplusShipped(procs, ros, xplus_dir)
    rd4_procs = Procs(rd4_dir)                     # its logs apart from the X-PLUS MT's
    request.addfinalizer(rd4_procs.kill_all)
    rd4 = Rd4Shipped(rd4_procs, ros, rd4_dir)
    for b in (xplus, rd4):
        for d in ('axis1', 'axis2'):
            b.enable(d)
    parts = {xplus: (VENDORS['xplus_mt'], ('xplus_joint1', 'xplus_joint2')),
             rd4: (VENDORS['rd4'], ('rd4_joint1', 'rd4_joint2'))}
    # points further apart than the RD4 line's shortest segment (3 x 2 moves of about 0.1 s),
    # so that neither node merges any: each point is a point of both plans
    times_s = [0.8, 1.6, 2.4, 3.2]
    # every joint one way only: each point is passed once, its time read between two samples
    rad = {'xplus_joint1': [1.0, 2.0, 2.5, 3.5], 'xplus_joint2': [-0.5, -1.0, -1.5, -1.75],
           'rd4_joint1': [1.0, 2.0, 2.5, 3.5], 'rd4_joint2': [0.5, 1.0, 1.5, 1.75]}
    tracks = {(b, d): Track(ros, b.true_topic(d)) for b in parts for d in ('axis1', 'axis2')}
    # one stamp, a little ahead, as MoveIt gives both parts
    stamp_ros = ros.node.get_clock().now().nanoseconds * 1e-9 + 0.8
    start_t = time.monotonic() + 0.8
    clients = []
    for b, (_, joints) in parts.items():
        msg = JointTrajectory(joint_names=list(joints))
        msg.header.stamp = Time(sec=int(stamp_ros), nanosec=int((stamp_ros % 1) * 1e9))
        for k, t in enumerate(times_s):
            msg.points.append(JointTrajectoryPoint(positions=[rad[j][k] for j in joints],
                                                   time_from_start=duration(t)))
        clients.append(Client(b, FollowJointTrajectory.Goal(trajectory=msg)))
    for c in clients:
        result = c.result(10.0)
        assert result.error_code == Result.SUCCESSFUL, result.error_string
    due = [start_t + t for t in times_s]
    for (b, d), track in tracks.items():            # the true positions' last samples are in
        track.wait_still(0.2, 5.0, f'{b.vendor} {d} at rest')
    hits = {}
    for b, ((_, _, steps_per_rad, _, _), joints) in parts.items():
        for d, j in zip(('axis1', 'axis2'), joints):
            hits[j] = [crossing(tracks[(b, d)], due[k - 1] - 0.2 if k else 0.0,
                                round(rad[j][k] * steps_per_rad)) for k in range(len(times_s))]
    # a poll period of each node, one RD4 transaction (the second axis's move goes out after
    # the first's on the line), the 20 Hz samples' interpolation and the middleware's hops
    bound = 1 / 50.0 + 1 / 10.0 + 0.025 + Track.SAMPLE_S + MIDDLEWARE_S
    for k in range(len(times_s)):
        at = {j: hits[j][k] for j in hits}
        assert all(h is not None for h in at.values()), (k, at)
        spread = max(at.values()) - min(at.values())
        assert spread <= bound, (k, spread, {j: h - due[k] for j, h in at.items()})
        for j, h in at.items():            # at the point's time, within the same bound
            assert abs(h - due[k]) <= bound, (k, j, h - due[k])
