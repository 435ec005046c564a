"""What the bus owner does next: the order rules, as pure functions of the slots and the time.

`decide` is called once per pass of the owner (before every transaction: keep it one loop over
the slots, no lists but the due polls and the drives that running jobs also write). It reads the
slots and what the owner passes in, and changes nothing; the owner carries the decision out
(owner.py). The rules, highest first:

 1. QUIET_CYCLE   the pass after a quiet cycle, while no request came, the polls are due and
                  the owner's own next event is not: straight to the next quiet cycle
 2. URGENT        an urgent job waits (stop, quick stop, disable, the watchdog's stop)
 3. TIMERS        a timer (after()) or a poll waiter's time-out is due
 4. NOT_DRIVEN    a connected drive was refused (its link is dropped) } the first drive, in
    WATCHDOG      a velocity watchdog deadline passed (a stop)        } the bus' order
 5. OVERDUE_POLL  the longest-due poll is a period late and MAX_JOBS_BEFORE_OVERDUE_POLL jobs
                  or steps went first since the last poll
 6. POLL_STEP     the next step of a poll under way is due (at its own wake time), and no step
                  or start of a job that moves is: the earliest (a poll is a few transactions;
                  it goes before a save or a register access, as a due poll does)
 7. POLLS_BEFORE_STEP  a step of a running job is due, and so are polls, and the step has
    STEP          not yet waited a period for them: the polls first; else the step (no job
                  holds the owner; an overrun of polls does not stop an operation)
 8. POLLS_BEFORE_JOB  a drive has a waiting job and none running, polls are due, and a job
    START_JOB     or a step went since the last poll: the polls first; else the job of the
                  drive whose turn it is (`next_turn`): a command goes before the due polls,
                  but a run of commands does not hold them
    POLL_STEP     a poll step due behind a move's steps: a move's strings are on a deadline,
                  and on a slow line polls and moves do not both fit (X-MIND K: a trajectory
                  finished 1.2 s late when poll steps went first)
 9. RECONNECT     a disconnected drive's next connection attempt is due
10. POLLS         polls are due: the longest-due first (a quiet cycle when all are due)
11. DISCONNECTED_CYCLE  no drive connected: their DISCONNECTED status, at the poll rate
12. SLEEP         until `next_wake`

So while the polls fit the period, no drive's poll gap exceeds its period, the longest single
step of a job on the bus and one transaction, whatever runs beside it.

A poll is due when the drive is connected, no poll of it is under way, no job of it runs (but
one that asked to be polled between its steps: a stream of set points), no job of another drive
that also writes it runs (a group start: its poll would read what the job is changing, and take
a transaction the start is waiting for), and its grid time came or poll_soon() asked for it.
"""

from __future__ import annotations

import enum
import math
from typing import NamedTuple, Sequence

from .slot import Slot

# After this many commands or steps while a poll is overdue, one poll goes first (fairness).
MAX_JOBS_BEFORE_OVERDUE_POLL = 4
# An owner whose drives a poll group polls (poll_group.py) polls them itself once a poll is
# this late, or two poll periods if longer: the group is late or gone.
GROUP_GRACE_S = 0.25
# The owner wakes at least this often.
MAX_SLEEP_S = 0.5


class Rule(enum.Enum):
    QUIET_CYCLE = 1
    URGENT = 2
    TIMERS = 3
    NOT_DRIVEN = 4
    WATCHDOG = 5
    OVERDUE_POLL = 6
    POLL_STEP = 7
    POLLS_BEFORE_STEP = 8
    STEP = 9
    POLLS_BEFORE_JOB = 10
    START_JOB = 11
    RECONNECT = 12
    POLLS = 13
    DISCONNECTED_CYCLE = 14
    SLEEP = 15


class Vouched(NamedTuple):
    """What the drives vouched for at the last quiet cycle (polling.py)."""

    changes: int        # the bus' change count then
    until_t: float      # the drives' state is unchanged until then, if nothing else happens
    writes: int         # the owner's write count then (a job of any drive since: ask again)


