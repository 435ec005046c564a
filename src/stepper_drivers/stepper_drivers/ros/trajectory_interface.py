"""Trajectories through ROS: `~/joint_trajectory` and `~/follow_joint_trajectory` of a DriveNode.

The action is control_msgs/action/FollowJointTrajectory, so MoveIt's simple controller manager and
every client written for ros2_controllers' JointTrajectoryController drive the node. The semantics
are JointTrajectoryController's (see motion/trajectory.py); the following is motion/follow.py's,
through the bus owners. This module checks the goal and converts: joint units to steps with each
drive's UnitConversion (the one conversion place), the goal's tolerances as JTC resolves them (-1
not checked, 0 the default: the constraints.* parameters, > 0 the bound), header stamps to the
monotonic clock the owners use, and outcomes to the result.

As JTC: a goal the node cannot take when it arrives is REJECTED in the goal callback (the reason
in the log, with the result code it would have had), so that MoveIt cancels the other parts of
the same plan; a goal that fails later ends ABORTED with the code of its cause (GoalError's
code, set where the cause is found), a newer goal replaces it with INVALID_GOAL, and a cancel
stops its joints from the cancel callback.
"""

from __future__ import annotations

import concurrent.futures
import math
import time
from typing import Any, Mapping, Protocol

from control_msgs.action import FollowJointTrajectory
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.time import Time
from std_msgs.msg import Header
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from ..contract.drive import DriveError
from ..motion.follow import (
    INVALID_GOAL,
    INVALID_JOINTS,
    OLD_HEADER_TIMESTAMP,
    Axis,
    Follower,
    GoalError,
    Run,
    Tolerances,
)
from ..motion.trajectory import JointLimits, Trajectory, TrajectoryError, build
from ..owner import BusOwner
from .handle import DriveHandle, JobAwaiter

FEEDBACK_PERIOD_S = 0.1
ERASE = -1.0              # control_msgs/JointTolerance: "erased", not checked
ERASE_EPS = 1.1920929e-07  # JTC compares with float's epsilon
CODE_NAMES = {INVALID_GOAL: 'INVALID_GOAL', INVALID_JOINTS: 'INVALID_JOINTS',
              OLD_HEADER_TIMESTAMP: 'OLD_HEADER_TIMESTAMP'}


def check_goal(goal) -> None:
    """What no node here can take: multi-DOF joints and their component tolerances."""
    multi = goal.multi_dof_trajectory
    if multi.joint_names or multi.points:
        raise GoalError(INVALID_GOAL, f'multi_dof_trajectory (joints '
                        f'{list(multi.joint_names)}, {len(multi.points)} points): these '
                        'drives are single-DOF joints (revolute or prismatic); send them in '
                        'trajectory')
    for where in ('component_path_tolerance', 'component_goal_tolerance'):
        items = getattr(goal, where)
        if items:
            raise GoalError(INVALID_GOAL, f'{where} ({[c.joint_name for c in items]}): '
                            'component tolerances apply to multi-DOF joints, and this node '
                            'drives none')


def result_code(error: TrajectoryError) -> int:
    """The result code of a refusal: GoalError carries it; motion/trajectory.py's refusals
    (times, values, limits, segments, path tolerance of merged points) are all
    INVALID_GOAL."""
    return error.code if isinstance(error, GoalError) else INVALID_GOAL


class TrajectoryHost(JobAwaiter, Protocol):
    """What the trajectory interface needs of its node (node.DriveNode): its joints and bus
    owners, whether it takes commands, its callback groups and QoS, the awaiting of owner-thread
    futures, and the rclpy Node calls below."""

    by_joint: Mapping[str, DriveHandle]
    bus_owners: list[BusOwner]
    accepting: bool          # commands are taken (a managed node: while active)
    cmd_group: Any           # the command subscriptions' callback group
    srv_group: Any           # the services' and actions' callback group
    command_qos: Any         # the QoS of the command topics
    log: Any                 # the node's logger

    def lifecycle_state_label(self) -> str: ...

    def create_subscription(self, *args: Any, **kwargs: Any) -> Any: ...

    def get_parameter(self, name: str) -> Any: ...

    def get_clock(self) -> Any: ...


