"""X-PLUS MT simulator checked by an independent client: plain pymodbus ModbusTcpClient.

Register numbers and values come from the manual (§12 CW sequence, T13/T14, §13 registers) and
spec/xplus_mt.md §3.5/§10/§12; 32-bit words are packed here by hand, not with the driver's codec.
"""

import json
import os
import socket
import struct
import time

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException
import pytest
from stepper_sim.harness import wait_for
from stepper_sim.xplus_mt.sim import XplusMtDriveConfig, XplusMtSim

SW, CW, MODE, DISPLAY = 1001, 1040, 1041, 1002
POS, VEL, ERR_REG, ERR_CODE = 1004, 1020, 1006, 1007
TARGET, PROFILE_V, PROFILE_A, TARGET_V, PROFILE_D = 1042, 1044, 1046, 1048, 1072


def words32(value: int, order: str = 'little') -> list[int]:
    raw = value & 0xFFFFFFFF
    low, high = raw & 0xFFFF, raw >> 16
    return [low, high] if order == 'little' else [high, low]


def value32(words, order: str = 'little', signed: bool = True) -> int:
    low, high = (words[0], words[1]) if order == 'little' else (words[1], words[0])
    raw = high << 16 | low
    return raw - (1 << 32) if signed and raw & 0x80000000 else raw


class Client:
    """Tiny independent Modbus helper around ModbusTcpClient (unit = device_id)."""

    def __init__(self, port: int, order: str = 'little', timeout: float = 1.0):
        self.mb = ModbusTcpClient('127.0.0.1', port=port, timeout=timeout, retries=0)
        assert self.mb.connect()
        self.order = order

    def read(self, address, count=1, unit=1):
        rr = self.mb.read_holding_registers(address, count=count, device_id=unit)
        assert not rr.isError(), rr
        return rr.registers

    def exception(self, rr):
        assert rr.isError()
        return rr.exception_code

    def sw(self, unit=1):
        return self.read(SW, unit=unit)[0]

    def read32(self, address, unit=1, signed=True):
        return value32(self.read(address, 2, unit), self.order, signed)

    def write(self, address, value, unit=1):
        rr = self.mb.write_register(address, value, device_id=unit)
        assert not rr.isError(), rr

    def write32(self, address, value, unit=1):
        rr = self.mb.write_registers(address, words32(value, self.order), device_id=unit)
        assert not rr.isError(), rr

    def cw(self, value, unit=1):
        self.write(CW, value, unit)

    def enable(self, unit=1, mode=None):
        if mode is not None:
            self.write(MODE, mode, unit)
        for cw, expected_state in ((0x0006, 0x0021), (0x0007, 0x0023), (0x000F, 0x0027)):
            self.cw(cw, unit)
            wait_for(lambda want=expected_state: self.sw(unit) & 0x006F == want, 1.0)

    def close(self):
        self.mb.close()


DRIVES = [XplusMtDriveConfig('axis1', unit_id=1, home_switch_steps=20_000.0,
                             home_switch_width_steps=6_400.0, limit_neg_steps=-200_000.0,
                             limit_pos_steps=200_000.0, index_phase_steps=21_000.0),
          XplusMtDriveConfig('axis2', unit_id=2, home_switch_steps=None)]


@pytest.fixture
def sim(tmp_path):
    s = XplusMtSim(port=0, drives=DRIVES, storage_dir=str(tmp_path))
    s.start()
    yield s
    s.stop()


@pytest.fixture
def client(sim):
    c = Client(sim.port)
    yield c
    c.close()


def test_identity_and_power_on_values(sim, client):
    assert client.sw() == 0x0270                      # SOD, HV present (spec §10.2)
    assert client.sw(unit=2) == 0x0270
    ident = client.read(1152, 8)
    assert value32(ident[0:2]) == 51                  # Software Version (T15 default)
    assert value32(ident[6:8], signed=False) == 100_001   # serial number of unit 1
    assert value32(client.read(1158, 2, unit=2), signed=False) == 100_002
    assert client.read(1162) == [1]                   # little endian (default)
    assert client.read(DISPLAY) == [0] and client.read(ERR_REG, 2) == [0, 0]
    assert client.read(PROFILE_V, 4) == words32(24_000) + words32(640_000)   # App.1 defaults
    fc4 = client.mb.read_input_registers(1001, count=2, device_id=1)
    assert fc4.registers == client.read(1001, 2)      # FC04 serves the same image


