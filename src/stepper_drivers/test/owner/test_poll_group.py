"""PollGroup: one thread polls the idle links of several bus owners (X-PLUS MT hosts).

Real parts: an X-PLUS MT simulator per host (pymodbus servers, in-process), the project's
ModbusTcpBus and XplusMtDrive, a BusOwner per link. Bounds come from the poll period and
the bus timeout under test.
"""

import math
import threading
import time

import pytest
from stepper_drivers.owner import GROUP_GRACE_S, BusOwner
from stepper_drivers.owner.commands import Command
from stepper_drivers.owner.poll_group import REPLY_WAIT_PERIODS, PollGroup
from stepper_drivers.vendors.xplus_mt import VENDOR
from stepper_sim.harness import wait_for
from stepper_sim.xplus_mt.sim import XplusMtDriveConfig, XplusMtSim

RATE_HZ = 50.0
PERIOD_S = 1.0 / RATE_HZ
TIMEOUT_S = 0.3            # the buses' timeout_s
COMMAND_TIMEOUT_S = 0.3    # the velocity watchdog


class Links:
    """`n` X-PLUS MT hosts with one drive each, a bus owner per host, and a poll group."""

    def __init__(self, tmp_path, n=3, strict=()):
        self.sims, self.bus_owners, self.cycles = [], [], []     # cycles: (thread name, bus, t)
        self.settings = {'publish_rate_hz': RATE_HZ, 'command_timeout_s': COMMAND_TIMEOUT_S,
                         'reconnect_period_s': 0.5}
        for k in range(n):
            sim = XplusMtSim(port=0, drives=[XplusMtDriveConfig(f'axis{k + 1}', unit_id=1)],
                             storage_dir=str(tmp_path / f'host{k}'), strict=k in strict)
            sim.start()
            self.sims.append(sim)
            bus = VENDOR.make_bus({'host': '127.0.0.1', 'port': sim.port,
                                   'timeout_s': TIMEOUT_S})
            drive = VENDOR.make_drive(bus, f'axis{k + 1}', {
                'unit_id': 1, 'word_order': 'little', 'steps_per_rev': 12800,
                'joint_name': f'joint{k + 1}'})
            self.bus_owners.append(BusOwner(bus, {f'axis{k + 1}': drive}, self.settings,
                                           on_cycle=self._on_cycle, name=bus.description))
        self.group = PollGroup(self.bus_owners)
        for bus_owner in self.bus_owners:
            bus_owner.start()
        wait_for(lambda: all(s.connected for o in self.bus_owners for s in o.slots.values()),
                 10.0, 'every drive connected')
        self.group.start()

    def _on_cycle(self, bus_owner):
        self.cycles.append((threading.current_thread().name, bus_owner.name, time.monotonic()))

    def slot(self, k):
        return self.bus_owners[k].slots[f'axis{k + 1}']

    def polls_times(self, k, t0, t1):
        return [t for _, name,
                t in self.cycles if name == self.bus_owners[k].name and t0 <= t <= t1]

    def close(self):
        for bus_owner in self.bus_owners:
            bus_owner.shutdown(1.0)
        self.group.stop()
        for sim in self.sims:
            sim.stop()


@pytest.fixture
def links(tmp_path):
    lk = Links(tmp_path)
    yield lk
    lk.close()


def settle(links):
    """Past the start: the group polls every link, and every owner went to sleep after that
    (an owner asleep since before wakes once at its old poll time)."""
    wait_for(lambda: all(s.group_polled for o in links.bus_owners for s in o.slots.values()),
             2.0, 'every link polled by the group')
    time.sleep(2 * PERIOD_S)


