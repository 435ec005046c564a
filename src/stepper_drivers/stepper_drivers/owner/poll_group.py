"""PollGroup: one thread polls the drives of several buses (no rclpy).

A node whose drives sit on several links of a NonblockingPolls bus (X-PLUS MT: every drive is
its own Modbus TCP server) has a bus owner per link (owner/), so that a host that stops
answering stalls only its own drives. Polled by their owners, eight links cost eight thread
wake-ups and eight owner passes a poll period; the bare loop that reads the same registers from
one thread costs less than two thirds of that (docs/benchmarks.md). This thread does the idle
links' periodic polls instead: once a period (the buses share one grid) it borrows each link
whose owner sleeps with only its polls due (`BusOwner.lend`), sends every lent link's state
request at once, takes the replies as they come (select), and gives each link back as soon as
its polls are done; the owners sleep on. Everything else stays the owner's: commands, steps,
connects, the velocity watchdog, polls while a job runs, and any poll this thread misses.

Threads and what they own:
- This thread owns a lent link (its bus and its lent drives' slots) from lend() to give_back();
  meanwhile the owner waits for it (a command or a stop waits for the poll in flight, as with
  the owner's own polls). It calls the drives only through state_requests() and
  state_from_replies() (capabilities.SplitPoll), the bus only through send_request(),
  take_reply() and fileno() (capabilities.NonblockingPolls).
- A link whose replies are not complete within REPLY_WAIT_PERIODS of a period (at most the
  bus's timeout_s) is given back unpolled: its owner polls it again at once, with its own
  timeout, after the late reply (one request in flight on a link: ModbusTcpBus), and the link
  is not lent again before that poll. A host that stops answering costs the other links
  nothing.
- A link error is handled as the owner's poll would (the drive lost, reconnect: the owner's
  job). Any other error gives the link back unpolled: the owner's read_state() then decides
  (a Modbus exception reply: the drive's own fallback).
- When this thread ends (stop(), every owner stopped, or a bug: an exception that escapes), it
  gives every link back with its drives unpolled: the owners poll them themselves from then on,
  at once (a drive-side watchdog of a few poll periods does not notice).

The owners wake for a poll only once it is late by GROUP_GRACE_S (owner/schedule.py); a
link polled by its owner (a job ran at the grid point) is lent again at a later period.
"""

from __future__ import annotations

import logging
import math
import select
import threading
import traceback
from typing import Any, Callable

from ..contract.drive import LinkError
from . import BusOwner, Slot
from .priority import set_priority

logger = logging.getLogger(__name__)

# A lent link's reply is waited for at most this part of a poll period (and the bus's timeout_s):
# less than a period, so the next tick starts on time; as much as that, since a link given back
# unpolled costs its owner the rest of that reply and a poll of its own (8 hosts simulated in one
# process answered later than half a period several times a second: docs/benchmarks.md).
REPLY_WAIT_PERIODS = 0.8


class _Loan:
    """One lent link: its drives' polls in turn, one request in flight at a time."""

    def __init__(self, bus_owner: BusOwner, polls: list[tuple[Slot, list[Any]]]):
        self.bus_owner = bus_owner
        self.bus: Any = bus_owner.bus
        self.polls = polls
        self.k = 0              # the poll in flight
        self.replies: list[Any] = []      # its replies so far
        self.fd = self.bus.fileno()

    def send(self) -> bool:
        """Send the next request of the poll in flight; False (the link given back) if it
        failed."""
        slot, requests = self.polls[self.k]
        try:
            self.bus.send_request(requests[len(self.replies)])
        except Exception as exc:  # noqa: BLE001 - _failed sorts them
            self._failed(slot, exc)
            return False
        return True

    def readable(self) -> bool:
        """What came for the request in flight; True while the link awaits another reply."""
        slot, requests = self.polls[self.k]
        try:
            reply = self.bus.take_reply(requests[len(self.replies)])
            if reply is None:
                return True
            self.replies.append(reply)
            if len(self.replies) < len(requests):
                return self.send()
            state = slot.drive.state_from_replies(self.replies)
        except Exception as exc:  # noqa: BLE001 - _failed sorts them
            self._failed(slot, exc)
            return False
        self.replies = []
        self.bus_owner.group_polled(slot, state, self.bus_owner.clock())
        self.k += 1
        if self.k == len(self.polls):
            self.give_back()
            return False
        return self.send()

    def _failed(self, slot: Slot, exc: Exception) -> None:
        if isinstance(exc, LinkError):
            self.bus_owner.group_poll_failed(slot, exc)      # the drive lost, as the owner's poll
            self.k += 1
        self.give_back()

    def give_back(self) -> None:
        polls, self.polls = self.polls, []
        if polls:
            self.bus_owner.give_back([slot for slot, _ in polls[self.k:]])
        self.k, self.replies = 0, []


class PollGroup:
    """The periodic polls of idle links of several bus owners, from one thread; see the module
    docstring. Start it after the owners; it ends by itself once every owner stopped."""

    def __init__(self, bus_owners: list[BusOwner], name: str = 'poll group',
                 on_event: Callable[[str, str, str], None] | None = None):
        self.bus_owners = list(bus_owners)
        self.name = name
        self.on_event = on_event or (lambda level, who, text: getattr(logger, level)(
            '%s: %s', who, text))
        self.clock = self.bus_owners[0].clock
        t0 = self.clock()
        for bus_owner in self.bus_owners:
            bus_owner.share_grid(t0)
        self._t0 = t0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.failure = ''

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _period_s(self) -> float:
        return 1.0 / self.bus_owners[0].settings['publish_rate_hz']

    def _run(self) -> None:
        first = self.bus_owners[0]               # the owners' priority: this thread polls for them
        set_priority(int(first.settings.get('owner_thread_priority', 0)), first.on_event,
                     first.name)
        try:
            while not self._stop.is_set():
                if all(bus_owner.stopping or not bus_owner.alive for bus_owner in self.bus_owners):
                    return
                period = self._period_s()
                now = self.clock()
                tick = self._t0 + (math.floor((now - self._t0) / period) + 1) * period
                while now < tick:              # (a timed wait may end a little early)
                    if self._stop.wait(tick - now):
                        return
                    now = self.clock()
                self._tick(now, period)
        except Exception as exc:  # noqa: BLE001 - the owners poll by themselves again
            self.failure = f'{self.name} failed: {exc!r}'
            self.on_event('error', self.name, f'{self.failure}; the bus owners poll their '
                          'drives themselves\n' + traceback.format_exc())
        finally:        # (nothing is lent here) the owners poll their drives from now on
            for bus_owner in self.bus_owners:
                bus_owner.give_back(bus_owner.slots.values())

    def _tick(self, now: float, period: float) -> None:
        loans = []
        try:
            for bus_owner in self.bus_owners:
                polls = bus_owner.lend(now)
                if polls:
                    loans.append(_Loan(bus_owner, polls))
            if not loans:
                return
            waiting = {loan.fd: loan for loan in loans if loan.send()}
            deadline = now + min(REPLY_WAIT_PERIODS * period,
                                 min(getattr(loan.bus, 'timeout_s', period) for loan in loans))
            poller = select.poll()
            for fd in waiting:
                poller.register(fd, select.POLLIN)
            while waiting:
                remaining = deadline - self.clock()
                if remaining <= 0:
                    break
                for fd, _ in poller.poll(remaining * 1000.0):
                    loan = waiting.get(fd)
                    if loan is not None and not loan.readable():
                        poller.unregister(fd)
                        del waiting[fd]
        finally:
            for loan in loans:              # unanswered in time, or this thread fails
                loan.give_back()
