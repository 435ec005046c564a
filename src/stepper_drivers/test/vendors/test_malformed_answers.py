"""A well-framed but malformed answer during connect (and a read) is a LinkError that names the
request and the bytes received, for each of the four drivers, never an IndexError, a parse or
a decode error from inside the driver, and never an IdentityError.

Each vendor runs on its real transport against a peer that answers one request with crafted
bytes and the others as the drive would: an X-MIND K simulator device on a pty, an RD4
simulator unit on a pty, a scripted Modbus TCP server, a scripted CANopen node on the loopback
CAN broker.
"""

import re
import struct
import threading

import can
import pytest
from rigs_modbus_tcp import ScriptedServer
from rigs_vector_step import params as vector_step_params
from rigs_xmind_k import OtherDevice
from rigs_xmind_k import Rig as XmindKRig
from stepper_drivers.contract.drive import DriveError, IdentityError, LinkError, complete
from stepper_drivers.protocol import modbus_rtu as rtu
from stepper_drivers.protocol import xmind_k as xk
from stepper_drivers.vendors import rd4
from stepper_drivers.vendors import vector_step as vs
from stepper_drivers.vendors.vector_step import regmap as vm
from stepper_drivers.vendors.xplus_mt import VENDOR as XPLUS_MT
from stepper_sim.core.socketcand_broker import SocketcandBroker
from stepper_sim.rd4.sim import Rd4DriveSim, RtuLine


def raised(call):
    """The exception a connect (or read) raised, run to its end."""
    with pytest.raises(Exception) as err:
        complete(call())
    return err.value


def assert_names(exc, *texts):
    assert isinstance(exc, LinkError) and not isinstance(exc, IdentityError), repr(exc)
    for text in texts:
        assert text in str(exc), f'{text!r} not in {exc}'


# ------------------------------------------------------------------------------- X-MIND K
@pytest.mark.parametrize('request_, answer', [
    ('01QS,RS', b'01Y\r'),                 # a confirmation to a data request (§4.4.1)
    ('01QS,RS', b'01QS,RS\r'),             # no value (the request echoed)
    ('01QS,RS', b'01QS,RS,Z7\r'),          # a value outside §4.2.2.3
    ('01QS,RS', b'01?S,RS,D2\r'),          # one character garbled (the field's noise)
    ('01QS,RS', b'01QS,RS,D2,5\r'),        # a field too many
    ('01QS,AD', b'01Y\r'),
    ('01QS,RD', b'01QS,RD,x\r'),
    ('01QE', b'01QE,00\r'),                # a field short
    ('01QO,FA', b'01QO,FA,2\r'),           # not a bit
    ('01QO,F7', b'01Y\r'),
    ('01QA', b'01QA\r'),                   # no value
    ('01QA', b'01Y\r'),
])
def test_x_mind_k_connect_names_the_request_and_the_malformed_answer(tmp_path, request_,
                                                                       answer):
    r = XmindKRig(tmp_path, devices=[OtherDevice('a1', 1, {request_: answer})], connect=False)
    try:
        exc = raised(r.drives['a1'].connect)
        assert_names(exc, f"'{request_}'", repr(answer))
    finally:
        r.close()


def test_x_mind_k_n_to_a_data_request_is_a_link_error_and_reads_stay_clean(tmp_path):
    device = OtherDevice('a1', 1, {'01QE': b'01N\r', '01QS,CM': b'01QS,CM,2\r'})
    r = XmindKRig(tmp_path, devices=[device], connect=False)
    try:
        d = r.drives['a1']
        # a request garbled on its way draws N from any X-MIND K (§4.4.2): not an identity
        assert_names(raised(d.connect), "'01QE' was answered N")
        del device.replies['01QE']
        complete(d.connect())
        # §8 A12: CM 2 answered without its kkk is read as it came, not re-encoded (which
        # raised FrameSyntaxError out of read_register)
        assert d.read_register('QS,CM', 'string') == '01QS,CM,2'
        device.replies['01QA'] = b'01Y\r'
        with pytest.raises(DriveError, match=re.escape(repr(b'01Y\r'))) as err:
            complete(d.read_state())
        assert "b'01QA\\r'" in str(err.value)
    finally:
        r.close()


