"""ModbusTcpBus against a real pymodbus 3.16.1 TCP server on 127.0.0.1 (no mocks)."""

import asyncio
import contextlib
import socket
import threading
import time

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
import pytest
from rigs_modbus_tcp import ScriptedServer
from stepper_drivers.contract.drive import DriveError, LinkError
from stepper_drivers.protocol.modbus_tcp import ModbusExceptionError, ModbusTcpBus, make_bus

READ_ONLY = 1001


def _free_port():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def _silent_server_bus(timeout_s: float):
    """An open bus to a server that accepts the connection and never answers: (bus, port)."""
    with socket.socket() as silent:
        silent.bind(('127.0.0.1', 0))
        silent.listen()
        port = silent.getsockname()[1]
        b = ModbusTcpBus('127.0.0.1', port, timeout_s=timeout_s)
        b.open()
        try:
            yield b, port
        finally:
            b.close()


class Server:
    """A 100-register device (address 1000..1099) in a thread; 1001 is read-only."""

    def __init__(self):
        self.port = _free_port()
        self.writes = []
        self.loop = asyncio.new_event_loop()
        self.ready = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    async def action(self, fc, block_start, start, count, regs, set_values):
        if set_values is not None:
            self.writes.append((fc, start, list(set_values)))
            if start <= READ_ONLY < start + count:
                return ExcCodes.ILLEGAL_ADDRESS
        return None

    async def _main(self):
        device = SimDevice(id=1, simdata=[SimData(address=1000, count=100, values=0,
                                                  datatype=DataType.REGISTERS)],
                           action=self.action)
        self.server = ModbusTcpServer(device, address=('127.0.0.1', self.port),
                                      framer=FramerType.SOCKET)
        self.ready.set()
        await self.server.serve_forever()

    def _run(self):
        asyncio.set_event_loop(self.loop)
        self.loop.run_until_complete(self._main())

    def start(self):
        self.thread.start()
        assert self.ready.wait(5)
        deadline = time.monotonic() + 5
        while True:            # listening once a TCP connect succeeds
            try:
                socket.create_connection(('127.0.0.1', self.port), timeout=1).close()
                return self
            except OSError:
                assert time.monotonic() < deadline, 'server did not listen'
                time.sleep(0.01)

    def stop(self):
        asyncio.run_coroutine_threadsafe(self.server.shutdown(), self.loop).result(5)
        self.thread.join(5)
        self.loop.close()


@pytest.fixture
def server():
    srv = Server().start()
    yield srv
    srv.stop()


@pytest.fixture
def bus(server):
    b = ModbusTcpBus('127.0.0.1', server.port, timeout_s=0.5)
    b.open()
    yield b
    b.close()


def test_write_and_read_back(bus, server):
    bus.write_registers(1, 1042, [0xA980, 0x0003])            # FC16
    bus.write_register(1, 1040, 0x000F)                        # FC06
    assert bus.read_holding_registers(1, 1040, 4) == [0x000F, 0, 0xA980, 0x0003]
    assert [w[0] for w in server.writes] == [16, 6]
    assert bus.counters() == {'transactions': 3, 'errors': 0, 'exceptions': 0, 'timeouts': 0,
                              'stale_replies': 0}
    assert bus.is_open and bus.description == f'modbus tcp 127.0.0.1:{server.port}'


def test_exception_reply_names_fc_address_and_code(bus):
    with pytest.raises(DriveError) as err:
        bus.write_registers(1, 1000, [1, 2, 3])
    assert not isinstance(err.value, LinkError)
    assert isinstance(err.value, ModbusExceptionError) and err.value.code == 0x02
    assert 'unit 1: FC16 write 3 at 1000: exception 0x02 ILLEGAL DATA ADDRESS' in str(err.value)
    assert err.value.function_code == 0x10
    with pytest.raises(ModbusExceptionError,
                       match='FC06 write 0x0005 at 1001: exception 0x02 ILLEGAL DATA'):
        bus.write_register(1, 1001, 5)
    with pytest.raises(ModbusExceptionError, match=r'FC03 read 5 at 1098: exception 0x02'):
        bus.read_holding_registers(1, 1098, 5)                         # past the end of the map
    assert bus.counters()['exceptions'] == 3
    assert bus.read_holding_registers(1, 1002, 1) == [0]               # the link is still fine


