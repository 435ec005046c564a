"""BusOwner: the owner thread of one bus, its public API and its loop.

What each pass does is decided by schedule.decide (the order rules, one place) and carried out
by the parts the class is made of: running.py (jobs), polling.py (polls, cycles, the poll
group's loans), link.py (connect, loss, shutdown). One lock (`_cv`) and one thread per bus.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
import traceback
from typing import Any, Callable, Iterable

from ..contract.drive import Bus, Drive
from . import schedule
from .commands import Command
from .jobs import URGENT, Cancelled, Job, Superseded, enqueue, resolve
from .link import LinkPart
from .polling import PollingPart
from .priority import set_priority
from .running import RunningPart
from .schedule import QuietPass, Rule, Vouched
from .slot import Slot
from .timers import Timers

logger = logging.getLogger('stepper_drivers.owner')
# submit(hand_over=True) to a sleeping owner waits at most this long for it to take the job [s].
HAND_OVER_MAX_S = 0.002


def _nothing() -> None:
    """What removes a timer that was called at once (after() once the bus shuts down)."""


class BusOwner(RunningPart, PollingPart, LinkPart):
    """Owns one Bus and its drives in one thread; see the package docstring."""

    def __init__(self, bus: Bus, drives: dict[str, Drive], settings: dict[str, Any],
                 on_cycle: Callable[['BusOwner'], None] | None = None,
                 on_connected: Callable[['BusOwner', Slot], str] | None = None,
                 on_event: Callable[[str, str, str], None] | None = None,
                 auto_enable: Iterable[str] = (), clock: Callable[[], float] = time.monotonic,
                 name: str = 'bus',
                 on_failure: Callable[['BusOwner', str], None] | None = None):
        """`settings` is read live: 'publish_rate_hz', 'command_timeout_s',
        'reconnect_period_s'. `on_cycle` runs once every connected drive was polled (a cycle),
        at once when a drive is lost (its DISCONNECTED status) and at the poll rate while none
        is connected: in the owner thread, or in the poll group's thread when a poll of the
        group's ends the cycle or finds the link lost (poll_group.py; the owner waits
        meanwhile); `on_connected` may return a reason not to drive a drive (duplicate identity);
        `on_event(level, drive, text)` reports what happened ('info'/'warning'/'error');
        `on_failure(bus_owner,
                    why)` runs in the owner thread when an internal error ended it, after
        its drives were stopped and its bus closed (the node then ends: a bus without its owner
        is neither polled nor watched)."""
        self.bus = bus
        self.settings = settings
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._run, name=f'owner {name}', daemon=True)
        self._lender: threading.Thread | None = None   # the poll group's thread, while lent
        self.slots = {n: Slot(n, d, settings['reconnect_period_s'], self)
                      for n, d in drives.items()}
        self._slot_list = list(self.slots.values())
        self.on_cycle = on_cycle or (lambda bus_owner: None)
        self.on_connected = on_connected or (lambda bus_owner, slot: '')
        self.on_event = on_event or self._log_event
        self.on_failure = on_failure or (lambda bus_owner, why: None)
        self.failure = ''           # why the owner ended by itself ('' while it runs)
        self.auto_enable = set(auto_enable)
        self.clock = clock
        self.name = name
        self._urgent: collections.deque[Job] = collections.deque()
        self._stopping = False
        self._shutdown_request: tuple[float, set[str]] | None = None
        self._jobs_since_poll = 0
        self._turns = 0             # jobs started from the drives' queues (owner thread)
        self._timers = Timers(self._cv)
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
        self._quiet_pass: QuietPass | None = None    # left by the last quiet cycle
        self._vouched = Vouched(0, 0.0, 0)           # the last vouching (polling.py)
        self._writes = 0            # the slots' write_seq increments, all drives (owner thread)
        self._fresh_s = 0.0         # the state_fresh_s the quiet cycles last gave the drives
        # (owner thread, during on_cycle) the cycle is a quiet pass': since the cycle before,
        # no other thread asked for anything, the owner did nothing else and no drive has
        # anything new; what the slots hold is as it was then (on_cycle may skip a look)
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

    @property
    def stopping(self) -> bool:
        """The drives' shutdown began (shutdown(), or the owner failed): no job, poll or timer
        is taken any more."""
        return self._stopping

    def acting_owner(self) -> threading.Thread | None:
        """The thread that may write the slots' owner fields now: the poll group's while it
        holds a loan, else the owner thread once started (None before: any thread)."""
        lender = self._lender
        if lender is not None:
            return lender
        return self._thread if self._thread.ident is not None else None

    def submit(self, drive: str, command: Command, *, hand_over: bool = False):
        """Queue `command` for `drive` (its fn is called in the owner thread; may return
        Operation); its kind and flags come from its constructor (commands.py). Returns the job's
        future; `future.submitted` numbers the drive's submissions (compare with
        `slots[drive].submitted`: was anything submitted since?).

        hand_over: when the owner sleeps, wait (at most HAND_OVER_MAX_S, GIL released) until
        it has taken the job. For commands from a ROS callback: without it the executor thread
        goes on holding the GIL through rclpy's wait-set rebuild after the callback, and the
        woken owner waits for it, up to the 0.5 ms switch interval and more under load (the
        command-to-wire figures in docs/benchmarks.md). A busy owner (a transaction in
        flight) is not waited for: on a serial line that would hold the executor 20-30 ms."""
        job = Job.of(drive, command, self.clock())
        fut = job.future
        unknown = [n for n in job.also if n not in self.slots or n == drive]
        if unknown:      # (in the caller's thread: the owner would fail on them)
            raise ValueError(f'{job.label}: also {unknown}: not other drives of this bus')
        with self._cv:
            slot = self.slots[drive]
            job.arm_seq = slot.arm_seq
            if self._stopping:
                resolve(fut, exc=Cancelled(f'{job.label}: the node is shutting down'))
                return fut
            if hand_over and self._idle:
                job.taken = threading.Event()
            slot.submitted += 1
            fut.submitted = slot.submitted
            if job.kind == URGENT:
                self._urgent.append(job)
            else:
                replaced = enqueue(slot.queue, job)
                if replaced is not None:
                    resolve(replaced.future, exc=Superseded(
                        f'{replaced.label}: replaced by the newer {job.label} before it was '
                        'sent'))
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
            self.slots[drive].poll_requested = True
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
                slot.poll_waiters = slot.poll_waiters + [
                    (self.clock() + timeout_s, callback, after)]
                self._notify()
                return
        callback(False)

    def after(self, delay_s: float, callback: Callable[[], None]) -> Callable[[], None]:
        """Call callback() from the owner thread once delay_s has passed; at once (in this
        thread) once the bus shuts down, as the owner then calls every timer still waiting:
        what awaits one (a service, an action) ends rather than wait for ever. Returns what
        removes the timer (from any thread; nothing once it was called)."""
        with self._cv:
            if not self._stopping:
                remove = self._timers.add(self.clock() + delay_s, callback)
                self._notify()
                return remove
        callback()
        return _nothing

    def report_error(self, drive: str, text: str) -> None:
        """From any thread: `text` is the drive's last error (its status shows it until the
        next one or a reconnect). The owner writes it: at once from the owner thread (a job's
        done-callback), else at its next pass; not once the bus shuts down."""
        slot = self.slots[drive]
        if threading.current_thread() is self.acting_owner():
            slot.last_error = text
        else:
            self.after(0.0, lambda: None if self._stopping else setattr(
                slot, 'last_error', text))

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

    def _run(self) -> None:
        set_priority(int(self.settings.get('owner_thread_priority', 0)), self.on_event,
                     self.name)
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
        """Do one unit of work (one transaction or one step), as schedule.decide says; return
        how long to sleep."""
        self.passes += 1
        now = self.clock()
        events = self._events
        quiet, self._quiet_pass = self._quiet_pass, None
        while True:
            d = schedule.decide(
                self._slot_list, now, self._period_s(), events=events,
                urgent=bool(self._urgent), quiet=quiet, jobs_since_poll=self._jobs_since_poll,
                next_timer_t=self._timers.next_t(), last_cycle_t=self._last_cycle_t)
            rule = d.rule
            if rule is not Rule.QUIET_CYCLE:
                break
            if self._quiet_cycle(self._slot_list, now, quiet.vouched):
                return self._after_quiet_cycle(events)
            quiet = None                   # the drives do not vouch: the rules without it
        if rule is Rule.SLEEP:
            return self._next_wake(now) - now
        if rule is Rule.POLLS:
            dues = d.dues
            if len(dues) == len(self._slot_list) and self._quiet_cycle(dues, now):
                return self._after_quiet_cycle(events)
            if self._poll_due(dues, now):
                # every due poll done and published, nothing else was due at the pass' start
                # (what came since is in _events or due by its time): the next wake-up, without
                # a pass over the slots to find it
                now = self.clock()
                return self._next_wake(now) - now
        else:
            self._carry_out(d, now)
        return 0.0

    def _carry_out(self, d: schedule.Decision, now: float) -> None:
        """One unit of work of a rule other than SLEEP, POLLS and QUIET_CYCLE."""
        rule = d.rule
        if rule is Rule.URGENT:
            with self._cv:
                urgent = self._urgent.popleft() if self._urgent else None
            if urgent is not None:
                if urgent.taken is not None:
                    urgent.taken.set()
                self._run_urgent(urgent)
        elif rule is Rule.STEP:
            self._jobs_since_poll += 1
            self._step_active(d.slot)
        elif rule is Rule.START_JOB:
            self._jobs_since_poll += 1
            self._start_job(d.slot)
        elif rule is Rule.POLLS_BEFORE_STEP or rule is Rule.POLLS_BEFORE_JOB:
            self._poll_due(d.dues, now)        # (ends at the step or job: it is due)
        elif rule is Rule.OVERDUE_POLL or rule is Rule.POLL_STEP:
            self._poll_step(d.slot, now)
        elif rule is Rule.TIMERS:
            self._expire_waiters(now)
        elif rule is Rule.WATCHDOG:
            self._watchdog_stop(d.slot)
        elif rule is Rule.NOT_DRIVEN:
            self._drive_lost(d.slot, f'not driven: {d.slot.not_driven}')
        elif rule is Rule.RECONNECT:
            self._connect(d.slot)
        elif rule is Rule.DISCONNECTED_CYCLE:
            self._cycle()     # the DISCONNECTED status goes on at the poll rate

    def _period_s(self) -> float:
        return 1.0 / self.settings['publish_rate_hz']

    def _next_wake(self, now: float) -> float:
        return schedule.next_wake(self._slot_list, now, self._period_s(), self._timers.next_t(),
                                  self._last_cycle_t)

    def _next_event_t(self) -> float:
        return schedule.next_event_t(self._slot_list, self._timers.next_t())

    def _next_grid_t(self, now: float) -> float:
        return schedule.next_grid_t(self._grid_t0, self._period_s(), now)