def test_control_word_sequence_status_words(client):
    # §12 "requested Control Word command sequence"; effects visible at once (<= 12 ms)
    for cw, sw in ((0x0006, 0x0231), (0x0007, 0x0233), (0x000F, 0x0637),
                   (0x0007, 0x0233), (0x000F, 0x0637), (0x0006, 0x0231),
                   (0x000F, 0x0637), (0x0000, 0x0270)):
        client.cw(cw)
        assert client.sw() == sw, f'CW 0x{cw:04X}'
    client.cw(0x0007)                                  # Switch On in SOD: no transition
    assert client.sw() == 0x0270


def test_without_hv_switch_on_is_refused_until_hv_is_stable(sim, client):
    assert sim.inject_fault('axis1', 'hv_off')[0]
    assert client.sw() == 0x0260
    client.cw(0x0006)
    assert client.sw() == 0x0221                       # §12: RTSO without High Voltage
    client.cw(0x0007)
    assert client.sw() == 0x0221                       # "the transition cannot be completed"
    t_on = time.monotonic()
    assert sim.inject_fault('axis1', 'hv_on')[0]
    assert client.sw() == 0x0231
    wait_for(lambda: client.sw() == 0x0233, 2.0)       # A4: the held Switch On completes
    assert time.monotonic() - t_on >= 0.45             # §12 transition 3: >= 500 ms of HV


def test_profile_position_absolute_and_relative(sim, client):
    client.enable(mode=1)
    assert client.read(DISPLAY) == [1]
    client.write32(TARGET, 24_000)
    client.write32(PROFILE_V, 100_000)
    client.write32(PROFILE_A, 1_000_000)
    client.cw(0x001F)                                  # bit 4 edge, absolute
    sw = client.sw()
    assert sw & 0x1000 and not sw & 0x0400             # set point acknowledged, moving
    assert sw == 0x1237
    client.cw(0x000F)
    assert client.sw() == 0x0237                       # ack follows bit 4 (A23)
    wait_for(lambda: client.sw() == 0x0637, 3.0)       # target reached
    assert client.read32(POS) == 24_000
    assert sim.drives['axis1'].true_position_steps == 24_000
    client.write32(TARGET, -4_000)
    client.cw(0x005F)                                  # relative: 24000 - 4000
    wait_for(lambda: client.sw() == 0x1637, 3.0)       # reached, bit 4 still held
    assert client.read32(POS) == 20_000
    client.cw(0x004F)
    assert client.sw() == 0x0637


def test_multi_set_point_retarget_and_halt(sim, client):
    client.enable(mode=1)
    client.write32(PROFILE_V, 100_000)
    client.write32(PROFILE_A, 400_000)
    client.write32(TARGET, 200_000)
    client.cw(0x003F)                                  # change set immediately
    client.cw(0x002F)
    wait_for(lambda: client.read32(POS) > 20_000, 2.0)
    client.write32(TARGET, 30_000)                     # not monotonous: stop, come back
    client.cw(0x003F)
    wait_for(lambda: client.sw() & 0x0400, 5.0)
    assert client.read32(POS) == 30_000
    client.cw(0x002F)
    # Halt during a move: decelerate, bit 10 = 1 at rest; release: bit 10 = 0, no restart
    client.write32(TARGET, 150_000)
    client.cw(0x003F)
    wait_for(lambda: client.read32(POS) > 40_000, 2.0)
    client.cw(0x013F)
    wait_for(lambda: client.sw() & 0x0400, 2.0)
    stopped = client.read32(POS)
    assert 40_000 < stopped < 150_000
    client.cw(0x003F)                                  # Halt released, bit 4 still high
    assert not client.sw() & 0x0400                    # §13 bit 8: Target Reached -> 0
    time.sleep(0.05)                                   # nothing moves meanwhile
    assert client.read32(POS) == stopped


