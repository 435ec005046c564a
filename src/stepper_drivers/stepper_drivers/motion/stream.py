"""Interpolated-position streaming (`Stream`): the set points of the trajectory being followed,
one per SYNC period, to the axes of one bus whose drives implement InterpolatingDrive (Vector
Step mode 7), as one step-wise job of its bus owner.

`Streams` keeps a follower's streams, one per bus: a newer run's joints continue the stream of
the run before. Not here: the plan the set points come from (Run.desired_steps, follow.py, on
trajectory.planned_at), nor the drives' side of interpolation (the vendor's drive)."""

from __future__ import annotations

import concurrent.futures
import threading
from typing import Protocol

from ..owner.commands import Command
from .axis import Axis, FollowerView
from .trajectory import Trajectory


class StreamedRun(Protocol):
    """What a stream needs of the run whose joints it streams (follow.Run): its trajectory, which
    of its joints are streamed, where they should be at a time, its end and its outcome."""

    traj: Trajectory
    streamed: set[str]           # the run's interpolated joints
    end_t: float                 # the clock's time of the trajectory's last point
    done: concurrent.futures.Future

    def desired_steps(self, t: float) -> dict[str, float]: ...

# An interpolated axis is where its set point was this many SYNC periods ago: the point written
# at a tick waits in the buffer behind the one before, is taken at the next tick's SYNC and
# reached one period later.
STREAM_LEAD_PERIODS = 2


class Stream:
    """One bus's interpolated axes (Vector Step mode 7): a step-wise job of the bus owner that
    starts interpolation on every axis, then, once a SYNC period, writes each axis's position of
    the current trajectory one buffer ahead (STREAM_LEAD_PERIODS) and sends the SYNC itself, so
    each drive takes exactly one point per SYNC: its two-position buffer never runs dry (EMCY
    FF03) or over. The periodic SYNC producer is paused meanwhile and restarted at the end, also
    when a stop cuts the job short (a node that hangs sends no SYNC: the drives' SYNC watchdogs
    stop them). Ends a few periods after the current trajectory's end, leaving the axes at rest
    out of interpolation (bit 4 low)."""

    def __init__(self, follower: FollowerView, axes: list[Axis]):
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


class Streams:
    """A follower's streams, one per bus: a run's interpolated joints on a bus join the stream
    running there when it streams every one of them already, else a new one starts."""

    def __init__(self, follower: FollowerView, lock: threading.Lock):
        self.follower = follower
        self._lock = lock            # the follower's (it plans and swaps runs under it)
        self._by_bus: dict[int, Stream] = {}

    def jobs(self, run: StreamedRun) -> list[concurrent.futures.Future]:
        """The streaming jobs `run`'s interpolated joints need: one per bus, shared with the
        run before it when that one streamed the same bus (a newer trajectory continues the
        stream from its take-over)."""
        futs = []
        by_bus: dict[int, list[Axis]] = {}
        for joint in run.traj.joints:
            if joint in run.streamed:
                axis = self.follower.axes[joint]
                by_bus.setdefault(id(axis.bus_owner), []).append(axis)
        with self._lock:
            for key, axes in by_bus.items():
                job = self._by_bus.get(key)
                if job is None or job.future.done() or \
                        not {a.joint for a in axes} <= set(job.axes):
                    job = Stream(self.follower, axes)
                    self._by_bus[key] = job
                    job.future = axes[0].bus_owner.submit(axes[0].drive_name, Command.move(
                        job.run, f'interpolated trajectory of {[a.joint for a in axes]}',
                        polled=True))
                futs.append(job.future)
        return futs
