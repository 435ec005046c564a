"""Trajectories through ROS: `~/joint_trajectory` and `~/follow_joint_trajectory` of a DriveNode.

The semantics are JointTrajectoryController's (see trajectory.py); the following is follow.py's,
through the bus owners. This module only converts: joint units to steps with each drive's
UnitConversion (the one conversion place), header stamps to the monotonic clock the owners use,
and outcomes to the FollowJointTrajectory result.
"""

from __future__ import annotations

import concurrent.futures
import time
from typing import TYPE_CHECKING

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.time import Time
from std_msgs.msg import Header
from stepper_drivers_msgs.action import FollowJointTrajectory
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from .follow import (INVALID_GOAL, INVALID_JOINTS, OLD_HEADER_TIMESTAMP, Axis, Follower, Run,
                     Tolerances)
from .trajectory import JointLimits, Trajectory, TrajectoryError, build

if TYPE_CHECKING:
    from .node import DriveHandle, DriveNode

FEEDBACK_PERIOD_S = 0.1


class TrajectoryInterface:
    def __init__(self, node: 'DriveNode'):
        self.node = node
        self.follower = Follower({})
        from .node import COMMAND_QOS      # (node.py imports this module)
        node.create_subscription(JointTrajectory, '~/joint_trajectory', self.on_trajectory,
                                 COMMAND_QOS, callback_group=node.cmd_group)

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
                h.drive.start_stop_steps_s)
            axis = Axis(joint, h.name, h.sup, h.drive, limits)
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

    def _start(self, msg: JointTrajectory, tol: Tolerances = Tolerances()) -> Run:
        if not self.node.accepting:
            raise TrajectoryError(f'the node is not active (lifecycle state '
                                  f'{self.node.lifecycle_state_label()}); activate it first')
        traj = self._trajectory(msg)
        self._ready(traj.joints)
        self.follower.axes = self._axes()
        return self.follower.follow(traj, self._start_t(msg.header.stamp), tol)

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
        def steps(items) -> dict[str, float]:
            out = {}
            for t in items:
                if t.name in self.node.by_joint and t.position > 0:
                    out[t.name] = abs(self._handle(t.name).conv.to_steps(t.position))
            return out
        d = goal.goal_time_tolerance
        return Tolerances(steps(goal.path_tolerance), steps(goal.goal_tolerance),
                          d.sec + d.nanosec * 1e-9)

    async def execute(self, goal_handle):
        goal = goal_handle.request
        result = FollowJointTrajectory.Result()
        msg = goal.trajectory
        if not msg.points:
            self.follower.stop('empty trajectory on follow_joint_trajectory')
            goal_handle.succeed()
            result.error_code, result.error_string = 0, 'empty trajectory: stopped'
            return result
        try:
            run = self._start(msg, self._tolerances(goal))
        except TrajectoryError as e:
            goal_handle.abort()
            text = str(e)
            result.error_code = (INVALID_JOINTS if 'not driven by this node' in text
                                 or 'name a joint twice' in text else
                                 OLD_HEADER_TIMESTAMP if 'ended' in text else INVALID_GOAL)
            result.error_string = text
            self.node.log.warning(f'follow_joint_trajectory refused: {text}')
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
        outcome = await self.node._await(run.done)
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
            # the error is then the drive's following error, not the age of the snapshot
            want = h.conv.from_steps(run.desired_steps(h.slot.state_t)[joint])
            d.positions.append(float(want))
            a.positions.append(float(h.position))
            e.positions.append(float(want - h.position))
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
        self.node.supervisors[0].after(seconds, fire)
        await self.node._await(wake)