def test_quick_stop_active_and_back(client):
    client.enable(mode=1)
    client.write32(PROFILE_V, 100_000)
    client.write32(PROFILE_A, 200_000)
    client.write32(TARGET, 500_000)
    client.cw(0x001F)
    client.cw(0x000F)
    wait_for(lambda: client.read32(VEL) > 50_000, 2.0)
    client.cw(0x0002)                                  # quick stop (T13), transition 11
    assert client.sw() == 0x0217                       # QSA, decelerating, bit 10 = 0
    wait_for(lambda: client.sw() == 0x0617, 2.0)       # at rest: bit 10 = 1, current on
    client.cw(0x000F)                                  # transition 16 (option code 5)
    assert client.sw() == 0x0637
    client.cw(0x0002)
    client.cw(0x0000)                                  # transition 12
    assert client.sw() == 0x0270


def test_profile_velocity_run_and_halt(client):
    client.write(MODE, 3)
    client.cw(0x0006)
    wait_for(lambda: client.sw() == 0x1231, 1.0)       # PV at rest: zero speed bit 12
    client.cw(0x000F)
    assert client.sw() == 0x1237                       # §12: "0x1237" in OE (A9)
    client.write32(TARGET_V, -50_000)                  # signed (A8): reverse
    client.write32(PROFILE_A, 1_000_000)
    client.write32(PROFILE_D, 1_000_000)
    client.cw(0x001F)                                  # A10: bit 4 edge starts
    wait_for(lambda: client.read32(VEL) == -50_000, 2.0)
    wait_for(lambda: client.sw() & 0x0400, 1.0)        # |v| > 1062 for 1063 ms: bit 10
    assert not client.sw() & 0x1000
    p1 = client.read32(POS)
    time.sleep(0.05)
    assert client.read32(POS) < p1 - 1_000
    client.write32(TARGET_V, 30_000)                   # on the fly, through zero
    wait_for(lambda: client.read32(VEL) == 30_000, 2.0)
    client.cw(0x011F)                                  # Halt: ramp down on 1072
    wait_for(lambda: client.read32(VEL) == 0, 2.0)
    wait_for(lambda: client.sw() == 0x1237, 1.0)


def test_pv_following_error_goes_through_fault_reaction_active(sim, client):
    client.write(1085, 2)                              # following error -> fault
    client.enable(mode=3)
    client.write32(TARGET_V, 100_000)
    client.write32(PROFILE_A, 1_000_000)
    client.write32(PROFILE_D, 200_000)                 # 0.5 s coast-down
    client.cw(0x001F)
    wait_for(lambda: client.read32(VEL) == 100_000, 2.0)
    ok, message = sim.inject_fault('axis1', 'drive_fault', 0x8611, 0)
    assert ok and 'FAULT REACTION ACTIVE' in message
    assert client.sw() == 0x201F                       # §13 "Register 1085" 0x02, A6
    wait_for(lambda: client.sw() == 0x1218, 2.0)       # Fault once stopped (C)
    assert client.read(ERR_CODE) == [0x8611]
    client.cw(0x0000)
    client.cw(0x0080)                                  # D: fault reset
    assert client.sw() & 0x004F == 0x0040


@pytest.mark.parametrize('method,edge,index', [(19, 20_000, False), (21, 26_400, False),
                                               (5, 26_400, True), (35, None, False)])
def test_homing_methods_with_the_switch(sim, client, method, edge, index):
    client.write(1088, 14)                             # IC0 = 0: I0 is the proximity input
    client.write(MODE, 6)
    client.write(1050, method)
    client.write32(1052, 100_000)                      # search for switch
    client.write32(1054, 16_000)                       # search for zero (start-stop)
    client.write32(1056, 1_000_000)
    client.write32(1058, 1_000)                        # Home Offset (G11)
    if method in (5, 21):                              # negative home switch: start above it
        sim.drives['axis1'].axis.motion.set_position(0)
        sim.drives['axis1'].axis.motion.move_to(40_000, 400_000, 4_000_000)
        wait_for(lambda: not sim.drives['axis1'].axis.moving, 2.0)
    client.enable()
    assert client.sw() == 0x0637                       # IDLE: bits 13/12/10 = 0/0/1
    client.cw(0x001F)                                  # homing start
    if method != 35:
        assert client.sw() & 0x3400 == 0               # in progress
    wait_for(lambda: client.sw() == 0x1637, 5.0)       # homing complete + target reached
    assert client.read32(POS) == 1_000
    raw = sim.drives['axis1'].axis.raw_position_steps
    if index:                                          # first index right of the edge 26400
        assert raw == pytest.approx(21_000 + 12_800, abs=1e-6)
    elif edge is not None:
        assert raw == pytest.approx(edge, abs=1e-6)


