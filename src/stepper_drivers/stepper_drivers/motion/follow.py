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
(capabilities.Retargeting) and the axis goes on in the same direction, it passes the point on
its way to the next one: that move goes at once, so a late axis is not held at every point
(each hold would add the wait to see it arrive and the move's own transactions).

Velocity-continuous joints (capabilities.Retargeting, not streamed: RD4, X-PLUS MT, Vector
Step in profile position): their moves are planned by trajectory.plan(continuous=...) to take
effect before the segment starts (half their speed change before the point) with the next point
as their target, so that the joint passes its points at speed. Their jobs are submitted that much
earlier, wait in the owner (giving the bus back) until their lead before the planned instant, and
solve their cruise speed again on the drive's profile from where the move before (as it really
went out) has the drive then (continuous.solve_cruise): a move that goes out late passes its
point in time all the same, within the joint's max_velocity.

Here: the Follower (one trajectory at a time: planning, take-over, stops) and each Run (when
its segments' moves go, the checks while it runs, its outcome). Elsewhere: the joints (Axis,
axis.py), the jobs that send the moves (moves.py), the interpolated stream (stream.py), the
tolerances and their checks (tolerances.py), the plan (trajectory.py, continuous.py).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import math
import threading
import time
from typing import Callable

from ..contract.capabilities import Retargeting
from ..owner.commands import Command
from .axis import Axis
from .chain import chained_plan
from .moves import MoveJobs, retimed_move
from .stream import Streams
from .tolerances import Tolerances, off_goal, off_path
from .trajectory import (
    Segment,
    Trajectory,
    TrajectoryError,
    check_positions,
    plan,
    planned_at,
)

logger = logging.getLogger(__name__)

TICK_S = 0.02                 # how often a run checks tolerances and cancellation
WAIT_STANDSTILL_S = 0.005     # a late axis's move waits for the segment before: checked this often
# A late axis counts as at its point within this fraction of its segment's distance (at least
# ARRIVED_STEPS): closer, it takes the next target at once
ARRIVED_FRACTION = 0.005
ARRIVED_STEPS = 2.0
STREAM_PREPARE_S = 0.3        # interpolated axes: mode 7 set up before a trajectory for now
GOAL_WAIT_MAX_S = 10.0        # without a goal_time_tolerance: the longest wait for standstill
# A segment lasts at least this many times what its bus needs to send the moves of its axes:
# the polls and the other drives' commands share the line meanwhile.
SEGMENT_MARGIN = 3.0
# ... and on a bus whose axes all follow velocity-continuously this many: a move that goes out a
# little late only shifts its speed change, the axis does not stop for it.
CONTINUOUS_SEGMENT_MARGIN = 2.0

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
# follow() and check() without tolerances: each one's default (Tolerances)
_NO_TOLERANCES = Tolerances()