def test_one_thread_polls_every_link_at_the_rate_while_the_owners_sleep(links):
    settle(links)
    passes0 = [bus_owner.passes for bus_owner in links.bus_owners]
    polls0 = [links.slot(k).polls for k in range(3)]
    t0 = time.monotonic()
    time.sleep(1.0)
    elapsed = time.monotonic() - t0
    for k, bus_owner in enumerate(links.bus_owners):
        polls = links.slot(k).polls - polls0[k]
        assert polls >= 0.8 * elapsed * RATE_HZ, \
            f'{bus_owner.name}: {polls} polls in {elapsed:.2f} s'
        threads = [name for name, bus, t in links.cycles if bus == bus_owner.name and t >= t0]
        own = len(threads) - threads.count('poll group')
        # the owner polls only what the group gave back (a reply later than the group's wait)
        assert own <= 0.25 * polls, f'{bus_owner.name}: {own} of {polls} polls by the owner'
        woke = bus_owner.passes - passes0[k]
        # ... and wakes otherwise only for a poll late by the grace: the group polled it
        assert woke <= elapsed / GROUP_GRACE_S + 2 + 2 * own, \
            f'{bus_owner.name}: the owner woke {woke} times, polled {own} times'


def test_a_host_that_stops_answering_stalls_only_its_own_drive(links):
    settle(links)
    links.sims[0].inject_fault('axis1', 'no_reply')
    t0 = time.monotonic()
    wait_for(lambda: not links.slot(0).connected,
             REPLY_WAIT_PERIODS * PERIOD_S + TIMEOUT_S + 2 * PERIOD_S + 0.5,
             "the silent host's drive DISCONNECTED")
    lost_after = time.monotonic() - t0
    # the group gives the silent link back after its reply wait; its owner's own poll then
    # times out: the drive is lost after about both, not at the group's next tries
    assert lost_after <= REPLY_WAIT_PERIODS * PERIOD_S + TIMEOUT_S + 2 * PERIOD_S + 0.1
    time.sleep(0.2)
    t1 = time.monotonic()
    for k in (1, 2):
        times = links.polls_times(k, t0, t1)
        gaps = [b - a for a, b in zip(times, times[1:])]
        assert len(times) >= 0.8 * (t1 - t0) * RATE_HZ, f'axis{k + 1}: {len(times)} polls'
        # the silent host's timeout never shows in the others' polls (a tick waits for it at
        # most its reply wait)
        assert max(gaps) < TIMEOUT_S / 2, \
            f'axis{k + 1}: a gap of {max(gaps) * 1000:.0f} ms between polls'
        assert links.slot(k).connected


def test_a_command_for_a_lent_link_waits_for_the_groups_poll_and_is_not_lost(links):
    settle(links)
    delay_s = REPLY_WAIT_PERIODS * PERIOD_S / 2            # answered within the group's wait
    links.sims[1].inject_fault('axis2', 'late_reply', value=delay_s)
    bus_owner = links.bus_owners[1]
    seen = []
    for _ in range(5):
        wait_for(lambda: bus_owner._lent, 2.0, 'the group holds the link')
        t0 = time.monotonic()
        fut = bus_owner.submit('axis2', Command.maintenance(
            lambda: seen.append((bus_owner._lent, time.monotonic())), 'mark'))
        fut.result(timeout=2.0)
        lent, t = seen[-1]
        assert not lent, 'the command ran while the group had the link'
        # the group's poll ends with its reply or its reply wait (not the bus timeout), then
        # the command
        assert t - t0 < TIMEOUT_S / 2, \
            f'the command waited {(t - t0) * 1000:.0f} ms'


def test_the_velocity_watchdog_fires_on_its_own_clock_while_the_group_polls(links):
    settle(links)
    bus_owner = links.bus_owners[2]
    bus_owner.submit('axis3',
                     Command.enable(bus_owner.slots['axis3'].drive.enable)).result(timeout=5.0)
    settle(links)
    t0 = time.monotonic()
    bus_owner.arm_watchdog('axis3')
    wait_for(lambda: not bus_owner.watchdog_armed('axis3'), COMMAND_TIMEOUT_S + 2.0,
             'the watchdog stop')
    took = time.monotonic() - t0
    # its deadline, then the stop's transactions (and at most one poll in flight), not at the
    # owner's next wake for a poll the group missed (GROUP_GRACE_S)
    assert COMMAND_TIMEOUT_S <= took < COMMAND_TIMEOUT_S + GROUP_GRACE_S / 2, f'{took:.3f} s'