def test_homing_errors(sim, client):
    client.write(MODE, 6)
    client.write(1050, 19)
    client.write32(1054, 3_200)
    client.enable()
    client.cw(0x001F)                                  # 1088 = 15: I0 not a proximity input
    assert client.sw() == 0x2637                       # bit 13 error, bit 12 0, bit 10 1
    client.cw(0x000F)
    client.write(1088, 14)
    client.write(1050, 3)
    client.cw(0x0007)
    client.write(1085, 17)                             # no encoder: index methods refused
    client.cw(0x000F)
    client.cw(0x001F)
    assert client.sw() == 0x2637
    client.cw(0x000F)
    client.write(1050, 2)                              # not an X-PLUS MT method
    client.cw(0x001F)
    assert client.sw() == 0x2637


def test_fault_injection_alarm_log_and_reset(sim, client):
    client.enable(mode=1)
    ok, message = sim.inject_fault('axis1', 'drive_fault', 0x4310, 0)
    assert ok and 'Error drive excessive temperature' in message
    assert client.sw() == 0x0218                       # Fault, HV present, current off
    assert client.read(ERR_REG, 2) == [1, 0x4310]
    log = client.read(1220, 20)
    assert log[1] == 0x4310 and log[0] <= 2 and log[2:] == [0] * 18
    client.cw(0x0000)
    client.cw(0x0080)                                  # cause still present: refused (G15)
    assert client.sw() == 0x0218
    assert sim.inject_fault('axis1', 'clear_fault', 0x4310, 0)[0]
    client.cw(0x0000)
    client.cw(0x0080)
    assert client.sw() == 0x0270                       # transition 15
    assert client.read(ERR_REG, 2) == [0, 0]
    assert client.read(1221) == [0x4310]               # the log is kept
    client.write(1240, 1)
    assert client.read(1220, 20) == [0] * 20
    ok, message = sim.inject_fault('axis1', 'drive_fault', 0x1234, 0)
    assert not ok and '0x8611' in message
    ok, message = sim.inject_fault('axis1', 'explode', 0, 0)
    assert not ok and 'drive_fault' in message and 'late_reply' in message
    assert client.sw(unit=2) == 0x0270                 # the other drive is untouched


def test_watchdog_faults_without_traffic(sim, client):
    client.write(1097, 100)                            # §13 "Register 1097": 100 ms
    time.sleep(0.25)                                   # the silence under test
    assert client.sw() & 0x004F == 0x0008
    assert client.read(ERR_CODE) == [0x8400]           # configurable code (A15)
    client.write(1097, 0)
    client.cw(0x0000)
    client.cw(0x0080)
    assert client.sw() == 0x0270


def test_a_stalled_simulator_does_not_blame_the_master(sim, client):
    """A starved host stops the simulator's loop; requests wait in the socket meanwhile. A real
    drive would have seen them in time, so the stall does not count against the master."""
    client.write(1097, 200)
    sim._loop.call_soon_threadsafe(time.sleep, 0.5)    # the server loop stalls for 0.5 s
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:                 # the master polls all along
        assert client.sw() & 0x004F != 0x0008          # never Fault
        time.sleep(0.02)
    client.write(1097, 0)


def test_save_restore_and_load_at_start(sim, client, tmp_path):
    client.write(1080, 50)                             # Current Ratio (storable **)
    client.write(1122, 1234)                           # User Data RAM (not storable)
    client.write(1260, 0x6173)
    path = tmp_path / 'xplus_mt_unit1.json'
    stored = json.loads(path.read_text())
    assert stored['registers']['1080'] == 50 and '1122' not in stored['registers']
    assert stored['names']['1080'] == 'CURRENT_RATIO'
    assert client.read(1260) == [0]
    assert client.exception(client.mb.write_register(1260, 0x1234, device_id=1)) == 3
    client.write(1261, 0x6F6C)                         # restore defaults (RAM)
    assert client.read(1080) == [70]
    client.close()
    sim.stop()
    again = XplusMtSim(port=0, drives=DRIVES, storage_dir=str(tmp_path))
    again.start()
    try:
        c = Client(again.port)
        assert c.read(1080) == [50] and c.read(1122) == [0]
        assert not os.path.exists(tmp_path / 'xplus_mt_unit2.json')
        c.close()
    finally:
        again.stop()


