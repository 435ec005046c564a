"""Error frames the CAN interface reports reach the link's counters (CanBus.counters: the link
entry of /diagnostics, `errors` in every drive's status.link_errors) and its log, bus-off at once.
canopen's own listener drops them. Through a real CanBus on python-can's in-process `virtual`
interface, a second bus on the same channel sending the error frames."""

import itertools
import logging
import os

import can
import pytest
from stepper_drivers.protocol import canopen_link
from stepper_drivers.protocol.canopen_link import CanBus
from stepper_sim.harness import wait_for

LOGGER = 'stepper_drivers.protocol.canopen_link'
_channels = itertools.count()


@pytest.fixture
def link():
    """(the node's CanBus, another station on its bus) on a private virtual channel."""
    channel = f'error-frames-{os.getpid()}-{next(_channels)}'
    bus = CanBus(interface='virtual', channel=channel)
    bus.open()
    peer = can.Bus(interface='virtual', channel=channel)
    yield bus, peer
    peer.shutdown()
    bus.close()


def error_frame(can_id, data=bytes(8)):
    return can.Message(arbitration_id=can_id, is_error_frame=True, is_extended_id=False,
                       data=data)


def warnings_of(caplog):
    return [r.getMessage() for r in caplog.records
            if r.name == LOGGER and r.levelno >= logging.WARNING]


def test_error_frames_are_link_errors_in_the_counters(link, caplog):
    bus, peer = link
    caplog.set_level(logging.WARNING, LOGGER)
    peer.send(can.Message(arbitration_id=0x701, is_extended_id=False, data=b'\x05'))
    peer.send(error_frame(0x040))
    peer.send(error_frame(0x004))
    wait_for(lambda: bus.counters()['error_frames'] == 2, 5.0, 'two error frames counted')
    counters = bus.counters()
    assert counters['errors'] == 2 and counters['garbage_rx'] == 0
    assert counters['bus_off'] == 0          # 'virtual' is not SocketCAN: counted, not decoded
    (line,) = warnings_of(caplog)            # one line per period
    assert line.startswith('CAN virtual error-frames-')
    assert 'link error: the CAN interface reports an error frame (0x040 [8]' in line


def test_socketcan_error_frames_are_decoded_and_bus_off_is_logged_at_once(
        link, caplog, monkeypatch):
    bus, peer = link
    # the virtual bus carries frames in SocketCAN's encoding here (linux/can/error.h)
    monkeypatch.setattr(canopen_link, 'SOCKETCAN_ERROR_INTERFACES', ('virtual',))
    caplog.set_level(logging.WARNING, LOGGER)
    peer.send(error_frame(0x004, bytes([0, 0x20, 0, 0, 0, 0, 0x80, 0])))     # TX passive
    wait_for(lambda: bus.counters()['error_frames'] == 1, 5.0, 'error passive counted')
    peer.send(error_frame(0x040))                                            # bus-off
    wait_for(lambda: bus.counters()['error_frames'] == 2, 5.0, 'bus-off counted')
    assert bus.counters()['bus_off'] == 1 and bus.counters()['errors'] == 2
    passive, bus_off = warnings_of(caplog)
    assert 'reports controller, TX error passive (0x004 [8] 00 20 00 00 00 00 80 00' in passive
    assert 'reports BUS-OFF (0x040 [8]' in bus_off and '2 error frames so far' in bus_off


def test_health_warns_after_error_frames_and_is_an_error_after_bus_off(link, monkeypatch):
    """health(): what the node adds to the link's /diagnostics level and to the drives' alarms,
    for HEALTH_WINDOW_S after the last such frame, then nothing."""
    bus, peer = link
    monkeypatch.setattr(canopen_link, 'SOCKETCAN_ERROR_INTERFACES', ('virtual',))
    monkeypatch.setattr(canopen_link, 'HEALTH_WINDOW_S', 0.5)
    assert bus.health() is None
    peer.send(error_frame(0x004, bytes([0, 0x20, 0, 0, 0, 0, 0x80, 0])))     # TX passive
    wait_for(lambda: bus.health() is not None, 5.0, 'error passive in health()')
    assert bus.health() == ('warn', 'CAN error frames within 0.5 s, last: controller, '
                                    'TX error passive')
    peer.send(error_frame(0x040))                                            # bus-off
    wait_for(lambda: bus.health()[0] == 'error', 5.0, 'bus-off in health()')
    assert 'bus-off' in bus.health()[1]
    wait_for(lambda: bus.health() is None, 0.5 + 1.0, 'health clear after the window')