def test_a_drive_that_refuses_the_block_read_is_polled_in_three_reads(tmp_path):
    """A strict drive refuses the block read over its register holes (exception 02): its
    owner's poll finds out and reads the state in three requests from then on; so does the
    group, without an error."""
    lk = Links(tmp_path, strict=(0,))
    try:
        settle(lk)
        slot, bus = lk.slot(0), lk.bus_owners[0].bus
        polls0, transactions0, t0 = slot.polls, bus.transactions, time.monotonic()
        time.sleep(0.5)
        polls, transactions = slot.polls - polls0, bus.transactions - transactions0
        assert polls >= 0.8 * (time.monotonic() - t0) * RATE_HZ
        # three requests a poll (the edges of the window may hold part of one, and a reply
        # later than the group's wait costs the owner's poll three more)
        assert 2.5 * polls <= transactions <= 3.5 * polls, f'{transactions} for {polls} polls'
        assert slot.group_polled and slot.connected and slot.last_error == ''
        assert bus.errors == 1          # the one refused block read
    finally:
        lk.close()


def test_shutdown_during_the_groups_polls_stops_every_drive_and_ends_the_group(links):
    settle(links)
    links.sims[0].inject_fault('axis1', 'late_reply', value=REPLY_WAIT_PERIODS * PERIOD_S / 2)
    wait_for(lambda: links.bus_owners[0]._lent, 2.0, 'the group holds the first link')
    for bus_owner in links.bus_owners:
        bus_owner.shutdown(1.0)
    assert all(not bus_owner.alive for bus_owner in links.bus_owners)
    wait_for(lambda: not links.group.alive, 2 * PERIOD_S + 1.0, 'the group ended')


def test_when_the_group_ends_the_owners_poll_their_drives_at_once(links):
    settle(links)
    t0 = time.monotonic()
    links.group.stop()
    assert not links.group.alive
    stopped = time.monotonic()
    time.sleep(0.3)
    t1 = time.monotonic()
    for k, bus_owner in enumerate(links.bus_owners):
        times = links.polls_times(k, t0 - PERIOD_S, t1)
        gaps = [b - a for a, b in zip(times, times[1:])]
        # not after GROUP_GRACE_S, when an owner would find its drive's poll late
        assert max(gaps) < GROUP_GRACE_S / 2, f'{bus_owner.name}: a gap of {max(gaps):.3f} s'
        assert not links.slot(k).group_polled
        threads = {name for name, bus, t in links.cycles if bus == bus_owner.name and t > stopped}
        assert threads == {f'owner {bus_owner.name}'}


def test_a_host_that_answers_after_the_groups_wait_is_polled_by_its_owner_and_kept(links):
    """Replies later than the group's wait, for a second: the owner polls the drive each
    time, after the reply to the group's request (one request in flight: the simulator's
    pymodbus server, like many devices, answers only the first of two that arrive together);
    the drive is never lost."""
    settle(links)
    slot, bus = links.slot(1), links.bus_owners[1].bus
    reconnects, timeouts = slot.reconnects, bus.timeouts
    late_s = (REPLY_WAIT_PERIODS + 0.25) * PERIOD_S
    links.sims[1].inject_fault('axis2', 'late_reply', value=late_s)
    polls0, t0 = slot.polls, time.monotonic()
    time.sleep(1.0)
    polls = slot.polls - polls0
    assert slot.connected and slot.reconnects == reconnects and bus.timeouts == timeouts
    # a poll: the group's wait and the rest of its request's late reply, then the owner's own,
    # to the next grid point
    poll_s = math.ceil(2 * late_s / PERIOD_S) * PERIOD_S
    assert polls >= 0.8 * (time.monotonic() - t0) / poll_s
    assert not slot.group_polled and bus.stale_replies > 0
