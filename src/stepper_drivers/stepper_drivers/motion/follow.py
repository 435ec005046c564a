"""Following joint trajectories through the bus owners (no rclpy).

Threads and what they own:
- Each `Run` (one accepted trajectory) has a thread of its own that only waits for segment times
  and submits jobs; every call to a drive runs in that drive's bus owner as a COMMAND job (in
  order with the drive's other commands; a stop overtakes and drops it).
- `Follower.follow()` / `stop()` are called from the ROS executor thread; the run threads only
  read the bus_owners' snapshots.

How the axes arrive together (trajectory.py has the plan): at each segment's start time every
moving axis gets one move job. Inside the job, in the owner thread, the profile is computed again
for the time that is really left: the segment's end minus now minus the axis's lead (what its
drive's move took the times before: the checks and writes before the drive runs, tens of ms on
a serial line). An axis whose job starts late, behind other drives' jobs on one line, moves
faster and arrives with the others: with the planned ramp time when its limits allow, else with
the shortest ramp its max_acceleration allows; only when neither fits does it arrive late (the
goal tolerance decides). A late axis's move waits for the segment before to end on its axis: a
drive that cannot take a new target while it runs (X-MIND K) would stop short and start again,
and one that turns there would cut its point. Where the drive takes a new target on the way
(Drive.retargets_on_the_way) and the axis goes on in the same direction, it passes the point on
its way to the next one: that move goes at once, so a late axis is not held at every point
(each hold would add the wait to see it arrive and the move's own transactions).

Velocity-continuous joints (Drive.retargets_on_the_way, not streamed: RD4, X-PLUS MT, Vector
Step in profile position): their moves are planned by trajectory.plan(continuous=...) to take
effect before the segment starts (half their speed change before the point) with the next point
as their target, so that the joint passes its points at speed. Their jobs are submitted that much
earlier, wait in the owner (giving the bus back) until their lead before the planned instant, and
solve their cruise speed again on the drive's profile from where the move before (as it really
went out) has the drive then (trajectory.solve_cruise): a move that goes out late passes its
point in time all the same, within the joint's max_velocity.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import math
import threading
import time
from typing import Callable

from ..contract.drive import Drive, DriveError, InterpolatingDrive, Motion, is_operation
from ..owner import BusOwner
from ..owner.commands import Command
from .trajectory import (
    EDGE_MARGIN,
    AxisMove,
    JointLimits,
    Segment,
    Trajectory,
    TrajectoryError,
    cruise,
    plan,
    planned_at,
    retimed,
)

logger = logging.getLogger(__name__)

TICK_S = 0.02                 # how often a run checks tolerances and cancellation
WAIT_STANDSTILL_S = 0.005     # a late axis's move waits for the segment before: checked this often
# A late axis counts as at its point within this fraction of its segment's distance (at least
# ARRIVED_STEPS): closer, it takes the next target at once
ARRIVED_FRACTION = 0.005
ARRIVED_STEPS = 2.0
LEAD_SMOOTHING = 0.5          # weight of the newest measured lead of a move
LEAD_MAX_S = 0.5              # a lead measured longer than this (a busy line) counts as this
STREAM_PREPARE_S = 0.3        # interpolated axes: mode 7 set up before a trajectory for now
GOAL_WAIT_MAX_S = 10.0        # without a goal_time_tolerance: the longest wait for standstill
# A segment lasts at least this many times what its bus needs to send the moves of its axes:
# the polls and the other drives' commands share the line meanwhile.
SEGMENT_MARGIN = 3.0
# ... and on a bus whose axes all follow velocity-continuously this many: a move that goes out a
# little late only shifts its speed change, the axis does not stop for it.
CONTINUOUS_SEGMENT_MARGIN = 2.0
# A continuous move's job is submitted this many times its bus's moves of one segment (what
# they cost) before the move's planned instant, so it is in the owner's queue by then.
CONTINUOUS_SUBMIT_AHEAD = 1.5
# An interpolated axis is where its set point was this many SYNC periods ago: the point written
# at a tick waits in the buffer behind the one before, is taken at the next tick's SYNC and
# reached one period later.
STREAM_LEAD_PERIODS = 2

# Result codes, as control_msgs/action/FollowJointTrajectory names them.
SUCCESSFUL = 0
INVALID_GOAL = -1
INVALID_JOINTS = -2
OLD_HEADER_TIMESTAMP = -3
PATH_TOLERANCE_VIOLATED = -4
GOAL_TOLERANCE_VIOLATED = -5
# A run a newer trajectory took over ends aborted with INVALID_GOAL, as JointTrajectoryController
# ends a preempted goal ("Current goal preempted by new incoming action.")
REPLACED = 'replaced by a newer goal or joint_trajectory message'
# A goal position tolerance in steps comes from joint units (step size x n is n within a few
# ulp): a position this close beyond it is within it.
ROUNDING_STEPS = 1e-6


class GoalError(TrajectoryError):
    """A trajectory refused before anything moves, with the FollowJointTrajectory result code
    of its cause."""

    def __init__(self, code: int, text: str):
        super().__init__(text)
        self.code = code


@dataclasses.dataclass
class Axis:
    """One joint the follower may move."""

    joint: str
    drive_name: str
    bus_owner: BusOwner
    drive: Drive
    limits: JointLimits
    lead_s: float = 0.0     # learned: a move's own transactions before the drive runs
    move_time_s: float = 0.0   # the drive's own estimate of lead_s (Drive.move_time_s)

    @property
    def continuous(self) -> bool:
        """Followed velocity-continuously: its drive takes a new target on the way and it gets
        point-to-point moves (trajectory.plan's `continuous`)."""
        return bool(self.drive.retargets_on_the_way) and not self.interpolated

    @property
    def interpolated(self) -> bool:
        """Its drive follows a stream of set points (Vector Step interpolated position at
        these settings), not point-to-point moves."""
        return isinstance(self.drive, InterpolatingDrive) and \
            self.drive.interpolation_period_s is not None

    def position_steps(self) -> float:
        return float(self.bus_owner.slots[self.drive_name].state.position_steps)

    def sample(self) -> tuple[float, float]:
        """(position, when it was true): the last poll's position and the bus owner's state
        time (the poll's end, or the drive's own measurement time, DriveState.measured_at_s)."""
        state, t = self.bus_owner.slots[self.drive_name].sample
        return float(state.position_steps), t

    def moving(self) -> bool:
        return bool(self.bus_owner.slots[self.drive_name].state.moving)

    def move_cost_s(self) -> float:
        """What a move costs on the bus before the drive runs: as measured once one was,
        the drive's estimate before."""
        return self.lead_s if self.lead_s > 0 else self.move_time_s

    def velocity_steps_s(self) -> float | None:
        """The last poll's velocity; None where the drive cannot report one."""
        state = self.bus_owner.slots[self.drive_name].state
        return float(state.velocity_steps_s) if state.velocity_valid else None


@dataclasses.dataclass(frozen=True)
class Outcome:
    """How a run ended: status 'succeeded', 'aborted' or 'canceled', the result code and why."""

    status: str
    code: int
    text: str


def _succeeded(text: str) -> Outcome:
    return Outcome('succeeded', SUCCESSFUL, text)


def _aborted(code: int, text: str) -> Outcome:
    return Outcome('aborted', code, text)


@dataclasses.dataclass(frozen=True)
class Tolerances:
    """Per joint, in drive units, as JointTrajectoryController resolves a goal's tolerances
    (the node turns -1 into 'not checked' and 0 into the default).

    Path (position, velocity): absent or 0: not checked. Goal position: absent or 0: one step
    (the drive's resolution); None: not checked. Goal velocity: absent or 0: standstill (the
    drive's own moving flag); None: not checked; > 0: |velocity| within it, a drive that
    reports standstill counting as 0 (a velocity reading can be older than its moving flag:
    the RD4 refreshes it once a second) and a moving one that reports no velocity as outside.
    goal_time_s: 0 no limit (until every joint stands still, at most GOAL_WAIT_MAX_S).
    path_bound_steps: how far the plan (merged segments, continuous profiles) may pass from the
    trajectory's points, per joint (the path tolerance where there is one, else the node's
    default); absent or 0: not bounded."""

    path_steps: dict[str, float] = dataclasses.field(default_factory=dict)
    goal_steps: dict[str, float | None] = dataclasses.field(default_factory=dict)
    goal_time_s: float = 0.0
    path_velocity_steps_s: dict[str, float] = dataclasses.field(default_factory=dict)
    goal_velocity_steps_s: dict[str, float | None] = dataclasses.field(default_factory=dict)
    path_bound_steps: dict[str, float] = dataclasses.field(default_factory=dict)


class Run:
    """One trajectory being followed; `done` resolves to an Outcome."""

    def __init__(self, follower: 'Follower', traj: Trajectory, start_t: float,
                 start_steps: dict[str, float], segments: list[Segment], tol: Tolerances,
                 min_segment_s: float = 0.0):
        self.follower = follower
        self.min_segment_s = min_segment_s
        self.traj = traj
        self.start_t = start_t
        self.start_steps = start_steps
        self.segments = segments
        self.tol = tol
        self.done: concurrent.futures.Future = concurrent.futures.Future()
        self.end_t = start_t + (traj.points[-1].time_s if traj.points else 0.0)
        self._cancel = threading.Event()
        # how the run ends when _cancel is set: canceled by the client, or ended from outside
        # (Follower.stop); written before _cancel is set, under the follower's submit_lock
        self._end: Outcome | None = None
        self._replaced_at: float | None = None
        self._jobs: list[concurrent.futures.Future] = []
        self._streams: list[concurrent.futures.Future] = []
        # joint: when its last move of this run had gone out (written by the owner threads'
        # jobs, read by the run thread: one dict item)
        self._moved_t: dict[str, float] = {}
        # joint: its last continuous move as it went out (when it ran, entry position and
        # velocity, target, cruise), by the owner threads' jobs, one after the other per joint
        self._went: dict[str, tuple[float, AxisMove]] = {}
        self.final_steps = dict(start_steps)
        for point in traj.points:
            self.final_steps.update(zip(traj.joints, point.positions_steps))
        # joints whose drive follows a stream of set points (Vector Step interpolated
        # position) rather than point-to-point moves
        self.streamed = {j for j in traj.joints if follower.axes[j].interpolated}
        self._thread = threading.Thread(target=self._run, name='trajectory', daemon=True)

    # ------------------------------------------------------------------------ other threads
    def desired_steps(self, t: float) -> dict[str, float]:
        """Where each joint of the trajectory should be at monotonic time t (the planned
        trapezoids, each from when its move reaches the drive)."""
        return self.desired(t)[0]

    def desired(self, t: float) -> tuple[dict[str, float], dict[str, float]]:
        """The planned position and velocity of each joint at monotonic time t."""
        return planned_at(self.segments, self.start_steps, t - self.start_t)

    def merge_summary(self) -> str | None:
        """One line on the points merged into longer segments; None when none were."""
        merged = sum(seg.merged for seg in self.segments)
        if not merged:
            return None
        worst: dict[str, float] = {}
        for seg in self.segments:
            for joint, dev in seg.deviation_steps:
                worst[joint] = max(worst.get(joint, 0.0), dev)
        far = ', '.join(f'{j} {d / self.follower.axes[j].limits.steps_per_unit:.3g} '
                        f'{self.follower.axes[j].limits.unit}' for j, d in worst.items())
        return (f'{len(self.segments) + merged} points followed as {len(self.segments)} '
                f'segments of at least {self.min_segment_s:.3g} s (what the bus needs to send '
                f"the moves of its axes) or as long as the joints' accelerations need; the "
                f"plan passes the trajectory's points within {far}")

    def cancel(self, why: str, hand_over: bool = False) -> None:
        """The client canceled: the run ends 'canceled' and its joints stop now, their stops
        urgent jobs queued before this returns (hand_over: taken by idle owners by then), so
        they reach the wire behind at most the transaction in flight. A run a newer trajectory
        has taken over stops nothing: its joints are the newer one's."""
        self._finish(Outcome('canceled', SUCCESSFUL, why), hand_over)

    def abort(self, code: int, why: str) -> None:
        """Ended from outside (an empty trajectory on the topic, the node's shutdown or
        deactivation): the run ends aborted with `code` and its joints stop."""
        self._finish(_aborted(code, why), False)

    def _finish(self, outcome: Outcome, hand_over: bool) -> None:
        # under submit_lock: a move of the run thread is either queued before the stops (which
        # drop it or cut it short) or not sent (the thread sees _cancel before it submits)
        with self.follower.submit_lock:
            if self._end is None:
                self._end = outcome
            self._cancel.set()
        if self._replaced_at is None:
            self._stop_axes(hand_over)

    def replace_at(self, t: float) -> None:
        """A newer trajectory takes over from monotonic time t: no segment from then on."""
        self._replaced_at = t

    # ------------------------------------------------------------------------- the thread
    def _run(self) -> None:
        try:
            self.done.set_result(self._follow())
        except Exception as exc:  # noqa: BLE001 - every failure ends in an outcome
            logger.exception('trajectory run failed')
            self._stop_axes()
            self.done.set_result(_aborted(INVALID_GOAL, f'trajectory failed: {exc!r}'))

    def _follow(self) -> Outcome:
        clock = self.follower.clock
        previous = dict(self.start_steps)
        before: dict[str, float] = {}       # where each axis's last move started from
        # interpolated axes: the stream starts now, holding them, so they are in mode 7 when
        # the first segment begins
        self._streams = self.follower.stream(self)
        self._jobs += self._streams
        for seg in self.segments:
            seg_t = self.start_t + seg.start_s
            if self._replaced_at is not None and seg_t >= self._replaced_at:
                return _aborted(INVALID_GOAL, REPLACED)
            problem = self._wait_until(seg_t + self._ahead_s(seg))
            if problem is not None:
                return problem
            if self._replaced():
                return _aborted(INVALID_GOAL, REPLACED)
            # The moves go out back to back. An axis still on its way to the point before (it
            # arrived late, _still_on_the_way) gets its move once it stands there, so that it
            # passes the point; one that is there, or was on plan at its last snapshot (on a
            # serial line up to a poll period old: waiting for a newer one would make every
            # segment late), takes the new target at once (on the way where its drive can: RD4
            # position override, X-PLUS MT and Vector Step change set immediately). An axis with
            # no move of this run yet is on no way of this run's: a run that takes over from
            # another sends its first moves at once, whatever the old run's move is doing. A
            # drive that takes no command while it runs (X-MIND K) waits in
            # until_ready_for_move for a run that ends.
            # Rest-to-rest moves of two or more axes on one bus that can start them in one
            # instant (Bus.group_start: the X-MIND K's broadcast) go out as one job, once every
            # one of them may start (none still on the way).
            end_t = self.start_t + seg.end_s
            waiting = self._units([m for m in seg.moves if m.joint not in self.streamed])
            while waiting:
                for unit in list(waiting):
                    on_the_way = [
                        move.joint in before and self._still_on_the_way(
                            self.follower.axes[move.joint], seg_t, previous[move.joint],
                            before[move.joint], self._to(move))
                        for move in unit]
                    if clock() < end_t and any(on_the_way):
                        continue
                    with self.follower.submit_lock:
                        if self._cancel.is_set():
                            return self._end
                        if self._replaced():
                            return _aborted(INVALID_GOAL, REPLACED)
                        self._submit(unit, previous, seg_t, end_t)
                    for move in unit:
                        before[move.joint] = previous[move.joint]
                        previous[move.joint] = self._to(move)
                    waiting.remove(unit)
                if waiting:
                    problem = self._check()
                    if problem is not None:
                        return problem
                    self._cancel.wait(WAIT_STANDSTILL_S)
        problem = self._wait_until(self.end_t)
        if problem is not None:
            return problem
        for joint in self.traj.joints:     # the end seen at once, not at the next poll
            axis = self.follower.axes[joint]
            axis.bus_owner.poll_soon(axis.drive_name)
        if self._replaced_at is not None:
            return _aborted(INVALID_GOAL, REPLACED)
        # goal_time_tolerance 0: no time limit (JointTrajectoryController's meaning), here until
        # every joint stands still, at most GOAL_WAIT_MAX_S
        deadline = self.end_t + (self.tol.goal_time_s or GOAL_WAIT_MAX_S)
        while True:
            problem = self._check()
            if problem is not None:
                return problem
            far = self._off_goal()
            if not far:
                return _succeeded('every joint reached its goal')
            if not self.tol.goal_time_s and self._standing():
                return _aborted(GOAL_TOLERANCE_VIOLATED, '; '.join(far))
            if clock() >= deadline:
                self._stop_axes()
                return _aborted(GOAL_TOLERANCE_VIOLATED, '; '.join(far))
            self._cancel.wait(TICK_S)

    @staticmethod
    def _to(move) -> float:
        """Where the move takes its axis by the segment's end (a continuous move's point)."""
        return move.target_steps if move.via_steps is None else move.via_steps

    def _units(self, moves: list) -> list[list]:
        """The segment's moves as they are submitted: each alone, but the rest-to-rest moves
        of two or more axes on one bus with a group start together (in the order of their
        first move)."""
        units: list[list] = []
        groups: dict[int, list] = {}
        for move in moves:
            axis = self.follower.axes[move.joint]
            if move.via_steps is None:
                group = groups.get(id(axis.bus_owner))
                if group is None:
                    group = groups[id(axis.bus_owner)] = []
                    units.append(group)
                group.append(move)
            else:
                units.append([move])
        out: list[list] = []
        for unit in units:
            axes = [self.follower.axes[m.joint] for m in unit]
            if len(unit) > 1 and axes[0].drive.bus.group_start(
                    [a.drive for a in axes]) is None:
                out += [[m] for m in unit]           # no group start: one job per axis
            else:
                out.append(unit)
        return out

    def _submit(self, unit: list, previous: dict[str, float], seg_t: float,
                end_t: float) -> None:
        """Submit the unit's job(s) (under submit_lock): one move job per axis, or for a
        group one job under its first axis's drive that also writes the others' drives."""
        axes = [self.follower.axes[m.joint] for m in unit]
        starter = axes[0].drive.bus.group_start([a.drive for a in axes]) \
            if len(unit) > 1 else None
        if starter is None:
            for axis, move in zip(axes, unit):
                self._jobs.append(axis.bus_owner.submit(axis.drive_name, Command.move(
                    self._move_job(axis, move, previous[move.joint], seg_t, end_t),
                    f'trajectory segment to {move.target_steps:g} steps')))
            return
        members = [(a, m, previous[m.joint]) for a, m in zip(axes, unit)]
        self._jobs.append(axes[0].bus_owner.submit(axes[0].drive_name, Command.move(
            self._group_job(starter, members, seg_t, end_t),
            f'trajectory segment of {[a.joint for a in axes]} started together',
            also=tuple(a.drive_name for a in axes[1:]))))

    def _group_job(self, starter: Callable, members: list, seg_t: float,
                   end_t: float) -> Callable:
        """One job that starts the rest-to-rest moves of several axes of one bus in one
        instant (Bus.group_start). As _move_job per axis: each axis's run before ends first,
        the profile is computed again for the time really left, `_moved_t` per joint; the
        lead (job start to the starting string on the wire) is the group's, each axis
        learning its share, so that the bus's moves of one segment cost it (min_segment_s).

        A member the starter left out (`skipped`: a stop or disable of its drive since the
        job was decided, a refusal, a write without its confirmation) did not get its move:
        the job fails, naming it, and the run stops its joints and ends aborted, as for a
        failed segment job. It is not sent again on its own: a stop that came between must
        stay a stop, and the other joints have already left without it."""
        clock = self.follower.clock

        def job():
            for axis, _, _ in members:
                ready = axis.drive.until_ready_for_move()   # (X-MIND K: its run ends first)
                if ready is not None:
                    yield from ready
            t0 = clock()
            lead_s = sum(axis.lead_s for axis, _, _ in members)
            moves = []
            for axis, move, from_steps in members:
                runs_t = max(t0 + lead_s, seg_t + move.start_delay_s)
                v, a = self._retimed(axis, move, from_steps, end_t - runs_t)
                if math.isinf(a):                # start-stop: the drive ignores the ramp
                    a = axis.limits.max_acceleration_steps_s2
                moves.append((axis.drive, int(round(move.target_steps)), Motion(v, a, a)))
            result = yield from starter(moves)
            now = clock()
            skipped = getattr(result, 'skipped', {})
            for axis, _, _ in members:
                if axis.drive_name not in skipped:
                    self._moved_t[axis.joint] = now
            sent = getattr(result, 'sent_t', None)
            lead = (sent if sent is not None and sent >= t0 else now) - t0
            share = min(lead, LEAD_MAX_S) / len(members)
            for axis, _, _ in members:
                axis.lead_s += LEAD_SMOOTHING * (share - axis.lead_s)
            if skipped:
                names = {axis.drive_name: axis.joint for axis, _, _ in members}
                raise DriveError('; '.join(f'{names.get(name, name)}: its move did not go '
                                           f'out ({why})' for name, why in skipped.items()))
            return result
        return job

    def _standing(self) -> bool:
        """The run is over: no job of it is left (a move that has not gone out yet; a stream
        still running: an interpolated axis rests between set points now and then, its
        'moving' is no sign of the end), and every joint stands still as a snapshot since its
        last move shows (an older one is asked for: the drive is polled at once)."""
        if not all(f.done() for f in self._jobs):
            return False
        for joint in self.traj.joints:
            axis = self.follower.axes[joint]
            _, at = axis.sample()
            if at < self._moved_t.get(joint, -math.inf):
                axis.bus_owner.poll_soon(axis.drive_name)
                return False
            if axis.moving():
                return False
        return True

    def _still_on_the_way(self, axis: Axis, seg_t: float, target: float, start: float,
                          next_target: float) -> bool:
        """The axis is short of `target` (its last move's, from `start`) by more than
        ARRIVED_FRACTION of that move's distance: as a snapshot since seg_t shows it moving, or,
        where the last snapshot is older, as that one was behind the plan by as much (then the
        drive is polled at once, and the next check has a snapshot since seg_t). Never where
        its drive takes `next_target` on the way and that lies beyond `target` in the
        direction of travel: the axis passes `target` on its way."""
        if axis.drive.retargets_on_the_way and (next_target - target) * (target - start) > 0:
            return False
        position, at = axis.sample()
        if not axis.moving():
            return False
        short = max(ARRIVED_STEPS, ARRIVED_FRACTION * abs(target - start))
        if at >= seg_t:
            return abs(target - position) > short
        if abs(self.desired_steps(at)[axis.joint] - position) <= short:
            return False                     # on plan then: it arrives with the plan
        axis.bus_owner.poll_soon(axis.drive_name)
        return True

    def _ahead_s(self, seg: Segment) -> float:
        """When the segment's moves are submitted, against its start: its continuous moves'
        earliest planned instant (<= 0), less CONTINUOUS_SUBMIT_AHEAD times what their moves
        cost on the bus; 0 for a segment of rest-to-rest moves only."""
        cont = [m for m in seg.moves if m.via_steps is not None]
        if not cont:
            return 0.0
        cost = sum(self.follower.axes[m.joint].move_cost_s() for m in cont)
        return min(m.start_delay_s for m in cont) - CONTINUOUS_SUBMIT_AHEAD * cost

    def _continuous_job(self, axis: Axis, move, seg_t: float, end_t: float) -> Callable:
        """A continuous move's job (the module's docstring): it waits until its lead before the
        move's planned instant, then sends the speed that passes the segment's point at its
        end from where the drive is then on the profile of the move before."""
        clock = self.follower.clock
        lim = axis.limits

        def job():
            effect_t = seg_t + move.start_delay_s
            early = effect_t - axis.lead_s - clock()
            if early > 0:
                yield early                          # the bus is the other drives' meanwhile
            t0 = clock()
            runs_t = max(t0 + axis.lead_s, effect_t)
            went = self._went.get(axis.joint)
            if went is None:                         # the run's first: where the plan has it
                x, u = move.entry_steps, move.entry_velocity_steps_s
            else:
                x, u = went[1].state(runs_t - went[0])
                # closed on the drive's position: as far off the move before's profile as its
                # last snapshot since that move (a drive that lags keeps no lag to its point)
                position, at = axis.sample()
                if went[0] <= at and t0 - at <= LEAD_MAX_S:
                    x += position - went[1].state(at - went[0])[0]
            found = None
            if (move.via_steps - x) * (move.via_steps - move.target_steps) <= 0:
                found = cruise(x, u, move.via_steps, move.target_steps, end_t - runs_t,
                               move.acceleration_steps_s2, lim)
            if found is None:
                # past its point already (the plan's speed), or it passes it late (the fastest)
                past = (move.via_steps - x) * (move.via_steps - move.target_steps) > 0
                top = EDGE_MARGIN * lim.max_acceleration_steps_s2
                found = (move.velocity_steps_s, move.acceleration_steps_s2,
                         move.deceleration_steps_s2) if past else \
                    (lim.max_velocity_steps_s, top, top)
            v, a, dec = found
            if move.velocity_steps_s <= lim.start_stop_steps_s < v:
                # start-stop as planned, a little late, rather than ramps that make it later
                v, a, dec = (move.velocity_steps_s, move.acceleration_steps_s2,
                             move.deceleration_steps_s2)
            # (start-stop: the drive ignores its ramp registers)
            result = axis.drive.move_to(int(round(move.target_steps)), Motion(v, a, dec))
            if is_operation(result):
                result = yield from result
            self._went[axis.joint] = (runs_t, dataclasses.replace(
                move, velocity_steps_s=v, acceleration_steps_s2=a, deceleration_steps_s2=dec,
                entry_steps=x, entry_velocity_steps_s=u))
            self._moved(axis, t0)
            return result
        return job

    def _move_job(self, axis: Axis, move, from_steps: float, seg_t: float, end_t: float
                  ) -> Callable:
        if move.via_steps is not None:
            return self._continuous_job(axis, move, seg_t, end_t)
        clock = self.follower.clock

        def job():
            ready = axis.drive.until_ready_for_move()    # (X-MIND K: its run ends first)
            if ready is not None:
                yield from ready
            t0 = clock()
            # the drive runs after this move's own transactions, and not before the plan
            # expects it to (the moves of the other axes on the bus go out meanwhile)
            runs_t = max(t0 + axis.lead_s, seg_t + move.start_delay_s)
            v, a = self._retimed(axis, move, from_steps, end_t - runs_t)
            if math.isinf(a):                    # start-stop: the drive ignores the ramp
                a = axis.limits.max_acceleration_steps_s2
            result = axis.drive.move_to(int(round(move.target_steps)), Motion(v, a, a))
            if is_operation(result):
                result = yield from result
            self._moved(axis, t0)
            return result
        return job

    def _moved(self, axis: Axis, t0: float) -> None:
        """(Owner thread, a move job of `axis` that began at t0 ended) Its move went out, and
        its own transactions (checks, writes) before the drive runs are learned: up to its
        motion frame where the move goes on after it (a set-point handshake)."""
        now = self.follower.clock()
        self._moved_t[axis.joint] = now
        sent = axis.drive.motion_sent_t
        lead = (sent if sent is not None and sent >= t0 else now) - t0
        axis.lead_s += LEAD_SMOOTHING * (min(lead, LEAD_MAX_S) - axis.lead_s)

    @staticmethod
    def _retimed(axis: Axis, move, from_steps: float, left_s: float) -> tuple[float, float]:
        """The segment's profile for the time really left (trajectory.retimed), else the
        planned one (it arrives late)."""
        planned = (move.velocity_steps_s, move.acceleration_steps_s2)
        again = retimed(move.target_steps - from_steps, left_s, planned, axis.limits)
        return planned if again is None else again

    def _wait_until(self, t: float) -> Outcome | None:
        clock = self.follower.clock
        while True:
            problem = self._check()
            if problem is not None:
                return problem
            left = t - clock()
            if left <= 0:
                return None
            self._cancel.wait(min(left, TICK_S))

    def _replaced(self) -> bool:
        """A newer trajectory has taken over by now."""
        return self._replaced_at is not None and self.follower.clock() >= self._replaced_at

    def _check(self) -> Outcome | None:
        if self._cancel.is_set():
            return self._end
        if self._replaced():
            return _aborted(INVALID_GOAL, REPLACED)
        for fut in self._jobs:
            if fut.done() and fut.exception() is not None:
                self._stop_axes()
                return _aborted(INVALID_GOAL, f'a segment failed: {fut.exception()}')
        now = self.follower.clock()
        for joint, tol in self.tol.path_steps.items():
            if tol > 0 and joint in self.follower.axes:
                # the plan at the time the position was true, not now: a position up to a poll
                # period old (and a Vector Step's TxPDO inhibit time) is no path error
                position, at = self.follower.axes[joint].sample()
                at = min(at, now)
                desired = self.desired_steps(at).get(joint)
                if desired is None:
                    continue
                err = position - desired
                if abs(err) > tol:
                    self._stop_axes()
                    return _aborted(PATH_TOLERANCE_VIOLATED,
                                    f'{joint}: {err:+.0f} steps from the path (path tolerance '
                                    f'{tol:g} steps) at {now - self.start_t:.3f} s, by its '
                                    f'position of {at - self.start_t:.3f} s')
        for joint, tol in self.tol.path_velocity_steps_s.items():
            if tol > 0 and joint in self.follower.axes:
                axis = self.follower.axes[joint]
                velocity = axis.velocity_steps_s()
                if velocity is None:
                    continue                   # refused at the goal: the drive reports none
                _, at = axis.sample()
                err = velocity - self.desired(min(at, now))[1].get(joint, 0.0)
                if abs(err) > tol:
                    self._stop_axes()
                    return _aborted(PATH_TOLERANCE_VIOLATED,
                                    f"{joint}: velocity {err:+.0f} steps/s from the path's "
                                    f'(path velocity tolerance {tol:g} steps/s) at '
                                    f'{now - self.start_t:.3f} s')
        return None

    def _off_goal(self) -> list[str]:
        far = []
        for joint in self.traj.joints:
            axis = self.follower.axes[joint]
            why = []
            tol = self.tol.goal_steps.get(joint, 0.0)
            if tol is not None:
                tol = tol or 1.0                          # the default: the final step
                err = axis.position_steps() - self.final_steps[joint]
                if abs(err) > tol + ROUNDING_STEPS:
                    why.append(f'{err:+.0f} steps from the goal (goal tolerance {tol:.6g} '
                               'steps)')
            vtol = self.tol.goal_velocity_steps_s.get(joint, 0.0)
            if vtol is None or not axis.moving():
                pass                          # not checked, or standing: at velocity 0
            elif not vtol:
                why.append('still moving')
            else:
                velocity = axis.velocity_steps_s()
                if velocity is None:
                    why.append('still moving (its drive reports no velocity)')
                elif abs(velocity) > vtol:
                    why.append(f'at {velocity:+.0f} steps/s (goal velocity tolerance {vtol:.6g} '
                               'steps/s)')
            if why:
                far.append(f'{joint}: {", ".join(why)}')
        return far

    def _stop_axes(self, hand_over: bool = False) -> None:
        for joint in self.traj.joints:
            self.follower.stop_axis(self.follower.axes[joint], 'trajectory stopped', hand_over)


class Follower:
    """The node's trajectories: one at a time; a new one replaces the rest of the one before
    it from its own start time; an empty one stops the joints of the one running."""

    def __init__(self, axes: dict[str, Axis], clock: Callable[[], float] = time.monotonic):
        self.axes = axes
        self.clock = clock
        self._lock = threading.Lock()
        # Held while a run checks that it is not replaced and submits a move, and while the
        # joints a newer run does not name are stopped at its take-over: a replaced run's move
        # is either queued before that stop (which drops it, or cuts it short) or not sent.
        self.submit_lock = threading.Lock()
        self.current: Run | None = None
        self._streams: dict[int, Stream] = {}

    def follow(self, traj: Trajectory, start_t: float | None = None,
               tol: Tolerances = Tolerances()) -> Run:
        """Plan and start `traj` at monotonic start_t (None: now); TrajectoryError (nothing
        moves) when it cannot be followed."""
        with self._lock:
            old = self.current
            start_t, take_over, start_steps, segments, min_segment_s = self._plan(
                traj, start_t, tol, old)
            run = Run(self, traj, start_t, start_steps, segments, tol, min_segment_s)
            if old is not None and not old.done.done():
                old.replace_at(take_over)
                # joints the new trajectory does not name hold: those the old one was moving
                # stop at the take-over (JointTrajectoryController holds them the same way)
                held = [j for j in old.traj.joints if j not in traj.joints]
                if held:
                    self._stop_later(held, take_over)
            self.current = run
        run._thread.start()
        return run

    def check(self, traj: Trajectory, start_t: float | None = None,
              tol: Tolerances = Tolerances()) -> None:
        """What follow() would refuse if it were called now, without starting anything (the
        action's goal callback): the TrajectoryError it would raise."""
        with self._lock:
            self._plan(traj, start_t, tol, self.current)

    def _plan(self, traj: Trajectory, start_t: float | None, tol: Tolerances,
              old: Run | None) -> tuple[float, float, dict[str, float], list[Segment], float]:
        """(start_t, take-over time, start positions, segments, least segment duration) of
        `traj` planned now, taking over from `old` where it runs."""
        now = self.clock()
        start_t = now if start_t is None else start_t
        if traj.points and start_t + traj.points[-1].time_s < now:
            ago = now - start_t - traj.points[-1].time_s
            raise GoalError(OLD_HEADER_TIMESTAMP, f'the trajectory ended {ago:.3f} s ago '
                            '(header.stamp plus the last time_from_start)')
        running = old is not None and not old.done.done()
        if any(self.axes[j].interpolated for j in traj.joints) \
                and start_t < now + STREAM_PREPARE_S and not running:
            # interpolated axes need their drives in mode 7 before the first point: a
            # trajectory for now starts STREAM_PREPARE_S later, on every axis alike
            start_t = now + STREAM_PREPARE_S
        take_over = max(start_t, now)
        start_velocity: dict[str, float] = {}
        if running:
            start_steps, start_velocity = old.desired(take_over)
            start_steps = {j: start_steps.get(j, self.axes[j].position_steps())
                           for j in traj.joints}
        else:
            start_steps = {j: self.axes[j].position_steps() for j in traj.joints}
        min_segment_s = self.min_segment_s(traj.joints)
        bound = {j: tol.path_bound_steps.get(j) or tol.path_steps.get(j, 0.0)
                 for j in traj.joints}
        segments = plan(traj, start_steps, {j: self.axes[j].limits for j in traj.joints},
                        from_s=max(0.0, now - start_t), min_segment_s=min_segment_s,
                        path_tolerance_steps=bound,
                        move_times_s=self.move_times_s(traj.joints),
                        continuous={j for j in traj.joints if self.axes[j].continuous},
                        start_velocity_steps_s={j: start_velocity.get(j, 0.0)
                                                for j in traj.joints})
        return start_t, take_over, start_steps, segments, min_segment_s

    def move_times_s(self, joints) -> dict[str, tuple[object, float]]:
        """Per joint moved by moves (not streamed): its bus and what a move costs there (the
        measured time, or the drive's estimate before the first)."""
        return {j: (id(self.axes[j].bus_owner), self.axes[j].move_cost_s())
                for j in joints if not self.axes[j].interpolated}

    def min_segment_s(self, joints) -> float:
        """The least duration of a segment: what the busiest bus needs to send one move to
        each of its axes (a move's measured time, or the drive's estimate before the first),
        times SEGMENT_MARGIN (CONTINUOUS_SEGMENT_MARGIN where every axis of the bus follows
        velocity-continuously). Streamed (interpolated) axes take no moves."""
        per_bus: dict[int, float] = {}
        stepwise: set[int] = set()
        for joint in joints:
            axis = self.axes[joint]
            if not axis.interpolated:
                per_bus[id(axis.bus_owner)] = per_bus.get(id(axis.bus_owner),
                                                          0.0) + axis.move_cost_s()
                if not axis.continuous:
                    stepwise.add(id(axis.bus_owner))
        return max((cost * (SEGMENT_MARGIN if bus in stepwise else CONTINUOUS_SEGMENT_MARGIN)
                    for bus, cost in per_bus.items()), default=0.0)

    def _stop_later(self, joints: list[str], t: float) -> None:
        def stop():
            with self.submit_lock:
                for j in joints:
                    self.stop_axis(self.axes[j], 'held: not in the newer trajectory')
        delay = t - self.clock()
        if delay <= 0:
            stop()
        else:
            timer = threading.Timer(delay, stop)
            timer.daemon = True
            timer.start()

    def stop(self, why: str) -> None:
        """An empty trajectory on the topic, the node's shutdown or deactivation: stop the
        joints of the running trajectory; it ends aborted (INVALID_GOAL, as
        JointTrajectoryController ends a goal at its deactivation), `why` its text."""
        with self._lock:
            run = self.current
        if run is not None and not run.done.done():
            run.abort(INVALID_GOAL, why)

    # ------------------------------------------------------------------ interpolated axes
    def stream(self, run: Run) -> list[concurrent.futures.Future]:
        """The streaming jobs `run`'s interpolated joints need: one per bus, shared with the
        run before it when that one streamed the same bus (a newer trajectory continues the
        stream from its take-over)."""
        futs = []
        by_bus: dict[int, list[Axis]] = {}
        for joint in run.traj.joints:
            if joint in run.streamed:
                axis = self.axes[joint]
                by_bus.setdefault(id(axis.bus_owner), []).append(axis)
        with self._lock:
            for key, axes in by_bus.items():
                job = self._streams.get(key)
                if job is None or job.future.done() or \
                        not {a.joint for a in axes} <= set(job.axes):
                    job = Stream(self, axes)
                    self._streams[key] = job
                    job.future = axes[0].bus_owner.submit(axes[0].drive_name, Command.move(
                        job.run, f'interpolated trajectory of {[a.joint for a in axes]}',
                        polled=True))
                futs.append(job.future)
        return futs

    def stop_axis(self, axis: Axis, label: str, hand_over: bool = False
                  ) -> concurrent.futures.Future:
        """The axis's stop, an urgent job (hand_over: from a ROS callback, as
        BusOwner.submit describes)."""
        return axis.bus_owner.submit(axis.drive_name, Command.stop(axis.drive.stop, label),
                               hand_over=hand_over)


class Stream:
    """One bus's interpolated axes (Vector Step mode 7): a step-wise job of the bus owner that
    starts interpolation on every axis, then, once a SYNC period, writes each axis's position of
    the current trajectory one buffer ahead (STREAM_LEAD_PERIODS) and sends the SYNC itself, so
    each drive takes exactly one point per SYNC: its two-position buffer never runs dry (EMCY
    FF03) or over. The periodic SYNC producer is paused meanwhile and restarted at the end, also
    when a stop cuts the job short (a node that hangs sends no SYNC: the drives' SYNC watchdogs
    stop them). Ends a few periods after the current trajectory's end, leaving the axes at rest
    out of interpolation (bit 4 low)."""

    def __init__(self, follower: Follower, axes: list[Axis]):
        self.follower = follower
        self.axes = {a.joint: a for a in axes}
        self.period_s = axes[0].drive.interpolation_period_s
        self.bus = axes[0].drive.bus
        self.future: concurrent.futures.Future | None = None
        self.held: dict[str, float] = {}

    def run(self):
        clock = self.follower.clock
        self.bus.own_sync()
        try:
            next_t = clock()
            for axis in self.axes.values():           # SYNC goes on between the steps
                steps = axis.drive.start_interpolation(self.period_s)
                try:
                    while True:
                        delay = next(steps)
                        next_t = self._tick(next_t, started=self.held)
                        yield min(delay, max(0.0, next_t - clock()))
                except StopIteration as done:
                    self.held[axis.joint] = float(done.value)
            while True:
                next_t = self._tick(next_t, started=self.held, final=True)
                if next_t is None:
                    break
                yield max(0.0, next_t - clock())
        finally:
            self.bus.periodic_sync()
        for axis in self.axes.values():              # at rest on the last point: leave mode 7
            axis.drive.stop()

    def _tick(self, next_t: float, started: dict, final: bool = False) -> float | None:
        """At or after next_t: one point per started axis, then the SYNC. Returns the next
        tick time; None (final) once the current trajectory is over."""
        clock = self.follower.clock
        now = clock()
        if now < next_t:
            return next_t
        run = self.follower.current
        lead_t = now + STREAM_LEAD_PERIODS * self.period_s
        desired = run.desired_steps(lead_t) if run is not None else {}
        for joint in started:
            if joint in desired and joint in run.traj.joints:
                started[joint] = desired[joint]
            self.axes[joint].drive.interpolation_point(int(round(started[joint])))
        self.bus.send_sync()
        if final and (run is None or run.done.done() or not set(self.axes) & set(run.traj.joints)
                      or now > run.end_t + (STREAM_LEAD_PERIODS + 3) * self.period_s):
            return None
        following = next_t + self.period_s
        # late by more than a period (a busy owner): the next SYNC a period from now, not a
        # burst of them (the drives check the SYNC timing: EMCY FF04 too early)
        return following if following > now else now + self.period_s
