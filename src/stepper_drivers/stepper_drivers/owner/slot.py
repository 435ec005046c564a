"""One drive's state on the bus, in two parts by who writes it.

- `OwnerPart`: written by the bus's acting owner only, without a lock: the owner thread, or
  the poll group's thread while it holds the bus on loan (poll_group.py, lend() to give_back():
  the owner waits meanwhile). Other threads read these fields: each is one reference
  assignment, so a reader sees a whole value (`sample` pairs a state with its time for that).
- `RequestPart`: what other threads ask for, written by any thread with the bus lock held
  (the owner takes it too to change them).

`name` and `drive` are set once. With STEPPER_DRIVERS_CHECK_WRITERS=1 in the environment, or
after check_writers() (the test suite does both: test/conftest.py for the nodes it starts,
src/stepper_drivers/test/conftest.py), every write to a slot is checked against these rules:
a write from the wrong thread, or without the lock, raises WriterError at the write. Without
it a slot is a plain object (no cost).
"""

from __future__ import annotations

import collections
import concurrent.futures
import os
import threading
from typing import Any, Callable

from ..contract.drive import Drive, DriveState, State
from .jobs import Job, Suspended

# A drive whose connect raised IdentityError is connected again after this long, doubling up
# to IDENTITY_RECHECK_MAX_S (link.py).
IDENTITY_RECHECK_S = 30.0
IDENTITY_RECHECK_MAX_S = 300.0


class OwnerPart:
    """Written by the acting owner (the module docstring); read by anyone."""

    OWNER_FIELDS = frozenset((
        'state', 'sample', 'connected', 'identity', 'polls', 'reconnects', 'last_error',
        'active', 'active_operation', 'wake_t', 'suspended', 'poll_operation', 'poll_wake_t',
        'next_poll_t', 'next_connect_t', 'backoff_s', 'identity_backoff_s', 'turn',
        'watchdog_retry_t', 'write_seq', 'poll_seq', 'group_polled', 'connect_waiters'))

    def _init_owner_part(self, reconnect_period_s: float) -> None:
        self.state = DriveState(state=State.DISCONNECTED)
        # (the last polled state, clock() when its position was true), set in one assignment:
        # a reader in another thread takes both from it, never a state with another's time
        self.sample: tuple[DriveState, float] = (self.state, 0.0)
        self.connected = False
        self.identity: dict[str, str] = {}
        self.polls = 0               # successful read_state() results
        self.reconnects = 0          # successful connects, the first one included
        self.last_error = ''
        self.active: Job | None = None
        self.active_operation = None     # generator of the running job
        self.wake_t = 0.0            # next step of the running job / connect
        # running jobs an urgent one did not preempt: the last one goes on when the job
        # running now ends
        self.suspended: list[Suspended] = []
        self.poll_operation = None       # generator of a read_state() in progress
        self.poll_wake_t = 0.0       # its next step
        self.next_poll_t = 0.0       # the next poll, on the bus' grid
        self.next_connect_t = 0.0
        self.backoff_s = reconnect_period_s
        self.identity_backoff_s = IDENTITY_RECHECK_S
        # jobs the owner had started when it started this drive's last one (0: none yet): the
        # drive with waiting work and the lowest turn goes next (schedule.next_turn)
        self.turn = 0
        self.watchdog_retry_t = 0.0
        # writes to the drive: +1 when one of its jobs starts and +1 when it ends; a snapshot
        # stamped with it followed every write counted
        self.write_seq = 0
        # write_seq when the poll under way (or the last one) began: its snapshot's stamp
        self.poll_seq = 0
        # the last poll was the poll group's: the owner need not wake for the next one unless
        # the group misses it by GROUP_GRACE_S
        self.group_polled = False
        self.connect_waiters: list[concurrent.futures.Future] = []   # recheck() callers


class RequestPart:
    """Written by any thread with the bus lock held."""

    REQUEST_FIELDS = frozenset((
        'queue', 'poll_waiters', 'velocity_deadline', 'arm_seq', 'submitted', 'not_driven',
        'identity_recheck', 'poll_requested', 'owner_polls'))

    def _init_request_part(self) -> None:
        self.queue: collections.deque[Job] = collections.deque()
        # (deadline, callback, the least write count of a snapshot that answers it): wait_poll
        self.poll_waiters: list[tuple[float, Callable[[bool], None], int]] = []
        self.velocity_deadline: float | None = None
        self.arm_seq = 0             # velocity commands accepted so far (arm_watchdog calls)
        self.submitted = 0           # jobs submitted for this drive
        self.not_driven = ''         # why the node does not drive this drive ('' while it does)
        # not driven for its identity: connected again at next_connect_t; False with
        # not_driven set: refused for as long as the node runs (refuse_drive)
        self.identity_recheck = False
        self.poll_requested = False  # poll_soon(): poll at once, ahead of the grid
        # the poll group gave this drive back unpolled: the owner polls it before the group
        # lends the link again (a request of the group's may still await its reply)
        self.owner_polls = False


class WriterError(AssertionError):
    """A slot field written by a thread the rules above do not allow (test-only check)."""


class Slot(OwnerPart, RequestPart):
    """Runtime state of one drive on the bus (who writes what: the module docstring)."""

    def __init__(self, name: str, drive: Drive, reconnect_period_s: float, bus_owner: Any = None):
        object.__setattr__(self, '_owner', None)
        self.name = name
        self.drive = drive
        self._init_owner_part(reconnect_period_s)
        self._init_request_part()
        object.__setattr__(self, '_owner', bus_owner)   # its BusOwner: the write check


def _checked_setattr(self: Slot, field: str, value: Any) -> None:
    owner = self._owner
    if owner is not None:
        if field in RequestPart.REQUEST_FIELDS:
            if not owner._cv._is_owned():
                raise WriterError(f'{self.name}.{field} written without the bus lock '
                                  f'(thread {threading.current_thread().name})')
        elif field in OwnerPart.OWNER_FIELDS:
            acting = owner.acting_owner()
            if acting is not None and acting is not threading.current_thread():
                raise WriterError(f'{self.name}.{field} written by thread '
                                  f'{threading.current_thread().name}, not by the acting '
                                  f'owner {acting.name}')
        elif field not in ('name', 'drive'):
            raise WriterError(f'{self.name}.{field}: not a field of a slot')
    object.__setattr__(self, field, value)


def check_writers() -> None:
    """(Tests) From now on every write to a slot of this process is checked."""
    Slot.__setattr__ = _checked_setattr    # type: ignore[method-assign]


if os.environ.get('STEPPER_DRIVERS_CHECK_WRITERS') == '1':
    check_writers()