class QuietPass(NamedTuple):
    """Left by a quiet cycle: what lets the next pass go straight to the next one."""

    events: int         # other threads' requests counted when the quiet cycle's pass began
    polls_t: float      # every drive's next poll (one grid time)
    horizon_t: float    # the owner's own next event (a timer, a deadline, a step)
    vouched: Vouched


class Decision(NamedTuple):
    rule: Rule
    slot: Slot | None = None
    dues: list[Slot] | None = None       # POLLS, POLLS_BEFORE_*: the drives due


def written_by_jobs(slots: Sequence[Slot]) -> frozenset[str]:
    """The drives that a running job of another drive also writes (Command.also)."""
    return frozenset(name for slot in slots if slot.active is not None
                     for name in slot.active.also)


def poll_due(slot: Slot, now: float, written: frozenset[str] = frozenset()) -> bool:
    """`written`: the drives that another drive's running job also writes (Command.also)."""
    return (slot.active.polled if slot.active is not None else slot.name not in written) \
        and slot.poll_operation is None and (now >= slot.next_poll_t or slot.poll_requested)


class Seen(NamedTuple):
    """One look at every drive of the bus (`look`): what the rules of `decide` ask about."""

    waiter_due: bool            # a poll waiter's time-out has come
    check: Slot | None          # the first connected drive not driven or past its watchdog
    due: Slot | None            # of the connected drives due for a poll, the most overdue
    dues: list[Slot]            # every connected drive due for a poll
    step: Slot | None           # the first drive whose running job's next step is due
    moving: bool                # a job with a due step is a motion
    poll_step: Slot | None      # the drive whose poll under way is due soonest
    reconnect: Slot | None      # the first disconnected drive due for a connect
    queued: bool                # a drive has a job waiting and none running
    connected: bool             # a drive is connected


def look(slots: Sequence[Slot], now: float) -> Seen:
    """Every drive looked at once (one loop): what `decide` needs of them."""
    waiter_due = queued = connected = moving = False
    check = due = step = poll_step = reconnect = None
    dues: list[Slot] = []
    written = written_by_jobs(slots)
    for slot in slots:
        if slot.poll_waiters and not waiter_due:
            waiter_due = any(w[0] <= now for w in slot.poll_waiters)
        if slot.connected:
            connected = True
            if check is None and (slot.not_driven or (
                    slot.velocity_deadline is not None and now >= slot.velocity_deadline
                    and now >= slot.watchdog_retry_t)):
                check = slot
            if poll_due(slot, now, written):
                dues.append(slot)
                if due is None or slot.next_poll_t < due.next_poll_t:
                    due = slot
        elif reconnect is None and (not slot.not_driven or slot.identity_recheck) \
                and slot.active is None and now >= slot.next_connect_t:
            reconnect = slot
        if slot.active is None:
            queued = queued or bool(slot.queue)
        elif slot.active_operation is not None and now >= slot.wake_t:
            if step is None:
                step = slot
            moving = moving or slot.active.motion
        if slot.poll_operation is not None and now >= slot.poll_wake_t \
                and (poll_step is None or slot.poll_wake_t < poll_step.poll_wake_t):
            poll_step = slot
    return Seen(waiter_due, check, due, dues, step, moving, poll_step, reconnect, queued,
                connected)