def test_big_endian_word_order_and_fc06_latch(tmp_path):
    sim = XplusMtSim(port=0, drives=DRIVES, word_order='big', storage_dir=str(tmp_path))
    sim.start()
    try:
        c = Client(sim.port, order='big')
        assert c.read(1162) == [0]
        c.mb.write_registers(TARGET, [0x0003, 0xA980], device_id=1)     # G2: 240000 in BE
        assert c.read32(TARGET) == 240_000
        assert c.read(PROFILE_V, 2) == [0, 24_000]
        c.write(1162, 1)                                               # now little endian
        assert c.read(TARGET, 2) == [0xA980, 0x0003]
        # FC06 on the first word alone is held until the second word (§11 "Data Format")
        c.write(TARGET, 0xFC18)
        assert c.read(TARGET, 2) == [0xA980, 0x0003]
        c.write(TARGET + 1, 0xFFFF)
        assert c.read(TARGET, 2) == [0xFC18, 0xFFFF]                    # -1000 (G2)
        c.close()
    finally:
        sim.stop()


def test_exceptions(client):
    mb = client.mb
    assert client.exception(mb.read_holding_registers(1003, count=1, device_id=1)) == 2
    assert client.exception(mb.read_holding_registers(1001, count=21, device_id=1)) == 2
    assert client.exception(mb.read_holding_registers(900, count=1, device_id=1)) == 2
    assert client.exception(mb.write_register(1001, 1, device_id=1)) == 2      # read-only
    assert client.exception(mb.write_register(1003, 1, device_id=1)) == 2      # hole
    assert client.exception(mb.write_register(1080, 121, device_id=1)) == 3    # 0..120 %
    assert client.exception(mb.write_register(MODE, 2, device_id=1)) == 3      # no mode 2
    assert client.exception(mb.write_registers(PROFILE_A, words32(1_000), device_id=1)) == 3
    assert client.exception(mb.write_register(1097, 50, device_id=1)) == 3     # 100..32000
    assert client.exception(mb.read_coils(1001, count=1, device_id=1)) == 1
    assert client.exception(mb.readwrite_registers(read_address=1001, read_count=1,
                                                   write_address=1122, values=[1],
                                                   device_id=1)) == 1
    assert client.exception(mb.read_holding_registers(1001, count=1, device_id=9)) == 0x0B
    # a refused FC16 changes nothing, not even its valid part
    assert client.exception(mb.write_registers(1080, [50, 12_801], device_id=1)) == 3
    assert client.read(1080) == [70]
    assert client.sw() == 0x0270


def raw_request(port: int, pdu: bytes, unit: int = 1, transaction: int = 0x1234) -> bytes:
    """One Modbus TCP request over a plain socket; the whole reply (MBAP header + PDU)."""
    with socket.create_connection(('127.0.0.1', port), timeout=2.0) as s:
        s.sendall(struct.pack('>HHHB', transaction, 0, len(pdu) + 1, unit) + pdu)
        header = b''
        while len(header) < 7:
            header += s.recv(7 - len(header))
        length = struct.unpack('>H', header[4:6])[0]
        body = b''
        while len(body) < length - 1:
            body += s.recv(length - 1 - len(body))
    return header + body


