"""BusOwner without ROS: order, preemption, the velocity watchdog, link loss, shutdown.

The drives here are a scripted implementation of the Drive interface (`ScriptDrive`,
rigs_owner.py): each call takes one "transaction" of TX_S on a shared line and is recorded with
its time, so the tests see the order in which calls reached the wire. The vendor drives are
tested against their simulators elsewhere; this file tests the scheduling that sits above all
of them.
"""

from __future__ import annotations

import concurrent.futures
import os
import threading
import time

import pytest
from rigs_owner import RATE_HZ, TX_S, Line, ScriptDrive
from stepper_drivers import owner
from stepper_drivers.contract.capabilities import CachedState
from stepper_drivers.contract.drive import (
    DriveError,
    DriveState,
    IdentityError,
    LinkError,
    State,
)
from stepper_drivers.owner import (
    COMMAND,
    MAINTENANCE,
    STREAM,
    URGENT,
    BusOwner,
    Cancelled,
    NotConnected,
    Superseded,
)
from stepper_drivers.owner.commands import Command
from stepper_sim.harness import fifo_allowed, wait_for


def make(n_drives=2, kinds=None, **settings):
    """A started owner of `n_drives` ScriptDrives (or of `kinds`: drive name -> ScriptDrive
    class) on one Line, every drive connected and polled."""
    line = Line()
    kinds = kinds or {f'axis{i + 1}': ScriptDrive for i in range(n_drives)}
    drives = {name: kind(line, name) for name, kind in kinds.items()}
    cfg = {'publish_rate_hz': RATE_HZ, 'command_timeout_s': 0.3, 'reconnect_period_s': 0.05}
    cfg.update(settings)
    events = []
    bus_owner = BusOwner(line, drives, cfg, on_event=lambda *e: events.append(e))
    bus_owner.events = events
    bus_owner.start()
    wait_for(lambda: all(s.connected and s.polls > 0 for s in bus_owner.slots.values()), 2.0,
             'every drive connected and polled')
    return bus_owner, line, drives


@pytest.fixture
def bus():
    bus_owners = []

    def factory(*args, **kw):
        bus_owner, line, drives = make(*args, **kw)
        bus_owners.append(bus_owner)
        return bus_owner, line, drives
    yield factory
    for bus_owner in bus_owners:
        bus_owner.shutdown(0.5)


def result(fut: concurrent.futures.Future, timeout_s=3.0):
    return fut.result(timeout_s)


# ----------------------------------------------------------------------------------- order
def test_jobs_of_one_drive_run_in_the_order_submitted(bus):
    bus_owner, line, d = bus()
    futs = [bus_owner.submit('axis1', Command(COMMAND, lambda i=i: d['axis1'].move_to(i, None),
                                              f'm{i}'))
            for i in range(10)]
    for f in futs:
        result(f)
    assert [c[3][0] for c in line.calls('axis1', 'move_to')] == list(range(10))


def test_a_newer_stream_command_replaces_the_one_still_waiting(bus):
    bus_owner, line, d = bus()
    # keep the drive busy so the stream commands wait
    busy = bus_owner.submit('axis1', Command(MAINTENANCE, d['axis1'].save_params, 'save',
                                             motion=False))
    wait_for(lambda: line.calls('axis1', 'save step'), 1.0, 'save started')
    f1 = bus_owner.submit('axis1', Command(STREAM, lambda: d['axis1'].set_velocity(1.0, None),
                                           'v1',
                                     topic='velocity'))
    f2 = bus_owner.submit('axis1', Command(STREAM, lambda: d['axis1'].set_velocity(2.0, None),
                                           'v2',
                                     topic='velocity'))
    with pytest.raises(Superseded, match='replaced by the newer v2'):
        result(f1)
    result(f2)
    result(busy)
    assert [c[3][0] for c in line.calls('axis1', 'set_velocity')] == [2.0]


def test_a_stream_command_does_not_jump_over_a_command_between(bus):
    bus_owner, line, d = bus()
    busy = bus_owner.submit('axis1', Command(MAINTENANCE, d['axis1'].save_params, 'save',
                                             motion=False))
    wait_for(lambda: line.calls('axis1', 'save step'), 1.0, 'save started')
    f1 = bus_owner.submit('axis1', Command(STREAM, lambda: d['axis1'].move_to(1, None), 'p1',
                                     topic='position'))
    f2 = bus_owner.submit('axis1', Command(COMMAND, lambda: d['axis1'].fault_reset(), 'reset',
                                     motion=False))
    f3 = bus_owner.submit('axis1', Command(STREAM, lambda: d['axis1'].move_to(3, None), 'p3',
                                     topic='position'))
    for f in (busy, f1, f2, f3):
        result(f)
    calls = [c[2] for c in line.calls('axis1') if c[2] in ('move_to', 'fault_reset')]
    assert calls == ['move_to', 'fault_reset', 'move_to']


