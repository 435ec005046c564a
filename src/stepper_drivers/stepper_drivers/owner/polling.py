"""Polls in the owner thread: one drive's poll, a cycle's polls in one pass, the quiet cycle,
the poll waiters, and the poll group's loans.

Every snapshot carries the drive's write count in force when its read began
(`DriveState.after_write`: set when the poll began, by the owner or at the poll group's loan; a
snapshot a drive vouches for in a quiet cycle, the count at the vouching). A poll under way
when a job starts (a step-wise poll, whose steps go on between the job's) ends with a count
below the job's end. `wait_poll` answers a waiter only with a snapshot at or above the count it
names: what a service judges its answer by was read after its own writes.
"""

from __future__ import annotations

import math
import threading
import traceback
from typing import Any, Iterable

from ..contract.capabilities import CachedState, ChangeCounting, FreshPollState, SplitPoll
from ..contract.drive import DriveError, DriveState, LinkError, is_operation
from .schedule import QuietPass, Vouched
from .slot import Slot


class PollingPart:
    """The polls part of BusOwner (owner thread, or the poll group's while lent)."""

    def _poll_begins(self, slot: Slot) -> None:
        """A poll of slot's drive begins (or a quiet cycle counts one): it answers every
        poll_soon() so far, and its snapshot follows every write so far."""
        if slot.poll_requested or slot.owner_polls:
            with self._cv:
                slot.poll_requested = slot.owner_polls = False
        slot.poll_seq = slot.write_seq

    def _poll_step(self, slot: Slot, now: float) -> None:
        self._jobs_since_poll = 0
        try:
            if slot.poll_operation is None:
                self._poll_begins(slot)
                result = slot.drive.read_state()
                if is_operation(result):
                    slot.poll_operation = result
                    slot.next_poll_t = self._next_grid_t(now)
                    result = next(result)
                    slot.poll_wake_t = self.clock() + (result or 0.0)
                    return
                state = result
                slot.next_poll_t = self._next_grid_t(now)
            else:
                delay = next(slot.poll_operation)
                slot.poll_wake_t = self.clock() + (delay or 0.0)
                return
        except StopIteration as stop:
            slot.poll_operation = None
            state = stop.value
        except Exception as exc:  # noqa: BLE001 - _poll_failed sorts them
            slot.poll_operation = None
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
        if isinstance(slot.drive, FreshPollState):
            slot.drive.state_fresh_s = self._period_s()  # (the rate can change at run time)
        # when the position was true (the trajectory feedback compares the plan at that time)
        slot.sample = (state, self.clock() if state.measured_at_s is None
                       else state.measured_at_s)
        slot.polls += 1
        self._resolve_waiters(slot, True)
        self._cycle_polled.add(slot.name)
        if self._cycle_done():
            self._cycle()

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
            if slot.poll_operation is not None or not slot.connected:
                return False
            if not isinstance(slot.drive, CachedState) or self.bus.transactions != transactions:
                now = self.clock()                   # a poll on the wire: time passed
                if horizon is None:
                    horizon = self._next_event_t()
                if now >= horizon:
                    return False
        return True

    def _quiet_cycle(self, dues: list[Slot], now: float, vouched: Vouched | None = None
                     ) -> bool:
        """A cycle in which no drive has anything new: every drive of the bus is due, and each
        says its read_state() would give the very state of its last poll
        (CachedState.unchanged_until: a cache that nothing changed since, no frame, no command).
        Then the polls are that, the cycle's bookkeeping one loop, and its publishing as after
        any cycle. False, with nothing done, at the first drive that is not so (a poll under
        way, a waiter): then the polls go one by one (_poll_step). On 8 idle CANopen drives at
        50 Hz this is most cycles (docs/benchmarks.md).

        vouched: what the drives vouched for at the last quiet cycle, given by a pass that
        knows nothing else happened since (no request, no work of the owner's: the quiet pass
        of _work_once); while the bus counted no change, no job started or ended and that time
        is ahead, the drives are not asked again. Each snapshot counted polled is stamped with
        its drive's write count now."""
        if not isinstance(self.bus, ChangeCounting):
            return False                 # nothing tells when a vouching stops holding
        changes = self.bus.changes                   # before what the drives vouch for
        if vouched is not None and vouched.changes == changes and now < vouched.until_t \
                and vouched.writes == self._writes:  # (no job of any drive since)
            until = vouched.until_t
        else:
            until = math.inf
            for slot in dues:
                if not slot.connected or slot.poll_operation is not None or slot.poll_waiters:
                    return False
                if not isinstance(slot.drive, CachedState):
                    return False
                t = slot.drive.unchanged_until(slot.state)
                if t <= now:
                    return False
                until = min(until, t)
        self._vouched = Vouched(changes, until, self._writes)
        self._jobs_since_poll = 0
        next_t = self._next_grid_t(now)
        period = self._period_s()
        t = self.clock()
        for slot in dues:
            # a read now would give it: it follows the writes so far (the vouching is asked
            # again after any job: _writes above)
            self._poll_begins(slot)
            if slot.group_polled:
                slot.group_polled = False
            slot.next_poll_t = next_t
            state = slot.state
            state.after_write = slot.write_seq
            slot.sample = (state, t if state.measured_at_s is None else state.measured_at_s)
            slot.polls += 1
        if period != self._fresh_s:        # (the rate can change at run time)
            self._fresh_s = period
            for slot in dues:
                if isinstance(slot.drive, FreshPollState):
                    slot.drive.state_fresh_s = period
        self.cycle_unchanged = vouched is not None     # the quiet pass': nothing else since
        try:
            self._cycle()
        finally:
            self.cycle_unchanged = False
        return True

    def _after_quiet_cycle(self, events: int) -> float:
        """The delay to the next wake-up after a quiet cycle, and what lets the next pass
        skip its look over the slots (`_quiet_pass`, schedule.QuietPass): nothing else was to
        be done when this pass began (`events` other threads' requests then), every drive's
        next poll is at one time, and the owner's own next event (a timer, a deadline, a step)
        is no sooner than it was found now."""
        now = self.clock()
        next_t = self._slot_list[0].next_poll_t
        horizon = self._next_event_t()
        self._quiet_pass = QuietPass(events, next_t, horizon, self._vouched)
        return min(next_t, horizon, now + 0.5) - now

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
        """The timers due, and the poll waiters whose time is up (False)."""
        for callback in self._timers.pop_due(now):
            callback()
        for slot in self._slot_list:
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
                if s.connected and not s.not_driven and s.poll_operation is None \
                        and not s.poll_waiters and (now >= s.next_poll_t or s.poll_requested):
                    requests = s.drive.state_requests() if isinstance(s.drive, SplitPoll) \
                        else []
                    if requests:
                        out.append((s, requests))
            if out:
                # (no job of the drive runs until give_back: the owner waits)
                self._lent, self._lender = True, threading.current_thread()
                for s, _ in out:
                    self._poll_begins(s)
            return out

    def give_back(self, unpolled: Iterable[Slot] = ()) -> None:
        """(The poll group's thread) The end of a loan, or of the group (then nothing is
        lent). The owner polls the `unpolled` drives itself, at their grid time (no grace for
        the group's poll), before the group may borrow them again."""
        with self._cv:
            unpolled = list(unpolled)
            for s in unpolled:
                s.owner_polls = True
            self._lent, self._lender = False, None
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
