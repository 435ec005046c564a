"""The SYNC and heartbeat producer of a CanBus (protocol/canopen_producers): what the drives'
0x1006 watchdog needs, kept going whatever the node's threads do.

Real python-can, canopen and broker: the socketcand broker runs as a process of its own here, so
that it stamps each frame it relays (the `timestamp` a listener receives) on time while this
test process holds its GIL; the listener reads those stamps, and the SYNC gaps measured are the
gaps on the wire. A thread that holds the GIL in a blocking call is what rclpy's publish did
inside Fast DDS on a loaded machine (120-330 ms); ctypes.PyDLL calls a C function without
releasing the GIL, so `usleep` through it is that call.
"""

import ctypes
import logging
import os
import signal
import subprocess
import sys
import time

import can
import pytest
from stepper_drivers.contract.drive import LinkError
from stepper_drivers.protocol import canopen_link, canopen_producers
from stepper_drivers.protocol.canopen_link import CanBus
from stepper_sim.harness import Proc, SyncListener, executable, fifo_allowed, max_gap, wait_for

PERIOD_S = 0.05                # the SYNC period of these buses
SYNC_TIMEOUT_S = 0.5           # the drives' 0x1006 time (sync_timeout_s, the shipped default)
WARN_S = SYNC_TIMEOUT_S / 2    # canopen_link.SYNC_GAP_WARN_SHARE of it: health() says WARN


def hold_gil(seconds):
    """Block in C with the GIL held, as rcl_publish blocked in Fast DDS."""
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


@pytest.fixture
def broker(tmp_path):
    """The loopback broker as a process of its own; its port."""
    proc = Proc([executable('stepper_sim', 'socketcand_broker'), '--port', '0'], tmp_path,
                'broker')
    proc.wait_line('listening on', 10.0)
    port = int(proc.output().split('listening on ')[1].split()[0].rsplit(':', 1)[1])
    yield port
    proc.kill()


@pytest.fixture
def link(broker):
    """(the node's CanBus on the broker, a listener); both closed at the end."""
    listener = SyncListener(broker)
    bus = CanBus(interface='socketcand', port=broker, sync_period_s=PERIOD_S,
                 master_heartbeat_ms=100)
    bus.open()
    yield bus, listener
    bus.close()
    listener.close()


def test_a_thread_holding_the_gil_does_not_hold_up_the_sync(link):
    """Three times 0.8 s of a thread of the node blocked with the GIL held (longer than the
    drives' 0.5 s 0x1006 time): the SYNC goes on at its period meanwhile."""
    bus, listener = link
    listener.wait_syncs(3)
    mark = listener.count()
    for _ in range(3):
        hold_gil(0.8)
        time.sleep(PERIOD_S)
    before = listener.count()
    listener.wait_syncs(1, before)
    stamps = listener.since(mark)
    assert len(stamps) >= 2.4 / PERIOD_S * 0.8          # ~every period of the 2.55 s
    assert max_gap(stamps) < WARN_S, max_gap(stamps)    # no gap near 0x1006
    assert bus.health() is None


def test_a_late_sync_shows_with_its_gap_before_the_drives_fault(link):
    """The SYNC gaps are recorded: an ordinary one is a period and no alarm; a producer held
    up for 0.3 s right after a SYNC (SIGSTOP: the process of its own, frozen as a starved one
    would be) is a WARN naming the gap and the drives' 0x1006 time while it lasts, and after
    it for the link's diagnostics window, with the largest gap in the counters."""
    bus, listener = link
    bus.sync_watch('axis1', SYNC_TIMEOUT_S)         # as RemoteDrive.write of 0x1006 does
    bus.sync_watch('axis2', 2.0)                    # the smallest time counts
    listener.wait_syncs(3)
    assert bus.health() is None
    assert PERIOD_S * 1000 * 0.5 <= bus.counters()['sync_gap_max_ms'] < WARN_S * 1000
    pid = bus.producer_pid
    seen = listener.count()
    listener.wait_syncs(1, seen)
    os.kill(pid, signal.SIGSTOP)
    try:
        stopped = time.monotonic()
        open_gap = wait_for(bus.health, SYNC_TIMEOUT_S, 'a WARN while the SYNC is late')
        assert time.monotonic() - stopped < SYNC_TIMEOUT_S      # before the drives fault
        assert open_gap[0] == 'warn' and "ms of the drives' 500 ms sync_timeout_s" in open_gap[1]
        wait_for(lambda: time.monotonic() - stopped >= 0.3, 1.0, '0.3 s', 0.002)
    finally:
        os.kill(pid, signal.SIGCONT)
    mark = listener.count()
    listener.wait_syncs(2, mark)
    level, text = bus.health()
    gap_ms = bus.counters()['sync_gap_max_ms']
    assert level == 'warn' and text == f"SYNC gap {gap_ms} ms of the drives' 500 ms sync_timeout_s"
    assert 300 <= gap_ms < 500
    wire = max_gap(listener.since(0))
    assert abs(wire * 1000 - gap_ms) < 100            # the gap the listener saw on the bus


