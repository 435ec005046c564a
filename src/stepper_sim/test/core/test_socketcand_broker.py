"""The loopback socketcand broker: stock python-can clients share one simulated CAN bus."""

import logging
import socket
import subprocess
import sys

import can
import pytest
from stepper_sim.core.socketcand_broker import SocketcandBroker

logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)


def client(port, channel='can0'):
    return can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel=channel,
                   tcp_tune=True)


def frame(can_id, data):
    return can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=can_id > 0x7FF)


@pytest.fixture
def broker():
    b = SocketcandBroker(port=0, ready_delay_s=0.01)
    b.start()
    yield b
    b.stop()


def test_frames_reach_every_other_client_in_order_and_not_the_sender(broker):
    a, b, c = client(broker.port), client(broker.port), client(broker.port)
    try:
        sent = [frame(0x601, [0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0]), frame(0x701, []),
                frame(0x181, [0x37, 0x06, 0x01]), frame(0x18FF0001, [1, 2, 3, 4, 5, 6, 7, 8])]
        for msg in sent:
            a.send(msg)
        for listener in (b, c):
            got = [listener.recv(2.0) for _ in sent]
            assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in got] == \
                [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in sent]
        assert a.recv(0.1) is None                                  # no echo to the sender
        c.send(frame(0x581, [0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x04, 0x00]))
        assert bytes(a.recv(2.0).data) == bytes.fromhex('4300100092010400')
        assert bytes(b.recv(2.0).data) == bytes.fromhex('4300100092010400')
    finally:
        for bus in (a, b, c):
            bus.shutdown()
    assert broker.frames_in == 5 and broker.frames_out == 10


def test_channels_are_separate_buses(broker):
    a, b = client(broker.port, 'can0'), client(broker.port, 'can1')
    try:
        a.send(frame(0x100, [1]))
        assert b.recv(0.2) is None
    finally:
        a.shutdown()
        b.shutdown()


def test_burst_without_loss(broker):
    a, b = client(broker.port), client(broker.port)
    try:
        n = 3000
        for i in range(n):
            a.send(frame(0x281, i.to_bytes(4, 'little')))
        for i in range(n):
            msg = b.recv(5.0)
            assert msg is not None and int.from_bytes(msg.data, 'little') == i
    finally:
        a.shutdown()
        b.shutdown()


def test_listens_on_loopback_only():
    with pytest.raises(ValueError, match='loopback'):
        SocketcandBroker(host='0.0.0.0')
    with SocketcandBroker() as b:
        with socket.create_connection(('127.0.0.1', b.port), 1.0) as s:
            assert s.recv(16) == b'< hi >'
            assert s.getpeername()[0] == '127.0.0.1'


def test_runs_as_a_module_and_prints_its_port():
    proc = subprocess.Popen([sys.executable, '-m', 'stepper_sim.core.socketcand_broker',
                             '--port', '0'], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith('socketcand_broker: listening on 127.0.0.1:'), line
        port = int(line.rsplit(':', 1)[1])
        a, b = client(port), client(port)
        a.send(frame(0x80, []))
        assert b.recv(2.0).arbitration_id == 0x80
        a.shutdown()
        b.shutdown()
    finally:
        proc.terminate()
        assert proc.wait(10) == 0