class TrajectoryInterface:
    def __init__(self, node: TrajectoryHost):
        self.node = node
        self.follower = Follower({})
        # goal id -> the run of that goal, while its execute callback awaits it
        self._runs: dict[bytes, Run] = {}
        # accepted goals not yet executed: id(goal request) -> (it, when it was received)
        self._received: dict[int, tuple[object, float]] = {}
        node.create_subscription(JointTrajectory, '~/joint_trajectory', self.on_trajectory,
                                 node.command_qos, callback_group=node.cmd_group)

        async def execute(goal_handle):
            with node.handling():                # answered before the node ends
                return await self.execute(goal_handle)
        ActionServer(node, FollowJointTrajectory, '~/follow_joint_trajectory',
                     execute_callback=execute, goal_callback=self.on_goal,
                     cancel_callback=self.on_cancel, callback_group=node.srv_group)

    # ------------------------------------------------------------------------------ converting
    def _handle(self, joint: str) -> DriveHandle:
        return self.node.by_joint[joint]

    @staticmethod
    def _step_limits(h: DriveHandle) -> tuple[int, int]:
        """The steps min_position and max_position are sent as (the nearest ones, as every
        position). A point is within the limits when the step it is sent as is within these:
        MoveIt's interpolation (from + (to - from) * t) ends a plan at a limit up to an ulp
        beyond it, and a joint standing at the step nearest a limit reports a position up to
        half a step beyond it, which every point of a plan that does not move it keeps."""
        lo, hi = sorted((h.conv.to_steps(h.param('min_position')),
                         h.conv.to_steps(h.param('max_position'))))
        return int(round(lo)), int(round(hi))

    def _axes(self) -> dict[str, Axis]:
        """Every joint with its limits in steps, read now (the limits can change at run time);
        the position limits as _step_limits takes them."""
        axes = {}
        for joint, h in self.node.by_joint.items():
            to = h.conv.to_steps
            lo, hi = self._step_limits(h)
            limits = JointLimits(
                lo - 0.5, hi + 0.5, abs(to(h.param('max_velocity'))),
                abs(to(h.param('max_acceleration'))),
                h.conv.steps_per_unit, h.cfg.params.get('unit', 'rad'),
                h.drive.start_stop_steps_s, h.drive.min_velocity_steps_s)
            axis = Axis(joint, h.name, h.bus_owner, h.drive, limits,
                        move_time_s=h.drive.move_time_s())
            old = self.follower.axes.get(joint)
            if old is not None and old.drive is h.drive:
                axis.lead_s, axis.busy_s = old.lead_s, old.busy_s  # what its moves took so far
            axes[joint] = axis
        return axes

    def _trajectory(self, msg: JointTrajectory) -> Trajectory:
        joints = list(msg.joint_names)
        known = list(self.node.by_joint)
        unknown = [j for j in joints if j not in self.node.by_joint]
        if unknown:
            raise GoalError(INVALID_JOINTS, f'joints {unknown} are not driven by this node (its '
                            f'joints: {known})')
        if len(set(joints)) != len(joints):
            raise GoalError(INVALID_JOINTS, f'joint_names {joints} name a joint twice')
        if not joints:
            raise GoalError(INVALID_JOINTS, f'joint_names is empty (this node drives {known})')
        times, positions, velocities, accelerations = [], [], [], []
        for k, point in enumerate(msg.points):
            if len(point.positions) != len(joints):
                raise GoalError(INVALID_GOAL, f'point {k}: {len(point.positions)} positions for '
                                f'{len(joints)} joints {joints}')
            times.append(point.time_from_start.sec + point.time_from_start.nanosec * 1e-9)
            positions.append([self._handle(j).conv.to_steps(p)
                              for j, p in zip(joints, point.positions)])
            # rates: steps per unit times the value
            for rows, values in ((velocities, point.velocities),
                                 (accelerations, point.accelerations)):
                rows.append([self._handle(j).conv.steps_per_unit * x
                             for j, x in zip(joints, values)] if len(values) == len(joints)
                            else list(values))
        return build(joints, times, positions, known, velocities, accelerations)

    def _start_t(self, stamp) -> float | None:
        """The monotonic time of a header stamp (None: zero stamp, start now)."""
        if stamp.sec == 0 and stamp.nanosec == 0:
            return None
        ros_now = self.node.get_clock().now()
        return time.monotonic() + (Time.from_msg(stamp) - ros_now).nanoseconds * 1e-9

    def _ready(self, joints) -> None:
        """Every joint's drive can move now; GoalError naming the first that cannot."""
        for joint in joints:
            h = self._handle(joint)
            s = h.state
            why = ''
            if h.slot.not_driven:
                why = f'drive {h.name} is not driven: {h.slot.not_driven}'
            elif not h.connected:
                why = f'drive {h.name} is DISCONNECTED'
            elif s.fault:
                why = f'drive {h.name} is in FAULT 0x{s.fault_code:04X} ({s.fault_text})'
            elif not s.enabled:
                why = f'drive {h.name} is not enabled (state {s.state.value}); call enable first'
            if why:
                raise GoalError(INVALID_GOAL, f'{joint}: {why}')

    def _check_limits(self, traj: Trajectory, start_t: float | None) -> None:
        """GoalError naming the first point beyond min_position..max_position (_step_limits).
        Points already past when the trajectory arrives (a stamp in the past) are dropped by
        the plan and not checked, as trajectory.plan does."""
        from_s = 0.0 if start_t is None else max(0.0, time.monotonic() - start_t)
        steps = {joint: self._step_limits(self._handle(joint)) for joint in traj.joints}
        for k, point in enumerate(traj.points):
            if point.time_s <= from_s:
                continue
            for joint, x in zip(traj.joints, point.positions_steps):
                lo, hi = steps[joint]
                if not lo <= int(round(x)) <= hi:
                    h = self._handle(joint)
                    unit = h.cfg.params.get('unit', 'rad')
                    raise GoalError(INVALID_GOAL, f'{joint}: point {k} at '
                                    f'{h.conv.from_steps(x):g} {unit} is outside '
                                    f"min_position..max_position ({h.param('min_position'):g}.."
                                    f"{h.param('max_position'):g} {unit})")

    def _prepare(self, msg: JointTrajectory) -> tuple[Trajectory, float | None]:
        """The trajectory in steps and its monotonic start time (None: now), checked against
        what the node knows now (its lifecycle state, its joints, the clock, the drives'
        snapshots, the limits); GoalError with the result code of the first problem."""
        if not self.node.accepting:
            raise GoalError(INVALID_GOAL, f'the node is not active (lifecycle state '
                            f'{self.node.lifecycle_state_label()}); activate it first')
        traj = self._trajectory(msg)
        start_t = self._start_t(msg.header.stamp)
        if start_t is not None and traj.points:
            ago = time.monotonic() - start_t - traj.points[-1].time_s
            if ago > 0:
                raise GoalError(OLD_HEADER_TIMESTAMP, f'the trajectory ended {ago:.3f} s ago '
                                '(header.stamp plus the last time_from_start)')
        self._ready(traj.joints)
        self._check_limits(traj, start_t)
        return traj, start_t

    def _start(self, traj: Trajectory, start_t: float | None, tol: Tolerances,
               received_t: float) -> Run:
        """Follow `traj`; a zero stamp (start_t None) starts it when it was received
        (Follower._start_for_now)."""
        self.follower.axes = self._axes()
        run = self.follower.follow(traj, start_t, tol, received_t=received_t)
        merged = run.merge_summary()
        if merged:
            self.node.log.info(f'trajectory of {list(traj.joints)}: {merged}')
        return run

    # ---------------------------------------------------------------------------------- topic
    def on_trajectory(self, msg: JointTrajectory) -> None:
        received_t = time.monotonic()
        if not msg.points:
            self.follower.stop('empty trajectory on joint_trajectory')
            self.node.log.info('joint_trajectory: empty trajectory: stopping')
            return
        try:
            traj, start_t = self._prepare(msg)
            run = self._start(traj, start_t, Tolerances(path_bound_steps=self._bounds(
                traj.joints)), received_t)
        except TrajectoryError as e:
            self.node.log.warning(f'joint_trajectory refused: {e}')
            return
        run.done.add_done_callback(lambda f: self._log_outcome('joint_trajectory', f))

    def _log_outcome(self, what: str, fut: concurrent.futures.Future) -> None:
        outcome = fut.result()
        if outcome.status == 'succeeded':
            self.node.log.info(f'{what}: {outcome.text}')
        else:
            self.node.log.warning(f'{what}: {outcome.status}: {outcome.text}')

    def _bounds(self, joints) -> dict[str, float]:
        """The plan's bound of a trajectory on the topic (no tolerances): per joint
        constraints.<joint>.trajectory where > 0, else constraints.<joint>.path_bound [steps]."""
        out = {}
        for joint in joints:
            steps = abs(self._handle(joint).conv.steps_per_unit)
            for name in ('trajectory', 'path_bound'):
                value = self.node.get_parameter(f'constraints.{joint}.{name}').value
                if value > 0:
                    out[joint] = value * steps
                    break
        return out

    # --------------------------------------------------------------------------------- action
    def _tolerances(self, goal, joints) -> Tolerances:
        """The tolerances of a goal for `joints` in drive units, resolved as
        JointTrajectoryController does: > 0 the bound, 0 the default (the constraints.*
        parameters, read now: 0 there is not checked), -1 not checked; GoalError for anything
        else, for a joint this node does not drive, and for what no drive here can check
        (acceleration; velocity of a drive that reports none)."""
        known = self.node.by_joint
        param = self.node.get_parameter
        stopped = param('constraints.stopped_velocity_tolerance').value
        out: dict[str, dict[str, float | None]] = {'path': {}, 'path_v': {}, 'goal': {},
                                                   'goal_v': {}, 'bound': {}}
        for joint in joints:
            steps = abs(self._handle(joint).conv.steps_per_unit)
            for key, value in (('path', param(f'constraints.{joint}.trajectory').value),
                               ('goal', param(f'constraints.{joint}.goal').value),
                               ('goal_v', stopped),
                               ('bound', param(f'constraints.{joint}.path_bound').value)):
                out[key][joint] = value * steps if value > 0 else None
        for where, items, pos_key, vel_key in (
                ('path_tolerance', goal.path_tolerance, 'path', 'path_v'),
                ('goal_tolerance', goal.goal_tolerance, 'goal', 'goal_v')):
            for t in items:
                if t.name not in known:
                    raise GoalError(INVALID_JOINTS, f'{where}: joint {t.name!r} is not driven '
                                    f'by this node (its joints: {list(known)})')
                h = self._handle(t.name)
                unit = h.cfg.params.get('unit', 'rad')
                values = {}
                for field in ('position', 'velocity', 'acceleration'):
                    value = getattr(t, field)
                    if not math.isfinite(value) or (value < 0 and
                                                     abs(value - ERASE) > ERASE_EPS):
                        raise GoalError(INVALID_GOAL, f'{where} of {t.name}: {field} {value:g} '
                                        'is not a tolerance (> 0 a bound, 0 the default, -1 '
                                        'not checked)')
                    values[field] = None if value < 0 else value
                if values['acceleration']:
                    raise GoalError(INVALID_GOAL, f'{where} of {t.name}: acceleration '
                                    f'{values["acceleration"]:g} {unit}/s^2 cannot be checked: '
                                    'the drives report no acceleration (0 or -1: not checked)')
                if values['velocity'] and not h.state.velocity_valid:
                    raise GoalError(INVALID_GOAL, f'{where} of {t.name}: velocity '
                                    f'{values["velocity"]:g} {unit}/s cannot be checked: drive '
                                    f'{h.name} reports no velocity (0 or -1: not checked)')
                steps = abs(h.conv.steps_per_unit)
                for key, field in ((pos_key, 'position'), (vel_key, 'velocity')):
                    value = values[field]
                    if value is None:
                        out[key][t.name] = None              # -1: not checked
                    elif value > 0:
                        out[key][t.name] = value * steps
                    # 0: the default (above)
        d = goal.goal_time_tolerance
        goal_time_s = d.sec + d.nanosec * 1e-9
        if goal_time_s < 0 and abs(goal_time_s - ERASE) > ERASE_EPS:
            raise GoalError(INVALID_GOAL, f'goal_time_tolerance {goal_time_s:g} s is not a '
                            'tolerance (> 0 a bound, 0 the default: constraints.goal_time, -1 '
                            'none)')
        if goal_time_s == 0:
            goal_time_s = param('constraints.goal_time').value
        # the plan's bound: the path tolerance where there is one, else constraints.*.path_bound
        bound = {j: out['path'].get(j) or out['bound'][j] for j in joints}
        return Tolerances(
            path_bound_steps={j: v for j, v in bound.items() if v is not None},
            path_steps={j: v for j, v in out['path'].items() if v is not None},
            goal_steps=out['goal'], goal_time_s=max(goal_time_s, 0.0),
            path_velocity_steps_s={j: v for j, v in out['path_v'].items() if v is not None},
            goal_velocity_steps_s=out['goal_v'])

    def _goal(self, goal) -> tuple[Trajectory, float | None, Tolerances]:
        """A goal's trajectory in steps, its start time and its tolerances, checked as far as
        the node can before it plans; GoalError with the result code of the first problem (or
        trajectory.build's TrajectoryError: times, values)."""
        traj, start_t = self._prepare(goal.trajectory)
        if not traj.points:
            raise GoalError(INVALID_GOAL, 'empty trajectory (no points): nothing to follow (to '
                            'stop a running goal, cancel it)')
        check_goal(goal)
        return traj, start_t, self._tolerances(goal, traj.joints)

    def on_goal(self, goal) -> GoalResponse:
        """The goal callback (executor thread): a goal the node cannot take now is REJECTED,
        as JointTrajectoryController does (MoveIt then cancels the parts of its plan it sent
        to other controllers); the reason goes to the log, a rejection carries none. Planned
        too (Follower.check): a segment beyond a joint's limits or tolerances is known now."""
        received_t = time.monotonic()
        try:
            traj, start_t, tol = self._goal(goal)
            self.follower.axes = self._axes()
            self.follower.check(traj, start_t, tol, received_t=received_t)
        except TrajectoryError as e:
            code = result_code(e)
            self.node.log.warning(f'follow_joint_trajectory: goal rejected '
                                  f'({CODE_NAMES.get(code, code)}): {e}')
            return GoalResponse.REJECT
        # the execute callback starts it from here (the goal request is the handle's request)
        self._received[id(goal)] = (goal, received_t)
        return GoalResponse.ACCEPT

    def on_cancel(self, goal_handle) -> CancelResponse:
        """The cancel callback (executor thread): the goal's joints stop now, their stops
        urgent jobs handed to the bus owners before this returns (JointTrajectoryController
        holds position inside its cancel callback); the goal then ends CANCELED. A goal whose
        execute callback has not begun ends CANCELED there, nothing sent."""
        run = self._runs.get(bytes(goal_handle.goal_id.uuid))
        if run is not None and not run.done.done():
            run.cancel('canceled by the client', hand_over=True)
            self.node.log.info(f'follow_joint_trajectory: canceled: {list(run.traj.joints)} '
                               'stopping')
        return CancelResponse.ACCEPT

    def _received_t(self, goal) -> float:
        """When the goal callback received `goal` (now where it did not: a goal the callback
        never saw)."""
        entry = self._received.pop(id(goal), None)
        return entry[1] if entry is not None and entry[0] is goal else time.monotonic()

    async def execute(self, goal_handle):
        result = FollowJointTrajectory.Result()
        received_t = self._received_t(goal_handle.request)
        if goal_handle.is_cancel_requested:
            goal_handle.canceled()
            result.error_string = 'canceled before it started'
            return result
        try:
            # checked again: a drive can have faulted since the goal callback
            traj, start_t, tol = self._goal(goal_handle.request)
            run = self._start(traj, start_t, tol, received_t)
        except TrajectoryError as e:
            goal_handle.abort()
            result.error_code, result.error_string = result_code(e), str(e)
            self.node.log.warning(f'follow_joint_trajectory refused: {e}')
            return result
        key = bytes(goal_handle.goal_id.uuid)
        self._runs[key] = run
        try:
            fb = FollowJointTrajectory.Feedback()
            fb.joint_names = list(run.traj.joints)
            while not run.done.done():
                self._feedback(run, fb)
                goal_handle.publish_feedback(fb)
                await self._sleep(FEEDBACK_PERIOD_S, run.done)
            outcome = await self.node.await_future(run.done)
        finally:
            self._runs.pop(key, None)
        # answered once joint_states and the statuses of the joints' drives that show the end
        # went out: a client (MoveIt's start state of the next plan) reads them after this
        try:
            await self.node.published(*[self._handle(j) for j in run.traj.joints])
        except DriveError:
            pass           # the node shuts down (Cancelled) or the link is lost: the outcome says
        result.error_code, result.error_string = outcome.code, outcome.text
        if outcome.status == 'succeeded':
            goal_handle.succeed()
        elif outcome.status == 'canceled':
            goal_handle.canceled()     # only on_cancel cancels a run: the goal is CANCELING
        else:
            goal_handle.abort()        # with a nonzero code (motion/follow.py's aborted outcomes)
        self._log_outcome('follow_joint_trajectory', run.done)
        return result

    def _feedback(self, run: Run, fb) -> None:
        fb.header = Header(stamp=self.node.get_clock().now().to_msg())
        d, a, e = JointTrajectoryPoint(), JointTrajectoryPoint(), JointTrajectoryPoint()
        for joint in run.traj.joints:
            h = self._handle(joint)
            # desired at the time of the snapshot `actual` comes from (up to a poll period old):
            # the error is then the drive's following error, not the age of the snapshot. The
            # snapshot and its time are read once (the owner thread replaces them meanwhile).
            s, t = h.slot.sample
            positions, velocities = run.desired(t)
            want = h.conv.from_steps(positions[joint])
            want_v = h.conv.from_steps(velocities[joint])
            have = h.conv.from_steps(s.position_steps)
            have_v = h.conv.from_steps(s.velocity_steps_s) if s.velocity_valid else math.nan
            d.positions.append(float(want))
            d.velocities.append(float(want_v))
            a.positions.append(float(have))
            a.velocities.append(float(have_v))
            e.positions.append(float(want - have))
            e.velocities.append(float(want_v - have_v))
        fb.desired, fb.actual, fb.error = d, a, e

    async def _sleep(self, seconds: float, done: concurrent.futures.Future) -> None:
        """Await `seconds` or `done`, whichever comes first, without holding a thread."""
        wake: concurrent.futures.Future = concurrent.futures.Future()

        def fire(_f=None):
            if not wake.done():
                try:
                    wake.set_result(None)
                except concurrent.futures.InvalidStateError:
                    pass
        done.add_done_callback(fire)
        remove_timer = self.node.bus_owners[0].after(seconds, fire)
        wake.add_done_callback(lambda _f: remove_timer())
        await self.node.await_future(wake)