def decide(slots: Sequence[Slot], now: float, period_s: float, *, events: int, urgent: bool,
           quiet: QuietPass | None, jobs_since_poll: int, next_timer_t: float,
           last_cycle_t: float) -> Decision:
    """The rule that applies now (module docstring), with the drive(s) it applies to: the rules
    in their order, each one `if`."""
    if quiet is not None and quiet.events == events and not urgent \
            and quiet.polls_t <= now < quiet.horizon_t:
        return Decision(Rule.QUIET_CYCLE)
    if urgent:
        return Decision(Rule.URGENT)
    seen = look(slots, now)
    due, step, poll_step = seen.due, seen.step, seen.poll_step
    if next_timer_t <= now or seen.waiter_due:
        return Decision(Rule.TIMERS)
    if seen.check is not None:
        return Decision(Rule.NOT_DRIVEN if seen.check.not_driven else Rule.WATCHDOG, seen.check)
    if due is not None and now >= due.next_poll_t + period_s \
            and jobs_since_poll >= MAX_JOBS_BEFORE_OVERDUE_POLL:
        return Decision(Rule.OVERDUE_POLL, due)
    turn = next_turn(slots) if seen.queued else None
    if poll_step is not None and not seen.moving and (turn is None or not turn.queue[0].motion):
        return Decision(Rule.POLL_STEP, poll_step)
    if step is not None:
        if due is not None and now < step.wake_t + period_s:
            return Decision(Rule.POLLS_BEFORE_STEP, due, seen.dues)
        return Decision(Rule.STEP, step)
    if turn is not None:
        if due is not None and jobs_since_poll:
            return Decision(Rule.POLLS_BEFORE_JOB, due, seen.dues)
        return Decision(Rule.START_JOB, turn)
    if poll_step is not None:
        return Decision(Rule.POLL_STEP, poll_step)
    if seen.reconnect is not None:     # before due polls: they may be due all the time
        return Decision(Rule.RECONNECT, seen.reconnect)
    if due is not None:
        return Decision(Rule.POLLS, due, seen.dues)
    if not seen.connected and now >= last_cycle_t + period_s:
        return Decision(Rule.DISCONNECTED_CYCLE)
    return Decision(Rule.SLEEP)


def next_turn(slots: Sequence[Slot]) -> Slot | None:
    """The drive whose waiting job starts next: of the drives with a job waiting and none
    running, the one whose last job started longest ago (of those that never started one, the
    one whose first waiting job is the oldest). Drives with work take turns: a drive whose
    newer set point keeps replacing its waiting one (a stream) goes again only after every
    other drive that waited meanwhile had its job started. (Only the owner takes jobs from a
    queue, and a replacement is in place: a queue seen non-empty here stays so.)"""
    return min((s for s in slots if s.queue and s.active is None),
               key=lambda s: (s.turn, s.queue[0].enqueued_t), default=None)


def next_grid_t(grid_t0: float, period_s: float, now: float) -> float:
    """The next poll of a drive polled now: the first point after `now` of one grid of poll
    periods that every drive of the bus shares, so a cycle's polls run back to back and the
    owner wakes once a cycle, not once a drive (an overrun skips to the next point: no
    catch-up burst)."""
    return grid_t0 + (math.floor((now - grid_t0) / period_s) + 1) * period_s


def next_event_t(slots: Sequence[Slot], next_timer_t: float) -> float:
    """When the owner next has something to do other than a due poll: a step of a job or of a
    poll, a watchdog deadline, a reconnect, a timer, a waiter's time-out (math.inf: none)."""
    t = math.inf
    for s in slots:
        if s.active is not None and s.active_operation is not None and s.wake_t < t:
            t = s.wake_t
        if s.poll_operation is not None and s.poll_wake_t < t:
            t = s.poll_wake_t
        if s.connected:
            if s.velocity_deadline is not None:
                t = min(t, max(s.velocity_deadline, s.watchdog_retry_t))
        elif (not s.not_driven or s.identity_recheck) and s.active is None \
                and s.next_connect_t < t:
            t = s.next_connect_t                # (a connect under way wakes at wake_t)
        for w in s.poll_waiters:
            t = min(t, w[0])
    return min(t, next_timer_t)


def next_wake(slots: Sequence[Slot], now: float, period_s: float, next_timer_t: float,
              last_cycle_t: float) -> float:
    """The owner's next wake-up: its next event, the next poll (a poll the group makes: its
    grace later, unless the group gave the drive back), at most MAX_SLEEP_S ahead. (Once a
    cycle: loops, no lists.)"""
    t = min(now + MAX_SLEEP_S, next_event_t(slots, next_timer_t))
    grace = max(GROUP_GRACE_S, 2.0 * period_s)
    connected = False
    written = written_by_jobs(slots)
    for s in slots:
        if s.connected:
            connected = True
            if (s.active.polled if s.active is not None else s.name not in written) \
                    and s.poll_operation is None:
                if s.poll_requested:
                    return now
                poll_t = s.next_poll_t + grace if s.group_polled and not s.owner_polls \
                    else s.next_poll_t
                if poll_t < t:
                    t = poll_t
    if not connected:
        t = min(t, last_cycle_t + period_s)
    return t
