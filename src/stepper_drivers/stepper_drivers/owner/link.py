"""The link in the owner thread: connect (a job of the drive's own), the identity check and its
recheck, a drive lost, the reconnect back-off, and the drives' shutdown.

A drive whose connect raised IdentityError (a well-formed answer naming another device) is not
driven, and connected again after IDENTITY_RECHECK_S, doubling up to IDENTITY_RECHECK_MAX_S,
for as long as the node runs (`recheck()`, fault_reset, at once): a drive swapped or set right
comes back without a restart. Noise is a LinkError, retried on the reconnect back-off.

A drive lost keeps its velocity watchdog armed: a velocity run the drive may still be doing is
stopped as soon as it answers again (an expired deadline stops it at once).
"""

from __future__ import annotations

import collections
import concurrent.futures
import logging
import time
import traceback
from typing import Any, Callable

from ..contract.drive import DriveError, DriveState, IdentityError, State, complete
from . import slot as slot_rules
from .commands import Command
from .jobs import CONNECT, Cancelled, Job, NotConnected, resolve, steps_of
from .slot import Slot

logger = logging.getLogger('stepper_drivers.owner')


class LinkPart:
    """The link part of BusOwner (owner thread; attributes: owner.py)."""

    def _drive_lost(self, slot: Slot, why: str) -> None:
        if not slot.connected:
            return
        slot.connected = False
        slot.poll_operation = None
        self._cut_all(slot, f'link lost ({why})')
        with self._cv:
            queued, slot.queue = list(slot.queue), collections.deque()
        for job in queued:
            resolve(job.future, exc=NotConnected(f'{job.label}: link lost ({why})'))
        slot.state = DriveState(state=State.DISCONNECTED, position_steps=slot.state.position_steps,
                                homed=slot.state.homed, after_write=slot.write_seq)
        slot.backoff_s = self.settings['reconnect_period_s']
        slot.next_connect_t = self.clock() + slot.backoff_s
        self.on_event('error', slot.name, f'link lost ({why}); reconnecting every '
                      f"{self.settings['reconnect_period_s']:g} s and more (back-off)")
        self._resolve_waiters(slot, False)
        self._cycle_polled.discard(slot.name)
        if not any(s.connected for s in self._slot_list):
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
        identity = yield from steps_of(slot.drive.connect())
        state = yield from steps_of(slot.drive.read_state())
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
        slot.identity_backoff_s = slot_rules.IDENTITY_RECHECK_S
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
        if not any(s.connected for s in self._slot_list):
            self._close_bus()
        period = self.settings['reconnect_period_s']
        slot.last_error = str(exc)
        if isinstance(exc, IdentityError):
            # Another device, or not the one configured: not driven, checked again slowly.
            delay = slot.identity_backoff_s
            slot.identity_backoff_s = min(delay * 2, slot_rules.IDENTITY_RECHECK_MAX_S)
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
            resolve(fut, exc=Cancelled(f'{slot.name}: the node is shutting down'))
        elif slot.connected:
            resolve(fut, slot.identity)
        elif slot.not_driven and not slot.identity_recheck:
            resolve(fut, exc=DriveError(f'not driven: {slot.not_driven}'))
        else:
            slot.connect_waiters.append(fut)
            slot.next_connect_t = min(slot.next_connect_t, self.clock())

    def _resolve_connect_waiters(self, slot: Slot, exc: Exception | None,
                                 result: Any = None) -> None:
        waiters, slot.connect_waiters = slot.connect_waiters, []
        for fut in waiters:
            resolve(fut, result, exc)

    # --------------------------------------------------------------------------- shutdown
    def _shutdown_drives(self, standstill_timeout_s: float, disable: set[str]) -> None:
        with self._cv:
            self._stopping = True
            queued = [j for s in self._slot_list for j in s.queue] + list(self._urgent)
            for s in self._slot_list:
                s.queue.clear()
            self._urgent.clear()
        for job in queued:
            resolve(job.future, exc=Cancelled(f'{job.label}: the node is shutting down'))
        live = [s for s in self._slot_list if s.connected]
        for s in self._slot_list:
            self._cut_all(s, 'the node is shutting down')
            s.poll_operation = None
            self._resolve_waiters(s, False)
            self._resolve_connect_waiters(s, Cancelled(f'{s.name}: the node is shutting down'))
        with self._cv:      # after the jobs: a job's time-out timer then finds it ended
            due = self._timers.take_all()
        for callback in due:
            callback()
        for s in live:                 # every drive decelerates at once ...
            self._shutdown_step(s, 'stop', s.drive.stop)
        deadline = self.clock() + standstill_timeout_s
        for s in live:                 # ... then each is disabled once it stands still
            if s.name in disable:
                self._shutdown_step(s, 'wait for standstill', self._wait_standstill, s, deadline)
                self._shutdown_step(s, 'disable', s.drive.disable)
        for s in self._slot_list:
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
