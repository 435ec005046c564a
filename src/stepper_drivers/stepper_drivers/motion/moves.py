"""The jobs that send a run's segment moves to the drives, each in its drive's bus owner thread:
a rest-to-rest move per axis, the rest-to-rest moves of several axes of one bus started in one
instant (GroupStarting), and a velocity-continuous move. A job computes its profile again for
the time really left (trajectory.retimed; continuous.cruise from where the move before has the
drive) and learns its axis's lead (Axis.lead_s: what a move takes before the drive runs).

Not here: when the moves are submitted, waiting for an axis still on its way, the tolerances
and the outcome (follow.Run); the plan (trajectory.py, continuous.py); streamed axes (stream.py).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import math
from typing import Callable

from ..contract.capabilities import Chaining, GroupStarting
from ..contract.drive import DriveError, Motion, Operation, is_operation
from ..owner.commands import Command
from .axis import Axis, FollowerView
from .continuous import cruise
from .trajectory import EDGE_MARGIN, AxisMove, Segment, retimed

LEAD_SMOOTHING = 0.5          # weight of the newest measured lead of a move
# A joint's last move whose estimate leaves it no more than this to go checks the estimate
# against its last snapshot (catch_up_speed).
THERE_STEPS = 2.0
LEAD_MAX_S = 0.5              # a lead measured longer than this (a busy line) counts as this
CHAIN_LEAD_MAX_S = 2.0        # the same for a chain's (a WN per run per drive)
# A continuous move's job is submitted this many times its bus's moves of one segment (what
# they cost) before the move's planned instant, so it is in the owner's queue by then.
CONTINUOUS_SUBMIT_AHEAD = 1.5


def timed(steps: Operation, clock: Callable[[], float]) -> Operation[tuple[object, float]]:
    """`steps` as the bus owner runs it; (its value, the time its steps took: the transactions
    in them, not the waits they yield). Closed with it (a stop cuts it short)."""
    spent = 0.0
    try:
        while True:
            began = clock()
            try:
                delay = next(steps)
            except StopIteration as stop:
                return stop.value, spent + clock() - began
            spent += clock() - began
            yield delay
    finally:
        steps.close()


def learned(old: float, measured: float, most_s: float = LEAD_MAX_S) -> float:
    """A learned time after one more measurement: the first as it is, then smoothed
    (LEAD_SMOOTHING), at most `most_s`."""
    measured = min(measured, most_s)
    return measured if old <= 0 else old + LEAD_SMOOTHING * (measured - old)


def retimed_move(axis: Axis, move: AxisMove, from_steps: float, left_s: float
                 ) -> tuple[float, float]:
    """A rest-to-rest move's profile (velocity, acceleration) for the time really left of its
    segment (trajectory.retimed), else the planned one (it arrives late)."""
    planned = (move.velocity_steps_s, move.acceleration_steps_s2)
    again = retimed(move.target_steps - from_steps, left_s, planned, axis.limits)
    return planned if again is None else again


def group_starter(axes: list[Axis]) -> Callable | None:
    """How the bus of `axes` (two or more, one bus) starts their moves together, or None: it
    cannot now, or its bus has no group start (capabilities.GroupStarting)."""
    bus = axes[0].drive.bus
    if not isinstance(bus, GroupStarting):
        return None
    return bus.group_start([a.drive for a in axes])


def chain_starter(axes: list[Axis]) -> Callable | None:
    """How the bus of `axes` (one bus) stores and starts their chains (capabilities.Chaining),
    or None where it has none."""
    bus = getattr(axes[0].drive, 'bus', None)
    if not isinstance(bus, Chaining) or not bus.chain_runs:
        return None
    return bus.chain_start([a.drive for a in axes])


def catch_up_speed(axis: Axis, move: AxisMove, x: float, end_t: float) -> float:
    """For a joint's last move, where it stops, when the estimate it starts from (`x`) has the
    drive at its end already (within THERE_STEPS): the least cruise speed that brings it there
    by the segment's end (`end_t`, the follower's clock) from where, how fast and when its last
    snapshot saw it [steps/s]; 0 for every other move. The estimate (the plan's profile, closed
    on a snapshot only when one came since the move before) could put the drive at its point
    while it was a few steps short, and the least cruise speed from there was the RD4's minimum
    of 1 Hz: the joint crept its last steps for a second past the trajectory's end. Only then: a
    floor on every last move made joints arrive early, apart from the others (not together at
    the end), and one on the moves before the last stalled them at the next point."""
    way = 1.0 if move.target_steps >= move.entry_steps else -1.0
    if move.via_steps != move.target_steps or (move.via_steps - x) * way > THERE_STEPS:
        return 0.0
    position, velocity, at = axis.sample_motion()
    if (move.via_steps - position) * way <= 0 or end_t <= at:
        return 0.0
    found = cruise(position, velocity, move.via_steps, move.target_steps, end_t - at,
                   move.acceleration_steps_s2, axis.limits)
    return found[0] if found is not None else axis.limits.max_velocity_steps_s


class MoveJobs:
    """The move jobs of one run (follow.Run submits them, segment by segment), and what their
    moves left for the run: when each joint's last move went out, and each continuous joint's
    last move as it went out (where the next one starts from)."""

    def __init__(self, follower: FollowerView):
        self.follower = follower
        # joint: when its last move of this run had gone out (written by the owner threads'
        # jobs, read by the run thread: one dict item)
        self.moved_t: dict[str, float] = {}
        # joint: its last continuous move as it went out (when it ran, entry position and
        # velocity, target, cruise), by the owner threads' jobs, one after the other per joint
        self._went: dict[str, tuple[float, AxisMove]] = {}

    def units(self, moves: list) -> list[list]:
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
            if unit[0].knots:
                out.append(unit)                     # chains: one job per bus, always
            elif len(unit) > 1 and group_starter(axes) is None:
                out += [[m] for m in unit]           # no group start: one job per axis
            else:
                out.append(unit)
        return out

    def submit(self, unit: list, previous: dict[str, float], seg_t: float,
               end_t: float) -> list[concurrent.futures.Future]:
        """Submit the unit's job(s) (under the follower's submit_lock): one move job per axis,
        or for a group one job under its first axis's drive that also writes the others'
        drives; their futures."""
        jobs = []
        axes = [self.follower.axes[m.joint] for m in unit]
        if unit[0].knots:
            members = [(a, m) for a, m in zip(axes, unit)]
            return [axes[0].bus_owner.submit(axes[0].drive_name, Command.move(
                self._chain_job(chain_starter(axes), members, seg_t, end_t),
                f'trajectory of {[a.joint for a in axes]} as chained runs',
                also=tuple(a.drive_name for a in axes[1:])))]
        starter = group_starter(axes) if len(unit) > 1 else None
        if starter is None:
            for axis, move in zip(axes, unit):
                jobs.append(axis.bus_owner.submit(axis.drive_name, Command.move(
                    self._move_job(axis, move, previous[move.joint], seg_t, end_t),
                    f'trajectory segment to {move.target_steps:g} steps')))
            return jobs
        members = [(a, m, previous[m.joint]) for a, m in zip(axes, unit)]
        jobs.append(axes[0].bus_owner.submit(axes[0].drive_name, Command.move(
            self._group_job(starter, members, seg_t, end_t),
            f'trajectory segment of {[a.joint for a in axes]} started together',
            also=tuple(a.drive_name for a in axes[1:]))))
        return jobs

    def ahead_s(self, seg: Segment) -> float:
        """When the segment's moves are submitted, against its start: its continuous moves'
        earliest planned instant (<= 0), less CONTINUOUS_SUBMIT_AHEAD times what their moves
        cost on the bus; 0 for a segment of rest-to-rest moves only."""
        cont = [m for m in seg.moves if m.via_steps is not None]
        if not cont:
            return 0.0
        cost = sum(self.follower.axes[m.joint].move_cost_s() for m in cont)
        return min(m.start_delay_s for m in cont) - CONTINUOUS_SUBMIT_AHEAD * cost

    def _group_job(self, starter: Callable, members: list, seg_t: float,
                   end_t: float) -> Callable:
        """One job that starts the rest-to-rest moves of several axes of one bus in one
        instant (GroupStarting). As _move_job per axis: each axis's run before ends first,
        the profile is computed again for the time really left, `moved_t` per joint; the
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
                v, a = retimed_move(axis, move, from_steps, end_t - runs_t)
                if math.isinf(a):                # start-stop: the drive ignores the ramp
                    a = axis.limits.max_acceleration_steps_s2
                moves.append((axis.drive, int(round(move.target_steps)), Motion(v, a, a)))
            result = yield from starter(moves)
            now = clock()
            skipped = getattr(result, 'skipped', {})
            for axis, _, _ in members:
                if axis.drive_name not in skipped:
                    self.moved_t[axis.joint] = now
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

    def _chain_job(self, starter: Callable, members: list, seg_t: float,
                   end_t: float) -> Callable:
        """One job that stores the chains of the axes of one bus and starts them
        (capabilities.Chaining), each knot at its instant on the follower's clock (the
        segment's end is the last knot's). A member left out fails the job, as in
        _group_job. Each axis learns the chain's lead (Axis.chain_lead_s: from the segment's
        start, `seg_t`, to the string that started the last drive); a move's lead is not
        learned from it (a chain's strings, a WN per run, are not a move's)."""
        clock = self.follower.clock

        def job():
            offset = end_t - members[0][1].knots[-1][0]
            moves = [(axis.drive, tuple((offset + t, int(round(x))) for t, x in move.knots))
                     for axis, move in members]
            result = yield from starter(moves)
            now = clock()
            skipped = getattr(result, 'skipped', {})
            sent = getattr(result, 'sent_t', None)
            for axis, _ in members:
                if axis.drive_name not in skipped:
                    self.moved_t[axis.joint] = now
                if sent is not None:
                    axis.chain_lead_s = learned(axis.chain_lead_s, sent - seg_t,
                                                CHAIN_LEAD_MAX_S)
            if skipped:
                names = {axis.drive_name: axis.joint for axis, _ in members}
                raise DriveError('; '.join(f'{names.get(name, name)}: its chain did not go '
                                           f'out ({why})' for name, why in skipped.items()))
            return result
        return job

    def _continuous_job(self, axis: Axis, move, seg_t: float, end_t: float) -> Callable:
        """A continuous move's job (follow.py's docstring): it waits until its lead before the
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
            v = max(v, catch_up_speed(axis, move, x, end_t))
            if move.velocity_steps_s <= lim.start_stop_steps_s < v:
                # start-stop as planned, a little late, rather than ramps that make it later
                v, a, dec = (move.velocity_steps_s, move.acceleration_steps_s2,
                             move.deceleration_steps_s2)
            # (start-stop: the drive ignores its ramp registers)
            began = clock()
            result = axis.drive.move_to(int(round(move.target_steps)), Motion(v, a, dec))
            busy = clock() - began
            if is_operation(result):
                result, spent = yield from timed(result, clock)
                busy += spent
            self._went[axis.joint] = (runs_t, dataclasses.replace(
                move, velocity_steps_s=v, acceleration_steps_s2=a, deceleration_steps_s2=dec,
                entry_steps=x, entry_velocity_steps_s=u))
            self._moved(axis, t0)
            axis.busy_s = learned(axis.busy_s, busy)
            return result
        return job

    def _move_job(self, axis: Axis, move, from_steps: float, seg_t: float, end_t: float
                  ) -> Callable:
        if move.via_steps is not None:
            return self._continuous_job(axis, move, seg_t, end_t + move.shift_s)
        clock = self.follower.clock

        def job():
            ready = axis.drive.until_ready_for_move()    # (X-MIND K: its run ends first)
            if ready is not None:
                yield from ready
            t0 = clock()
            # the drive runs after this move's own transactions, and not before the plan
            # expects it to (the moves of the other axes on the bus go out meanwhile)
            runs_t = max(t0 + axis.lead_s, seg_t + move.start_delay_s)
            v, a = retimed_move(axis, move, from_steps, end_t - runs_t)
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
        self.moved_t[axis.joint] = now
        sent = axis.drive.motion_sent_t
        lead = (sent if sent is not None and sent >= t0 else now) - t0
        axis.lead_s += LEAD_SMOOTHING * (min(lead, LEAD_MAX_S) - axis.lead_s)