def test_x_mind_k_scan_lists_a_device_that_answers_n_or_y(tmp_path):
    """stepperctl scan read the RS of an N answer and ended with IndexError."""
    import argparse

    from stepper_drivers.contract.scanning import Deadline
    from stepper_drivers.vendors.xmind_k import scan as xmind_k_scan
    devices = [OtherDevice('a1', 1, {'01QS,RS': b'01N\r'}),
               OtherDevice('a2', 2, {'02QS,RD': b'02Y\r', '02QE': b'02N\r'})]
    r = XmindKRig(tmp_path, devices=devices, connect=False)
    r.bus.close()
    try:
        args = argparse.Namespace(addresses='1-2', port=r.line.link_path, local_echo=False,
                                  timeout=0.1, answer_delay_ms=10)
        (result,) = xmind_k_scan.scan(args, Deadline(10.0))
        one, two = result.drives
        assert one.address == 1 and 'answered N to QS,RS' in one.notes[0]
        assert two.identity['RS'] == 'D2' and 'RD' not in two.identity and 'QE' not in \
            two.identity
    finally:
        r.close()


def test_x_mind_k_parser_refuses_y_to_a_data_request():
    with pytest.raises(xk.FrameSyntaxError, match="'02Y' to the data request QA"):
        xk.parse_answer(b'02Y\r', xk.Frame(2, 'QA'))
    assert xk.parse_answer(b'02N\r', xk.Frame(2, 'QA')) == xk.Frame(2, 'N')
    assert xk.parse_answer(b'02Y\r', xk.Frame(2, 'CY')) == xk.Frame(2, 'Y')


# ------------------------------------------------------------------------------------ RD4
class CraftedUnit(Rd4DriveSim):
    """An RD4 that answers one request (function code, address) with crafted bytes."""

    def __init__(self, crafted):
        super().__init__('axis1', 1)
        self.crafted = crafted

    def handle(self, request, frame):
        reply = self.crafted.get((request.function_code, request.address))
        return reply if reply is not None else super().handle(request, frame)


def _crc(hex_text):
    return rtu.add_crc(bytes.fromhex(hex_text))


@pytest.mark.parametrize('key, reply, what', [
    ((4, 0x0C), _crc('01 04 06 00 03 00 01 01 02'), 'FC04 read 4 at 0x0C'),   # 3 of 4 words
    ((4, 0x0C), _crc('01 03 08 00 03 00 01 01 02 00 01'), 'FC04 read 4 at 0x0C'),  # FC03
    ((4, 0x0C), _crc('02 04 08 00 03 00 01 01 02 00 01'), 'FC04 read 4 at 0x0C'),  # node 2
    ((4, 0x0C), _crc('01 84 02 00'), 'FC04 read 4 at 0x0C'),          # exception of 3 bytes
    ((3, 0x00), _crc('01 03 32' + ' 00 01' * 25), 'FC03 read 26 at 0x00'),   # 25 of 26
    ((3, 0x29), _crc('01 03 04 00 00 00 84'), 'FC03 read 4 at 0x29'),      # 2 of 4
])
def test_rd4_connect_names_the_request_and_the_malformed_reply(tmp_path, key, reply, what):
    line = RtuLine([CraftedUnit({key: reply})], tmp_path / 'rd4.pty', baud_switch=0x03)
    line.start()
    bus = rd4.make_bus({'port': str(tmp_path / 'rd4.pty'), 'baudrate': 19200, 'parity': 'N',
                        'timeout_s': 0.1})
    bus.open()
    try:
        d = rd4.make_drive(bus, 'axis1', {'node_id': 1, 'steps_per_rev': 1024.0})
        exc = raised(d.connect)
        # the frame as it came, or the part of it that came before the silence
        assert_names(exc, what, reply[:5].hex(' '))
    finally:
        bus.close()
        line.stop()


# ------------------------------------------------------------------------------ X-PLUS MT
XPLUS_REGISTERS = {1162: 1, 1081: 12800, 1097: 1000, 1088: 15, 1001: 0x0250}


def xplus_peer(target, malformed):
    """A scripted X-PLUS MT: FC03 from XPLUS_REGISTERS, writes echoed; the read at `target`
    answered malformed(request ADU)."""
    def answer(adu):
        tid, unit, fc, address, count = adu[0:2], adu[6], adu[7], *struct.unpack('>HH', adu[8:12])
        if fc == 3 and address == target:
            return malformed(adu)
        if fc == 3:
            data = b''.join(XPLUS_REGISTERS.get(address + i, 0).to_bytes(2, 'big')
                            for i in range(count))
            pdu = bytes((3, len(data))) + data
        else:
            pdu = adu[7:12]
        return tid + b'\x00\x00' + (len(pdu) + 1).to_bytes(2, 'big') + bytes((unit,)) + pdu
    return ScriptedServer(answer)


def _adu(adu, pdu, unit=None, protocol=b'\x00\x00'):
    unit = adu[6] if unit is None else unit
    return adu[0:2] + protocol + (len(pdu) + 1).to_bytes(2, 'big') + bytes((unit,)) + pdu


