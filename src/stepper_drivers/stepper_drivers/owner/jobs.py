"""Jobs: what the bus owner runs for a caller, the queue rules, and the futures' life cycle.

A job's future is pending while the job waits, running from when the owner starts it (`begin`:
`set_running_or_notify_cancel`), then done. Only a waiting job can be cancelled (its waiter's
time-out): the owner then skips it. A job that started runs to its end and its future gets its
result; nothing a future raises reaches the owner loop (`resolve`).
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import threading
from typing import Any, Callable, NamedTuple

from ..contract.drive import DriveError, is_operation
from .commands import Command, JobKind

URGENT, COMMAND, STREAM = JobKind.URGENT, JobKind.COMMAND, JobKind.STREAM
MAINTENANCE, CONNECT = JobKind.MAINTENANCE, JobKind.CONNECT


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
    also: tuple[str, ...] = ()  # other drives it writes (Command.also): their writes counted too

    @classmethod
    def of(cls, drive: str, command: Command, enqueued_t: float, arm_seq: int = 0) -> 'Job':
        """The job of `command` for `drive`, with a future of its own."""
        return cls(drive, command.kind, command.fn, command.label, concurrent.futures.Future(),
                   command.topic, command.disarms, command.motion, enqueued_t, arm_seq,
                   command.polled, also=command.also)

    def preempted_by(self, urgent: 'Job') -> bool:
        """A stop drops motion; a disable (an URGENT job that is not motion itself) drops
        everything but maintenance that cannot move (save, register reads)."""
        if self.motion:
            return True
        return not urgent.motion and self.kind != MAINTENANCE and self.kind != CONNECT


class Suspended(NamedTuple):
    """A running job an urgent one did not preempt (a save during a disable): it goes on at
    `wake_t` once the urgent job ended."""

    job: Job
    steps: Any          # its generator (None: not step-wise)
    wake_t: float


def enqueue(queue: collections.deque[Job], job: Job) -> Job | None:
    """Append `job` (not URGENT) to its drive's queue. A STREAM job takes the place of a STREAM
    job of the same topic still waiting at the tail, which is returned (the drive gets the
    newest set point): in place, so a reader never sees the queue empty meanwhile. Under the
    bus lock."""
    if job.kind == STREAM and queue:
        tail = queue[-1]
        if tail.kind == STREAM and tail.topic == job.topic:
            queue[-1] = job
            return tail
    queue.append(job)
    return None


def split_preempted(queue: collections.deque[Job], urgent: Job
                    ) -> tuple[collections.deque[Job], list[Job]]:
    """(what stays queued, what `urgent` drops): queued jobs that would move after a stop, or
    change the drive after a disable."""
    kept = collections.deque(j for j in queue if not j.preempted_by(urgent))
    return kept, [j for j in queue if j.preempted_by(urgent)]


def steps_of(result: Any):
    """`yield from steps_of(drive.method())`: the result of a plain or a step-wise call."""
    if is_operation(result):
        return (yield from result)
    return result


def resolve(fut: concurrent.futures.Future, result: Any = None,
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


def begin(fut: concurrent.futures.Future) -> bool:
    """The owner starts the job of `fut`: from now on it cannot be cancelled (it is awaited to
    its end). False: its waiter cancelled it while it waited, and it is not run."""
    try:
        return fut.set_running_or_notify_cancel()
    except RuntimeError:       # not pending (ended already): nothing to run it for
        return False
