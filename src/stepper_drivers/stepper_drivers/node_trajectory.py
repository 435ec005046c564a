"""Trajectories through ROS: `~/joint_trajectory` and `~/follow_joint_trajectory` of a DriveNode.

The action is control_msgs/action/FollowJointTrajectory, so MoveIt's simple controller manager
and every client written for ros2_controllers' JointTrajectoryController drive the node. The
semantics are JointTrajectoryController's (see trajectory.py); the following is follow.py's,
through the bus owners. This module checks the goal and converts: joint units to steps with each
drive's UnitConversion (the one conversion place), the goal's tolerances as JTC resolves them
(-1 not checked, 0 the default, > 0 the bound), header stamps to the monotonic clock the owners
use, and outcomes to the result. Unlike JTC, which rejects a goal it cannot take without saying
why, a goal is accepted and then aborted with the result code and a text naming the problem.
"""

from __future__ import annotations

import concurrent.futures
import math
import time
from typing import TYPE_CHECKING

from control_msgs.action import FollowJointTrajectory
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.time import Time
from std_msgs.msg import Header
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from .drive import DriveError
from .follow import (INVALID_GOAL, INVALID_JOINTS, OLD_HEADER_TIMESTAMP, Axis, Follower, Run,
                     Tolerances)
from .trajectory import JointLimits, Trajectory, TrajectoryError, build

if TYPE_CHECKING:
    from .node import DriveHandle, DriveNode

FEEDBACK_PERIOD_S = 0.1
ERASE = -1.0              # control_msgs/JointTolerance: "erased", not checked
ERASE_EPS = 1.1920929e-07  # JTC compares with float's epsilon


class GoalError(TrajectoryError):
    """A goal refused before anything moves, with its FollowJointTrajectory result code."""

    def __init__(self, code: int, text: str):
        super().__init__(text)
        self.code = code


