"""The bus owner's order rules (owner/schedule.py), as tables: no threads, no drives.

Each row sets up the slots of one bus at one instant and names the rule that must apply and
the drive it applies to. Time is in seconds from an arbitrary origin; the poll period is
PERIOD_S."""

from __future__ import annotations

import collections
import math
import types

import pytest
from stepper_drivers.owner import schedule
from stepper_drivers.owner.schedule import (
    MAX_JOBS_BEFORE_OVERDUE_POLL,
    QuietPass,
    Rule,
    Vouched,
    decide,
)

PERIOD_S = 0.1
NOW = 10.0


def job(polled=False, enqueued_t=0.0, motion=True, also=()):
    return types.SimpleNamespace(polled=polled, enqueued_t=enqueued_t, motion=motion,
                                 also=also)


def slot(name, **fields):
    """A drive at rest: connected, polled just now (next poll a period ahead), no work."""
    s = types.SimpleNamespace(
        name=name, connected=True, not_driven='', identity_recheck=False,
        velocity_deadline=None, watchdog_retry_t=0.0, active=None, active_operation=None,
        wake_t=0.0, poll_operation=None, poll_wake_t=0.0, next_poll_t=NOW + PERIOD_S,
        poll_requested=False, owner_polls=False, group_polled=False, next_connect_t=0.0,
        queue=collections.deque(), turn=0, poll_waiters=[])
    for k, v in fields.items():
        setattr(s, k, v)
    return s


def running(steps_due=True, polled=False, motion=True, also=(), **fields):
    """A drive whose step-wise job runs; its next step is due (or not); `also`: the other
    drives it writes (a group start)."""
    return dict(active=job(polled, motion=motion, also=also), active_operation=iter(()),
                wake_t=NOW - 0.001 if steps_due else NOW + 1.0, **fields)


def late_step():
    """A running job whose next step has waited a poll period for the polls."""
    return dict(running(), wake_t=NOW - PERIOD_S)


DUE = dict(next_poll_t=NOW - 0.01)                 # its poll is due
OVERDUE = dict(next_poll_t=NOW - PERIOD_S - 0.01)  # a period late
QUEUED = dict(queue=collections.deque([job()]))                    # a move waits
QUEUED_SAVE = dict(queue=collections.deque([job(motion=False)]))   # a save waits


def run(slots, *, urgent=False, quiet=None, events=0, jobs_since_poll=0,
        next_timer_t=math.inf, last_cycle_t=NOW):
    return decide(slots, NOW, PERIOD_S, events=events, urgent=urgent, quiet=quiet,
                  jobs_since_poll=jobs_since_poll, next_timer_t=next_timer_t,
                  last_cycle_t=last_cycle_t)


QUIET = QuietPass(events=3, polls_t=NOW - 0.001, horizon_t=NOW + 1.0,
                  vouched=Vouched(0, NOW + 1.0, 0))