def test_counts_checked_before_sending(bus):
    with pytest.raises(DriveError, match='read of 126 registers at 1000: count 126 outside '
                                         r'1\.\.125'):
        bus.read_holding_registers(1, 1000, 126)
    with pytest.raises(DriveError, match='count 124 outside 1..123'):
        bus.write_registers(1, 1000, [0] * 124)
    assert bus.transactions == 0


def test_threads_share_one_bus(bus):
    errors = []

    def worker(k):
        try:
            for i in range(50):
                bus.write_registers(1, 1010 + k, [i])
                assert bus.read_holding_registers(1, 1010 + k, 1) == [i]
        except Exception as exc:    # noqa: BLE001 - collected and asserted below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert errors == []
    assert bus.transactions == 400 and bus.errors == 0


def test_connection_refused_names_host_port_and_timeout():
    port = _free_port()
    b = make_bus({'host': '127.0.0.1', 'port': port, 'timeout_s': 0.2})
    with pytest.raises(LinkError, match=rf'127.0.0.1:{port} .*timeout 0.2 s'):
        b.open()
    assert not b.is_open
    with pytest.raises(LinkError, match='not connected'):
        b.read_holding_registers(1, 1001, 1)


def test_silent_server_times_out_then_reopens():
    with _silent_server_bus(0.1) as (b, port):
        with pytest.raises(LinkError, match=rf'127.0.0.1:{port} unit 1: FC03 read 1 at 1001: '
                                            r'no answer within 0.1 s'):
            b.read_holding_registers(1, 1001, 1)
        assert b.counters()['timeouts'] == 1 and b.errors == 1
        b.close()
        assert not b.is_open


def test_a_connection_reset_by_the_peer_is_a_link_error_in_one_line():
    """A server that accepts and then resets (RST) the connection: pymodbus lets the
    ConnectionResetError through, which would end in a traceback."""
    import struct
    with socket.socket() as listener:
        listener.bind(('127.0.0.1', 0))
        listener.listen()
        port = listener.getsockname()[1]
        b = ModbusTcpBus('127.0.0.1', port, timeout_s=1.0)
        b.open()
        peer, _ = listener.accept()

        def reset_after_the_request():
            peer.recv(260)                # the request arrived: now reset, with no reply
            peer.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack('ii', 1, 0))
            peer.close()                  # linger 0: the close sends RST
        server = threading.Thread(target=reset_after_the_request)
        server.start()
        with pytest.raises(LinkError, match=rf'127.0.0.1:{port} unit 1: FC03 read 1 at '
                                            r'1001: ') as err:
            b.read_holding_registers(1, 1001, 1)
        server.join()
        assert '\n' not in str(err.value)
        assert b.errors == 1
        b.close()


def _fc03_reply(request_adu, value):
    return (request_adu[0:2] + b'\x00\x00\x00\x05' + request_adu[6:7] + b'\x03\x02'
            + value.to_bytes(2, 'big'))


def test_a_late_reply_to_a_timed_out_request_is_not_taken_for_the_next_one():
    """The first request gets no answer in time; its reply arrives together with the reply to
    the second: the bus matches transaction ids and returns the second's value (111, the
    first request's register read back as the second's, would be a wrong drive value)."""
    first = []

    def answer(adu):
        if not first:
            first.append(adu)
            return None                                       # silent: the bus times out
        return _fc03_reply(first[0], 111) + _fc03_reply(adu, 222)

    srv = ScriptedServer(answer)
    b = ModbusTcpBus('127.0.0.1', srv.port, timeout_s=0.2)
    b.open()
    try:
        with pytest.raises(LinkError, match='no answer within 0.2 s'):
            b.read_holding_registers(1, 1001, 1)
        assert b.read_holding_registers(1, 1001, 1) == [222]
        assert b.counters()['stale_replies'] == 1
    finally:
        b.close()
        srv.close()