class TrajectoryInterface:
    def __init__(self, node: 'DriveNode'):
        self.node = node
        self.follower = Follower({})
        node.create_subscription(JointTrajectory, '~/joint_trajectory', self.on_trajectory,
                                 node.command_qos, callback_group=node.cmd_group)

        async def execute(goal_handle):
            with node.handling():                # answered before the node ends
                return await self.execute(goal_handle)
        ActionServer(node, FollowJointTrajectory, '~/follow_joint_trajectory',
                     execute_callback=execute,
                     goal_callback=lambda _req: GoalResponse.ACCEPT,
                     cancel_callback=lambda _goal: CancelResponse.ACCEPT,
                     callback_group=node.srv_group)

    # ------------------------------------------------------------------------------ converting
    def _handle(self, joint: str) -> 'DriveHandle':
        return self.node.by_joint[joint]

    def _axes(self) -> dict[str, Axis]:
        """Every joint with its limits in steps, read now (the limits can change at run time)."""
        axes = {}
        for joint, h in self.node.by_joint.items():
            to = h.conv.to_steps
            lo, hi = sorted((to(h.param('min_position')), to(h.param('max_position'))))
            limits = JointLimits(
                lo, hi, abs(to(h.param('max_velocity'))), abs(to(h.param('max_acceleration'))),
                h.conv.steps_per_unit, h.cfg.params.get('unit', 'rad'),
                h.drive.start_stop_steps_s, h.drive.min_velocity_steps_s)
            axis = Axis(joint, h.name, h.sup, h.drive, limits,
                        move_time_s=h.drive.move_time_s())
            old = self.follower.axes.get(joint)
            if old is not None and old.drive is h.drive:
                axis.lead_s = old.lead_s            # what its moves took so far
            axes[joint] = axis
        return axes

    def _trajectory(self, msg: JointTrajectory) -> Trajectory:
        joints = list(msg.joint_names)
        known = list(self.node.by_joint)
        times, positions = [], []
        for k, point in enumerate(msg.points):
            if len(point.positions) != len(joints):
                raise TrajectoryError(f'point {k}: {len(point.positions)} positions for '
                                      f'{len(joints)} joints {joints}')
            times.append(point.time_from_start.sec + point.time_from_start.nanosec * 1e-9)
            positions.append([self._handle(j).conv.to_steps(p) if j in self.node.by_joint
                              else 0.0 for j, p in zip(joints, point.positions)])
        return build(joints, times, positions, known)

    def _start_t(self, stamp) -> float | None:
        """The monotonic time of a header stamp (None: zero stamp, start now)."""
        if stamp.sec == 0 and stamp.nanosec == 0:
            return None
        ros_now = self.node.get_clock().now()
        return time.monotonic() + (Time.from_msg(stamp) - ros_now).nanoseconds * 1e-9

    def _ready(self, joints) -> None:
        """Every joint's drive can move now; TrajectoryError naming the first that cannot."""
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
                raise TrajectoryError(f'{joint}: {why}')

    def _start(self, msg: JointTrajectory, tol: Tolerances | None = None) -> Run:
        tol = Tolerances() if tol is None else tol
        if not self.node.accepting:
            raise TrajectoryError(f'the node is not active (lifecycle state '
                                  f'{self.node.lifecycle_state_label()}); activate it first')
        traj = self._trajectory(msg)
        self._ready(traj.joints)
        self.follower.axes = self._axes()
        run = self.follower.follow(traj, self._start_t(msg.header.stamp), tol)
        merged = run.merge_summary()
        if merged:
            self.node.log.info(f'trajectory of {list(traj.joints)}: {merged}')
        return run

    # ---------------------------------------------------------------------------------- topic
    def on_trajectory(self, msg: JointTrajectory) -> None:
        if not msg.points:
            self.follower.stop('empty trajectory on joint_trajectory')
            self.node.log.info('joint_trajectory: empty trajectory: stopping')
            return
        try:
            run = self._start(msg)
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

    # --------------------------------------------------------------------------------- action
    def _tolerances(self, goal) -> Tolerances:
        """The goal's tolerances in drive units, resolved as JointTrajectoryController does:
        > 0 the bound, 0 the node's default, -1 not checked; GoalError for anything else, for a
        joint this node does not drive, and for what no drive here can check (acceleration;
        velocity of a drive that reports none)."""
        known = self.node.by_joint
        out = {'path': {}, 'path_v': {}, 'goal': {}, 'goal_v': {}}
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
                    else:
                        out[key].pop(t.name, None)           # 0: the default
        d = goal.goal_time_tolerance
        goal_time_s = d.sec + d.nanosec * 1e-9
        if goal_time_s < 0 and abs(goal_time_s - ERASE) > ERASE_EPS:
            raise GoalError(INVALID_GOAL, f'goal_time_tolerance {goal_time_s:g} s is not a '
                            'tolerance (> 0 a bound, 0 the default: none, -1 none)')
        return Tolerances(
            path_steps={j: v for j, v in out['path'].items() if v is not None},
            goal_steps=out['goal'], goal_time_s=max(goal_time_s, 0.0),
            path_velocity_steps_s={j: v for j, v in out['path_v'].items() if v is not None},
            goal_velocity_steps_s=out['goal_v'])

    @staticmethod
    def _check_goal(goal) -> None:
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

    @staticmethod
    def _code(error: TrajectoryError) -> int:
        if isinstance(error, GoalError):
            return error.code
        text = str(error)
        return (INVALID_JOINTS if 'not driven by this node' in text
                or 'name a joint twice' in text else
                OLD_HEADER_TIMESTAMP if 'ended' in text else INVALID_GOAL)

    async def execute(self, goal_handle):
        goal = goal_handle.request
        result = FollowJointTrajectory.Result()
        msg = goal.trajectory
        try:
            self._check_goal(goal)
            tol = self._tolerances(goal)
            if not msg.points:
                self.follower.stop('empty trajectory on follow_joint_trajectory')
                goal_handle.succeed()
                result.error_code, result.error_string = 0, 'empty trajectory: stopped'
                return result
            run = self._start(msg, tol)
        except TrajectoryError as e:
            goal_handle.abort()
            result.error_code, result.error_string = self._code(e), str(e)
            self.node.log.warning(f'follow_joint_trajectory refused: {e}')
            return result
        fb = FollowJointTrajectory.Feedback()
        fb.joint_names = list(run.traj.joints)
        while not run.done.done():
            if goal_handle.is_cancel_requested:
                run.cancel('canceled by the client')
                run._stop_axes()
                break
            self._feedback(run, fb)
            goal_handle.publish_feedback(fb)
            await self._sleep(FEEDBACK_PERIOD_S, run.done)
        outcome = await self.node.await_future(run.done)
        # answered once joint_states and the statuses of the joints' drives that show the end
        # went out: a client (MoveIt's start state of the next plan) reads them after this
        try:
            await self.node.published(*[self._handle(j) for j in run.traj.joints])
        except DriveError:
            pass           # the node shuts down (Cancelled) or the link is lost: the outcome says
        result.error_code, result.error_string = outcome.code, outcome.text
        if outcome.status == 'succeeded':
            goal_handle.succeed()
        elif outcome.status == 'canceled' and goal_handle.is_cancel_requested:
            goal_handle.canceled()
        else:
            goal_handle.abort()
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
        remove_timer = self.node.supervisors[0].after(seconds, fire)
        wake.add_done_callback(lambda _f: remove_timer())
        await self.node.await_future(wake)