@pytest.mark.parametrize('target, malformed, shown', [
    (1152, lambda adu: _adu(adu, b'\x03\x04\x00\x33\x00\x00'), '03 04 00 33 00 00'),  # 2 of 8
    (1152, lambda adu: _adu(adu, b'\x04\x02\x00\x33'), '04 02 00 33'),             # FC04
    (1152, lambda adu: _adu(adu, b'\x03\x02\x00\x33', unit=9), '03 02 00 33'),      # unit 9
    (1162, lambda adu: _adu(adu, b'\x83\x02\x00'), '83 02 00'),           # 3-byte exception
    (1162, lambda adu: _adu(adu, b'\x03\x02\x00\x01', protocol=b'\x3f\x00'), '3f 00'),  # MBAP
    (1081, lambda adu: _adu(adu, b'\x03\x22' + bytes(30)), '03 22 00'),      # 15 of 17 words
])
def test_x_plus_mt_connect_names_the_request_and_the_malformed_reply(target, malformed, shown):
    srv = xplus_peer(target, malformed)
    bus = XPLUS_MT.make_bus({'host': '127.0.0.1', 'port': srv.port, 'timeout_s': 0.3})
    bus.open()
    try:
        d = XPLUS_MT.make_drive(bus, 'axis1', {'unit_id': 1})
        assert_names(raised(d.connect), 'FC03 read', f'at {target}', shown)
    finally:
        bus.close()
        srv.close()


def test_x_plus_mt_peer_answers_a_whole_connect():
    """The scripted peer itself is a valid X-PLUS MT (the cases above differ in one reply)."""
    srv = xplus_peer(None, None)
    bus = XPLUS_MT.make_bus({'host': '127.0.0.1', 'port': srv.port, 'timeout_s': 0.3})
    bus.open()
    try:
        assert XPLUS_MT.make_drive(bus, 'axis1', {'unit_id': 1}).connect()['product'] == \
            'X-PLUS MT'
    finally:
        bus.close()
        srv.close()


# ---------------------------------------------------------------------------- Vector Step
NODE_ID = 5
PEER_OBJECTS = {(vm.DEVICE_TYPE, 0): vm.DEVICE_TYPE_VALUE,
                (vm.IDENTITY_OBJECT, 1): vm.VENDOR_ID_AEC}


class SdoPeer:
    """A CANopen node on the broker that answers SDO uploads: PEER_OBJECTS expedited, the
    object `target` with the crafted frame."""

    def __init__(self, port, target, crafted):
        self.target, self.crafted = target, crafted
        self.bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port,
                           channel='can0', tcp_tune=True)
        self.lock = threading.Lock()
        self.notifier = can.Notifier(self.bus, [self._on], 0.1)

    def _on(self, msg):
        if msg.arbitration_id != 0x600 + NODE_ID or len(msg.data) != 8 or msg.data[0] != 0x40:
            return
        index, sub = int.from_bytes(msg.data[1:3], 'little'), msg.data[3]
        if (index, sub) == self.target:
            data = self.crafted
        elif (index, sub) in PEER_OBJECTS:
            data = bytes((0x43,)) + msg.data[1:4] + PEER_OBJECTS[index, sub].to_bytes(4, 'little')
        else:
            data = bytes((0x80,)) + msg.data[1:4] + (0x06020000).to_bytes(4, 'little')
        with self.lock:
            self.bus.send(can.Message(arbitration_id=0x580 + NODE_ID, data=data,
                                      is_extended_id=False))

    def close(self):
        self.notifier.stop()
        self.bus.shutdown()


@pytest.mark.parametrize('crafted', [
    bytes.fromhex('4b 18 10 01 bc 00 00 00'),        # 2 bytes for the UNSIGNED32 vendor-ID
    bytes.fromhex('43 19 10 01 bc 00 00 00'),        # the answer of another object
    bytes.fromhex('60 18 10 01 00 00 00 00'),        # a download answer to an upload
    bytes.fromhex('43 18 10 01 bc'),                  # 5 bytes: not an SDO frame
])
def test_vector_step_connect_names_the_request_and_the_malformed_answer(crafted):
    broker = SocketcandBroker(port=0, ready_delay_s=0.01)
    broker.start()
    peer = SdoPeer(broker.port, (vm.IDENTITY_OBJECT, 1), crafted)
    p = vector_step_params(**{'can.port': broker.port, 'timeout_s': 0.2, 'node_id': NODE_ID})
    bus = vs.make_bus(p)
    bus.open()
    try:
        d = vs.make_drive(bus, 'axis1', p)
        assert_names(raised(d.connect), 'read 0x1018:01', crafted.hex(' '))
    finally:
        bus.close()
        peer.close()
        broker.stop()
