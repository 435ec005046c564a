"""The bus owner: one thread per bus makes every call into the Bus and its Drives (no rclpy).

Where what lives:
    owner.py     BusOwner: the owner thread, its loop and the API other threads call
    schedule.py  what the owner does next: the order rules, pure functions with table tests
    jobs.py      Job, the queue rules (stream replacement, urgent preemption), futures
    running.py   jobs in the owner thread: start, step, finish, urgent, the watchdog's stop
    polling.py   polls, cycles, the quiet cycle, poll waiters, the poll group's loans
    link.py      connect, identity recheck, link loss and back-off, shutdown
    slot.py      one drive's state, in parts by who writes it (and a test-only write check)
    timers.py    after()'s timers
    priority.py  the owner thread's real-time priority

Threads and what they own:
- The owner thread (one per bus) makes every call into the Bus and its Drives: polls, commands,
  service transactions, reconnects, the velocity watchdog and shutdown all run there, as jobs.
  It writes a slot's owner fields (slot.py); other threads read them. While the poll group has
  the bus (poll_group.py, lend() to give_back(); the owner waits meanwhile) its thread is the
  acting owner of the lent drives: it polls them and writes what a poll writes (and a link loss
  found by its poll). `on_cycle` runs in whichever of the two ended the cycle.
- Any other thread (ROS callbacks) only calls `submit()`, `arm_watchdog()`, `poll_soon()`,
  `wait_poll()`, `after()`, `recheck()`, `refuse_drive()` and `shutdown()`, which take the bus
  lock (`_cv`) for a moment, write the slots' request fields, enqueue and return (a
  `concurrent.futures.Future` for a job). A command submitted with `hand_over=True` to a
  sleeping owner also waits (GIL released, at most HAND_OVER_MAX_S) until the owner has taken
  it: the GIL goes to the owner at once.
- A job's future is pending while the job waits, running from when the owner starts it, then
  done. Only a waiting job can be cancelled; a job that started runs to its end (jobs.py).

Order (the rules, one by one: schedule.py):
- Jobs of one drive run in the order submitted, one at a time; a step-wise job (a generator, see
  drive.py) keeps the drive until it ends, while other drives' jobs and polls run between its
  steps. A step-wise poll likewise: its next step comes at the time it asked for.
- A streaming command (kind STREAM: position or velocity) replaces a STREAM job of the same
  topic still waiting at the tail of that drive's queue: the drive gets the newest set point.
- Drives with waiting jobs take turns (schedule.next_turn): a stream on one drive keeps another
  drive's job waiting for at most one job of each other drive.
- URGENT jobs (stop, quick stop, disable, the watchdog's stop) go before everything else and
  reach the wire after at most the one transaction already in flight (running.py).
- No job holds the owner: a due poll goes before a running operation's next step, so while the
  polls fit the period no drive's poll gap exceeds its period, the longest single step of a
  job on the bus and one transaction beside a save, an enable or a register access; a move's
  steps go before the later steps of a poll (a slow line has no room for both). Every
  watchdog is checked on time.

Snapshot provenance: every snapshot carries the count of writes to its drive in force when its
read began (running.py counts them, polling.py stamps them); an answer is judged only by a
snapshot that followed its own writes (`wait_poll`).

The velocity watchdog: `arm_watchdog()` is called when a velocity command is accepted, before
anything is written; only a job submitted with `disarms=True` (a stop, a position or homing
command) that the drive confirmed disarms it. A refusal, a lost reply or a link loss leaves it
armed; after a reconnect an expired deadline stops the drive at once. It is checked on the
owner's clock (the loop wakes at the deadline), not once per poll.

An exception that escapes the owner loop (a bug, not a drive's error: those are the jobs' and
polls' results) stops every drive of the bus, closes it, marks the drives DISCONNECTED with the
error and calls `on_failure`: the node then ends, since nobody polls or watches these drives.
"""

from .bus_owner import HAND_OVER_MAX_S, BusOwner
from .jobs import (
    COMMAND,
    CONNECT,
    MAINTENANCE,
    STREAM,
    URGENT,
    Cancelled,
    Job,
    NotConnected,
    Superseded,
)
from .jobs import (
    steps_of as _steps,
)
from .running import WATCHDOG_RETRY_S
from .schedule import GROUP_GRACE_S, MAX_JOBS_BEFORE_OVERDUE_POLL
from .slot import IDENTITY_RECHECK_MAX_S, IDENTITY_RECHECK_S, Slot

__all__ = ['BusOwner', 'Slot', 'Job', 'Cancelled', 'NotConnected', 'Superseded',
           'URGENT', 'COMMAND', 'STREAM', 'MAINTENANCE', 'CONNECT', 'GROUP_GRACE_S',
           'HAND_OVER_MAX_S', 'IDENTITY_RECHECK_S', 'IDENTITY_RECHECK_MAX_S',
           'MAX_JOBS_BEFORE_OVERDUE_POLL', 'WATCHDOG_RETRY_S', '_steps']