# (id, slots, decide's other arguments, the rule, the drive it applies to)
TABLE = [
    # 1 the quiet pass: while nothing asked, the polls are due and the horizon is ahead
    ('quiet pass', [slot('a', **DUE), slot('b', **DUE)], dict(quiet=QUIET, events=3),
     Rule.QUIET_CYCLE, None),
    ('quiet pass, then a request came', [slot('a', **DUE)], dict(quiet=QUIET, events=4),
     Rule.POLLS, 'a'),
    ('quiet pass, an urgent job waits', [slot('a', **DUE)],
     dict(quiet=QUIET, events=3, urgent=True), Rule.URGENT, None),
    ('quiet pass, polls not due yet', [slot('a')],
     dict(quiet=QUIET._replace(polls_t=NOW + 0.01), events=3), Rule.SLEEP, None),
    ('quiet pass, the owner event came', [slot('a', **DUE)],
     dict(quiet=QUIET._replace(horizon_t=NOW), events=3), Rule.POLLS, 'a'),
    # 2 urgent before everything (a due watchdog, a due step, due timers)
    ('urgent first', [slot('a', velocity_deadline=NOW - 1, **running())],
     dict(urgent=True, next_timer_t=NOW - 1), Rule.URGENT, None),
    # 3 timers and waiters' time-outs before the drives' own work
    ('a timer is due', [slot('a', velocity_deadline=NOW - 1)], dict(next_timer_t=NOW),
     Rule.TIMERS, None),
    ('a waiter timed out', [slot('a', **QUEUED), slot('b', poll_waiters=[(NOW, None, 0)])],
     {}, Rule.TIMERS, None),
    ('a waiter still waits', [slot('a', poll_waiters=[(NOW + 1, None, 0)])], {},
     Rule.SLEEP, None),
    ('a timer not yet', [slot('a')], dict(next_timer_t=NOW + 0.01), Rule.SLEEP, None),
    # 4 a refused drive is dropped; a passed watchdog deadline stops: first drive in order
    ('not driven', [slot('a', not_driven='duplicate', **DUE)], {}, Rule.NOT_DRIVEN, 'a'),
    ('watchdog', [slot('a', **running()), slot('b', velocity_deadline=NOW)], {},
     Rule.WATCHDOG, 'b'),
    ('watchdog before a due poll and queued jobs',
     [slot('a', **DUE, **QUEUED), slot('b', velocity_deadline=NOW - 0.5)], {},
     Rule.WATCHDOG, 'b'),
    ('watchdog waits for its retry time', [slot('a', velocity_deadline=NOW - 0.5,
                                                watchdog_retry_t=NOW + 0.05)], {},
     Rule.SLEEP, None),
    ('watchdog deadline ahead', [slot('a', velocity_deadline=NOW + 0.01)], {}, Rule.SLEEP,
     None),
    ('the first drive in order of the two checks',
     [slot('a', velocity_deadline=NOW - 1), slot('b', not_driven='x')], {}, Rule.WATCHDOG,
     'a'),
    ('a disconnected drive has no watchdog stop',
     [slot('a', connected=False, velocity_deadline=NOW - 1, next_connect_t=NOW + 1)], {},
     Rule.SLEEP, None),
    # 5 an overdue poll after MAX_JOBS_BEFORE_OVERDUE_POLL jobs
    ('overdue poll after enough jobs', [slot('a', **OVERDUE), slot('b', **running())],
     dict(jobs_since_poll=MAX_JOBS_BEFORE_OVERDUE_POLL), Rule.OVERDUE_POLL, 'a'),
    ('overdue, fewer jobs: the polls before the step',
     [slot('a', **OVERDUE), slot('b', **running())],
     dict(jobs_since_poll=MAX_JOBS_BEFORE_OVERDUE_POLL - 1), Rule.POLLS_BEFORE_STEP, 'a'),
    ('the longest due of the overdue', [slot('a', next_poll_t=NOW - 0.15),
                                        slot('b', next_poll_t=NOW - 0.3), slot('c', **QUEUED)],
     dict(jobs_since_poll=MAX_JOBS_BEFORE_OVERDUE_POLL), Rule.OVERDUE_POLL, 'b'),
    # 6 the step of a poll under way, at its own wake time, before jobs that do not move
    ("a poll step before a save's step and a queued save",
     [slot('a', **running(motion=False)), slot('b', **QUEUED_SAVE),
      slot('c', poll_operation=iter(()), poll_wake_t=NOW)], {}, Rule.POLL_STEP, 'c'),
    ("a move's step before a poll step",
     [slot('a', **running()), slot('c', poll_operation=iter(()), poll_wake_t=NOW)], {},
     Rule.STEP, 'a'),
    ("a move's step also when a save's comes first in order",
     [slot('a', **running(motion=False)), slot('b', **running()),
      slot('c', poll_operation=iter(()), poll_wake_t=NOW)], {}, Rule.STEP, 'a'),
    ('a queued move before a poll step',
     [slot('b', **QUEUED), slot('c', poll_operation=iter(()), poll_wake_t=NOW)], {},
     Rule.START_JOB, 'b'),
    ('the earliest poll step', [slot('a', poll_operation=iter(()), poll_wake_t=NOW - 0.01),
                                slot('b', poll_operation=iter(()), poll_wake_t=NOW - 0.02)], {},
     Rule.POLL_STEP, 'b'),
    ('a poll step due', [slot('a', poll_operation=iter(()), poll_wake_t=NOW)], {},
     Rule.POLL_STEP, 'a'),
    ('a poll step not yet (the drive is not due again meanwhile)',
     [slot('a', poll_operation=iter(()), poll_wake_t=NOW + 0.06, **OVERDUE)], {}, Rule.SLEEP,
     None),
    ('a poll step before a reconnect', [slot('a', connected=False),
                                        slot('b', poll_operation=iter(()), poll_wake_t=NOW)], {},
     Rule.POLL_STEP, 'b'),
    # 7 a due step: the due polls first, unless the step waited a period for them
    ('polls before a step', [slot('a', **DUE), slot('b', **running())], {},
     Rule.POLLS_BEFORE_STEP, 'a'),
    ('a step that waited a period for the polls goes', [slot('a', **DUE),
                                                         slot('b', **late_step())], {},
     Rule.STEP, 'b'),
    ('a step, no poll due', [slot('a'), slot('b', **running())], {}, Rule.STEP, 'b'),
    ('a step before a queued job', [slot('a', **QUEUED), slot('b', **running())], {},
     Rule.STEP, 'b'),
    ('a step not yet due', [slot('a', **running(steps_due=False))], {}, Rule.SLEEP, None),
    ("a running job's own drive is not polled", [slot('a', **DUE, **running())], {},
     Rule.STEP, 'a'),
    ("a polled job's drive is", [slot('a', **DUE, **running(polled=True))], {},
     Rule.POLLS_BEFORE_STEP, 'a'),
    ('nor a drive that a running job of another drive also writes (a group start)',
     [slot('a', **DUE), slot('b', **running(also=('a',)))], {}, Rule.STEP, 'b'),
    ('that drive once no job writes it', [slot('a', **DUE), slot('b', **running(also=('c',)))],
     {}, Rule.POLLS_BEFORE_STEP, 'a'),
    # 8 a waiting job: the drive whose turn it is, unless a job went and polls are due
    ('a queued job', [slot('a'), slot('b', **QUEUED)], {}, Rule.START_JOB, 'b'),
    ('turns: the drive that went longest ago',
     [slot('a', turn=7, **QUEUED), slot('b', turn=3, **QUEUED)], {}, Rule.START_JOB, 'b'),
    ('turns: never started, the oldest job first',
     [slot('a', queue=collections.deque([job(enqueued_t=2.0)])),
      slot('b', queue=collections.deque([job(enqueued_t=1.0)]))], {}, Rule.START_JOB, 'b'),
    ('a queued job behind its running one waits', [slot('a', **QUEUED,
                                                        **running(steps_due=False))], {},
     Rule.SLEEP, None),
    ('a job before the due polls', [slot('a', **DUE), slot('b', **QUEUED)], {},
     Rule.START_JOB, 'b'),
    ('a job of a disconnected drive still starts (it fails at once)',
     [slot('a', connected=False, next_connect_t=NOW + 1, **QUEUED)], {}, Rule.START_JOB, 'a'),
    ('a job before the due polls, once a job went: the polls',
     [slot('a', **DUE), slot('b', **QUEUED)], dict(jobs_since_poll=1), Rule.POLLS_BEFORE_JOB,
     'a'),
    # 9 a reconnect before the due polls
    ('a reconnect', [slot('a', **DUE), slot('b', connected=False, next_connect_t=NOW)], {},
     Rule.RECONNECT, 'b'),
    ('not yet', [slot('a', connected=False, next_connect_t=NOW + 0.1)], {}, Rule.SLEEP, None),
    ('refused: no reconnect', [slot('a', connected=False, not_driven='refused')], {},
     Rule.SLEEP, None),
    ('refused for its identity: rechecked', [slot('a', connected=False, not_driven='id',
                                                  identity_recheck=True)], {},
     Rule.RECONNECT, 'a'),
    ('a connect under way is not started again',
     [slot('a', connected=False, **running(steps_due=False))], {}, Rule.SLEEP, None),
    # 10 the due polls, the longest due first
    ('polls', [slot('a', next_poll_t=NOW - 0.02), slot('b', next_poll_t=NOW - 0.05)], {},
     Rule.POLLS, 'b'),
    ('poll_soon ahead of the grid', [slot('a', poll_requested=True)], {}, Rule.POLLS, 'a'),
    # 11 no drive connected: the DISCONNECTED status at the poll rate
    ('all disconnected', [slot('a', connected=False, next_connect_t=NOW + 1)],
     dict(last_cycle_t=NOW - PERIOD_S), Rule.DISCONNECTED_CYCLE, None),
    ('all disconnected, within the period',
     [slot('a', connected=False, next_connect_t=NOW + 1)], dict(last_cycle_t=NOW - 0.05),
     Rule.SLEEP, None),
    # 12 nothing to do
    ('idle', [slot('a'), slot('b')], {}, Rule.SLEEP, None),
]


