"""Running jobs in the owner thread: start, step, finish, urgent preemption, the watchdog stop.

A step-wise job (a generator, drive.py) keeps its drive until it ends; between its steps the
owner does everything else (schedule.py). An URGENT job drops its drive's queued jobs that it
preempts (they would move after the stop), cuts the running ones short and runs at once, as
the drive's running job; a running job it does not preempt (a save during a disable) is
suspended until the urgent job ended (`_finish`), and goes on at its wake time.

Snapshot provenance: the owner counts the writes to each drive (`Slot.write_seq`: +1 when a
job of the drive starts, +1 when it ends); a job's future carries the count at its end as
`after_write`. A job that also writes other drives (Command.also: a group start queued under
one drive) counts its start and end as writes of each of them too, so a snapshot of another
drive read before the job does not answer for after it.
"""

from __future__ import annotations

import traceback
from typing import Any, Callable

from ..contract.drive import DriveError, LinkError, is_operation
from .commands import Command
from .jobs import CONNECT, Cancelled, Job, NotConnected, Suspended, begin, resolve, split_preempted
from .slot import Slot

# A watchdog stop that could not be sent is tried again after this long [s].
WATCHDOG_RETRY_S = 0.1


class RunningPart:
    """The jobs part of BusOwner (owner thread; attributes: owner.py)."""

    def _start_job(self, slot: Slot) -> None:
        with self._cv:
            job = slot.queue.popleft()
        if job.taken is not None:
            job.taken.set()
        if not begin(job.future):      # cancelled by its waiter while it waited
            return
        self._turns += 1
        slot.turn = self._turns
        if not slot.connected:
            resolve(job.future, exc=NotConnected(
                f'{job.label}: drive {slot.name} is DISCONNECTED ({self.bus.description})'))
            return
        slot.active = job
        self._wrote(slot, job)
        self._advance(slot, job.fn)

    def _wrote(self, slot: Slot, job: Job | None = None) -> None:
        """A job of slot's drive starts or ends: what is polled from now on follows it (and
        for every drive the job also writes, `job.also`)."""
        slot.write_seq += 1
        self._writes += 1
        for name in job.also if job is not None else ():
            other = self.slots[name]
            other.write_seq += 1
            self._writes += 1

    def _step_active(self, slot: Slot) -> None:
        steps = slot.active_operation
        self._advance(slot, lambda: next(steps))

    def _advance(self, slot: Slot, call: Callable[[], Any]) -> None:
        """Run the first call or the next step of slot.active; finish it when it ends."""
        job = slot.active
        try:
            result = call()
            if slot.active_operation is None and is_operation(result):
                slot.active_operation = result
                result = next(result)
            if slot.active_operation is not None:
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
        resolve(job.future, result)

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
        self._wrote(slot, slot.active)
        if slot.active is not None:
            slot.active.future.after_write = slot.write_seq
        if slot.suspended:
            slot.active, slot.active_operation, slot.wake_t = slot.suspended.pop()
        else:
            slot.active, slot.active_operation = None, None

    def _failed(self, slot: Slot, job: Job, exc: Exception) -> None:
        if isinstance(exc, LinkError):
            self._drive_lost(slot, f'{job.label}: {exc}')
        elif not isinstance(exc, DriveError):
            self.on_event('error', slot.name, f'internal error in {job.label}: {exc!r}\n'
                          + traceback.format_exc())
            exc = DriveError(f'internal error in {job.label}: {exc!r}')
        resolve(job.future, exc=exc)

    def _run_urgent(self, job: Job) -> None:
        """Drop the drive's queued jobs that the urgent one preempts, cut its running ones
        short, and start the job now (module docstring)."""
        if not begin(job.future):      # cancelled by its waiter while it waited
            return
        slot = self.slots[job.drive]
        with self._cv:
            slot.queue, dropped = split_preempted(slot.queue, job)
        for j in dropped:
            resolve(j.future, exc=Cancelled(f'{j.label}: dropped by {job.label}'))
        why = f'cut short by {job.label}'
        if slot.suspended:
            kept = [e for e in slot.suspended if not e.job.preempted_by(job)]
            for other in slot.suspended:
                if other.job.preempted_by(job):
                    self._abandon(slot, other.job, other.steps, why)
            slot.suspended = kept
        if slot.active is not None and slot.active.preempted_by(job):
            self._cut_short(slot, why)
        if not slot.connected:
            resolve(job.future, exc=NotConnected(
                f'{job.label}: drive {slot.name} is DISCONNECTED ({self.bus.description})'))
            return
        if slot.active is not None:
            slot.suspended.append(Suspended(slot.active, slot.active_operation, slot.wake_t))
            slot.active, slot.active_operation = None, None
        slot.active = job
        self._wrote(slot)
        self._advance(slot, job.fn)

    def _cut_short(self, slot: Slot, why: str) -> None:
        """End slot.active (Cancelled); the job it suspended, if any, goes on."""
        job, steps = slot.active, slot.active_operation
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
        resolve(job.future, exc=Cancelled(f'{job.label}: {why}'))

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