def test_a_reply_that_does_not_fit_the_request_is_a_link_error():
    """A reply from another unit id, and one whose byte count does not match the request:
    LinkError naming what was wrong (the node reconnects), never registers taken from it."""
    replies = iter([
        lambda adu: adu[0:4] + b'\x00\x05\x07' + b'\x03\x02\x00\x01',      # unit 7 answers
        lambda adu: adu[0:4] + b'\x00\x05' + adu[6:7] + b'\x03\x02\x00\x01',  # 1 of 2 words
    ])
    srv = ScriptedServer(lambda adu: next(replies)(adu))
    b = ModbusTcpBus('127.0.0.1', srv.port, timeout_s=0.5)
    b.open()
    try:
        with pytest.raises(LinkError, match='unit 1: FC03 read 1 at 1001: reply from unit 7'):
            b.read_holding_registers(1, 1001, 1)
        with pytest.raises(LinkError, match='FC03 read 2 at 1001: 2 data bytes for 2 registers'):
            b.read_holding_registers(1, 1001, 2)
        assert b.errors == 2 and b.exceptions == 0
    finally:
        b.close()
        srv.close()


def test_a_reply_taken_later_comes_in_pieces_and_the_next_request_waits_for_an_untaken_one():
    """send_request() then take_reply(), which never blocks: None until the whole reply came
    (here in two pieces). A request whose reply nobody took (the poll group gave the link back
    before it came): the next request goes out only after its reply, which is dropped; never
    two requests in flight (pymodbus answers only the first of two that arrive together)."""
    import select

    from stepper_drivers.protocol.modbus import FC_READ_HOLDING_REGISTERS, read_request
    rest = threading.Event()
    pipelined = []
    with socket.create_server(('127.0.0.1', 0)) as listener:
        port = listener.getsockname()[1]

        def serve():
            peer, _ = listener.accept()
            with peer:
                def request():                    # an FC03 request is 12 bytes; no more read
                    return peer.recv(12, socket.MSG_WAITALL)
                reply = _fc03_reply(request(), 111)
                peer.sendall(reply[:5])
                rest.wait(5)
                peer.sendall(reply[5:])
                untaken = request()
                time.sleep(0.1)                   # a slow answer, while the bus waits for it
                pipelined.append(bool(select.select([peer], [], [], 0)[0]))
                peer.sendall(_fc03_reply(untaken, 222))
                peer.sendall(_fc03_reply(request(), 333))
                peer.recv(1)
        server = threading.Thread(target=serve, daemon=True)
        server.start()
        b = ModbusTcpBus('127.0.0.1', port, timeout_s=0.5)
        b.open()
        try:
            request = read_request(1, FC_READ_HOLDING_REGISTERS, 1001, 1)
            b.send_request(request)
            deadline = time.monotonic() + 0.2
            while time.monotonic() < deadline:     # the first piece, never the whole reply
                assert b.take_reply(request) is None
            rest.set()
            deadline = time.monotonic() + 2.0
            while (words := b.take_reply(request)) is None:
                assert time.monotonic() < deadline, 'the rest of the reply did not come'
            assert words == [111]
            b.send_request(request)                # never taken
            assert b.read_holding_registers(1, 1001, 1) == [333]
            assert pipelined == [False], 'the next request went out before the reply'
            assert b.counters() == {'transactions': 3, 'errors': 0, 'exceptions': 0,
                                    'timeouts': 0, 'stale_replies': 1}
        finally:
            b.close()
            server.join(2)


def test_an_untaken_request_without_a_reply_is_a_link_error_naming_it():
    """The next request waits for it at most timeout_s from its sending, then the link is
    lost, naming the request that got no answer."""
    from stepper_drivers.protocol.modbus import FC_READ_HOLDING_REGISTERS, read_request
    with _silent_server_bus(0.1) as (b, port):
        b.send_request(read_request(1, FC_READ_HOLDING_REGISTERS, 1001, 21))
        t0 = time.monotonic()
        with pytest.raises(LinkError, match=rf'127.0.0.1:{port} unit 1: FC03 read 21 at '
                                            r'1001: no answer within 0.1 s'):
            b.read_holding_registers(1, 1040, 1)
        assert time.monotonic() - t0 < 2 * 0.1      # not its timeout and then our own
        assert b.counters()['timeouts'] == 1 and b.transactions == 1