@pytest.mark.parametrize('slots, kwargs, rule, drive',
                         [row[1:] for row in TABLE], ids=[row[0] for row in TABLE])
def test_the_rule_that_applies(slots, kwargs, rule, drive):
    d = run(slots, **kwargs)
    assert d.rule is rule, d
    assert (d.slot.name if d.slot is not None else None) == drive


def test_every_rule_has_a_row():
    assert {row[3] for row in TABLE} == set(Rule)


def test_the_due_polls_come_with_the_decision():
    a, b, c = slot('a', **DUE), slot('b'), slot('c', poll_requested=True)
    d = run([a, b, c])
    assert d.rule is Rule.POLLS and d.dues == [a, c]


def test_decide_changes_nothing():
    slots = [slot('a', **DUE, **QUEUED), slot('b', velocity_deadline=NOW - 1),
             slot('c', connected=False)]
    before = [dict(vars(s)) for s in slots]
    run(slots, next_timer_t=NOW - 1)
    assert [dict(vars(s)) for s in slots] == before


@pytest.mark.parametrize('fields, wake', [
    ({}, NOW + PERIOD_S),                                   # the next poll
    # the group polls it: the owner wakes only once the group is late by its grace
    (dict(group_polled=True), NOW + PERIOD_S + max(schedule.GROUP_GRACE_S, 2 * PERIOD_S)),
    (dict(group_polled=True, owner_polls=True), NOW + PERIOD_S),   # given back: no grace
    (dict(poll_requested=True), NOW),
    (dict(velocity_deadline=NOW + 0.03), NOW + 0.03),
    (dict(velocity_deadline=NOW + 0.03, watchdog_retry_t=NOW + 0.04), NOW + 0.04),
    (dict(poll_waiters=[(NOW + 0.02, None, 0)]), NOW + 0.02),
    (running(steps_due=False), NOW + 1.0 if 1.0 < schedule.MAX_SLEEP_S else
     NOW + schedule.MAX_SLEEP_S),
    (dict(next_poll_t=NOW + 5), NOW + schedule.MAX_SLEEP_S),
])
def test_next_wake(fields, wake):
    assert schedule.next_wake([slot('a', **fields)], NOW, PERIOD_S, math.inf, NOW) \
        == pytest.approx(wake)