class GoalError(TrajectoryError):
    """A trajectory refused before anything moves, with the FollowJointTrajectory result code
    of its cause."""

    def __init__(self, code: int, text: str):
        super().__init__(text)
        self.code = code


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
        # the jobs of its moves, and what they leave: when each joint's last move went out
        self._moves = MoveJobs(follower)
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
        """One line on the points merged into longer segments or a chain; None when none
        were."""
        merged = sum(seg.merged for seg in self.segments)
        chain = self.segments[0].moves[0].knots if len(self.segments) == 1 and \
            self.segments[0].moves else ()
        if not merged and not chain:
            return None
        worst: dict[str, float] = {}
        for seg in self.segments:
            for joint, dev in seg.deviation_steps:
                worst[joint] = max(worst.get(joint, 0.0), dev)
        far = ', '.join(f'{j} {d / self.follower.axes[j].limits.steps_per_unit:.3g} '
                        f'{self.follower.axes[j].limits.unit}' for j, d in worst.items())
        if chain:
            return (f'{len(chain) + merged} points followed as one chain of {len(chain)} '
                    'runs per joint, stored in the drives and run back to back at constant '
                    f"rates; the plan passes the trajectory's points within {far}")
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
        previous = dict(self.start_steps)   # where each axis's last move takes it
        before: dict[str, float] = {}       # where each axis's last move started from
        # interpolated axes: the stream starts now, holding them, so they are in mode 7 when
        # the first segment begins
        self._streams = self.follower.stream(self)
        self._jobs += self._streams
        for seg in self.segments:
            problem = self._segment(seg, previous, before)
            if problem is not None:
                return problem
        return self._at_the_end()

    def _segment(self, seg: Segment, previous: dict[str, float], before: dict[str, float]
                 ) -> Outcome | None:
        """Wait for the segment and send its moves; an Outcome where the run ends first."""
        seg_t = self.start_t + seg.start_s
        if self._replaced_at is not None and seg_t >= self._replaced_at:
            return _aborted(INVALID_GOAL, REPLACED)
        problem = self._wait_until(seg_t + self._moves.ahead_s(seg))
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
        # instant (capabilities.GroupStarting: the X-MIND K's broadcast) go out as one job,
        # once every one of them may start (none still on the way).
        return self._send_moves(seg, seg_t, previous, before)

    def _send_moves(self, seg: Segment, seg_t: float, previous: dict[str, float],
                    before: dict[str, float]) -> Outcome | None:
        """Submit the segment's moves (not the streamed joints'), each unit as soon as it may
        go (_held_back), checking the run while one waits; an Outcome where the run ends."""
        end_t = self.start_t + seg.end_s
        waiting = self._moves.units([m for m in seg.moves if m.joint not in self.streamed])
        while waiting:
            for unit in list(waiting):
                if self._held_back(unit, seg_t, end_t, previous, before):
                    continue
                problem = self._send(unit, previous, seg_t, end_t)
                if problem is not None:
                    return problem
                for move in unit:
                    before[move.joint] = previous[move.joint]
                    previous[move.joint] = self._to(move)
                waiting.remove(unit)
            if waiting:
                problem = self._check()
                if problem is not None:
                    return problem
                self._cancel.wait(WAIT_STANDSTILL_S)
        return None

    def _held_back(self, unit: list, seg_t: float, end_t: float, previous: dict[str, float],
                   before: dict[str, float]) -> bool:
        """The unit waits: an axis of it is still on its way to its point (_still_on_the_way,
        asked of every axis of the unit that has had a move of this run), and the segment's
        end has not come."""
        on_the_way = [
            move.joint in before and self._still_on_the_way(
                self.follower.axes[move.joint], seg_t, previous[move.joint],
                before[move.joint], self._to(move))
            for move in unit]
        return self.follower.clock() < end_t and any(on_the_way)

    def _send(self, unit: list, previous: dict[str, float], seg_t: float,
              end_t: float) -> Outcome | None:
        """Submit the unit's job(s) unless the run has ended (canceled, replaced by now): then
        its Outcome, and nothing is sent."""
        with self.follower.submit_lock:
            if self._cancel.is_set():
                return self._end
            if self._replaced():
                return _aborted(INVALID_GOAL, REPLACED)
            self._jobs += self._moves.submit(unit, previous, seg_t, end_t)
        return None

    def _at_the_end(self) -> Outcome:
        """After the last segment: once the trajectory's time is over, the outcome as the
        joints arrive (every one within its goal tolerances), stand still short of it, or the
        goal time is up."""
        clock = self.follower.clock
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
            far = off_goal(self.tol, self.follower.axes, self.traj.joints, self.final_steps)
            if not far:
                return _succeeded('every joint reached its goal')
            if not self.tol.goal_time_s and self._standing():
                return _aborted(GOAL_TOLERANCE_VIOLATED, '; '.join(far))
            if clock() >= deadline:
                self._stop_axes()
                return _aborted(GOAL_TOLERANCE_VIOLATED, '; '.join(far))
            self._cancel.wait(TICK_S)

    # a rest-to-rest move's profile for the time really left (its job's: moves.retimed_move)
    _retimed = staticmethod(retimed_move)

    @staticmethod
    def _to(move) -> float:
        """Where the move takes its axis by the segment's end (a continuous move's point)."""
        return move.target_steps if move.via_steps is None else move.via_steps

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
            if at < self._moves.moved_t.get(joint, -math.inf):
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
        if isinstance(axis.drive, Retargeting) and (next_target - target) * (target - start) > 0:
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
        why = off_path(self.tol, self.follower.axes, self.desired, self.follower.clock(),
                       self.start_t)
        if why is not None:
            self._stop_axes()
            return _aborted(PATH_TOLERANCE_VIOLATED, why)
        return None

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
        # the interpolated axes' streams, one per bus, kept under _lock
        self._streams = Streams(self, self._lock)

    def follow(self, traj: Trajectory, start_t: float | None = None,
               tol: Tolerances = _NO_TOLERANCES, received_t: float | None = None) -> Run:
        """Plan and start `traj` at monotonic start_t (None: now, or when it was received:
        `received_t`, _start_for_now); TrajectoryError (nothing moves) when it cannot be
        followed."""
        with self._lock:
            old = self.current
            start_t, take_over, start_steps, segments, min_segment_s = self._plan(
                traj, start_t, tol, old, received_t=received_t)
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
              tol: Tolerances = _NO_TOLERANCES, received_t: float | None = None) -> None:
        """What follow() would refuse if it were called now, without starting anything (the
        action's goal callback): the TrajectoryError it would raise. (A chain is planned only
        where the segments are refused: it is taken only within the bound, so it changes no
        verdict.)"""
        with self._lock:
            self._plan(traj, start_t, tol, self.current, decide=False, received_t=received_t)

    @staticmethod
    def _start_for_now(traj: Trajectory, received_t: float | None, now: float) -> float:
        """When a trajectory without a start time (a zero header stamp) starts: when it was
        received (JointTrajectoryController starts one at its first update after that), so the
        time the node takes to check and plan it is made up by its first moves, not kept by the
        joints as a lag to the end; now where that would leave a point of it in the past."""
        first = next((p.time_s for p in traj.points if p.time_s > 0), None)
        return received_t if received_t is not None and first is not None \
            and now - received_t < first else now

    def _plan(self, traj: Trajectory, start_t: float | None, tol: Tolerances,
              old: Run | None, decide: bool = True, received_t: float | None = None
              ) -> tuple[float, float, dict[str, float], list[Segment], float]:
        """(start_t, take-over time, start positions, segments, least segment duration) of
        `traj` planned now, taking over from `old` where it runs; `decide` False: the chain
        only where the segments are refused."""
        now = self.clock()
        if start_t is None:
            start_t = self._start_for_now(traj, received_t, now)
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
        limits = {j: self.axes[j].limits for j in traj.joints}
        from_s = max(0.0, now - start_t)
        check_positions(traj.joints, [(k, p) for k, p in enumerate(traj.points)
                                      if p.time_s > from_s], limits)
        segments: list[Segment] | None = None
        try:
            segments = plan(traj, start_steps, limits, from_s=from_s,
                            min_segment_s=min_segment_s, path_tolerance_steps=bound,
                            move_times_s=self.move_times_s(traj.joints),
                            continuous={j for j in traj.joints if self.axes[j].continuous},
                            start_velocity_steps_s={j: start_velocity.get(j, 0.0)
                                                    for j in traj.joints})
        except TrajectoryError:
            chained = None if running else chained_plan(
                traj, [self.axes[j] for j in traj.joints], start_steps, from_s, bound, None)
            if chained is None:
                raise
            return start_t, take_over, start_steps, chained, min_segment_s
        chained = chained_plan(traj, [self.axes[j] for j in traj.joints], start_steps, from_s,
                               bound, segments) if decide and not running else None
        return start_t, take_over, start_steps, chained or segments, min_segment_s

    def move_times_s(self, joints) -> dict[str, tuple[object, float]]:
        """Per joint moved by moves (not streamed): its bus and what a move costs there (the
        measured time, or the drive's estimate before the first): its lead, or for a
        continuous axis its time on the bus (Axis.move_busy_s: its moves go out one after the
        other's, trajectory._shifts)."""
        return {j: (id(self.axes[j].bus_owner), self.axes[j].move_busy_s()
                    if self.axes[j].continuous else self.axes[j].move_cost_s())
                for j in joints if not self.axes[j].interpolated}

    def min_segment_s(self, joints) -> float:
        """The least duration of a segment: what the busiest bus needs to send one move to
        each of its axes, times SEGMENT_MARGIN (CONTINUOUS_SEGMENT_MARGIN where every axis of
        the bus follows velocity-continuously). A move's need is its measured lead (what it
        takes before the drive runs), or the drive's estimate before the first; for a
        velocity-continuous axis, the time its steps take on the bus in all (Axis.move_busy_s:
        a set-point handshake after the motion frame too), not its lead: that holds the waits
        for the other axes' moves and the polls, which the sum and the margin count already.
        Streamed (interpolated) axes take no moves."""
        per_bus: dict[int, float] = {}
        stepwise: set[int] = set()
        for joint in joints:
            axis = self.axes[joint]
            if not axis.interpolated:
                need = axis.move_busy_s() if axis.continuous else axis.move_cost_s()
                per_bus[id(axis.bus_owner)] = per_bus.get(id(axis.bus_owner), 0.0) + need
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
        stream from its take-over); stream.Streams."""
        return self._streams.jobs(run)

    def stop_axis(self, axis: Axis, label: str, hand_over: bool = False
                  ) -> concurrent.futures.Future:
        """The axis's stop, an urgent job (hand_over: from a ROS callback, as
        BusOwner.submit describes)."""
        return axis.bus_owner.submit(axis.drive_name, Command.stop(axis.drive.stop, label),
                               hand_over=hand_over)