def test_the_producer_runs_at_the_owners_priority_whoever_opens_the_bus(broker, caplog,
                                                                         monkeypatch):
    """Opened from this (normal-priority) thread, the SYNC producer takes the bus owners'
    real-time priority itself: the process on socketcand, the thread on other interfaces (or,
    where SCHED_FIFO is not allowed, says so once and runs on the normal scheduler)."""
    caplog.set_level(logging.WARNING)
    monkeypatch.setattr(canopen_link, '_refusal_told', False)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    process_bus = CanBus(interface='socketcand', port=broker, sync_period_s=PERIOD_S,
                         owner_thread_priority=7)
    thread_bus = CanBus(interface='virtual', channel=f'sync-priority-{os.getpid()}',
                        sync_period_s=PERIOD_S, owner_thread_priority=7)
    process_bus.open()
    thread_bus.open()
    try:
        wait_for(lambda: thread_bus.producer_tid is not None, 2.0, 'the producer thread')
        wait_for(lambda: thread_bus.sync_record.count >= 1, 2.0, 'a SYNC from the thread')
        for task in (process_bus.producer_pid, thread_bus.producer_tid):
            if fifo_allowed(7):
                assert os.sched_getscheduler(task) == os.SCHED_FIFO
                assert os.sched_getparam(task).sched_priority == 7
            else:
                assert os.sched_getscheduler(task) == os.SCHED_OTHER
                assert any('SCHED_FIFO 7 refused' in r.getMessage() for r in caplog.records)
    finally:
        process_bus.close()
        thread_bus.close()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER        # this thread left as it was


def test_a_send_error_is_counted_and_the_sync_goes_on(monkeypatch):
    """python-can's cyclic task ended for good at the first exception of bus.send. Here the
    failed SYNCs are link errors, the next ones go out on time; only failures that persist make
    the link fail (check() raises LinkError: the owner reconnects, with a new producer)."""
    channel = f'sync-errors-{os.getpid()}'
    bus = CanBus(interface='virtual', channel=channel, sync_period_s=0.02)
    peer = can.Bus(interface='virtual', channel=channel)
    bus.open()
    try:
        wire = bus.network.bus
        real_send = wire.send
        failures = []

        def failing_send(msg, timeout=None):
            if msg.arbitration_id == 0x080 and len(failures) < 2:
                failures.append(msg)
                raise can.CanOperationError('Transmit buffer full')
            return real_send(msg, timeout)
        monkeypatch.setattr(wire, 'send', failing_send)
        wait_for(lambda: len(failures) == 2, 2.0, 'two failed SYNCs')
        seen = 0
        while seen < 3:                                  # three SYNCs after the failures
            msg = peer.recv(1.0)
            assert msg is not None, 'the SYNC stopped after a send error'
            seen += msg.arbitration_id == 0x080
        assert bus.counters()['errors'] == 2 and bus.sync_record.errors == 2
        bus.check()
        assert bus.receiving and bus.health() is None

        def dead_send(msg, timeout=None):
            raise can.CanOperationError('Network is down')
        monkeypatch.setattr(wire, 'send', dead_send)
        persistent = canopen_producers.PERSISTENT_ERRORS
        wait_for(lambda: bus.sync_record.failing >= persistent, 2.0, 'failures in a row')
        with pytest.raises(LinkError, match='SYNC and heartbeat not sent: .* Network is down'):
            bus.check()
        assert not bus.receiving and bus.health()[0] == 'error'
    finally:
        bus.close()
        peer.shutdown()


def test_own_sync_hands_the_sync_to_the_owner_and_back(link):
    """Interpolated position mode (follow.Stream): own_sync() returns once the periodic SYNC
    has stopped; each send_sync() is one SYNC, recorded like the producer's; periodic_sync()
    starts the producer again, one period after."""
    bus, listener = link
    listener.wait_syncs(2)
    bus.own_sync()
    mark = listener.count()
    for _ in range(3):
        before = listener.count()
        bus.send_sync()
        listener.wait_syncs(1, before)
        time.sleep(PERIOD_S)                            # the owner's period
    assert listener.count() - mark == 3                 # the owner's, none of the producer's
    before = listener.count()
    bus.periodic_sync()
    listener.wait_syncs(3, before)
    assert max_gap(listener.since(mark)) < WARN_S
    assert bus.counters()['sync_gap_max_ms'] < WARN_S * 1000


NODE = """
import sys, time
from stepper_drivers.protocol.canopen_link import CanBus
bus = CanBus(interface='socketcand', port=int(sys.argv[1]), sync_period_s=0.05)
bus.open()
print(bus.producer_pid, flush=True)
while True:
    time.sleep(1.0)
"""


def test_the_sync_stops_with_a_node_that_hangs_or_dies(broker):
    """The drives' watchdog must still stop them when the node cannot: a node process that
    hangs (SIGSTOP: nothing of it runs) loses its SYNC within the producer's lease, and has it
    again when it runs again; a killed node takes its producer along."""
    listener = SyncListener(broker)
    node = subprocess.Popen([sys.executable, '-c', NODE, str(broker)], stdout=subprocess.PIPE,
                            text=True)
    try:
        producer = int(node.stdout.readline())
        listener.wait_syncs(3)
        os.kill(node.pid, signal.SIGSTOP)
        stopped = time.time()
        lease_s = canopen_producers.LEASE_S
        wait_for(lambda: time.time() - stopped > lease_s + 5 * PERIOD_S, 3.0, 'the lease', 0.01)
        stamps = listener.since(0)
        assert stamps[-1] < stopped + lease_s + 2 * PERIOD_S   # it stopped within the lease
        assert stamps[-1] > stopped + lease_s - 0.3        # not before (the node's last sign)
        os.kill(node.pid, signal.SIGCONT)
        listener.wait_syncs(2, len(stamps))                # a node that runs again: SYNC again
        node.kill()
        node.wait()
        wait_for(lambda: not os.path.exists(f'/proc/{producer}'), 2.0, 'the producer ending')
    finally:
        if node.poll() is None:
            node.kill()
            node.wait()
        listener.close()