def test_the_owner_does_not_wake_for_a_drive_that_a_running_job_also_writes():
    """Its poll is not due while the job runs (no busy loop on its overdue grid time)."""
    written = slot('a', **DUE)
    writer = slot('b', **dict(running(also=('a',)), wake_t=NOW + 0.03))
    assert schedule.next_wake([written, writer], NOW, PERIOD_S, math.inf, NOW) \
        == pytest.approx(NOW + 0.03)                  # b's next step, not a's overdue poll
    writer.active = None
    assert schedule.next_wake([written, writer], NOW, PERIOD_S, math.inf, NOW) \
        == pytest.approx(written.next_poll_t)


def test_next_wake_of_a_timer_and_of_a_disconnected_bus():
    assert schedule.next_wake([slot('a')], NOW, PERIOD_S, NOW + 0.01, NOW) == NOW + 0.01
    down = slot('a', connected=False, next_connect_t=NOW + 0.3)
    assert schedule.next_wake([down], NOW, PERIOD_S, math.inf, NOW - 0.02) \
        == pytest.approx(NOW + PERIOD_S - 0.02)


@pytest.mark.parametrize('now, expected', [(0.0, 0.1), (0.05, 0.1), (0.1, 0.2),
                                           (0.37, 0.4)])
def test_the_poll_grid_skips_to_the_next_point(now, expected):
    assert schedule.next_grid_t(0.0, PERIOD_S, now) == pytest.approx(expected)