def test_many_publishers_alternating_then_zero_end_stopped(bus):
    """1000 alternating velocity commands from 4 threads, then one final 0.0: the last
    velocity the drive got is 0.0 (no older 1.0 overtakes it)."""
    bus_owner, line, d = bus(n_drives=1)
    barrier = threading.Barrier(4)

    def publisher(k):
        barrier.wait()
        for i in range(250):
            v = 1.0 if (i + k) % 2 else -1.0
            bus_owner.arm_watchdog('axis1')
            bus_owner.submit('axis1', Command(STREAM, lambda v=v: d['axis1'].set_velocity(v, None),
                                        f'v{v}', topic='velocity'))
    threads = [threading.Thread(target=publisher, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    last = bus_owner.submit('axis1', Command(STREAM, lambda: d['axis1'].set_velocity(0.0, None),
                                             'v0',
                                       topic='velocity', disarms=True))
    result(last, 10.0)
    assert line.calls('axis1', 'set_velocity')[-1][3][0] == 0.0
    assert d['axis1'].velocity == 0.0
    assert not bus_owner.watchdog_armed('axis1')
    # coalescing: far fewer writes than commands, and none after the final 0.0
    assert len(line.calls('axis1', 'set_velocity')) < 1001


def test_a_command_handed_over_to_a_sleeping_owner_is_taken_before_submit_returns(
        bus, monkeypatch):
    """hand_over=True (the node's commands): the submitting thread waits, GIL released,
    until the sleeping owner has taken the job, so the owner does not wait for the GIL behind
    rclpy's bookkeeping after the callback. Bounded by HAND_OVER_MAX_S, made long here so a
    loaded machine cannot end the wait first."""
    monkeypatch.setattr(owner.bus_owner, 'HAND_OVER_MAX_S', 5.0)
    bus_owner, line, d = bus(publish_rate_hz=0.5)     # the owner sleeps about 2 s between polls
    for i in range(5):
        wait_for(lambda: bus_owner.idle, 3.0, 'the owner asleep')
        fut = bus_owner.submit('axis1', Command(STREAM, lambda i=i: d['axis1'].move_to(i, None),
                                                f'p{i}',
                                          topic='position'), hand_over=True)
        assert not bus_owner.slots['axis1'].queue          # taken: popped from the drive's queue
        result(fut)
    assert [c[3][0] for c in line.calls('axis1', 'move_to')] == list(range(5))


def test_a_busy_owner_is_not_waited_for(bus, monkeypatch):
    """An owner in a transaction is not waited for (on a serial line that is 20-30 ms of the
    executor thread): submit returns at once and the job waits in the queue."""
    monkeypatch.setattr(owner.bus_owner, 'HAND_OVER_MAX_S', 5.0)
    bus_owner, line, d = bus()
    release = threading.Event()
    busy = bus_owner.submit('axis2', Command(COMMAND, lambda: release.wait(5.0),
                                             'a long transaction'))
    wait_for(lambda: bus_owner.slots['axis2'].active is not None, 1.0, 'the owner busy')
    t0 = time.monotonic()
    fut = bus_owner.submit('axis1', Command(STREAM, lambda: d['axis1'].move_to(1, None), 'p1',
                                      topic='position'), hand_over=True)
    waited = time.monotonic() - t0
    assert len(bus_owner.slots['axis1'].queue) == 1 and waited < owner.HAND_OVER_MAX_S
    release.set()
    result(busy)
    result(fut)


class SerialMoveDrive(ScriptDrive):
    """move_to as a drive on a slow serial line sends it: MOVE_TX transactions, one a step (an
    RD4 writes its profile, the target and the control word)."""

    MOVE_TX = 5

    def move_to(self, target_steps, motion):
        self._tx('move_to', target_steps)
        for i in range(1, self.MOVE_TX):
            yield 0.0
            self._tx('move_to write', i)


def test_drives_streamed_on_a_slow_line_take_turns(bus):
    """Both drives streamed a position set point every 10 ms in one message (ros2_control's
    topic interface; axis1's submitted first) on a line where a move takes 5 transactions:
    each drive's newer set point replaces its waiting one, and the drives take turns, so
    neither waits for more than the other's one move (and the polls due meanwhile)."""
    bus_owner, line, drives = bus(kinds={n: SerialMoveDrive for n in ('axis1', 'axis2')})
    stop = threading.Event()

    def stream():
        i = 0
        while not stop.wait(0.01):
            i += 1
            for name, drive in drives.items():
                bus_owner.submit(name, Command.position_stream(
                    lambda drive=drive, i=i: drive.move_to(i, None), f'p{i}'))
    publisher = threading.Thread(target=stream)
    publisher.start()
    try:
        wait_for(lambda: line.calls(call='move_to'), 1.0, 'the stream under way')
        t0 = time.monotonic()
        time.sleep(1.0)
        t1 = time.monotonic()
    finally:
        stop.set()
        publisher.join()
    # the moves that started in the window, in their order on the wire: they alternate (each
    # drive always has a newer set point waiting when the other's move ends), so a set point
    # waits for the move in flight and the other drive's one move at most
    moves = [c[1] for c in line.calls(call='move_to') if t0 <= c[0] <= t1]
    counts = {name: moves.count(name) for name in drives}
    repeated = [k for k in range(1, len(moves)) if moves[k] == moves[k - 1]]
    assert not repeated, f'a drive moved twice while the other waited: {counts} {moves}'
    # a round: the two moves, and every drive's poll once in each poll period it touches;
    # half the rounds that fit the window (a loaded machine stretches the transactions)
    move_s = SerialMoveDrive.MOVE_TX * TX_S
    round_s = 2 * move_s + (2 * move_s * RATE_HZ + 1) * len(drives) * TX_S
    assert min(counts.values()) >= (t1 - t0) / round_s / 2, counts


# --------------------------------------------------------------------------------- futures
def test_a_job_that_started_cannot_be_cancelled_and_gives_its_result(bus):
    """A job's future runs once the owner starts the job: a cancel() then (a service's time-out
    for jobs not started) fails, the job goes on to its end, its waiter gets its result and
    the owner lives on."""
    bus_owner, line, d = bus()
    failures = []
    bus_owner.on_failure = lambda s, why: failures.append(why)
    fut = bus_owner.submit('axis1', Command.homing(lambda: d['axis1'].start_homing(None)))
    wait_for(lambda: line.calls('axis1', 'homing step'), 1.0, 'homing started')
    time.sleep(0.3)
    cancelled = fut.cancel()
    wait_for(lambda: len(line.calls('axis1', 'homing step')) == 20, 3.0, 'the homing ended')
    after = bus_owner.submit('axis1', Command.fault_reset(d['axis1'].fault_reset))
    wait_for(lambda: failures or (after.done() and not after.exception()), 3.0, 'the next job')
    assert bus_owner.alive and not failures, failures
    assert not cancelled and result(fut) == ''


def test_a_job_cancelled_while_it_waits_never_runs_and_the_owner_goes_on(bus):
    """A waiting job (a command queued, a stop not yet taken) that its waiter cancels is not
    run, and what would have ended its future (a stop dropping queued motion) passes it by."""
    bus_owner, line, d = bus()
    failures = []
    bus_owner.on_failure = lambda s, why: failures.append(why)
    release = threading.Event()
    busy = bus_owner.submit('axis2', Command(COMMAND, lambda: release.wait(5.0),
                                             'a long transaction'))
    wait_for(lambda: bus_owner.slots['axis2'].active is not None, 1.0, 'the owner busy')
    move = bus_owner.submit('axis1', Command.move(lambda: d['axis1'].move_to(7, None), 'move'))
    stop = bus_owner.submit('axis1', Command.stop(d['axis1'].stop, 'stop 1'))
    assert move.cancel() and stop.cancel()
    stop2 = bus_owner.submit('axis1', Command.stop(d['axis1'].stop, 'stop 2'))
    release.set()
    wait_for(lambda: failures or (stop2.done() and not stop2.exception()), 3.0, 'stop 2')
    assert bus_owner.alive and not failures, failures
    result(busy)
    assert [c[2] for c in line.calls('axis1') if c[2] in ('move_to', 'stop')] == ['stop']


# ------------------------------------------------------------------------------ preemption
class SlowConnectDrive(ScriptDrive):
    WAIT_S = 1.0

    def connect(self):
        self._tx('connect')
        yield self.WAIT_S           # a CANopen boot-up wait: one step that waits
        return {'serial_number': '8'}


def thread_cpu_s(tid: int) -> float:
    with open(f'/proc/self/task/{tid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')   # utime + stime


def test_the_owner_sleeps_while_a_connect_waits():
    """A connect under way is not due again: its drive is not connected and its next
    reconnect time has passed, but the owner sleeps until the connect's next step."""
    line = Line()
    bus_owner = BusOwner(line, {'axis1': SlowConnectDrive(line, 'axis1')},
                        {'publish_rate_hz': RATE_HZ, 'command_timeout_s': 0.3,
                         'reconnect_period_s': 0.05})
    bus_owner.start()
    try:
        wait_for(lambda: line.calls('axis1', 'connect'), 2.0, 'the connect started')
        cpu0 = thread_cpu_s(bus_owner._thread.native_id)
        wait_for(lambda: bus_owner.slots['axis1'].connected, 3.0, 'connected')
        used = thread_cpu_s(bus_owner._thread.native_id) - cpu0
        assert used < 0.1 * SlowConnectDrive.WAIT_S, f'the owner used {used:.2f} s of CPU'
    finally:
        bus_owner.shutdown(0.5)


class CachedDrive(ScriptDrive, CachedState):
    """read_state() from what the drive sent by itself (a CANopen TxPDO cache): no transaction,
    recorded on the line's record without taking its time. It vouches for nothing."""

    def unchanged_until(self, state):
        return 0.0

    def read_state(self):
        with self.line.lock:
            self.line.wire.append((time.monotonic(), self.name, 'cached read', ()))
        if self.on_read is not None:
            on_read, self.on_read = self.on_read, None
            on_read()
        return DriveState(state=State.OPERATION_ENABLED, enabled=True)


def test_cached_polls_of_a_cycle_run_together_and_an_urgent_job_still_goes_between():
    """Drives whose state is a cache are polled one after the other in one pass of the owner,
    every one once per cycle; an urgent job that comes during that pass goes before the next
    poll."""
    line = Line()
    drives = {f'axis{i}': CachedDrive(line, f'axis{i}') for i in range(1, 5)}
    bus_owner = BusOwner(line, drives, {'publish_rate_hz': RATE_HZ, 'command_timeout_s': 0.3,
                                       'reconnect_period_s': 0.05})
    bus_owner.start()
    try:
        wait_for(lambda: all(s.polls > 2 for s in bus_owner.slots.values()), 3.0, 'polled')
        cycles0 = bus_owner.cycles
        start = time.monotonic()
        wait_for(lambda: bus_owner.cycles >= cycles0 + 4, 2.0, 'four cycles')
        reads = [w for w in line.calls() if w[0] >= start and w[2] == 'cached read']
        names = [w[1] for w in reads]
        for k in range(0, len(names) - 3, 4):          # each cycle: every drive once, in order
            assert names[k:k + 4] == ['axis1', 'axis2', 'axis3', 'axis4'], names
        drives['axis1'].on_read = lambda: bus_owner.submit('axis3', Command(URGENT,
                                                                            drives['axis3'].stop,
                                                                      'stop', motion=False))
        wait_for(lambda: line.calls('axis3', 'stop'), 2.0, 'the stop sent')
        (stop,) = line.calls('axis3', 'stop')
        after_stop = wait_for(lambda: (lambda names: names if len(names) >= 3 else None)(
            [w[1] for w in line.calls() if w[0] > stop[0] and w[2] == 'cached read']), 2.0,
            'polls after the stop')
        before_stop = [w for w in line.calls() if w[0] < stop[0] and w[2] == 'cached read']
        assert before_stop[-1][1] == 'axis1', 'the stop waited for polls after it came'
        assert after_stop[:3] == ['axis2', 'axis3', 'axis4'], after_stop
    finally:
        bus_owner.shutdown(0.5)


class QuietDrive(CachedDrive):
    """A cache-reading drive that can say its state is unchanged (CachedState.unchanged_until):
    until `until`, as long as the bus counted no change, as a CANopen drive with no new
    TxPDO."""

    def __init__(self, bus, name, params=None):
        super().__init__(bus, name, params)
        self.until = 0.0                 # what unchanged_until vouches for (0: nothing)
        self.asked = 0                   # unchanged_until calls
        self.state = DriveState(state=State.OPERATION_ENABLED, enabled=True)

    def read_state(self):
        super().read_state()
        return self.state

    def unchanged_until(self, state):
        self.asked += 1
        return self.until if state is self.state else 0.0


def quiet_bus(n=4):
    line = Line()
    drives = {f'axis{i}': QuietDrive(line, f'axis{i}') for i in range(1, n + 1)}
    bus_owner = BusOwner(line, drives, {'publish_rate_hz': RATE_HZ, 'command_timeout_s': 0.3,
                                       'reconnect_period_s': 0.05})
    return line, drives, bus_owner


def test_a_cycle_with_nothing_new_reads_no_drive_and_a_change_is_read_in_the_next():
    """Drives that vouch for their state (a cache nothing changed) are counted polled without a
    read_state() in every cycle, and published each cycle; the vouching is asked again when the
    bus counts a change, and a drive that then has something new is read in that cycle."""
    line, d, bus_owner = quiet_bus()
    for drive in d.values():
        drive.until = float('inf')
    bus_owner.start()
    try:
        wait_for(lambda: all(s.polls >= 1 for s in bus_owner.slots.values()), 3.0, 'first polls')
        cycles0, polls0 = bus_owner.cycles, bus_owner.slots['axis2'].polls
        start = time.monotonic()
        wait_for(lambda: bus_owner.cycles >= cycles0 + 6, 3.0, 'six cycles')
        assert line.calls(call='cached read') and \
            not [w for w in line.calls(call='cached read') if w[0] >= start]
        assert bus_owner.slots['axis2'].polls >= polls0 + 5
        assert d['axis2'].state is bus_owner.slots['axis2'].state
        # vouched for without a change on the bus: not asked again each cycle
        asked = d['axis3'].asked
        wait_for(lambda: bus_owner.cycles >= cycles0 + 10, 3.0, 'four more cycles')
        assert d['axis3'].asked == asked, 'asked again although the bus counted no change'
        # something new on axis3: the bus counts it, axis3 no longer vouches
        new = DriveState(state=State.OPERATION_ENABLED, enabled=True, position_steps=42)
        d['axis3'].state = new
        line.changes += 1
        wait_for(lambda: bus_owner.slots['axis3'].state is new, 4.0 / RATE_HZ,
                 'the new state polled')
        assert line.calls('axis3', 'cached read')[-1][0] >= start
    finally:
        bus_owner.shutdown(0.5)


def test_a_quiet_cycle_asks_again_when_its_vouching_ends_and_a_waiter_gets_a_real_poll():
    """What a drive vouches for ends (a heartbeat deadline): it is asked again, and read when
    it no longer vouches. A poll waiter (wait_poll) is answered after a real read_state()."""
    line, d, bus_owner = quiet_bus(n=2)
    for drive in d.values():
        drive.until = time.monotonic() + 3.0 / RATE_HZ
    bus_owner.start()
    try:
        wait_for(lambda: all(s.polls >= 1 for s in bus_owner.slots.values()), 3.0, 'first polls')
        asked = d['axis1'].asked
        wait_for(lambda: d['axis1'].asked > asked, 5.0 / RATE_HZ, 'axis1 asked again')
        start = time.monotonic()
        d['axis1'].until = 0.0                            # (its deadline passed)
        wait_for(lambda: [w for w in line.calls('axis1', 'cached read') if w[0] >= start],
                 3.0 / RATE_HZ, 'axis1 read once it no longer vouches')
        d['axis2'].until = float('inf')
        d['axis1'].until = float('inf')
        mark = time.monotonic()
        answered = threading.Event()
        bus_owner.wait_poll('axis2', 1.0, lambda ok: ok and answered.set())
        assert answered.wait(3.0 / RATE_HZ), 'the waiter not answered'
        assert [w for w in line.calls('axis2', 'cached read') if w[0] >= mark], \
            'a waiter answered without a poll'
    finally:
        bus_owner.shutdown(0.5)


def test_a_timer_set_after_the_owner_chose_its_wait_wakes_it_at_its_time():
    """A request that comes after the owner computed how long to sleep, before it sleeps (here:
    a timer, set from another thread at that moment), is not lost: the owner does not sleep
    until its next poll. At one poll a second, a lost wake-up delays the timer by a second."""
    fired, set_at = [], []

    class Owner(BusOwner):
        hook = None

        def _next_wake(self, now):
            t = super()._next_wake(now)
            hook, Owner.hook = Owner.hook, None
            if hook is not None:
                th = threading.Thread(target=hook)
                th.start()
                th.join()
            return t

    line = Line()
    drives = {'axis1': CachedDrive(line, 'axis1')}
    bus_owner = Owner(line, drives, {'publish_rate_hz': 1.0, 'command_timeout_s': 0.3,
                               'reconnect_period_s': 0.05})
    bus_owner.start()
    try:
        wait_for(lambda: bus_owner.slots['axis1'].polls >= 1 and bus_owner.idle, 3.0, 'first poll')

        def set_timer():
            set_at.append(time.monotonic())
            bus_owner.after(0.05, lambda: fired.append(time.monotonic()))
        Owner.hook = set_timer
        bus_owner.poll_soon('axis1')                     # a pass that ends in a wait
        wait_for(lambda: fired, 2.5, 'the timer fired')
        assert fired[0] - set_at[0] < 0.05 + 0.25, f'timer late by {fired[0] - set_at[0]:.3f} s'
    finally:
        bus_owner.shutdown(0.5)


def test_a_command_during_a_cycles_polls_goes_out_after_the_poll_in_flight(bus):
    """The polls of a cycle on the wire run back to back in one pass of the owner; a command
    that comes during one of them is the next transaction, before the cycle's other polls."""
    bus_owner, line, d = bus(n_drives=4)          # 4 polls of TX_S in a period of 5 TX_S
    d['axis1'].on_read = lambda: bus_owner.submit(
        'axis4', Command(COMMAND, lambda: d['axis4'].move_to(100, None), 'move'))
    wait_for(lambda: line.calls('axis4', 'move_to'), 2.0, 'the move sent')
    (move,) = line.calls('axis4', 'move_to')
    read = [w for w in line.calls('axis1', 'read_state') if w[0] < move[0]][-1]
    assert [w for w in line.calls() if read[0] < w[0] < move[0]] == []


def test_a_watchdog_deadline_during_a_cycles_polls_stops_before_the_next_poll(bus):
    """A watchdog deadline that falls due while the polls of a cycle run back to back stops the
    drive after the poll in flight, not after the cycle: it is armed at the end of a cycle's
    polls to fall due within the first poll of the next cycle."""
    period_s = 1.0 / RATE_HZ
    bus_owner, line, d = bus(n_drives=4, command_timeout_s=period_s - 3.5 * TX_S)
    deadlines = []

    def arm():
        bus_owner.arm_watchdog('axis1')
        deadlines.append(bus_owner.slots['axis1'].velocity_deadline)
    d['axis4'].on_read = arm
    wait_for(lambda: line.calls('axis1', 'stop'), 2.0, 'the watchdog stop')
    stop = line.calls('axis1', 'stop')[0]
    late = [w for w in line.calls(call='read_state') if deadlines[0] <= w[0] < stop[0]]
    # at most the poll whose turn was checked a moment before the deadline
    assert len(late) <= 1, late


def test_a_long_operation_gives_the_bus_to_the_other_drives(bus):
    bus_owner, line, d = bus()
    fut = bus_owner.submit('axis1', Command(COMMAND, lambda: d['axis1'].start_homing(None),
                                            'home'))
    wait_for(lambda: line.calls('axis1', 'homing step'), 1.0, 'homing started')
    t0 = time.monotonic()
    polls0 = bus_owner.slots['axis2'].polls
    wait_for(lambda: len(line.calls('axis1', 'homing step')) >= 10, 3.0, 'ten homing steps')
    elapsed = time.monotonic() - t0
    # axis2 keeps its poll rate during axis1's operation (one poll missed at most)
    assert bus_owner.slots['axis2'].polls - polls0 >= int(elapsed * RATE_HZ) - 1
    result(fut)


class BurstDrive(ScriptDrive):
    def burst(self, n: int):
        """n transactions back to back, one a step (a Vector Step SDO sequence yields 0.0)."""
        for i in range(n):
            self._tx('burst', i)
            yield 0.0
        return 'done'


@pytest.mark.parametrize('rate_hz', [5.0, 10.0])
def test_steps_back_to_back_delay_no_poll_by_more_than_one_step(bus, rate_hz):
    """A long operation whose steps follow each other at once (no wait between them) leaves
    every other drive its poll rate: a due poll goes before the operation's next step, so no
    poll gap exceeds the period, the step in flight and one transaction."""
    bus_owner, line, drives = bus(kinds=dict.fromkeys(('axis1', 'axis2', 'axis3'), BurstDrive),
                            publish_rate_hz=rate_hz)
    t0 = time.monotonic()
    assert result(bus_owner.submit('axis1', Command.maintenance(
        lambda: drives['axis1'].burst(100), 'burst')), 5.0) == 'done'
    t1 = time.monotonic()
    bound = 1.0 / rate_hz + TX_S + TX_S + 0.04     # period, a step, a transaction, slack
    for name in ('axis2', 'axis3'):
        reads = [c[0] for c in line.calls(name, 'read_state') if t0 <= c[0] <= t1]
        gap = max(b - a for a, b in zip([t0] + reads, reads + [t1]))
        assert gap <= bound, f'{name} not polled for {gap:.3f} s (bound {bound:.3f} s)'


def test_a_long_operation_goes_on_while_polls_overrun(bus):
    """Polls that do not fit the period (2 x 10 ms per 10 ms) do not stop a running operation:
    a step that waited a period for polls goes before them."""
    bus_owner, line, drives = bus(kinds=dict.fromkeys(('axis1', 'axis2', 'axis3'), BurstDrive),
                            publish_rate_hz=100.0)
    t0 = time.monotonic()
    assert result(bus_owner.submit('axis1', Command.maintenance(
        lambda: drives['axis1'].burst(20), 'burst')), 5.0) == 'done'
    # each step: at most a period of polls, a poll in flight, and itself
    assert time.monotonic() - t0 <= 20 * (0.01 + 2 * TX_S) + 0.3


def test_stop_of_another_drive_during_a_long_operation_goes_next(bus):
    bus_owner, line, d = bus()
    fut = bus_owner.submit('axis1', Command(MAINTENANCE, d['axis1'].save_params, 'save',
                                            motion=False))
    wait_for(lambda: line.calls('axis1', 'save step'), 1.0, 'save started')
    t0 = time.monotonic()
    stop = bus_owner.submit('axis2', Command(URGENT, d['axis2'].stop, 'stop', disarms=True))
    result(stop)
    stop_t = line.calls('axis2', 'stop')[0][0]
    # nothing but the one transaction in flight went before it
    before = [c for c in line.wire if t0 <= c[0] < stop_t]
    assert len(before) <= 1, before
    assert stop_t - t0 <= TX_S + 0.05
    assert result(fut) == 'saved'       # the save went on


def test_stop_during_homing_cuts_it_short_and_drops_queued_motion(bus):
    bus_owner, line, d = bus()
    home = bus_owner.submit('axis1', Command(COMMAND, lambda: d['axis1'].start_homing(None),
                                             'home'))
    queued = bus_owner.submit('axis1', Command(STREAM, lambda: d['axis1'].move_to(5, None), 'p5',
                                         topic='position'))
    wait_for(lambda: line.calls('axis1', 'homing step'), 1.0, 'homing started')
    stop = bus_owner.submit('axis1', Command(URGENT, d['axis1'].stop, 'stop', disarms=True))
    result(stop)
    n_steps = len(line.calls('axis1', 'homing step'))
    with pytest.raises(Cancelled, match='cut short by stop'):
        result(home)
    with pytest.raises(Cancelled, match='dropped by stop'):
        result(queued)
    bus_owner.submit('axis1', Command(COMMAND, d['axis1'].fault_reset, 'sync',
                                      motion=False)).result(2.0)
    assert len(line.calls('axis1', 'homing step')) == n_steps      # no step after the stop
    assert not line.calls('axis1', 'move_to')


def test_disable_drops_a_queued_enable_but_a_stop_does_not(bus):
    bus_owner, line, d = bus()
    busy = bus_owner.submit('axis1', Command(MAINTENANCE, d['axis1'].save_params, 'save',
                                             motion=False))
    wait_for(lambda: line.calls('axis1', 'save step'), 1.0, 'save started')
    enable = bus_owner.submit('axis1', Command(COMMAND, d['axis1'].enable, 'enable', motion=False))
    result(bus_owner.submit('axis1', Command(URGENT, d['axis1'].stop, 'stop', disarms=True)))
    assert not enable.done()
    result(bus_owner.submit('axis1', Command(URGENT, d['axis1'].disable, 'disable', disarms=True,
                                       motion=False)))
    with pytest.raises(Cancelled, match='dropped by disable'):
        result(enable)
    result(busy)


class SlowDisableDrive(ScriptDrive):
    """A 30-step save, and a disable that walks the state machine in 4 transactions, waiting
    DISABLE_WAIT_S for the drive after each."""

    DISABLE_WAIT_S = 0.25

    def disable(self):
        for i in range(4):
            self._tx('disable step', i)
            yield self.DISABLE_WAIT_S
        self.enabled = False
        self.velocity = 0.0

    def save_params(self):
        for i in range(30):
            self._tx('save step', i)
            yield 0.05
        return 'saved'


def test_an_urgent_job_during_a_long_operation_of_its_drive_holds_nobody_else(bus):
    """A disable that comes while its drive saves runs between the save's steps, stepped like
    any job: the other drive keeps its poll rate (a gap of at most its period, the longest step
    and one transaction) and its velocity watchdog stops it on time. The drive's own calls
    keep their order: the save's steps stop for the disable's, and go on after them."""
    bus_owner, line, drives = bus(kinds={'axis1': SlowDisableDrive, 'axis2': ScriptDrive})
    save = bus_owner.submit('axis1', Command.maintenance(drives['axis1'].save_params, 'save'))
    wait_for(lambda: len(line.calls('axis1', 'save step')) >= 3, 1.0, 'save under way')
    t0 = time.monotonic()
    bus_owner.arm_watchdog('axis2')          # falls due while the disable runs
    deadline = bus_owner.slots['axis2'].velocity_deadline
    result(bus_owner.submit('axis2', Command.velocity_stream(
        lambda: drives['axis2'].set_velocity(5.0, None), 'v5', 5.0)))
    disable = bus_owner.submit('axis1', Command.disable(drives['axis1'].disable))
    assert result(disable) is None
    t1 = time.monotonic()
    assert result(save, 5.0) == 'saved'
    assert t1 - t0 >= 4 * SlowDisableDrive.DISABLE_WAIT_S
    reads = [c[0] for c in line.calls('axis2', 'read_state') if t0 <= c[0] <= t1]
    gap = max(b - a for a, b in zip([t0] + reads, reads + [t1]))
    bound = 1.0 / RATE_HZ + TX_S + TX_S + 0.05     # period, a step, a transaction, slack
    assert gap <= bound, f'axis2 not polled for {gap:.3f} s (bound {bound:.3f} s)'
    stop_t = _stop_time(line, 'axis2', t0)
    assert stop_t is not None and 0.0 <= stop_t - deadline <= TX_S + 0.05, \
        (stop_t and stop_t - deadline)
    calls = [c[2] for c in line.calls('axis1') if c[2] in ('save step', 'disable step')]
    k = calls.index('disable step')
    assert calls[k:k + 4] == ['disable step'] * 4 and calls.count('save step') == 30
    assert [c[3][0] for c in line.calls('axis1', 'save step')] == list(range(30))


# -------------------------------------------------------------------------------- watchdog
def _stop_time(line, drive, after):
    calls = [c for c in line.calls(drive, 'stop') if c[0] >= after]
    return calls[0][0] if calls else None


def test_watchdog_stops_on_its_own_clock_not_at_the_next_poll(bus):
    timeout_s = 0.3
    bus_owner, line, d = bus(publish_rate_hz=2.0, command_timeout_s=timeout_s)   # 0.5 s polls
    t0 = time.monotonic()
    bus_owner.arm_watchdog('axis1')
    result(bus_owner.submit('axis1', Command(STREAM, lambda: d['axis1'].set_velocity(5.0, None),
                                             'v5',
                                       topic='velocity')))
    wait_for(lambda: _stop_time(line, 'axis1', t0), timeout_s + 1.0, 'watchdog stop')
    late = _stop_time(line, 'axis1', t0) - (t0 + timeout_s)
    # within one transaction in flight (and scheduling), far below the 0.5 s poll period
    assert 0.0 <= late <= TX_S + 0.05, late


@pytest.mark.parametrize('refused', ['stop', 'move_to', 'start_homing'])
def test_a_refused_command_during_a_velocity_run_leaves_the_watchdog_armed(bus, refused):
    timeout_s = 0.3
    bus_owner, line, d = bus(command_timeout_s=timeout_s)
    drive = d['axis1']
    bus_owner.arm_watchdog('axis1')
    result(bus_owner.submit('axis1', Command(STREAM, lambda: drive.set_velocity(5.0, None), 'v5',
                                       topic='velocity')))
    t0 = time.monotonic()
    drive.fail[refused if refused != 'start_homing' else 'homing step'] = \
        DriveError(f'{refused} refused: stop first')
    fn = {'stop': drive.stop, 'move_to': lambda: drive.move_to(1, None),
          'start_homing': lambda: drive.start_homing(None)}[refused]
    kind = URGENT if refused == 'stop' else COMMAND
    with pytest.raises(DriveError, match='refused'):
        result(bus_owner.submit('axis1', Command(kind, fn, refused, disarms=True)))
    assert bus_owner.watchdog_armed('axis1')
    stops = 2 if refused == 'stop' else 1          # the refused one, then the watchdog's
    wait_for(lambda: len(line.calls('axis1', 'stop')) >= stops, timeout_s + 1.0,
             'watchdog stop')
    assert line.calls('axis1', 'stop')[-1][0] - t0 <= timeout_s + TX_S + 0.05
    wait_for(lambda: drive.velocity == 0.0 and not bus_owner.watchdog_armed('axis1'), 5 * TX_S,
             'the stop done and confirmed')


def test_a_lost_reply_to_a_velocity_write_is_stopped_after_the_reconnect(bus):
    timeout_s = 0.3
    bus_owner, line, d = bus(command_timeout_s=timeout_s)
    drive = d['axis1']
    drive.fail['set_velocity'] = LinkError('no answer (timeout)')   # the write reached it
    bus_owner.arm_watchdog('axis1')
    t0 = time.monotonic()
    with pytest.raises(LinkError):
        result(bus_owner.submit('axis1', Command(STREAM, lambda: drive.set_velocity(5.0, None),
                                                 'v5',
                                           topic='velocity')))
    assert drive.velocity == 5.0 and bus_owner.watchdog_armed('axis1')
    wait_for(lambda: _stop_time(line, 'axis1', t0), timeout_s + 2.0, 'watchdog stop')
    wait_for(lambda: drive.velocity == 0.0 and not bus_owner.watchdog_armed('axis1'), 5 * TX_S,
             'the stop done and confirmed')


def test_a_stop_refused_while_disconnected_leaves_the_watchdog_armed(bus):
    timeout_s = 0.3
    bus_owner, line, d = bus(command_timeout_s=timeout_s, reconnect_period_s=0.2)
    drive = d['axis1']
    bus_owner.arm_watchdog('axis1')
    result(bus_owner.submit('axis1', Command(STREAM, lambda: drive.set_velocity(5.0, None), 'v5',
                                       topic='velocity')))
    drive.fail_always['read_state'] = LinkError('link down')
    drive.fail_always['connect'] = LinkError('link down')
    wait_for(lambda: not bus_owner.slots['axis1'].connected, 1.0, 'link lost')
    with pytest.raises(NotConnected):
        result(bus_owner.submit('axis1', Command(URGENT, drive.stop, 'stop', disarms=True)))
    assert bus_owner.watchdog_armed('axis1')
    t_back = time.monotonic()
    drive.fail_always.clear()
    wait_for(lambda: _stop_time(line, 'axis1', t_back), 2.0, 'stop after the reconnect')
    wait_for(lambda: drive.velocity == 0.0, 5 * TX_S, 'the stop done')


# --------------------------------------------------------------------------- link, identity
def test_an_identity_error_is_checked_again_on_the_slow_back_off_only(bus):
    """Not driven at the first IdentityError, and not tried again on the reconnect period:
    on IDENTITY_RECHECK_S (test_identity_recheck.py: for as long as the node runs)."""
    line = Line()
    drive = ScriptDrive(line, 'axis1')
    drive.fail_always['connect'] = IdentityError('register 1152 reads 0x1234: not an X')
    events = []
    bus_owner = BusOwner(line, {'axis1': drive}, {'publish_rate_hz': RATE_HZ,
                        'command_timeout_s': 0.3, 'reconnect_period_s': 0.02},
                        on_event=lambda *e: events.append(e))
    bus_owner.start()
    try:
        wait_for(lambda: bus_owner.slots['axis1'].not_driven, 3.0, 'not driven')
        assert 'register 1152' in bus_owner.slots['axis1'].not_driven
        assert f'in {owner.IDENTITY_RECHECK_S:g} s' in bus_owner.slots['axis1'].not_driven
        time.sleep(0.2)   # several reconnect periods: no further attempt may come
        assert len(line.calls('axis1', 'connect')) == 1
    finally:
        bus_owner.shutdown(0.5)


def test_shutdown_stops_every_drive_then_disables_those_named(bus):
    bus_owner, line, d = bus()
    for n in ('axis1', 'axis2'):
        d[n].velocity = 3.0
    t0 = time.monotonic()
    bus_owner.shutdown(1.0, disable=['axis2'])
    assert _stop_time(line, 'axis1', t0) and _stop_time(line, 'axis2', t0)
    assert [c[1] for c in line.calls(call='disable') if c[0] >= t0] == ['axis2']
    assert not line.is_open
    with pytest.raises(Cancelled):
        result(bus_owner.submit('axis1', Command(COMMAND, d['axis1'].fault_reset, 'late')))


def test_a_command_that_comes_while_the_shutdown_runs_never_reaches_the_wire(bus):
    """A service or topic callback may still run while the drives are stopped at shutdown
    (the executor spins until the end): its job is refused, not sent after the stop."""
    bus_owner, line, d = bus()
    d['axis2'].velocity = 3.0
    t0 = time.monotonic()
    ender = threading.Thread(target=bus_owner.shutdown, args=(1.0,), kwargs={'disable': ['axis2']})
    ender.start()
    wait_for(lambda: _stop_time(line, 'axis1', t0), 2.0, 'the shutdown stop of axis1')
    late = [bus_owner.submit('axis1', Command(STREAM, lambda: d['axis1'].set_velocity(7.0, None),
                                              'v7',
                                        topic='velocity')),
            bus_owner.submit('axis2', Command(COMMAND, d['axis2'].enable, 'enable', motion=False)),
            bus_owner.submit('axis2', Command(URGENT, d['axis2'].stop, 'stop'))]
    ender.join(3.0)
    assert not ender.is_alive()
    for fut in late:
        with pytest.raises(Cancelled, match='shutting down'):
            result(fut)
    sent = [c[1:3] for c in line.calls() if c[0] >= t0]
    assert ('axis1', 'set_velocity') not in sent and ('axis2', 'enable step') not in sent, sent
    assert sent[-1] == ('axis2', 'disable') and d['axis1'].velocity == 0.0, sent


def test_what_waits_for_a_poll_or_a_timer_is_answered_at_shutdown(bus):
    """A service awaiting a poll or a timer must not wait for ever once the owner is gone."""
    bus_owner, line, d = bus()
    calls = []
    bus_owner.after(60.0, lambda: calls.append('timer set before'))
    bus_owner.shutdown(0.5)
    assert calls == ['timer set before'] and bus_owner.stopping
    bus_owner.wait_poll('axis1', 60.0, lambda ok: calls.append(('poll', ok)))
    bus_owner.after(60.0, lambda: calls.append('timer set after'))
    assert calls[1:] == [('poll', False), 'timer set after']


def test_a_removed_timer_is_never_called_and_leaves_nothing_behind(bus):
    """after() gives what removes its timer (a service's time-out once its job ended): the
    callback is not called, and timers removed do not pile up in what the owner looks at."""
    bus_owner, line, d = bus()
    calls = []
    remove = bus_owner.after(0.1, lambda: calls.append('removed'))
    bus_owner.after(0.1, lambda: calls.append('kept'))
    remove()
    for _ in range(1000):
        bus_owner.after(60.0, lambda: calls.append('late'))()
    wait_for(lambda: calls, 1.0, 'the kept timer')
    time.sleep(0.1)
    assert calls == ['kept']
    assert len(bus_owner._timers) < 100
    remove()                                   # once more: nothing
    bus_owner.shutdown(0.5)
    assert calls == ['kept']


def test_a_shutdown_that_cannot_end_the_owner_says_so(bus):
    """An owner that does not end within the join time-out (a transaction that hangs) leaves
    its drives unstopped: shutdown() says so (False, and an error), it does not return as if
    they were stopped."""
    bus_owner, line, d = bus()
    release = threading.Event()
    bus_owner.submit('axis1', Command(COMMAND, lambda: release.wait(5.0), 'a hung transaction'))
    wait_for(lambda: bus_owner.slots['axis1'].active is not None, 1.0, 'the owner busy')
    try:
        assert bus_owner.shutdown(0.5, join_timeout_s=0.2) is False
        (error,) = [e for e in bus_owner.events if e[0] == 'error' and 'did not end' in e[2]]
        assert 'not stopped' in error[2], error
    finally:
        release.set()
    assert bus_owner.shutdown(0.5) is True and not bus_owner.alive


def test_a_confirmation_does_not_disarm_a_velocity_accepted_after_it(bus):
    """position p queued, then velocity v accepted (armed) and queued behind it: p confirmed
    must not disarm the watchdog that v, running next, needs."""
    timeout_s = 1.0         # longer than the save the commands wait behind (0.5 s)
    bus_owner, line, d = bus(command_timeout_s=timeout_s)
    drive = d['axis1']
    busy = bus_owner.submit('axis1', Command(MAINTENANCE, drive.save_params, 'save', motion=False))
    wait_for(lambda: line.calls('axis1', 'save step'), 1.0, 'save started')
    pos = bus_owner.submit('axis1', Command(STREAM, lambda: drive.move_to(1, None), 'p1',
                                      topic='position', disarms=True))
    bus_owner.arm_watchdog('axis1')
    vel = bus_owner.submit('axis1', Command(STREAM, lambda: drive.set_velocity(5.0, None), 'v5',
                                      topic='velocity'))
    result(busy)
    result(pos)
    result(vel)
    t_vel = line.calls('axis1', 'set_velocity')[-1][0]
    assert bus_owner.watchdog_armed('axis1')
    wait_for(lambda: _stop_time(line, 'axis1', t_vel), timeout_s + 1.0, 'watchdog stop')
    wait_for(lambda: drive.velocity == 0.0, 5 * TX_S, 'the stop done')


def test_the_state_time_is_when_the_drive_says_its_position_was_true(bus):
    """slot.sample's time (the time the trajectory feedback evaluates the plan at) is the
    drive's `measured_at_s` where it gives one (a Vector Step position held back by the inhibit
    time), else the end of the poll; its state is the one that poll read."""
    bus_owner, line, drives = bus(1)
    slot = bus_owner.slots['axis1']
    measured = time.monotonic() - 0.123
    drives['axis1'].measured_at_s = measured
    polls = slot.polls
    wait_for(lambda: slot.polls > polls + 1, 4 / RATE_HZ, 'a poll with measured_at_s')
    state, t = slot.sample
    assert t == measured and state.measured_at_s == measured
    drives['axis1'].measured_at_s = None
    t0 = time.monotonic()
    polls = slot.polls
    wait_for(lambda: slot.polls > polls + 1, 4 / RATE_HZ, 'a poll without')
    state, t = slot.sample
    assert t0 <= t <= time.monotonic() and state.measured_at_s is None


def test_when_polls_overrun_every_drive_gets_its_turn(bus):
    """Three drives whose polls do not fit the period (3 x 10 ms per 10 ms): each is polled
    in turn, none starves, and one cycle goes out per round."""
    bus_owner, line, d = bus(n_drives=3, publish_rate_hz=100.0)
    start = {n: s.polls for n, s in bus_owner.slots.items()}
    cycles0 = bus_owner.cycles
    wait_for(lambda: min(s.polls - start[n] for n, s in bus_owner.slots.items()) >= 20, 5.0,
             'twenty polls of every drive')
    counts = [s.polls - start[n] for n, s in bus_owner.slots.items()]
    assert max(counts) - min(counts) <= 2, counts
    assert bus_owner.cycles - cycles0 >= 19


class BurstWaitDrive(ScriptDrive):
    """read_state() sends its request, then waits WAIT_S for the answer in steps of STEP_S (the
    Vector Step's burst wait through link.wait): a poll that lasts longer than a poll period."""

    WAIT_S, STEP_S = 0.06, 0.002

    def __init__(self, bus, name, params=None):
        super().__init__(bus, name, params)
        self.steps = 0

    def read_state(self):
        self._tx('read_state')
        until = time.monotonic() + self.WAIT_S
        while time.monotonic() < until:
            self.steps += 1
            yield self.STEP_S
        return DriveState(state=State.OPERATION_ENABLED, enabled=True)


def test_a_step_wise_poll_longer_than_its_period_waits_between_its_steps():
    """A poll that outlasts the poll period is due again while it runs: its steps still come at
    the times it asked for (about one per STEP_S), not as fast as the owner can loop."""
    assert BurstWaitDrive.WAIT_S > 1.0 / RATE_HZ
    line = Line()
    drive = BurstWaitDrive(line, 'axis1')
    bus_owner = BusOwner(line, {'axis1': drive}, {'publish_rate_hz': RATE_HZ,
                        'command_timeout_s': 0.3, 'reconnect_period_s': 0.05})
    bus_owner.start()
    try:
        wait_for(lambda: bus_owner.slots['axis1'].polls >= 2, 2.0, 'polled')
        steps0, polls0 = drive.steps, bus_owner.slots['axis1'].polls
        time.sleep(1.0)
        steps, polls = drive.steps - steps0, bus_owner.slots['axis1'].polls - polls0
        bound = 1.0 / BurstWaitDrive.STEP_S * 1.2
        assert steps <= bound, f'{steps} steps of a poll in 1 s (bound {bound:.0f})'
        # back to back: each poll one transaction and WAIT_S (and a step's rounding)
        assert polls >= 1.0 / (TX_S + BurstWaitDrive.WAIT_S + 2 * BurstWaitDrive.STEP_S) - 3
    finally:
        bus_owner.shutdown(0.5)


def test_an_owner_that_fails_stops_its_drives_says_why_and_ends_once():
    """An internal error in the owner loop (here: in on_cycle, the node's publishing): every
    drive is stopped, the bus closed, the slots say DISCONNECTED with the reason, on_failure is
    told once; a later shutdown() does not stop them again on the closed bus."""
    line = Line()
    drives = {n: ScriptDrive(line, n) for n in ('axis1', 'axis2')}
    failures, cycles = [], []

    def on_cycle(bus_owner):
        cycles.append(1)
        if len(cycles) == 3:
            raise ZeroDivisionError('a bug in the publishing')
    bus_owner = BusOwner(line, drives, {'publish_rate_hz': RATE_HZ, 'command_timeout_s': 0.3,
                                       'reconnect_period_s': 0.05},
                        on_cycle=on_cycle, on_event=lambda *e: None,
                        on_failure=lambda s, why: failures.append((s, why)))
    for d in drives.values():
        d.velocity = 2.0
    t0 = time.monotonic()
    bus_owner.start()
    wait_for(lambda: failures, 3.0 / RATE_HZ + 1.0, 'on_failure')
    ((who, why),) = failures
    assert who is bus_owner and 'ZeroDivisionError' in why and bus_owner.failure == why
    assert _stop_time(line, 'axis1', t0) and _stop_time(line, 'axis2', t0)
    assert not line.is_open and not bus_owner.alive
    assert all(not s.connected and s.last_error == why for s in bus_owner.slots.values())
    on_wire = len(line.calls())
    bus_owner.shutdown(0.5)
    assert len(line.calls()) == on_wire
    with pytest.raises(Cancelled):
        result(bus_owner.submit('axis1', Command(COMMAND, drives['axis1'].fault_reset, 'late')))


@pytest.mark.parametrize('priority', [0, 10])
def test_owner_thread_priority_puts_the_owner_alone_on_sched_fifo(bus, priority):
    """owner_thread_priority: the owner thread on SCHED_FIFO at that priority (where this process
    may; otherwise the warning of the refusal below), no other thread; 0: nothing changes."""
    owner.priority._refusal_told = False         # (told once per process)
    bus_owner, _, drives = bus(owner_thread_priority=priority)
    thread_id = bus_owner._thread.native_id
    fifo = priority and fifo_allowed(priority)
    assert os.sched_getscheduler(thread_id) == (os.SCHED_FIFO if fifo else os.SCHED_OTHER)
    if fifo:
        assert os.sched_getparam(thread_id).sched_priority == priority
    assert os.sched_getscheduler(threading.get_native_id()) == os.SCHED_OTHER
    assert bool(priority and not fifo) == any('owner_thread_priority' in e[2]
                                              for e in bus_owner.events)
    assert result(bus_owner.submit('axis1', Command(COMMAND, lambda: drives['axis1'].move_to(5,
                                                                                             None),
                                              'move'))) is None


def test_a_refused_owner_thread_priority_is_a_warning_and_the_bus_works(bus):
    """A refused SCHED_FIFO (here a priority the kernel does not have, which fails for root too;
    the node's parameter allows 1..99) is one warning naming the parameter and why, and the
    owner runs on the normal scheduler. Told once per process: the owner of a second bus (a
    node's next drive host) is refused in silence."""
    owner.priority._refusal_told = False
    bus_owner, _, drives = bus(owner_thread_priority=100)
    assert os.sched_getscheduler(bus_owner._thread.native_id) == os.SCHED_OTHER
    (warning,) = [e for e in bus_owner.events if 'owner_thread_priority' in e[2]]
    assert warning[0] == 'warning' and 'owner_thread_priority 100: SCHED_FIFO refused' in \
        warning[2], warning
    assert '/etc/security/limits.conf' in warning[2] and 'owner_thread_priority: 0' in warning[2]
    other, _, _ = bus(owner_thread_priority=100)
    assert os.sched_getscheduler(other._thread.native_id) == os.SCHED_OTHER
    assert not [e for e in other.events if 'owner_thread_priority' in e[2]]
    assert result(bus_owner.submit('axis1', Command(COMMAND, lambda: drives['axis1'].move_to(5,
                                                                                             None),
                                              'move'))) is None


# ------------------------------------------------------------------------ snapshot provenance
class SlowReadDrive(ScriptDrive):
    """read_state() reads the drive's position with its request, then waits WAIT_S for the
    rest of its answer in steps (a poll that spans several steps, as a Vector Step's burst or
    an RD4 poll that writes after its read); move_to() sets the position at once."""

    WAIT_S, STEP_S = 0.12, 0.01

    def __init__(self, bus, name, params=None):
        super().__init__(bus, name, params)
        self.position = 0

    def read_state(self):
        self._tx('read_state')
        position = self.position                    # what the drive said when asked
        if self.on_read is not None:
            on_read, self.on_read = self.on_read, None
            on_read()
        until = time.monotonic() + self.WAIT_S
        while time.monotonic() < until:
            yield self.STEP_S
        return DriveState(state=State.OPERATION_ENABLED, enabled=True, position_steps=position)

    def move_to(self, target_steps, motion):
        self._tx('move_to', target_steps)
        self.position = target_steps


def test_an_answer_awaits_a_snapshot_read_after_its_command_not_one_in_flight_before_it():
    """A command that comes while a poll of its drive is under way (read, its answer still
    awaited) runs between the poll's steps and ends before it. A waiter for the drive's next
    snapshot registered at the command's end (a service that answers by what its command did)
    is not answered by that poll, whose read went out before the command's write, but by the
    next one, which shows the write; each snapshot carries the drive's write count in force
    when its read began, and the command's future the count at its end."""
    line = Line()
    drive = SlowReadDrive(line, 'axis1')
    bus_owner = BusOwner(line, {'axis1': drive}, {'publish_rate_hz': RATE_HZ,
                        'command_timeout_s': 0.3, 'reconnect_period_s': 0.05})
    slot = bus_owner.slots['axis1']
    bus_owner.start()
    try:
        wait_for(lambda: slot.polls >= 2, 3.0, 'polled')
        answers, stale, futs = [], [], []

        def answered(ok):                      # owner thread, once the waiter is answered
            answers.append((ok, slot.state, slot.state.position_steps))

        def move_ended(fut):                   # owner thread, at the command's end
            assert slot.poll_operation is not None, 'the poll no longer under way'
            stale.append(slot.state)
            bus_owner.wait_poll('axis1', 1.0, answered)

        def command():
            fut = bus_owner.submit('axis1', Command(COMMAND, lambda: drive.move_to(500, None),
                                                    'move'))
            fut.add_done_callback(move_ended)
            futs.append(fut)
        drive.on_read = command                 # during a poll's read: the poll goes on after
        wait_for(lambda: answers, 2.0, 'the waiter answered')
        assert result(futs[0]) is None
        ok, state, position = answers[0]
        assert ok and position == 500, f'answered by a snapshot read before the move: {position}'
        assert state.after_write >= futs[0].after_write > stale[0].after_write
        # the poll that was under way did publish its snapshot, stamped before the move
        wait_for(lambda: slot.state.position_steps == 500, 1.0, 'polled after')
    finally:
        bus_owner.shutdown(0.5)


def test_a_job_that_also_writes_another_drive_counts_as_its_write_too():
    """A job queued under axis1 that also writes axis2 (a group start, Command.also) runs
    while a poll of axis2 is under way (its read went out before the write). A waiter for
    axis2's next snapshot registered at the job's end is not answered by that poll but by the
    next one, which shows the write: the job's start and end count as writes of axis2 too."""
    bus_owner, line, d = make(kinds={'axis1': ScriptDrive, 'axis2': SlowReadDrive})
    slot = bus_owner.slots['axis2']
    try:
        wait_for(lambda: slot.polls >= 2, 3.0, 'polled')
        with pytest.raises(ValueError, match=r"also \['axis9'\]: not other drives"):
            bus_owner.submit('axis1', Command.move(lambda: None, 'x', also=('axis9',)))
        seq = slot.write_seq
        answers, futs = [], []

        def answered(ok):                      # owner thread, once the waiter is answered
            answers.append((ok, slot.state, slot.state.position_steps))

        def group_ended(fut):                  # owner thread, at the group job's end
            assert slot.poll_operation is not None, 'the poll of axis2 no longer under way'
            bus_owner.wait_poll('axis2', 1.0, answered)

        def group_start():
            fut = bus_owner.submit('axis1', Command.move(lambda: d['axis2'].move_to(500, None),
                                                   'group start', also=('axis2',)))
            fut.add_done_callback(group_ended)
            futs.append(fut)
        d['axis2'].on_read = group_start        # during axis2's read: its poll goes on after
        wait_for(lambda: answers, 2.0, 'the waiter answered')
        assert result(futs[0]) is None
        assert slot.write_seq >= seq + 2        # the group job's start and end
        ok, state, position = answers[0]
        assert ok and position == 500, f'answered by a snapshot read before the job: {position}'
        assert state.after_write >= seq + 2
    finally:
        bus_owner.shutdown(0.5)


def test_a_snapshot_a_drive_vouches_for_after_a_command_carries_the_count_of_that_vouch():
    """A quiet cycle counts a drive polled by its word that the last poll still holds: that
    snapshot is stamped with the write count in force at the vouching, after the command."""
    line, d, bus_owner = quiet_bus(n=2)
    for drive in d.values():
        drive.until = float('inf')
    slot = bus_owner.slots['axis1']
    bus_owner.start()
    try:
        wait_for(lambda: all(s.polls >= 1 for s in bus_owner.slots.values()), 3.0, 'first polls')
        fut = bus_owner.submit('axis1', Command(COMMAND, lambda: d['axis1'].fault_reset(),
                                                'reset'))
        result(fut)
        polls = slot.polls
        wait_for(lambda: slot.polls >= polls + 2, 6.0 / RATE_HZ, 'two quiet cycles')
        assert slot.state is d['axis1'].state
        assert slot.state.after_write == fut.after_write == slot.write_seq
    finally:
        bus_owner.shutdown(0.5)


# --------------------------------------------------------------------- who writes a slot
def test_the_write_check_catches_a_slot_written_by_the_wrong_thread(bus):
    """The suite runs with the slots' writer check on (conftest.py): an owner field written
    by another thread than the owner, or a request field written without the bus lock, fails
    at the write, naming the field and the thread."""
    bus_owner, _, _ = bus()
    slot = bus_owner.slots['axis1']
    with pytest.raises(owner.slot.WriterError, match=r'axis1\.next_poll_t written by '
                       r'thread MainThread, not by the acting owner owner bus'):
        slot.next_poll_t = 0.0
    with pytest.raises(owner.slot.WriterError,
                       match=r'axis1\.poll_requested written without the bus lock'):
        slot.poll_requested = True
    with pytest.raises(owner.slot.WriterError, match=r'axis1\.nxt_poll_t: not a field'):
        slot.nxt_poll_t = 0.0
    with bus_owner._cv:
        slot.poll_requested = True                # a request, under the lock: allowed
    done = []
    bus_owner.after(0.0, lambda: done.append(setattr(slot, 'next_poll_t', slot.next_poll_t)))
    wait_for(lambda: done, 1.0, 'the owner wrote its own field')
