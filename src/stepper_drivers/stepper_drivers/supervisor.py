"""BusSupervisor: the one owner of a bus (no rclpy).

Threads and what they own:
- The owner thread (one per bus) makes every call into the Bus and its Drives: polls, commands,
  service transactions, reconnects, the velocity watchdog and shutdown all run there, as jobs.
  It writes a slot's runtime fields (`state`, `sample`, `connected`, `identity`, `polls`, the
  running job, ...); other threads read them (one reference assignment each, so a reader sees a
  whole snapshot). Two exceptions: while the poll group has the bus (poll_group.py, lend() to
  give_back(), the owner waits meanwhile) its thread polls the lent drives and writes what a
  poll writes (and a link loss found by its poll); and other threads set the request fields
  under `_cv` (`queue`, `poll_waiters`, `velocity_deadline`/`arm_seq` by arm_watchdog(),
  `next_poll_t` by poll_soon(), `not_driven` by refuse_drive(), `owner_polls` by give_back()).
- Any other thread (ROS callbacks) only calls `submit()`, `arm_watchdog()`, `poll_soon()`,
  `wait_poll()`, `after()`, `recheck()`, `refuse_drive()` and `shutdown()`, which take `_cv` for
  a moment, enqueue and return (a `concurrent.futures.Future` for a job). A command submitted
  with `hand_over=True` to a sleeping owner also waits (GIL released, at most
  HAND_OVER_MAX_S) until the owner has taken it: the GIL goes to the owner at once.
- A job's future is pending while the job waits, running from when the owner starts it
  (`set_running_or_notify_cancel`), then done. Only a waiting job can be cancelled (its waiter's
  time-out): the owner then skips it. A job that started runs to its end and its future gets
  its result; nothing a future raises reaches the owner loop (`_resolve`).

Order:
- Jobs of one drive run in the order submitted, one at a time; a step-wise job (a generator, see
  drive.py) keeps the drive until it ends, while other drives' jobs and polls run between its
  steps, so nobody waits behind a long operation. A step-wise poll likewise: its next step
  comes at the time it asked for.
- A streaming command (kind STREAM: position or velocity) replaces a STREAM job of the same
  topic still waiting at the tail of that drive's queue: the drive gets the newest set point.
- Drives with waiting jobs take turns: the next job started is that of the drive whose last
  job started longest ago (`_next_turn`). A replacement keeps the drive's turn, so a stream on
  one drive (a newer set point always waiting) keeps another drive's job waiting for at most
  one job of each other drive, never until the stream ends.
- URGENT jobs (stop, quick stop, disable, the watchdog's stop) go before everything else: they
  drop the drive's queued motion jobs (which would move after the stop) and cut its running
  motion job short, and reach the wire after at most the one transaction already in flight.
  A running job that an urgent one does not preempt (a save during a disable) is suspended: its
  next step waits until the urgent job ended (`Slot.suspended`), which is stepped like any job.
- No job holds the owner: a due poll goes before a running operation's next step (`_work_once`),
  so while the polls fit the period no drive's poll gap exceeds its period, the longest single
  step of a job on the bus and one transaction, whatever runs beside it; every watchdog is
  checked on time.

Snapshot provenance: the owner counts the writes to each drive (`Slot.write_seq`: +1 when a job
of the drive starts, +1 when it ends; a job's future carries the count at its end as
`after_write`), and every snapshot carries the count in force when its read began
(`DriveState.after_write`: set when the poll began, by the owner or at the poll group's loan; a
snapshot a drive vouches for in a quiet cycle, the count at the vouching). A poll under way when
a job starts (a step-wise poll, whose steps go on between the job's) ends with a count below the
job's end. `wait_poll` answers a waiter only with a snapshot at or above the count it names (by
default the drive's count when it was registered): what a service judges its answer by was read
after its own writes.

The velocity watchdog: `arm_watchdog()` is called when a velocity command is
accepted, before anything is written; only a job submitted with `disarms=True` (a stop, a
position or homing command) that the drive confirmed disarms it. A refusal, a lost reply or a link
loss leaves it armed; after a reconnect an expired deadline stops the drive at once. It is checked
on the owner's clock (the loop wakes at the deadline), not once per poll.

An exception that escapes the owner loop (a bug, not a drive's error: those are the jobs' and
polls' results) stops every drive of the bus, closes it, marks the drives DISCONNECTED with the
error and calls `on_failure`: the node then ends, since nobody polls or watches these drives.

One file: it is one owner loop; scheduling (queues, URGENT, watchdog), link state (connect,
back-off, loss) and shutdown change the same slots, queues and futures under `_cv`, and the
order rules above span all three.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import heapq
import itertools
import logging
import math
import os
import threading
import time
import traceback
from typing import Any, Callable, Iterable

from .commands import Command, JobKind
from .drive import (Bus, Drive, DriveError, DriveState, IdentityError, LinkError, State, complete,
                    is_steps)

logger = logging.getLogger(__name__)

URGENT, COMMAND, STREAM = JobKind.URGENT, JobKind.COMMAND, JobKind.STREAM
MAINTENANCE, CONNECT = JobKind.MAINTENANCE, JobKind.CONNECT
# The refusal of SCHED_FIFO is told once per process (every bus owner of a node asks for it).
_priority_lock = threading.Lock()
_priority_refusal_told = False
# A drive whose connect raised IdentityError (a well-formed answer naming another device) is
# not driven, and connected again after IDENTITY_RECHECK_S, doubling up to
# IDENTITY_RECHECK_MAX_S, for as long as the node runs (`recheck()`, fault_reset, at once): a
# drive swapped or set right comes back without a restart. Noise is a LinkError, retried on the
# reconnect back-off.
IDENTITY_RECHECK_S = 30.0
IDENTITY_RECHECK_MAX_S = 300.0
# After this many commands or steps while a poll is overdue, one poll goes first (fairness).
# (A due poll goes before a running operation's next step anyway, unless that step has waited
# a period for polls: `_work_once`.)
MAX_JOBS_BEFORE_OVERDUE_POLL = 4
# A watchdog stop that could not be sent is tried again after this long [s].
WATCHDOG_RETRY_S = 0.1
# submit(hand_over=True) to a sleeping owner waits at most this long for it to take the job [s].
HAND_OVER_MAX_S = 0.002
# An owner whose drives a poll group polls (poll_group.py) polls them itself once a poll is this
# late, or two poll periods if longer: the group is late or gone.
GROUP_GRACE_S = 0.25


class Superseded(DriveError):
    """A newer streaming command replaced this one before it was sent."""


class Cancelled(DriveError):
    """A stop, a disable, a link loss or shutdown dropped or cut this job short."""


class NotConnected(DriveError):
    """The drive is DISCONNECTED (or not driven); the job was not run."""


@dataclasses.dataclass
class Job:
    drive: str
    kind: JobKind
    fn: Callable[[], Any]
    label: str
    future: concurrent.futures.Future
    topic: str = ''             # STREAM jobs: which stream ('position', 'velocity')
    disarms: bool = False       # confirmed success disarms the velocity watchdog
    motion: bool = True         # a stop of the drive drops this job, or cuts it short
    enqueued_t: float = 0.0
    arm_seq: int = 0            # the drive's watchdog arming count when this job was submitted
    # a step-wise job between whose steps the drive itself is still polled (a stream of set
    # points that lasts seconds: the drive's state must stay fresh meanwhile)
    polled: bool = False
    taken: threading.Event | None = None   # set when the owner takes it (see submit's hand_over)

    @classmethod
    def of(cls, drive: str, command: Command, enqueued_t: float, arm_seq: int = 0) -> 'Job':
        """The job of `command` for `drive`, with a future of its own."""
        return cls(drive, command.kind, command.fn, command.label, concurrent.futures.Future(),
                   command.topic, command.disarms, command.motion, enqueued_t, arm_seq,
                   command.polled)

    def preempted_by(self, urgent: 'Job') -> bool:
        """A stop drops motion; a disable (an URGENT job that is not motion itself) drops
        everything but maintenance that cannot move (save, register reads)."""
        if self.motion:
            return True
        return not urgent.motion and self.kind != MAINTENANCE and self.kind != CONNECT


class Slot:
    """Runtime state of one drive on the bus (who writes what: the module docstring)."""

    def __init__(self, name: str, drive: Drive, reconnect_period_s: float):
        self.name = name
        self.drive = drive
        self.state = DriveState(state=State.DISCONNECTED)
        # (the last polled state, clock() when its position was true), set in one assignment:
        # a reader in another thread takes both from it, never a state with another's time
        self.sample: tuple[DriveState, float] = (self.state, 0.0)
        self.connected = False
        self.identity: dict[str, str] = {}
        self.polls = 0               # successful read_state() results
        self.reconnects = 0          # successful connects, the first one included
        self.last_error = ''
        self.not_driven = ''         # why the node does not drive this drive ('' while it does)
        # not driven for its identity: connected again at next_connect_t (IDENTITY_RECHECK_S);
        # False with not_driven set: refused for as long as the node runs (refuse_drive)
        self.identity_recheck = False
        self.identity_backoff_s = IDENTITY_RECHECK_S
        self.connect_waiters: list[concurrent.futures.Future] = []   # recheck() callers
        self.queue: collections.deque[Job] = collections.deque()
        self.active: Job | None = None
        self.active_steps = None     # generator of the running job
        self.wake_t = 0.0            # next step of the running job / poll / connect
        # (job, steps, wake_t) of running jobs an urgent one did not preempt (a save during a
        # disable): the last one goes on when the job running now ends
        self.suspended: list[tuple[Job, Any, float]] = []
        self.poll_steps = None       # generator of a read_state() in progress
        self.poll_wake_t = 0.0
        self.next_poll_t = 0.0
        self.next_connect_t = 0.0
        self.backoff_s = reconnect_period_s
        self.velocity_deadline: float | None = None
        self.arm_seq = 0             # velocity commands accepted so far (arm_watchdog calls)
        # jobs the owner had started when it started this drive's last one (0: none yet): the
        # drive with waiting work and the lowest turn goes next (_next_turn)
        self.turn = 0
        self.submitted = 0           # jobs submitted for this drive (submit, under _cv)
        self.watchdog_retry_t = 0.0
        # (deadline, callback, the least write count of a snapshot that answers it): wait_poll
        self.poll_waiters: list[tuple[float, Callable[[bool], None], int]] = []
        # writes to the drive: +1 when one of its jobs starts and +1 when it ends (owner
        # thread; read by others); a snapshot stamped with it followed every write counted
        self.write_seq = 0
        # write_seq when the poll under way (or the last one) began: its snapshot's stamp
        self.poll_seq = 0
        # the last poll was the poll group's (poll_group.py): the owner need not wake for the
        # next one unless the group misses it by GROUP_GRACE_S
        self.group_polled = False
        # the group gave this drive back unpolled: the owner polls it before the group lends the
        # link again (a request of the group's may still await its reply: ModbusTcpBus)
        self.owner_polls = False


class BusSupervisor:
    """Owns one Bus and its drives in one thread; see the module docstring."""

    def __init__(self, bus: Bus, drives: dict[str, Drive], settings: dict[str, Any],
                 on_cycle: Callable[['BusSupervisor'], None] | None = None,
                 on_connected: Callable[['BusSupervisor', Slot], str] | None = None,
                 on_event: Callable[[str, str, str], None] | None = None,
                 auto_enable: Iterable[str] = (), clock: Callable[[], float] = time.monotonic,
                 name: str = 'bus',
                 on_failure: Callable[['BusSupervisor', str], None] | None = None):
        """`settings` is read live: 'publish_rate_hz', 'command_timeout_s',
        'reconnect_period_s'. `on_cycle` runs once every connected drive was polled (a cycle),
        at once when a drive is lost (its DISCONNECTED status) and at the poll rate while none
        is connected: in the owner thread, or in the poll group's thread when a poll of the
        group's ends the cycle or finds the link lost (poll_group.py; the owner waits
        meanwhile); `on_connected` may return a reason not to drive a drive (duplicate identity);
        `on_event(level, drive, text)` reports what happened ('info'/'warning'/'error');
        `on_failure(sup, why)` runs in the owner thread when an internal error ended it, after
        its drives were stopped and its bus closed (the node then ends: a bus without its owner
        is neither polled nor watched)."""
        self.bus = bus
        self.settings = settings
        self.slots = {n: Slot(n, d, settings['reconnect_period_s']) for n, d in drives.items()}
        self._slot_list = list(self.slots.values())
        self.on_cycle = on_cycle or (lambda sup: None)
        self.on_connected = on_connected or (lambda sup, slot: '')
        self.on_event = on_event or self._log_event
        self.on_failure = on_failure or (lambda sup, why: None)
        self.failure = ''           # why the owner ended by itself ('' while it runs)
        self.auto_enable = set(auto_enable)
        self.clock = clock
        self.name = name
        self._cv = threading.Condition()
        self._urgent: collections.deque[Job] = collections.deque()
        self._stopping = False
        self._shutdown_request: tuple[float, set[str]] | None = None
        self._thread = threading.Thread(target=self._run, name=f'owner {name}', daemon=True)
        self._jobs_since_poll = 0
        self._turns = 0             # jobs started from the drives' queues (owner thread)
        # after(): a heap (under _cv) of [when, sequence number, callback or None once removed
        # or called]; only the owner pops (its look at the first one takes no lock)
        self._timers: list[list[Any]] = []
        self._timer_seq = itertools.count()
        self._removed_timers = 0    # removed timers still in the heap
        self._cycle_polled: set[str] = set()
        self._last_cycle_t = 0.0
        self._grid_t0 = clock()
        self._idle = False          # the owner waits for its next wake-up (under _cv)
        # What the idle owner waits on: held except while a wake-up is pending. Only _notify
        # releases it (under _cv, and only while held: never twice), only the owner takes it.
        # One lock operation a wait; a Condition's wait costs a dozen more in Python, at
        # every cycle of an idle bus (docs/benchmarks.md).
        self._wake = threading.Lock()
        self._wake.acquire()
        self._events = 0            # _notify() calls: what other threads asked for (under _cv)
        self._closed = False        # _shutdown_drives ran: the drives stopped, the bus closed
        # the poll group's thread has the bus and the lent drives (lend() to give_back(), under
        # _cv): the owner waits meanwhile; _loan_waiter: it does (give_back wakes it)
        self._lent = False
        self._loan_waiter = False
        # (_events, the drives' next poll, the owner's next event, _vouched) after a quiet
        # cycle: the next pass may go straight to the next one (_after_quiet_cycle)
        self._quiet_pass: tuple[int, float, float, tuple[int, float, int]] | None = None
        # (bus.changes, until, _writes) of the last vouching: _quiet_cycle
        self._vouched: tuple[int, float, int] = (0, 0.0, 0)
        self._writes = 0            # the slots' write_seq increments, all drives (owner thread)
        self._fresh_s = 0.0         # the state_fresh_s the quiet cycles last gave the drives
        # (owner thread, during on_cycle) the cycle is a quiet pass' (_work_once): since the
        # cycle before, no other thread asked for anything, the owner did nothing else and no
        # drive has anything new; what the slots hold is as it was then (on_cycle may skip a
        # look)
        self.cycle_unchanged = False
        self.cycles = 0
        self.passes = 0             # _work_once calls: the owner's wake-ups and units of work

    # ---------------------------------------------------------------------- other threads
    def start(self) -> None:
        self._thread.start()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def idle(self) -> bool:
        """The owner sleeps, waiting for work or its next poll."""
        return self._idle

    def submit(self, drive: str, command: Command, *, hand_over: bool = False
               ) -> concurrent.futures.Future:
        """Queue `command` for `drive` (its fn is called in the owner thread; may return
        Steps); its kind and flags come from its constructor (commands.py).

        hand_over: when the owner sleeps, wait (at most HAND_OVER_MAX_S, GIL released) until
        it has taken the job. For commands from a ROS callback: without it the executor thread
        goes on holding the GIL through rclpy's wait-set rebuild after the callback, and the
        woken owner waits for it, up to the 0.5 ms switch interval and more under load (the
        command-to-wire figures in docs/benchmarks.md). A busy owner (a transaction in
        flight) is not waited for: on a serial line that would hold the executor 20-30 ms."""
        job = Job.of(drive, command, self.clock())
        fut, kind, label, topic = job.future, command.kind, command.label, command.topic
        with self._cv:
            job.arm_seq = self.slots[drive].arm_seq
            if self._stopping:
                _resolve(fut, exc=Cancelled(f'{label}: the node is shutting down'))
                return fut
            if hand_over and self._idle:
                job.taken = threading.Event()
            slot = self.slots[drive]
            slot.submitted += 1
            # which submission of this drive it is: a caller that compares it with
            # slot.submitted later knows whether any job was submitted for the drive since
            fut.submitted = slot.submitted
            if kind == URGENT:
                self._urgent.append(job)
            else:
                if kind == STREAM and slot.queue:
                    tail = slot.queue[-1]
                    if tail.kind == STREAM and tail.topic == topic:
                        slot.queue.pop()
                        _resolve(tail.future, exc=Superseded(
                            f'{tail.label}: replaced by the newer {label} before it was sent'))
                slot.queue.append(job)
            self._notify()
        if job.taken is not None:
            job.taken.wait(HAND_OVER_MAX_S)
        return fut

    def arm_watchdog(self, drive: str) -> None:
        """A velocity command was accepted: the drive must hear from us within the timeout."""
        with self._cv:
            slot = self.slots[drive]
            slot.velocity_deadline = self.clock() + self.settings['command_timeout_s']
            slot.arm_seq += 1
            self._notify()

    def watchdog_armed(self, drive: str) -> bool:
        return self.slots[drive].velocity_deadline is not None

    def poll_soon(self, drive: str) -> None:
        """Poll `drive` next, ahead of its place on the grid: a caller that waits for what the
        drive does now (the end of a trajectory, a service's answer) need not wait a period."""
        with self._cv:
            slot = self.slots[drive]
            slot.next_poll_t = min(slot.next_poll_t, self.clock())
            self._notify()

    def wait_poll(self, drive: str, timeout_s: float, callback: Callable[[bool], None],
                  after_write: int | None = None) -> None:
        """Call callback(True) from the owner thread after the next poll of `drive` whose
        snapshot followed write number `after_write` (its DriveState.after_write is at least
        that; a job's future has the number at the job's end as `after_write`; None: the
        drive's number now, every write so far), or callback(False) once timeout_s passed or
        the drive is lost; at once with False (in this thread) once the bus shuts down: no
        poll will come. A poll that began before that write (one under way while a job ran)
        does not answer it: the drive is polled again at once."""
        with self._cv:
            if not self._stopping:
                slot = self.slots[drive]
                after = slot.write_seq if after_write is None else after_write
                slot.poll_waiters.append((self.clock() + timeout_s, callback, after))
                self._notify()
                return
        callback(False)

    def after(self, delay_s: float, callback: Callable[[], None]) -> Callable[[], None]:
        """Call callback() from the owner thread once delay_s has passed; at once (in this
        thread) once the bus shuts down, as the owner then calls every timer still waiting:
        what awaits one (a service, an action) ends rather than wait for ever. Returns what
        removes the timer (from any thread; nothing once it was called): a time-out whose
        future ended is not kept until it falls due."""
        with self._cv:
            if not self._stopping:
                entry = [self.clock() + delay_s, next(self._timer_seq), callback]
                heapq.heappush(self._timers, entry)
                self._notify()
                return lambda: self._remove_timer(entry)
        callback()
        return _nothing

    def _remove_timer(self, entry: list[Any]) -> None:
        """The timer is not called. It leaves the heap when the owner comes to it, or with the
        other removed ones once they are most of the heap (a new list: the owner may be
        looking at the old one)."""
        with self._cv:
            if entry[2] is None:
                return
            entry[2] = None
            self._removed_timers += 1
            if self._removed_timers > 16 and 2 * self._removed_timers > len(self._timers):
                timers = [e for e in self._timers if e[2] is not None]
                heapq.heapify(timers)
                self._timers, self._removed_timers = timers, 0

    @property
    def stopping(self) -> bool:
        """The drives' shutdown began (shutdown(), or the owner failed): no job, poll or timer
        is taken any more."""
        return self._stopping

    def shutdown(self, standstill_timeout_s: float, disable: Iterable[str] = (),
                 join_timeout_s: float = 30.0) -> bool:
        """Stop every drive, wait (bounded) for standstill, disable those named, close the bus.
        Runs in the owner thread; this call waits for it, at most join_timeout_s. False, and an
        error event that says so, when the owner did not end by then (it is still in a call
        into the bus or a drive): its drives are not stopped yet."""
        with self._cv:
            self._shutdown_request = (standstill_timeout_s, set(disable))
            self._notify()
        if self._thread.is_alive():
            self._thread.join(join_timeout_s)
            if self._thread.is_alive():
                self.on_event('error', self.name, (
                    f'the bus owner did not end within {join_timeout_s:g} s of the shutdown '
                    f'(it is still in a call into {self.bus.description or "the bus"}): its '
                    'drives are not stopped yet, and are not if the process ends first'))
                return False
        elif not self._closed:   # never started (tests, a node that failed to start): do it here
            self._shutdown_drives(standstill_timeout_s, set(disable))
        return True

    # ------------------------------------------------------------------ the poll group
    def share_grid(self, t0: float) -> None:
        """Poll on the grid of periods that starts at t0 (the poll group's buses share one)."""
        self._grid_t0 = t0

    def lend(self, now: float) -> list[tuple[Slot, list[Any]]]:
        """(The poll group's thread) When the owner sleeps with nothing to do but polls: the
        drives whose polls are due at `now`, with their state requests; the bus and these
        drives are then the caller's until give_back() (the owner waits for it), and it may
        call group_polled() and group_poll_failed(). [] (nothing lent) otherwise."""
        with self._cv:
            if not self._idle or self._lent or self._stopping or self._urgent \
                    or self._shutdown_request is not None:
                return []
            out = []
            for s in self._slot_list:
                if s.queue or s.active is not None or s.owner_polls:
                    return []                   # the owner's turn: it is awake for it
                if s.connected and not s.not_driven and s.poll_steps is None \
                        and not s.poll_waiters and now >= s.next_poll_t:
                    requests = s.drive.state_requests()
                    if requests:
                        # (no job of the drive runs until give_back: the owner waits)
                        s.poll_seq = s.write_seq
                        out.append((s, requests))
            self._lent = bool(out)
            return out

    def give_back(self, unpolled: Iterable[Slot] = ()) -> None:
        """(The poll group's thread) The end of a loan. The owner polls the `unpolled` drives
        itself, at once."""
        with self._cv:
            self._lent = False
            unpolled = list(unpolled)
            for s in unpolled:
                s.group_polled = False
                s.owner_polls = True
            if unpolled or self._loan_waiter:
                self._notify()

    def group_polled(self, slot: Slot, state: DriveState, now: float) -> None:
        """(The poll group's thread, lent) slot's poll gave `state` at `now`."""
        self._jobs_since_poll = 0
        slot.next_poll_t = self._next_grid_t(now)
        slot.group_polled = True
        self._polled(slot, state)

    def group_poll_failed(self, slot: Slot, exc: Exception) -> None:
        """(The poll group's thread, lent) slot's poll failed as read_state() would have."""
        slot.group_polled = False
        self._poll_failed(slot, exc)

    def _notify(self) -> None:
        """(Under _cv, from another thread) wake the owner: a job, a timer, a waiter or a
        request came. A pass of polls ends at it (`_poll_due`)."""
        self._events += 1
        self._cv.notify()                  # an owner that waits for the poll group's loan
        if self._idle and self._wake.locked():
            self._wake.release()

    # ------------------------------------------------------------------------ owner thread
    def _log_event(self, level: str, drive: str, text: str) -> None:
        getattr(logger, level)('%s: %s', drive, text)

    def _set_priority(self) -> None:
        """SCHED_FIFO for this thread (owner_thread_priority, 0: not): the owner then runs as
        soon as a command wakes it, not when the scheduler gets round to it (docs/benchmarks.md:
        the owner's wake-up was most of the command path's tail). A refusal is not an error:
        the bus works as well, only later on a loaded machine; the first owner of the process
        that is refused says so, once."""
        global _priority_refusal_told
        priority = int(self.settings.get('owner_thread_priority', 0))
        if not priority:
            return
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as exc:
            with _priority_lock:
                told, _priority_refusal_told = _priority_refusal_told, True
            if not told:
                self.on_event(
                    'warning', self.name,
                    f'owner_thread_priority {priority}: SCHED_FIFO refused ({exc.strerror}): '
                    'the bus owners run on the normal scheduler; allow it with an rtprio limit '
                    f'of at least {priority} for this user in /etc/security/limits.conf (or '
                    'CAP_SYS_NICE), or set owner_thread_priority: 0')

    def _run(self) -> None:
        self._set_priority()
        try:
            while True:
                with self._cv:
                    while self._lent:              # the poll group has the bus: its poll ends
                        self._loan_waiter = True   # within its reply wait (poll_group.py)
                        self._cv.wait()
                    self._loan_waiter = False
                    request = self._shutdown_request
                if request is not None:
                    self._shutdown_drives(*request)
                    return
                # What another thread asks for during the pass (a job, a timer, a waiter: all
                # by _notify) is for the next pass, not for a wait: a pass that returns a delay
                # saw no job ready when it looked.
                events = self._events
                delay = self._work_once()
                if delay > 0:
                    with self._cv:
                        if self._urgent or self._shutdown_request is not None \
                                or self._events != events:
                            continue
                        self._idle = True
                    # a _notify() from here on releases _wake: the wait ends at once
                    self._wake.acquire(timeout=delay)
                    with self._cv:
                        self._idle = False
        except Exception as exc:  # noqa: BLE001 - the drives are stopped below, whatever
            why = f'bus owner failed: {exc!r}'
            try:
                self.on_event('error', self.name, f'{why}\n' + traceback.format_exc())
            finally:
                self._shutdown_drives(1.0, set())
                for slot in self.slots.values():    # what status and diagnostics say now
                    slot.connected, slot.last_error = False, why
                self.failure = why
                self.on_failure(self, why)

    def _work_once(self) -> float:
        """Do one unit of work (one transaction or one step); return how long to sleep.

        Priorities, highest first: an urgent job; a drive found not driven; a due watchdog
        stop; a poll overdue by a period once MAX_JOBS_BEFORE_OVERDUE_POLL jobs went first; the
        next step of a running operation, after the due polls unless it waited a period for
        them (so a long operation delays no poll by more than its step in flight, nor do
        overrunning polls stop it); the waiting command of the drive whose turn it is
        (`_next_turn`); the next step of a poll; a due reconnect; the longest-due poll. One
        pass over the slots (it runs before every transaction: the CPU budget,
        docs/benchmarks.md)."""
        self.passes += 1
        now = self.clock()
        events = self._events
        quiet, self._quiet_pass = self._quiet_pass, None
        if quiet is not None and quiet[0] == events and not self._urgent \
                and quiet[1] <= now < quiet[2] \
                and self._quiet_cycle(self._slot_list, now, quiet[3]):
            return self._after_quiet_cycle(events)
        if self._urgent:                   # (a deque's truth needs no lock; the pop does)
            with self._cv:
                urgent = self._urgent.popleft() if self._urgent else None
            if urgent is not None:
                if urgent.taken is not None:
                    urgent.taken.set()
                self._run_urgent(urgent)
                return 0.0
        self._expire_waiters(now)
        due = step = poll_step = reconnect = None
        dues: list[Slot] = []
        queued = False
        for slot in self._slot_list:
            if slot.connected:
                if slot.not_driven:
                    self._drive_lost(slot, f'not driven: {slot.not_driven}')
                    return 0.0
                if slot.velocity_deadline is not None and now >= slot.velocity_deadline \
                        and now >= slot.watchdog_retry_t:        # the watchdog, on its own clock
                    self._watchdog_stop(slot)
                    return 0.0
                # (a poll under way is not due again: its next step comes at poll_wake_t)
                if (slot.active is None or slot.active.polled) and slot.poll_steps is None \
                        and now >= slot.next_poll_t:
                    dues.append(slot)
                    if due is None or slot.next_poll_t < due.next_poll_t:
                        due = slot
            elif reconnect is None and (not slot.not_driven or slot.identity_recheck) \
                    and slot.active is None and now >= slot.next_connect_t:
                reconnect = slot
            active = slot.active
            if active is None:
                if slot.queue:
                    queued = True
            elif step is None and slot.active_steps is not None and now >= slot.wake_t:
                step = slot
            if poll_step is None and slot.poll_steps is not None and now >= slot.poll_wake_t:
                poll_step = slot
        if due is not None and now >= due.next_poll_t + self._period_s() \
                and self._jobs_since_poll >= MAX_JOBS_BEFORE_OVERDUE_POLL:
            self._poll_step(due, now)
            return 0.0
        if step is not None:                      # the next step of a running operation
            if due is not None and now < step.wake_t + self._period_s():
                self._poll_due(dues, now)         # (ends at the step: it is due)
                return 0.0
            self._jobs_since_poll += 1
            self._step_active(step)
            return 0.0
        if queued:
            slot = self._next_turn()
            if slot is not None:
                self._jobs_since_poll += 1
                self._start_job(slot)
                return 0.0
        if poll_step is not None:                 # a poll in progress, then one due
            self._poll_step(poll_step, now)
            return 0.0
        if reconnect is not None:          # before due polls: they may be due all the time
            self._connect(reconnect)
            return 0.0
        if due is not None:   # the longest due first: when polls overrun, every drive its turn
            if len(dues) == len(self._slot_list) and self._quiet_cycle(dues, now):
                return self._after_quiet_cycle(events)
            if self._poll_due(dues, now):
                # every due poll done and published, nothing else was due at the pass' start
                # (what came since is in _events or due by its time): the next wake-up, without
                # a pass over the slots to find it
                now = self.clock()
                return self._next_wake(now) - now
            return 0.0
        if not any(s.connected for s in self._slot_list) \
                and now >= self._last_cycle_t + self._period_s():
            self._cycle()     # the DISCONNECTED status goes on at the poll rate
            return 0.0
        return self._next_wake(now) - now

    def _poll_due(self, dues: list[Slot], now: float) -> bool:
        """The longest-due drive's poll; then the other drives due in the same pass, while
        nothing else is to be done: no other thread asked for anything meanwhile (a job, an
        urgent one, a timer, a waiter: `_events`) and, once a poll went on the wire (which takes
        a transaction's time), none of the owner's own events is due (`_next_event_t`: a
        watchdog deadline, a step, a reconnect). A cycle's polls take one pass of the owner,
        not one per drive; a poll that continues step-wise or loses its drive ends the pass.
        A command waits for at most the one transaction in flight, as between passes.
        True when every due poll was done (the rest of the pass has nothing to do)."""
        dues.sort(key=lambda s: s.next_poll_t)
        events = self._events
        horizon: float | None = None
        for k, slot in enumerate(dues):
            if k and (self._urgent or self._events != events):
                return False
            transactions = self.bus.transactions
            self._poll_step(slot, now)
            if slot.poll_steps is not None or not slot.connected:
                return False
            if not slot.drive.state_from_cache or self.bus.transactions != transactions:
                now = self.clock()                   # a poll on the wire: time passed
                if horizon is None:
                    horizon = self._next_event_t()
                if now >= horizon:
                    return False
        return True

    def _quiet_cycle(self, dues: list[Slot], now: float,
                     vouched: tuple[int, float, int] | None = None) -> bool:
        """A cycle in which no drive has anything new: every drive of the bus is due, and each
        says its read_state() would give the very state of its last poll
        (Drive.unchanged_until: a cache that nothing changed since, no frame, no command).
        Then the polls are that, the cycle's bookkeeping one loop, and its publishing as after
        any cycle. False, with nothing done, at the first drive that is not so (a poll under
        way, a waiter): then the polls go one by one (_poll_step). On 8 idle CANopen drives at
        50 Hz this is most cycles (docs/benchmarks.md).

        vouched: (the bus' `changes`, until when, the owner's write count) the drives vouched
        for at the last quiet cycle, given by a pass that knows nothing else happened since (no
        request, no work of the owner's: the quiet pass of _work_once); while the bus counted
        no change, no job started or ended and that time is ahead, the drives are not asked
        again. Each snapshot counted polled is stamped with its drive's write count now."""
        changes = self.bus.changes                   # before what the drives vouch for
        if vouched is not None and vouched[0] == changes and now < vouched[1] \
                and vouched[2] == self._writes:      # (no job of any drive since)
            until = vouched[1]
        else:
            until = math.inf
            for slot in dues:
                if not slot.connected or slot.poll_steps is not None or slot.poll_waiters:
                    return False
                t = slot.drive.unchanged_until(slot.state)
                if t <= now:
                    return False
                until = min(until, t)
        self._vouched = (changes, until, self._writes)
        self._jobs_since_poll = 0
        next_t = self._next_grid_t(now)
        period = self._period_s()
        t = self.clock()
        for slot in dues:
            if slot.owner_polls or slot.group_polled:
                slot.owner_polls = slot.group_polled = False
            slot.next_poll_t = next_t
            state = slot.state
            # a read now would give it: it follows the writes so far (the vouching is asked
            # again after any job: _writes above)
            state.after_write = slot.poll_seq = slot.write_seq
            slot.sample = (state, t if state.measured_at_s is None else state.measured_at_s)
            slot.polls += 1
        if period != self._fresh_s:        # (the rate can change at run time)
            self._fresh_s = period
            for slot in dues:
                slot.drive.state_fresh_s = period
        self.cycle_unchanged = vouched is not None     # the quiet pass': nothing else since
        try:
            self._cycle()
        finally:
            self.cycle_unchanged = False
        return True

    def _after_quiet_cycle(self, events: int) -> float:
        """The delay to the next wake-up after a quiet cycle, and what lets the next pass
        skip its look over the slots (`_quiet_pass`): nothing else was to be done when this
        pass began (`events` other threads' requests then), every drive's next poll is at one
        time, and the owner's own next event (a timer, a deadline, a step) is no sooner than
        it was found now. The next pass goes straight to a quiet cycle while that holds: no
        request came since, the polls are due, and that event is not."""
        now = self.clock()
        next_t = self._slot_list[0].next_poll_t
        horizon = self._next_event_t()
        self._quiet_pass = (events, next_t, horizon, self._vouched)
        return min(next_t, horizon, now + 0.5) - now

    def _next_turn(self) -> Slot | None:
        """The drive whose waiting job starts next: of the drives with a job waiting and none
        running, the one whose last job started longest ago (of those that never started one,
        the one whose first waiting job is the oldest). Drives with work take turns: a drive
        whose newer set point keeps replacing its waiting one (a stream) goes again only after
        every other drive that waited meanwhile had its job started."""
        with self._cv:        # (submit may replace a queue's only job meanwhile)
            return min((s for s in self._slot_list if s.queue and s.active is None),
                       key=lambda s: (s.turn, s.queue[0].enqueued_t), default=None)

    def _period_s(self) -> float:
        return 1.0 / self.settings['publish_rate_hz']

    def _next_grid_t(self, now: float) -> float:
        """The next poll of a drive polled now: the first point after `now` of one grid of
        poll periods that every drive of the bus shares, so a cycle's polls run back to back
        and the owner wakes once a cycle, not once a drive (an overrun skips to the next
        point: no catch-up burst)."""
        period = self._period_s()
        return self._grid_t0 + (math.floor((now - self._grid_t0) / period) + 1) * period

    def _next_wake(self, now: float) -> float:
        """The owner's next wake-up: its next event, the next poll (a poll the group makes:
        its grace later), at most half a second ahead. (Once a cycle: loops, no lists.)"""
        t = min(now + 0.5, self._next_event_t())
        grace = max(GROUP_GRACE_S, 2.0 * self._period_s())
        connected = False
        for s in self._slot_list:
            if s.connected:
                connected = True
                if (s.active is None or s.active.polled) and s.poll_steps is None:
                    poll_t = s.next_poll_t + grace if s.group_polled else s.next_poll_t
                    if poll_t < t:
                        t = poll_t
        if not connected:
            t = min(t, self._last_cycle_t + self._period_s())
        return t

    def _next_event_t(self) -> float:
        """When the owner next has something to do other than a due poll: a step of an
        operation or of a poll, a watchdog deadline, a reconnect, a timer, a waiter's
        time-out (math.inf: nothing)."""
        t = math.inf
        for s in self._slot_list:
            if s.active is not None and s.active_steps is not None and s.wake_t < t:
                t = s.wake_t
            if s.poll_steps is not None and s.poll_wake_t < t:
                t = s.poll_wake_t
            if s.connected:
                if s.velocity_deadline is not None:
                    t = min(t, max(s.velocity_deadline, s.watchdog_retry_t))
            elif (not s.not_driven or s.identity_recheck) and s.active is None \
                    and s.next_connect_t < t:
                t = s.next_connect_t                # (a connect under way wakes at wake_t)
            for w in s.poll_waiters:
                t = min(t, w[0])
        return min(t, self._next_timer_t())

    def _next_timer_t(self) -> float:
        """When the next timer falls due (math.inf: none). Removed timers at the top of the
        heap leave it here (only the owner pops)."""
        timers = self._timers
        if timers and timers[0][2] is None:
            with self._cv:
                timers = self._timers
                while timers and timers[0][2] is None:
                    heapq.heappop(timers)
                    self._removed_timers -= 1
        return timers[0][0] if timers else math.inf

    # ------------------------------------------------------------------------------ jobs
    def _start_job(self, slot: Slot) -> None:
        with self._cv:
            job = slot.queue.popleft()
        if job.taken is not None:
            job.taken.set()
        if not _begin(job.future):     # cancelled by its waiter while it waited
            return
        self._turns += 1
        slot.turn = self._turns
        if not slot.connected:
            _resolve(job.future, exc=NotConnected(
                f'{job.label}: drive {slot.name} is DISCONNECTED ({self.bus.description})'))
            return
        slot.active = job
        self._wrote(slot)
        self._advance(slot, job.fn)

    def _wrote(self, slot: Slot) -> None:
        """A job of slot's drive starts or ends: what is polled from now on follows it."""
        slot.write_seq += 1
        self._writes += 1

    def _step_active(self, slot: Slot) -> None:
        steps = slot.active_steps
        self._advance(slot, lambda: next(steps))

    def _advance(self, slot: Slot, call: Callable[[], Any]) -> None:
        """Run the first call or the next step of slot.active; finish it when it ends."""
        job = slot.active
        try:
            result = call()
            if slot.active_steps is None and is_steps(result):
                slot.active_steps = result
                result = next(result)
            if slot.active_steps is not None:
                slot.wake_t = self.clock() + (result or 0.0)
                return
        except StopIteration as stop:
            result = stop.value
        except Exception as exc:  # noqa: BLE001 - every failure goes to the job's waiter
            self._finish(slot)
            if job.kind == CONNECT:
                self._connect_failed(slot, exc)
            else:
                self._failed(slot, job, exc)
            return
        self._finish(slot)
        if job.kind == CONNECT:
            self._connected(slot, *result)
            return
        self._disarm(slot, job)
        _resolve(job.future, result)

    def _disarm(self, slot: Slot, job: Job) -> None:
        """A confirmed stop/position/homing disarms the watchdog, unless a velocity command
        was accepted after it was submitted (that one runs next and must stay watched)."""
        if job.disarms:
            with self._cv:
                if slot.arm_seq == job.arm_seq:
                    slot.velocity_deadline = None

    def _finish(self, slot: Slot) -> None:
        """slot.active ended: its future gets the drive's write count at its end (before its
        result), and the job an urgent one suspended goes on (at its wake time)."""
        self._wrote(slot)
        if slot.active is not None:
            slot.active.future.after_write = slot.write_seq
        if slot.suspended:
            slot.active, slot.active_steps, slot.wake_t = slot.suspended.pop()
        else:
            slot.active, slot.active_steps = None, None

    def _failed(self, slot: Slot, job: Job, exc: Exception) -> None:
        if isinstance(exc, LinkError):
            self._drive_lost(slot, f'{job.label}: {exc}')
        elif not isinstance(exc, DriveError):
            self.on_event('error', slot.name, f'internal error in {job.label}: {exc!r}\n'
                          + traceback.format_exc())
            exc = DriveError(f'internal error in {job.label}: {exc!r}')
        _resolve(job.future, exc=exc)

    def _run_urgent(self, job: Job) -> None:
        """Drop the drive's queued jobs that the urgent one preempts (they would move after
        the stop), cut its running ones short, and start the job now, as the drive's running
        job: a step-wise one (a disable walking the state machine) is stepped like any job,
        before anything queued. A running job it does not preempt (a save during a disable) is
        suspended until the urgent one ended (`_finish`)."""
        if not _begin(job.future):     # cancelled by its waiter while it waited
            return
        slot = self.slots[job.drive]
        with self._cv:
            dropped = [j for j in slot.queue if j.preempted_by(job)]
            slot.queue = collections.deque(j for j in slot.queue if not j.preempted_by(job))
        for j in dropped:
            _resolve(j.future, exc=Cancelled(f'{j.label}: dropped by {job.label}'))
        why = f'cut short by {job.label}'
        if slot.suspended:
            kept = [e for e in slot.suspended if not e[0].preempted_by(job)]
            for other, steps, _ in slot.suspended:
                if other.preempted_by(job):
                    self._abandon(slot, other, steps, why)
            slot.suspended = kept
        if slot.active is not None and slot.active.preempted_by(job):
            self._cut_short(slot, why)
        if not slot.connected:
            _resolve(job.future, exc=NotConnected(
                f'{job.label}: drive {slot.name} is DISCONNECTED ({self.bus.description})'))
            return
        if slot.active is not None:
            slot.suspended.append((slot.active, slot.active_steps, slot.wake_t))
            slot.active, slot.active_steps = None, None
        slot.active = job
        self._wrote(slot)
        self._advance(slot, job.fn)

    def _cut_short(self, slot: Slot, why: str) -> None:
        """End slot.active (Cancelled); the job it suspended, if any, goes on."""
        job, steps = slot.active, slot.active_steps
        self._finish(slot)
        self._abandon(slot, job, steps, why)

    def _cut_all(self, slot: Slot, why: str) -> None:
        """End slot.active and every job it suspended (a link loss, shutdown)."""
        while slot.active is not None:
            self._cut_short(slot, why)

    def _abandon(self, slot: Slot, job: Job, steps: Any, why: str) -> None:
        if steps is not None:
            try:
                steps.close()
            except Exception as exc:  # noqa: BLE001 - a vendor finally clause failed
                self.on_event('warning', slot.name, f'{job.label}: closing: {exc!r}')
        _resolve(job.future, exc=Cancelled(f'{job.label}: {why}'))

    def _watchdog_stop(self, slot: Slot) -> None:
        timeout_s = self.settings['command_timeout_s']
        self.on_event('warning', slot.name, f'velocity watchdog: no velocity_command for '
                      f'{timeout_s:g} s (command_timeout_s), stopping')
        slot.watchdog_retry_t = self.clock() + WATCHDOG_RETRY_S
        job = Job.of(slot.name, Command.stop(slot.drive.stop, 'watchdog stop'), self.clock(),
                     slot.arm_seq)
        job.future.add_done_callback(lambda f: f.exception() and self.on_event(
            'error', slot.name, f'velocity watchdog: stop failed: {f.exception()}'))
        self._run_urgent(job)

    # ----------------------------------------------------------------------------- polls
    def _poll_step(self, slot: Slot, now: float) -> None:
        self._jobs_since_poll = 0
        slot.owner_polls = False
        try:
            if slot.poll_steps is None:
                slot.poll_seq = slot.write_seq
                result = slot.drive.read_state()
                if is_steps(result):
                    slot.poll_steps = result
                    slot.next_poll_t = self._next_grid_t(now)
                    result = next(result)
                    slot.poll_wake_t = self.clock() + (result or 0.0)
                    return
                state = result
                slot.next_poll_t = self._next_grid_t(now)
            else:
                delay = next(slot.poll_steps)
                slot.poll_wake_t = self.clock() + (delay or 0.0)
                return
        except StopIteration as stop:
            slot.poll_steps = None
            state = stop.value
        except Exception as exc:  # noqa: BLE001 - _poll_failed sorts them
            slot.poll_steps = None
            self._poll_failed(slot, exc)
            return
        slot.group_polled = False
        self._polled(slot, state)

    def _poll_failed(self, slot: Slot, exc: Exception) -> None:
        if isinstance(exc, LinkError):
            self._drive_lost(slot, f'read state: {exc}')
        elif isinstance(exc, DriveError):
            self._note_error(slot, f'read state: {exc}')
        else:       # unknown trouble: treat as a link loss
            self.on_event('error', slot.name, f'read_state: {exc!r}\n' + ''.join(
                traceback.format_exception(exc)))
            self._drive_lost(slot, f'unexpected error {exc!r}')

    def _polled(self, slot: Slot, state: DriveState) -> None:
        """A poll's state: the slot's, its waiters', and the cycle's end when it was the last.
        The state is stamped with the write count in force when the poll began (a drive that
        returns the object of an earlier poll, its values unchanged, has it stamped again)."""
        state.after_write = slot.poll_seq
        slot.state = state
        slot.drive.state_fresh_s = self._period_s()      # (the rate can change at run time)
        # when the position was true (the trajectory feedback compares the plan at that time)
        slot.sample = (state, self.clock() if state.measured_at_s is None
                       else state.measured_at_s)
        slot.polls += 1
        self._resolve_waiters(slot, True)
        self._cycle_polled.add(slot.name)
        if self._cycle_done():
            self._cycle()

    def _cycle_done(self) -> bool:
        """Every connected drive was polled in this cycle. Polls go in the order of the slots,
        so the last ones are looked at first: one look a poll, not one a drive."""
        polled = self._cycle_polled
        if len(polled) == len(self._slot_list):
            return True
        for s in reversed(self._slot_list):
            if s.connected and s.name not in polled:
                return False
        return True

    def _cycle(self) -> None:
        """Every connected drive was polled once (or none is connected): publish."""
        self._cycle_polled = set()
        self._last_cycle_t = self.clock()
        self.cycles += 1
        self.on_cycle(self)

    def _resolve_waiters(self, slot: Slot, ok: bool) -> None:
        """ok: slot.state was polled: the waiters whose write number it reached (its
        after_write) are answered True; the others stay, and the drive is polled again at once.
        Not ok (the drive lost, shutdown): every waiter is answered False."""
        if not slot.poll_waiters:          # the usual case: no lock taken
            return
        stamp = slot.state.after_write
        with self._cv:
            waiters = slot.poll_waiters
            if ok:
                slot.poll_waiters = [w for w in waiters if w[2] > stamp]
                waiters = [w for w in waiters if w[2] <= stamp]
                if slot.poll_waiters:
                    slot.next_poll_t = min(slot.next_poll_t, self.clock())
            else:
                slot.poll_waiters = []
        for _, callback, _ in waiters:
            callback(ok)

    def _expire_waiters(self, now: float) -> None:
        if self._next_timer_t() <= now:
            due = []
            with self._cv:
                timers = self._timers
                while timers and timers[0][0] <= now:
                    entry = heapq.heappop(timers)
                    if entry[2] is None:
                        self._removed_timers -= 1
                    else:
                        due.append(entry[2])
                        entry[2] = None           # called: removing it does nothing
            for callback in due:
                callback()
        for slot in self.slots.values():
            if not slot.poll_waiters or not any(w[0] <= now for w in slot.poll_waiters):
                continue
            with self._cv:
                expired = [w for w in slot.poll_waiters if w[0] <= now]
                slot.poll_waiters = [w for w in slot.poll_waiters if w[0] > now]
            for _, callback, _ in expired:
                callback(False)

    def _note_error(self, slot: Slot, msg: str) -> None:
        if msg != slot.last_error:
            self.on_event('error', slot.name, msg)
        slot.last_error = msg

    # ------------------------------------------------------------------------ link state
    def _drive_lost(self, slot: Slot, why: str) -> None:
        if not slot.connected:
            return
        # velocity_deadline stays: a velocity run the drive may still be doing is stopped by
        # the watchdog as soon as the drive answers again.
        slot.connected = False
        slot.poll_steps = None
        self._cut_all(slot, f'link lost ({why})')
        with self._cv:
            queued, slot.queue = list(slot.queue), collections.deque()
        for job in queued:
            _resolve(job.future, exc=NotConnected(f'{job.label}: link lost ({why})'))
        slot.state = DriveState(state=State.DISCONNECTED, position_steps=slot.state.position_steps,
                                homed=slot.state.homed, after_write=slot.write_seq)
        slot.backoff_s = self.settings['reconnect_period_s']
        slot.next_connect_t = self.clock() + slot.backoff_s
        self.on_event('error', slot.name, f'link lost ({why}); reconnecting every '
                      f"{self.settings['reconnect_period_s']:g} s and more (back-off)")
        self._resolve_waiters(slot, False)
        self._cycle_polled.discard(slot.name)
        if not any(s.connected for s in self.slots.values()):
            self._close_bus()
        self._cycle()         # DISCONNECTED is published at once

    def _close_bus(self) -> None:
        try:
            self.bus.close()
        except Exception as exc:  # noqa: BLE001 - closing a dead link may fail any way
            logger.debug('close after link loss: %r', exc)

    def _connect(self, slot: Slot) -> None:
        """Start one connection attempt: a job of the drive's own, step-wise like any other
        (a CANopen boot-up wait gives the bus to the other drives)."""
        slot.active = Job.of(slot.name, Command(CONNECT, lambda: self._connect_steps(slot),
                                                'connect', motion=False), self.clock())
        self._wrote(slot)
        self._advance(slot, slot.active.fn)

    def _connect_steps(self, slot: Slot):
        if not self.bus.is_open:
            self.bus.open()
        identity = yield from _steps(slot.drive.connect())
        state = yield from _steps(slot.drive.read_state())
        return identity, state

    def _connected(self, slot: Slot, identity: dict[str, str], state: DriveState) -> None:
        state.after_write = slot.write_seq     # (read by the connect after its own writes)
        slot.identity, slot.state = identity, state
        why = self.on_connected(self, slot)
        if why:
            with self._cv:
                slot.not_driven, slot.identity_recheck = why, False
            slot.state = DriveState(state=State.DISCONNECTED)
            self.on_event('error', slot.name, f'not driven: {why}')
            self._resolve_connect_waiters(slot, DriveError(f'not driven: {why}'))
            return
        with self._cv:           # (refuse_drive may have refused it meanwhile: that stays)
            again = slot.identity_recheck
            if again:
                slot.not_driven, slot.identity_recheck = '', False
        slot.identity_backoff_s = IDENTITY_RECHECK_S
        slot.connected = True
        slot.reconnects += 1
        slot.last_error = ''
        slot.backoff_s = self.settings['reconnect_period_s']
        slot.next_poll_t = self.clock()
        identity_text = ', '.join(f'{k}={v}' for k, v in identity.items())
        self.on_event('info', slot.name, f'connected ({identity_text}); state '
                      f'{state.state.value}, position {state.position_steps} steps'
                      + ('; the identity matches again: driven' if again else ''))
        self._resolve_connect_waiters(slot, None, identity)
        if slot.name in self.auto_enable and slot.reconnects == 1:
            self.submit(slot.name, Command.enable(slot.drive.enable, 'auto_enable')) \
                .add_done_callback(lambda f, n=slot.name: self._auto_enabled(n, f))

    def _auto_enabled(self, name: str, fut: concurrent.futures.Future) -> None:
        if fut.exception() is None:
            self.on_event('info', name, 'enabled at start-up (auto_enable)')
        else:
            self.on_event('error', name, f'auto_enable failed: {fut.exception()}')

    def _connect_failed(self, slot: Slot, exc: Exception) -> None:
        """The status first, then the recheck() callers, who read it."""
        self._record_connect_failure(slot, exc)
        self._resolve_connect_waiters(slot, exc)

    def _record_connect_failure(self, slot: Slot, exc: Exception) -> None:
        if not isinstance(exc, DriveError):
            self.on_event('error', slot.name, f'connect: {exc!r}\n' + ''.join(
                traceback.format_exception(exc)))
        if not any(s.connected for s in self.slots.values()):
            self._close_bus()
        period = self.settings['reconnect_period_s']
        slot.last_error = str(exc)
        if isinstance(exc, IdentityError):
            # Another device, or not the one configured: not driven, checked again slowly.
            delay = slot.identity_backoff_s
            slot.identity_backoff_s = min(delay * 2, IDENTITY_RECHECK_MAX_S)
            slot.next_connect_t = self.clock() + delay
            at = time.strftime('%H:%M:%S', time.localtime(time.time() + delay))
            why = f'{exc} (checked again at {at}, in {delay:g} s; fault_reset checks at once)'
            with self._cv:
                if slot.not_driven and not slot.identity_recheck:
                    return                    # refused meanwhile (refuse_drive): that stays
                slot.not_driven, slot.identity_recheck = why, True
            self.on_event('error', slot.name, f'not driven: {why}')
            return
        with self._cv:   # no identity read: the wrong device may be gone, or noise came
            if slot.identity_recheck:
                slot.not_driven, slot.identity_recheck = '', False
        if slot.backoff_s == period or slot.reconnects == 0:
            self.on_event('warning', slot.name, f'cannot connect on {self.bus.description}: '
                          f'{exc}; retrying')
        slot.next_connect_t = self.clock() + slot.backoff_s
        slot.backoff_s = min(slot.backoff_s * 2, 8 * period)

    def refuse_drive(self, name: str, why: str) -> None:
        """From any thread: stop driving `name` (the owner drops its link at its next turn)."""
        with self._cv:
            self.slots[name].not_driven, self.slots[name].identity_recheck = why, False
            self._notify()
        self.on_event('error', name, f'not driven: {why}')

    def recheck(self, name: str) -> concurrent.futures.Future:
        """From any thread: connect a drive not driven for its identity now (fault_reset),
        not at its next check. The future gets the identity, or the connect's error
        (IdentityError: still not the drive); at once the identity of a connected drive, and
        a DriveError for a drive refused for as long as the node runs."""
        fut: concurrent.futures.Future = concurrent.futures.Future()
        slot = self.slots[name]
        self.after(0.0, lambda: self._recheck(slot, fut))
        return fut

    def _recheck(self, slot: Slot, fut: concurrent.futures.Future) -> None:
        """Owner thread (the caller's once the bus shuts down: then it is cancelled)."""
        if self._stopping:
            _resolve(fut, exc=Cancelled(f'{slot.name}: the node is shutting down'))
        elif slot.connected:
            _resolve(fut, slot.identity)
        elif slot.not_driven and not slot.identity_recheck:
            _resolve(fut, exc=DriveError(f'not driven: {slot.not_driven}'))
        else:
            slot.connect_waiters.append(fut)
            slot.next_connect_t = min(slot.next_connect_t, self.clock())

    def _resolve_connect_waiters(self, slot: Slot, exc: Exception | None,
                                 result: Any = None) -> None:
        waiters, slot.connect_waiters = slot.connect_waiters, []
        for fut in waiters:
            _resolve(fut, result, exc)

    # --------------------------------------------------------------------------- shutdown
    def _shutdown_drives(self, standstill_timeout_s: float, disable: set[str]) -> None:
        with self._cv:
            self._stopping = True
            queued = [j for s in self.slots.values() for j in s.queue] + list(self._urgent)
            for s in self.slots.values():
                s.queue.clear()
            self._urgent.clear()
        for job in queued:
            _resolve(job.future, exc=Cancelled(f'{job.label}: the node is shutting down'))
        live = [s for s in self.slots.values() if s.connected]
        for s in self.slots.values():
            self._cut_all(s, 'the node is shutting down')
            s.poll_steps = None
            self._resolve_waiters(s, False)
            self._resolve_connect_waiters(s, Cancelled(f'{s.name}: the node is shutting down'))
        with self._cv:      # after the jobs: a job's time-out timer then finds it ended
            timers, self._timers, self._removed_timers = sorted(self._timers), [], 0
            due = [e[2] for e in timers if e[2] is not None]
            for entry in timers:
                entry[2] = None
        for callback in due:
            callback()
        for s in live:                 # every drive decelerates at once ...
            self._shutdown_step(s, 'stop', s.drive.stop)
        deadline = self.clock() + standstill_timeout_s
        for s in live:                 # ... then each is disabled once it stands still
            if s.name in disable:
                self._shutdown_step(s, 'wait for standstill', self._wait_standstill, s, deadline)
                self._shutdown_step(s, 'disable', s.drive.disable)
        for s in self.slots.values():
            try:
                s.drive.close()
            except Exception:  # noqa: BLE001 - one drive's close must not keep the bus open
                pass
        self._close_bus()
        self._closed = True

    def _shutdown_step(self, slot: Slot, what: str, fn: Callable, *args) -> None:
        try:
            complete(fn(*args))
        except Exception as exc:  # noqa: BLE001 - go on with the other steps and drives
            self.on_event('error', slot.name, f'shutdown: {what}: {exc}')

    def _wait_standstill(self, slot: Slot, deadline: float) -> None:
        while self.clock() < deadline:
            slot.state = complete(slot.drive.read_state())
            if not slot.state.moving:
                return
            time.sleep(0.02)  # poll rate limit at shutdown: there is nothing else to wait on


def _steps(result: Any):
    """`yield from _steps(drive.method())`: the result of a plain or a step-wise call."""
    if is_steps(result):
        return (yield from result)
    return result


def _nothing() -> None:
    """What removes a timer that was called at once (after() once the bus shuts down)."""


def _resolve(fut: concurrent.futures.Future, result: Any = None,
             exc: BaseException | None = None) -> None:
    """End `fut` with `result`, or with `exc`, unless it ended already (its waiter cancelled
    it while its job waited): nothing a future raises reaches the owner loop."""
    try:
        if exc is None:
            fut.set_result(result)
        else:
            fut.set_exception(exc)
    except concurrent.futures.InvalidStateError:
        pass


def _begin(fut: concurrent.futures.Future) -> bool:
    """The owner starts the job of `fut`: from now on it cannot be cancelled (it is awaited to
    its end). False: its waiter cancelled it while it waited, and it is not run."""
    try:
        return fut.set_running_or_notify_cancel()
    except RuntimeError:       # not pending (ended already): nothing to run it for
        return False