@pytest.mark.parametrize('pdu,reply', [
    # function codes the drive does not have (§11 "Supported Function Code"): 0x01, wherever
    (bytes([0x01, 0x00, 0x00, 0x00, 0x01]), bytes([0x81, 0x01])),   # read coils at 0
    (bytes([0x01, 0x03, 0xE9, 0x00, 0x01]), bytes([0x81, 0x01])),   # ... at 1001
    (bytes([0x02, 0x00, 0x00, 0x00, 0x01]), bytes([0x82, 0x01])),
    (bytes([0x05, 0x00, 0x00, 0xFF, 0x00]), bytes([0x85, 0x01])),
    (bytes([0x07]), bytes([0x87, 0x01])),                           # read exception status
    (bytes([0x08, 0x00, 0x00, 0x12, 0x34]), bytes([0x88, 0x01])),   # diagnostics (echo)
    (bytes([0x11]), bytes([0x91, 0x01])),                           # report server id
    (bytes([0x2B, 0x0E, 0x01, 0x00]), bytes([0xAB, 0x01])),         # device identification
    (bytes([0x17, 0x03, 0xE9, 0x00, 0x01, 0x04, 0x62, 0x00, 0x01, 0x02, 0x00, 0x01]),
     bytes([0x97, 0x01])),
    # quantity outside 1..125 (Modbus Application Protocol §6.3/§6.4): 0x03 of that function
    (bytes([0x03, 0x03, 0xE9, 0x00, 0x00]), bytes([0x83, 0x03])),
    (bytes([0x03, 0x03, 0xE9, 0x00, 0x7E]), bytes([0x83, 0x03])),
    (bytes([0x04, 0x03, 0xE9, 0x00, 0x00]), bytes([0x84, 0x03])),
    (bytes([0x04, 0x03, 0xE9, 0x00, 0x7E]), bytes([0x84, 0x03])),
    (bytes([0x03, 0x03, 0xE9]), bytes([0x83, 0x03])),               # truncated request
    (bytes([0x10, 0x04, 0x10, 0x00, 0x00, 0x00]), bytes([0x90, 0x03])),
    # the normal answers stay as they were
    (bytes([0x03, 0x03, 0xE9, 0x00, 0x01]), bytes([0x03, 0x02, 0x02, 0x70])),
    (bytes([0x04, 0x03, 0xE9, 0x00, 0x01]), bytes([0x04, 0x02, 0x02, 0x70])),
    (bytes([0x03, 0x03, 0xE8, 0x00, 0x7D]), bytes([0x83, 0x02])),   # 1000 is no register
])
def test_exception_replies_on_the_wire(sim, pdu, reply):
    got = raw_request(sim.port, pdu)
    # MBAP: transaction id echoed, protocol 0, length = unit + PDU, unit echoed
    assert got == struct.pack('>HHHB', 0x1234, 0, len(reply) + 1, 1) + reply, got.hex(' ')


def test_several_units_on_one_port(sim, client):
    client.enable(unit=1, mode=1)
    assert client.sw(unit=1) == 0x0637 and client.sw(unit=2) == 0x0270
    client.write32(TARGET, 5_000, unit=1)
    client.write32(PROFILE_V, 16_000, unit=1)          # start-stop profile
    client.cw(0x001F, unit=1)
    wait_for(lambda: client.sw(unit=1) & 0x0400, 2.0)
    assert client.read32(POS, unit=1) == 5_000 and client.read32(POS, unit=2) == 0
    assert sim.drives['axis2'].true_position_steps == 0


def test_link_faults_through_the_proxy(sim):
    c = Client(sim.port, timeout=0.3)
    try:
        assert c.sw() == 0x0270
        assert sim.inject_fault('', 'no_reply')[0]
        with pytest.raises((ModbusException, AssertionError)):
            c.read(SW)
        assert sim.inject_fault('', 'link_ok')[0]
        c.mb.close()
        assert c.mb.connect()
        assert c.sw() == 0x0270
        ok, message = sim.inject_fault('', 'late_reply', 0, 0.0)
        assert not ok and 'delay' in message
        assert sim.inject_fault('', 'cut')[0]

        def reconnect():
            c.mb.close()
            return c.mb.connect()

        wait_for(lambda: not reconnect(), 2.0, 0.05)    # refused while cut
        assert sim.inject_fault('', 'link_ok')[0]
        wait_for(reconnect, 2.0, period_s=0.05)
        assert c.sw() == 0x0270
    finally:
        c.close()


def test_permissive_mode_reads_holes_as_zero():
    sim = XplusMtSim(port=0, drives=DRIVES, strict=False)
    sim.start()
    try:
        c = Client(sim.port)
        block = c.read(1001, 21)                           # 1001..1021 with holes
        assert block[0] == 0x0270 and block[2] == 0 and block[11] == 0   # 1003, 1012
        assert c.exception(c.mb.write_register(1003, 1, device_id=1)) == 2
        c.close()
    finally:
        sim.stop()
