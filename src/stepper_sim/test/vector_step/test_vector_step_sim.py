"""vector_step_sim on the bus: the golden frames of spec/aec_vector_step.md section 13.

A raw python-can client on the loopback socketcand broker sends the literal request bytes and
checks the literal answers: SDO (expedited, segmented, aborts), NMT and heartbeat, default and
remapped PDOs, EMCY, the state machine, fault recovery as the manual's procedure, homing, JOG,
save. The simulator runs in-process (no ROS); node 1 and node 125 (rotary switches at 00) share
the bus.
"""

import collections
import logging
import queue
import struct
import time

import can
import pytest
from stepper_drivers.vendors.vector_step import regmap as vm
from stepper_sim.core.socketcand_broker import SocketcandBroker
from stepper_sim.vector_step.sim import SYNC_CONFIRM_S, NodeConfig, VectorStepSim

logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)


def h(text: str) -> bytes:
    return bytes.fromhex(text)


class Wire:
    """A raw CAN client: send literal frames, wait for frames by COB-ID (a queue per COB-ID)."""

    def __init__(self, port: int):
        self.bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel='can0',
                           tcp_tune=True)
        self.queues: dict[int, 'queue.Queue[can.Message]'] = collections.defaultdict(queue.Queue)
        self.log: list[can.Message] = []
        self.notifier = can.Notifier(self.bus, [self._on_message], 0.1)

    def _on_message(self, msg: can.Message) -> None:
        self.queues[msg.arbitration_id].put(msg)
        self.log.append(msg)

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()

    def drain(self, cob: int | None = None) -> None:
        for key, frames in list(self.queues.items()):
            if cob is None or key == cob:
                while not frames.empty():
                    frames.get_nowait()

    def send(self, cob: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def expect(self, cob: int, timeout_s: float = 1.0, data: bytes | None = None) -> bytes:
        """Next frame on `cob`; with `data`, the next one equal to it."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                msg = self.queues[cob].get(timeout=max(left, 0.0))
            except queue.Empty:
                raise AssertionError(f'no frame on 0x{cob:03X}' + (
                    f' with {data.hex(" ")}' if data is not None else '') +
                    f' within {timeout_s} s') from None
            if data is None or bytes(msg.data) == data:
                return bytes(msg.data)

    def silent(self, cob: int, wait_s: float) -> bool:
        try:
            self.queues[cob].get(timeout=wait_s)
        except queue.Empty:
            return True
        return False

    def sdo(self, request: str, node: int = 1) -> bytes:
        self.drain(0x580 + node)
        self.send(0x600 + node, h(request))
        return self.expect(0x580 + node)

    def read(self, index: int, sub: int = 0, node: int = 1) -> int:
        data = self.sdo(f'40 {index & 0xFF:02X} {index >> 8:02X} {sub:02X} 00 00 00 00', node)
        assert data[0] & 0xE0 == 0x40, f'read 0x{index:04X}:{sub}: {data.hex(" ")}'
        size = 4 - ((data[0] >> 2) & 3)
        return int.from_bytes(data[4:4 + size], 'little')

    def write(self, index: int, sub: int, value: int, size: int, node: int = 1) -> bytes:
        command = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        payload = (value & ((1 << (8 * size)) - 1)).to_bytes(size, 'little').ljust(4, b'\0')
        request = bytes([command, index & 0xFF, index >> 8, sub]) + payload
        self.drain(0x580 + node)
        self.send(0x600 + node, request)
        return self.expect(0x580 + node)

    def sw(self, node: int = 1) -> int:
        return self.read(0x6041, 0, node)

    def wait_sw(self, cond, timeout_s: float = 3.0, node: int = 1) -> int:
        deadline = time.monotonic() + timeout_s
        while True:
            sw = self.sw(node)
            if cond(sw):
                return sw
            assert time.monotonic() < deadline, f'statusword 0x{sw:04X} after {timeout_s} s'
            time.sleep(0.01)


def make_bench(storage_dir):
    broker = SocketcandBroker(port=0, ready_delay_s=0.01)
    broker.start()
    sim = VectorStepSim([NodeConfig('axis1', 1, limit_neg_steps=-3200.0),
                         NodeConfig('spare', 125)], port=broker.port, reboot_delay_s=0.02,
                        storage_dir=str(storage_dir))
    wire = Wire(broker.port)
    sim.start()
    wire.expect(0x701, 2.0, h('00'))
    wire.expect(0x77D, 2.0, h('00'))          # G18: node-ID 125 (rotary switches at 00)
    return broker, sim, wire


@pytest.fixture
def bench(tmp_path):
    broker, sim, wire = make_bench(tmp_path)
    yield sim, wire
    wire.close()
    sim.stop()
    broker.stop()


@pytest.fixture(scope='module')
def shared(tmp_path_factory):
    """One bench for the read-only and refused requests (they change nothing)."""
    broker, sim, wire = make_bench(tmp_path_factory.mktemp('eeprom'))
    yield sim, wire
    wire.close()
    sim.stop()
    broker.stop()


def start(wire: Wire, node: int = 1) -> None:
    """NMT start; an SDO read after it returns once the node has handled it."""
    wire.send(0x000, bytes([0x01, node]))
    wire.read(0x1000, 0, node)


def enable(wire: Wire, cob: int = 0x201, tail: bytes = h('01')) -> None:
    for cw in (0x06, 0x07, 0x0F):
        wire.send(cob, struct.pack('<H', cw) + tail)
    wire.wait_sw(lambda sw: sw & 0x6F == 0x27)


# --- G1, G2: identity, constants, segmented upload -------------------------------------------
@pytest.mark.parametrize('request_, response', [
    ('40 00 10 00 00 00 00 00', '43 00 10 00 92 01 04 00'),     # 0x1000 device type
    ('40 18 10 01 00 00 00 00', '43 18 10 01 BC 00 00 00'),     # vendor ID
    ('40 18 10 00 00 00 00 00', '4F 18 10 00 04 00 00 00'),
    ('40 18 10 02 00 00 00 00', '43 18 10 02 8E 13 00 00'),     # SMD5006
    ('40 02 65 00 00 00 00 00', '43 02 65 00 21 00 01 00'),     # 0x6502
    ('40 01 10 00 00 00 00 00', '4F 01 10 00 00 00 00 00'),     # error register at rest
    ('40 61 60 00 00 00 00 00', '4F 61 60 00 01 00 00 00'),     # 0x6061 after power-on
    ('40 C2 60 01 00 00 00 00', '4F C2 60 01 04 00 00 00'),
    ('40 C2 60 02 00 00 00 00', '4F C2 60 02 FD 00 00 00'),
    ('40 2A 20 01 00 00 00 00', '43 2A 20 01 D2 02 96 49'),     # Rtestintmot
    ('40 00 20 00 00 00 00 00', '4F 00 20 00 01 00 00 00'),     # one axis
    ('40 02 64 00 00 00 00 00', '4B 02 64 00 09 00 00 00'),     # motor type 9 at power-on
    ('40 99 60 00 00 00 00 00', '4F 99 60 00 02 00 00 00'),
    ('40 99 60 01 00 00 00 00', '43 99 60 01 64 00 00 00'),
    ('40 99 60 02 00 00 00 00', '43 99 60 02 0A 00 00 00'),
    ('40 83 60 00 00 00 00 00', '43 83 60 00 E8 03 00 00'),
    ('40 85 60 00 00 00 00 00', '43 85 60 00 E8 03 00 00'),
    ('40 81 60 00 00 00 00 00', '43 81 60 00 64 00 00 00'),
    ('40 5A 60 00 00 00 00 00', '4B 5A 60 00 02 00 00 00'),
    ('40 5B 60 00 00 00 00 00', '4B 5B 60 00 00 00 00 00'),
    ('40 5E 60 00 00 00 00 00', '4B 5E 60 00 02 00 00 00'),
    ('40 FE 60 02 00 00 00 00', '43 FE 60 02 00 00 FF 00'),
    ('40 03 14 02 00 00 00 00', '4F 03 14 02 FE 00 00 00'),
    ('40 01 18 02 00 00 00 00', '4F 01 18 02 FE 00 00 00'),
])
def test_g1_identity_and_constants(shared, request_, response):
    _, wire = shared
    assert wire.sdo(request_) == h(response)


def test_g2_segmented_upload_of_the_catalog_address(shared):
    _, wire = shared
    assert wire.sdo('40 05 65 00 00 00 00 00') == h('41 05 65 00 0E 00 00 00')
    assert wire.sdo('60 00 00 00 00 00 00 00') == h('00 77 77 77 2E 61 65 63')     # "www.aec"
    assert wire.sdo('70 00 00 00 00 00 00 00') == h('11 2D 73 6D 64 2E 69 74')     # "-smd.it"


def test_g18_node_125_answers_on_its_own_cob_ids(shared):
    _, wire = shared
    assert wire.sdo('40 00 10 00 00 00 00 00', node=125) == h('43 00 10 00 92 01 04 00')
    assert wire.log[-1].arbitration_id == 0x5FD


# --- G8: aborts -------------------------------------------------------------------------------
@pytest.mark.parametrize('request_, response', [
    ('23 05 10 00 80 00 00 40', '80 05 10 00 30 00 09 06'),     # 0x1005 bit 30
    ('23 14 10 00 81 00 00 20', '80 14 10 00 30 00 09 06'),     # 0x1014 bit 29
    ('40 60 60 00 00 00 00 00', '80 60 60 00 01 00 01 06'),     # read write-only 0x6060
    ('23 00 10 00 05 00 00 00', '80 00 10 00 02 00 01 06'),     # write read-only 0x1000
    ('40 34 12 00 00 00 00 00', '80 34 12 00 00 00 02 06'),     # unknown index
    ('40 00 20 02 00 00 00 00', '80 00 20 02 11 00 09 06'),     # sub 2 of a single axis
    ('40 41 60 01 00 00 00 00', '80 41 60 01 11 00 09 06'),     # sub 1 of a VAR
    ('40 3B 20 01 00 00 00 00', '80 3B 20 01 01 00 01 06'),     # G23: Rcmdwr is WO
    ('2F 60 60 00 02 00 00 00', '80 60 60 00 30 00 09 06'),     # mode 2 not supported
    ('2F 98 60 00 13 00 00 00', '80 98 60 00 30 00 09 06'),     # CiA method 19: not AEC
    ('23 83 60 00 00 00 00 00', '80 83 60 00 30 00 09 06'),     # 0x6083 min 1
    ('2F 03 10 00 01 00 00 00', '80 03 10 00 30 00 09 06'),     # 0x1003:00 accepts only 0
    ('40 03 10 01 00 00 00 00', '80 03 10 01 24 00 00 08'),     # no error recorded yet
    ('2B 3B 20 01 0C 00 00 00', '80 3B 20 01 30 00 09 06'),     # Rcmdwr: one bit at a time
])
def test_g8_abort_codes(shared, request_, response):
    _, wire = shared
    assert wire.sdo(request_) == h(response)


def test_g8_duplicate_consumer_heartbeat_entry(bench):
    _, wire = bench
    assert wire.sdo('23 16 10 01 64 00 05 00') == h('60 16 10 01 00 00 00 00')
    assert wire.sdo('23 16 10 02 C8 00 05 00') == h('80 16 10 02 43 00 04 06')


def test_g8_mapping_longer_than_64_bits_and_missing_object(bench):
    _, wire = bench
    for request in ('2F 02 1A 00 00 00 00 00', '23 02 1A 01 20 00 64 60',
                    '23 02 1A 02 20 00 6C 60', '23 02 1A 03 20 00 7A 60'):
        assert wire.sdo(request)[0] == 0x60
    assert wire.sdo('2F 02 1A 00 03 00 00 00') == h('80 02 1A 00 42 00 04 06')
    assert wire.sdo('23 02 16 01 20 00 FF 60') == h('80 02 16 01 00 00 02 06')   # 0x60FF
    assert wire.sdo('23 02 16 01 10 00 41 60') == h('80 02 16 01 41 00 04 06')   # SW in RxPDO


# --- G19, NMT and guarding -------------------------------------------------------------------
def test_g19_heartbeat_follows_the_nmt_state(bench):
    _, wire = bench
    assert wire.sdo('2B 17 10 00 64 00 00 00') == h('60 17 10 00 00 00 00 00')
    wire.expect(0x701, 0.5, h('7F'))
    t0 = time.monotonic()
    wire.expect(0x701, 0.5, h('7F'))
    assert 0.07 < time.monotonic() - t0 < 0.2
    wire.send(0x000, h('01 01'))
    wire.expect(0x701, 0.5, h('05'))
    wire.send(0x000, h('02 01'))
    wire.expect(0x701, 0.5, h('04'))
    wire.drain()
    wire.send(0x601, h('40 00 10 00 00 00 00 00'))
    assert wire.silent(0x581, 0.3), 'SDO answered in STOPPED'
    wire.send(0x000, h('80 00'))                    # all nodes to PRE-OPERATIONAL
    wire.expect(0x701, 0.5, h('7F'))


def test_nmt_resets_boot_up_and_restore_defaults(bench):
    sim, wire = bench
    wire.write(0x1017, 0, 50, 2)
    enable_cmds = wire.write(0x605A, 0, 6, 2)
    assert enable_cmds[0] == 0x60
    wire.drain()
    wire.send(0x000, h('82 01'))                    # reset communication
    wire.expect(0x701, 1.0, h('00'))
    assert wire.read(0x1017) == 0                   # communication objects back to defaults
    assert wire.read(0x605A) == 6                   # application objects kept
    wire.send(0x000, h('81 01'))                    # reset node
    wire.expect(0x701, 1.0, h('00'))
    assert wire.read(0x605A) == 2


def test_node_guarding_answers_with_toggle(bench):
    _, wire = bench
    wire.drain()
    wire.send(0x701, b'')                           # an RTR travels as a 0-byte frame
    assert wire.expect(0x701, 0.5) == h('7F')
    wire.send(0x701, b'')
    assert wire.expect(0x701, 0.5) == h('FF')       # toggle bit 7


# --- G3, G4, G9, G10: PDOs and the state machine ------------------------------------------------
def test_g3_default_pdos(bench):
    _, wire = bench
    for index, sub, value in ((0x1A00, 1, 0x60410010), (0x1A00, 2, 0x60610008),
                              (0x1A01, 2, 0x60640020), (0x1600, 2, 0x60600008),
                              (0x1601, 2, 0x607A0020), (0x1600, 0, 2), (0x1602, 0, 0)):
        assert wire.read(index, sub) == value
    wire.drain()
    wire.send(0x000, h('01 01'))
    tpdo1 = wire.expect(0x181)
    tpdo2 = wire.expect(0x281)
    assert len(tpdo1) == 3 and tpdo1[2] == 0x01 and tpdo1[0] & 0x4F == 0x40
    assert len(tpdo2) == 6 and tpdo2[:2] == tpdo1[:2] and tpdo2[2:] == h('00000000')
    wire.send(0x201, h('06 00 01'))                 # RxPDO1: CW + mode
    assert wire.expect(0x181)[0] & 0x6F == 0x21     # TxPDO1 on change
    wire.send(0x301, h('07 00 00 00 00 00'))        # RxPDO2: CW + target
    assert wire.expect(0x181)[0] & 0x6F == 0x23


def test_g4_state_machine_transitions(bench):
    _, wire = bench
    start(wire)
    steps = [('06', 0x6F, 0x21), ('07', 0x6F, 0x23), ('0F', 0x6F, 0x27),
             ('07', 0x6F, 0x23),                    # 5
             ('06', 0x6F, 0x21),                    # 6
             ('00', 0x4F, 0x40),                    # 7
             ('06', 0x6F, 0x21), ('0F', 0x6F, 0x27),  # 0x0F in RTSO: 3 then 4
             ('06', 0x6F, 0x21),                    # 8
             ('07', 0x6F, 0x23), ('0F', 0x6F, 0x27), ('00', 0x4F, 0x40),   # 9
             ('06', 0x6F, 0x21), ('07', 0x6F, 0x23), ('00', 0x4F, 0x40),   # 10
             ('06', 0x6F, 0x21), ('0F', 0x6F, 0x27),
             ('02', 0x4F, 0x40)]                    # 11 then 12 (0x605A = 2, at rest)
    for cw, mask, value in steps:
        wire.send(0x201, h(cw + ' 00 01'))
        wire.wait_sw(lambda sw, mask=mask, value=value: sw & mask == value)
    wire.write(0x605A, 0, 6, 2)
    enable(wire)
    wire.send(0x201, h('02 00 01'))
    wire.wait_sw(lambda sw: sw & 0x6F == 0x07)      # stays QUICK STOP ACTIVE
    wire.send(0x201, h('0F 00 01'))
    wire.wait_sw(lambda sw: sw & 0x6F == 0x27)      # 16


def test_g9_remapping_by_the_manuals_procedure(bench):
    _, wire = bench
    for request in ('2F 01 16 00 00 00 00 00',      # 0x1601:00 = 0 disables
                    '23 01 14 01 01 03 00 00',      # COB-ID 0x301 (manual prints 0x181)
                    '2F 01 14 02 FE 00 00 00',
                    '23 01 16 01 10 00 40 60',      # 0x60400010 (printed 0x604000010)
                    '23 01 16 02 08 00 60 60',
                    '2F 01 16 00 02 00 00 00'):     # sub 0 = 2 enables again
        assert wire.sdo(request)[0] == 0x60, request
    start(wire)
    wire.send(0x301, h('06 00 01'))                 # now [CW, mode]: 3 bytes
    wire.wait_sw(lambda sw: sw & 0x6F == 0x21)
    wire.drain()
    wire.send(0x301, h('06 00 10 27 00 00'))        # the old 6-byte layout: too long
    emcy = wire.expect(0x081)
    assert emcy[:2] == h('10 82') and emcy[2] & 0x10      # 0x8210, error register bit 4


def test_g10_sync_types_and_event_timer(bench):
    _, wire = bench
    wire.write(0x1800, 2, 10, 1)                    # TxPDO1 every 10 SYNCs
    wire.write(0x1801, 1, 0x80000281, 4)            # TxPDO2 off
    start(wire)
    wire.drain()
    for _ in range(9):
        wire.send(0x080, b'')
    assert wire.silent(0x181, 0.2)
    wire.send(0x080, b'')
    assert len(wire.expect(0x181, 0.5)) == 3
    wire.write(0x1800, 2, 0xFE, 1)
    wire.write(0x1800, 5, 100, 2)                   # event timer 100 ms
    wire.drain()
    wire.expect(0x181, 0.5)
    t0 = time.monotonic()
    wire.expect(0x181, 0.5)
    assert 0.08 < time.monotonic() - t0 < 0.2


def test_g10_a_change_undone_within_the_inhibit_time_sends_nothing_and_the_sim_idles(bench):
    """0x1800:03 inhibit time: the statusword changes and changes back before the inhibit time
    is over. Nothing is left to send, and the simulator's cycle loop must go back to sleep: it
    spun instead (this process' CPU time over the wall time 0.2-0.5), which starved the node and
    the drives' motion beside it on two cores."""
    _, wire = bench
    wire.write(0x1800, 3, 5000, 2)                  # TxPDO1 inhibit 0.5 s
    start(wire)
    first = wire.expect(0x181, 0.5)
    wire.send(0x201, h('06 00 01'))                 # Shutdown: Ready to switch on
    wire.send(0x201, h('00 00 01'))                 # Disable voltage: back to the first sw
    wire.read(0x1000, 0, 1)                         # both handled
    cpu_s, wall_s = time.process_time(), time.monotonic()
    assert wire.silent(0x181, 0.6), 'TxPDO1 sent although its data came back to the last sent'
    share = (time.process_time() - cpu_s) / (time.monotonic() - wall_s)
    assert share < 0.1, f'the simulator used {share:.0%} of a core with nothing to do'
    wire.send(0x201, h('06 00 01'))                 # a change that stays is still sent
    assert wire.expect(0x181, 0.6) != first


def test_g10_the_event_timer_keeps_to_the_inhibit_time(bench):
    """The inhibit time (0x1800:03) is the least interval between two transmissions of the PDO,
    those of the event timer (0x1800:05) too: a 20 ms timer under a 50 ms inhibit sends every
    50 ms (before: every 20 ms, where a drive sends a fifth as many)."""
    _, wire = bench
    wire.write(0x1800, 3, 500, 2)                   # inhibit 50 ms
    wire.write(0x1800, 5, 20, 2)                    # event timer 20 ms
    start(wire)
    wire.expect(0x181, 0.5)
    wire.drain()
    t0 = time.monotonic()
    time.sleep(0.5)
    frames = len(wire.queues[0x181].queue)
    window_s = time.monotonic() - t0
    assert window_s / 0.05 / 2 <= frames <= window_s / 0.05 + 2, (frames, window_s)


# --- G5, G6, G7: faults, EMCY, history ---------------------------------------------------------
def test_g5_g7_fault_emcy_and_the_manuals_recovery(bench):
    sim, wire = bench
    start(wire)
    enable(wire)
    wire.drain()
    ok, _ = sim.inject_fault('axis1', 'drive_fault', 1 << 6, 0)   # over-temperature
    assert ok
    emcy = wire.expect(0x081)
    assert emcy[:2] == h('00 54') and emcy[2] & 0x01                # 0x5400, generic error
    assert int.from_bytes(emcy[3:7], 'little') == 1 << 6            # Ralarm32 in the VSD
    wire.wait_sw(lambda sw: sw & 0x4F == 0x08)
    assert wire.read(0x1001) & 1 and wire.read(0x1003) == 1
    assert wire.read(0x603F) == 0x5400 and wire.read(0x1003, 1) & 0xFFFF == 0x5400
    wire.send(0x201, h('00 00 01'))
    wire.send(0x201, h('80 00 01'))                 # cause still there: stays in FAULT
    assert wire.sw() & 0x4F == 0x08                 # (an SDO after a PDO sees its effect)
    sim.inject_fault('axis1', 'clear_fault', 0, 0)
    wire.send(0x201, h('00 00 01'))
    wire.send(0x201, h('80 00 01'))                 # history not cleared: still FAULT
    assert wire.sw() & 0x4F == 0x08
    assert wire.sdo('2F 03 10 00 00 00 00 00') == h('60 03 10 00 00 00 00 00')    # step 2
    assert wire.read(0x1003) == 0
    wire.drain()
    wire.send(0x201, h('00 00 01'))
    wire.send(0x201, h('80 00 01'))
    wire.wait_sw(lambda sw: sw & 0x4F == 0x40)
    assert wire.expect(0x081)[:3] == h('00 00 00')                  # error reset EMCY
    enable(wire)                                                    # step 3


def test_g6_history_keeps_the_two_newest(bench):
    sim, wire = bench
    for code in (0x8110, 0x8140, 0x8150):
        sim.inject_fault('axis1', 'emcy', code, 0)
    assert wire.read(0x1003) == 2
    assert wire.read(0x1003, 1) & 0xFFFF == 0x8150 and wire.read(0x1003, 2) & 0xFFFF == 0x8140
    assert wire.read(0x603F) == 0x8150
    assert wire.read(0x1001) & 0x10                               # communication error bit
    wire.write(0x1003, 0, 0, 1)
    assert wire.read(0x1003) == 0 and wire.read(0x1001) == 0


# --- G11..G14: motion ---------------------------------------------------------------------------
def test_g11_profile_position_handshake(bench):
    sim, wire = bench
    wire.write(0x6081, 0, 1000, 4)                  # 10 rev/s
    wire.write(0x6083, 0, 20000, 4)
    wire.write(0x6084, 0, 20000, 4)
    start(wire)
    enable(wire, 0x301, h('00 00 00 00'))
    wire.send(0x301, h('0F 00 10 27 00 00'))        # target 10000, absolute
    wire.send(0x301, h('1F 00 10 27 00 00'))        # new set-point
    wire.wait_sw(lambda sw: sw & 0x1000)            # set-point acknowledged
    assert wire.sw() & 0x0100                       # motor moving
    wire.send(0x301, h('0F 00 10 27 00 00'))
    wire.wait_sw(lambda sw: not sw & 0x1000)
    wire.wait_sw(lambda sw: sw & 0x0400 and not sw & 0x0100, 3.0)
    assert wire.read(0x6064) == 10000
    assert sim.true_position_steps('axis1') == pytest.approx(10000)
    wire.send(0x301, h('5F 00 F0 D8 FF FF'))        # relative -10000 (bit 6)
    wire.wait_sw(lambda sw: sw & 0x1000)
    wire.send(0x301, h('4F 00 F0 D8 FF FF'))
    wire.wait_sw(lambda sw: sw & 0x0400 and not sw & 0x0100, 3.0)
    assert wire.read(0x6064) == 0


def test_g12_homing_on_the_spot_forces_0x607c(bench):
    sim, wire = bench
    for method in (0x00, 0x23, 0x25):               # 0, 35, 37
        wire.write(0x6098, 0, method, 1)
        wire.write(0x607C, 0, 1000, 4)
        wire.write(0x6060, 0, 6, 1)
        wire.write(0x20C7, 1, 0, 2)                 # G24: write 0 clears "axis homed"
        assert not wire.read(0x20C7, 1) & 0x04
        start(wire)
        enable(wire, 0x201, h('06'))
        wire.send(0x201, h('1F 00 06'))
        sw = wire.wait_sw(lambda sw: sw & 0x1000)
        assert not sw & 0x2000
        assert wire.read(0x6064) == 1000 and wire.read(0x6061) == 6
        assert wire.read(0x20C7, 1) & 0x04          # Rstsflg bit 2 "Asse azzerato"
        assert wire.read(0x2052, 1) == method       # Rhmode mirrors 0x6098
        wire.send(0x201, h('00 00 06'))
        wire.wait_sw(lambda sw: sw & 0x4F == 0x40)


def test_g12_homing_on_bls_and_a_homing_error_emcy(bench):
    sim, wire = bench
    wire.write(0x6098, 0, 0xFF, 1)                  # -1: BLS, negative direction
    wire.write(0x6099, 1, 200, 4)                   # 2 rev/s search
    wire.write(0x6099, 2, 50, 4)
    wire.write(0x609A, 0, 2000, 4)
    wire.write(0x607C, 0, 500, 4)
    start(wire)
    enable(wire, 0x201, h('06'))
    wire.send(0x201, h('1F 00 06'))
    wire.wait_sw(lambda sw: sw & 0x1000, 5.0)
    node = sim.nodes['axis1']
    # the BLS edge (raw -3200) now reads 500; the axis stops just past it
    assert abs(node.axis.raw_position_steps + 3200 - (wire.read(0x6064) - 500)) < 1
    assert abs(wire.read(0x6064) - 500) < 50
    # Method -5 (TOP, negative direction) with the BLS active cannot start: Rhsts bit 3
    wire.write(0x6098, 0, 0xFB, 1)
    wire.drain()
    wire.send(0x201, h('0F 00 06'))
    wire.send(0x201, h('1F 00 06'))
    emcy = wire.expect(0x081)
    assert emcy[:2] == h('02 FF') and emcy[3] == 0x08                 # G7: "BLS error"
    assert wire.sw() & 0x2000 and wire.read(0x20CA, 1) == 0x08
    assert wire.read(0x20E3, 1) & (1 << 13)                          # Ralarm "Homing Error"


def test_g12_switch_not_found_within_rhmaxspc(bench):
    _, wire = bench
    wire.write(0x6098, 0, 0xF1, 1, node=125)        # -15: FLS + TOP (no FLS on this node)
    wire.write(0x2020, 1, 1600, 4, node=125)        # Rhmaxspc half a revolution
    wire.write(0x6099, 1, 400, 4, node=125)
    wire.write(0x609A, 0, 20000, 4, node=125)
    start(wire, 125)
    for cw in (0x06, 0x07, 0x0F):
        wire.send(0x27D, struct.pack('<H', cw) + h('06'))
    wire.wait_sw(lambda sw: sw & 0x6F == 0x27, node=125)
    wire.drain()
    wire.send(0x27D, h('1F 00 06'))
    emcy = wire.expect(0x0FD, 3.0)
    assert emcy[:2] == h('02 FF') and emcy[3] == 0x04                 # max travel
    assert wire.sw(125) & 0x2000


def test_g13_jog_mode(bench):
    sim, wire = bench
    assert wire.write(0x6060, 0, 0xFF, 1)[0] == 0x60
    assert wire.read(0x6061) == 0xFF                 # -1
    wire.write(0x6081, 0, 500, 4)                   # 5 rev/s
    wire.write(0x6083, 0, 5000, 4)
    wire.write(0x6084, 0, 5000, 4)
    start(wire)
    enable(wire, 0x201, h('FF'))
    wire.send(0x201, h('1F 00 FF'))                 # start, CW
    wire.wait_sw(lambda sw: sw & 0x0500 == 0x0500)  # moving and at speed
    assert not wire.sw() & 0x1000
    assert wire.read(0x606C) == 500
    wire.send(0x201, h('3F 00 FF'))                 # CCW
    wire.wait_sw(lambda sw: sw & 0x0400 and wire.read(0x606C) == 0xFFFFFE0C)   # -500
    wire.send(0x201, h('0F 00 FF'))                 # stop
    wire.wait_sw(lambda sw: sw & 0x1000 and not sw & 0x0100)
    assert wire.read(0x606C) == 0


def test_g14_mode_change_while_moving_aborts_but_keeps_the_state(bench):
    sim, wire = bench
    wire.write(0x6060, 0, 0xFF, 1)
    wire.write(0x6081, 0, 300, 4)
    start(wire)
    enable(wire, 0x201, h('FF'))
    wire.send(0x201, h('1F 00 FF'))
    wire.wait_sw(lambda sw: sw & 0x0100)
    wire.write(0x6060, 0, 6, 1)
    sw = wire.wait_sw(lambda sw: not sw & 0x0100)
    assert sw & 0x6F == 0x27 and wire.read(0x6061) == 6


def test_g23_rcmdwr_stop(bench):
    sim, wire = bench
    wire.write(0x6060, 0, 0xFF, 1)
    wire.write(0x6081, 0, 300, 4)
    start(wire)
    enable(wire, 0x201, h('FF'))
    wire.send(0x201, h('1F 00 FF'))
    wire.wait_sw(lambda sw: sw & 0x0100)
    assert wire.sdo('2B 3B 20 01 08 00 00 00') == h('60 3B 20 01 00 00 00 00')
    wire.wait_sw(lambda sw: not sw & 0x0100)
    assert wire.sw() & 0x6F == 0x27                  # stays enabled


# --- G15: save -------------------------------------------------------------------------------
def test_g15_save_through_rloadsav_and_restart(bench, tmp_path):
    sim, wire = bench
    assert wire.write(0x2020, 1, 123456, 4)[0] == 0x60           # Rhmaxspc (SAVE)
    assert wire.sdo('2B C2 20 01 81 00 00 00') == h('60 C2 20 01 00 00 00 00')
    assert wire.read(0x20C2, 1) == 0x81                          # busy
    deadline = time.monotonic() + 2.0
    while wire.read(0x20C2, 1) != 0:                             # "azzerato quando eseguito"
        assert time.monotonic() < deadline
        time.sleep(0.02)
    assert wire.read(0x20C4, 1) == 0
    assert '123456' in (tmp_path / 'vector_step_node1.json').read_text()
    wire.write(0x2020, 1, 7, 4)
    wire.drain()
    wire.write(0x20C2, 1, 0x8E, 2)
    wire.write(0x20C2, 1, 0x8F, 2)                  # restart
    wire.expect(0x701, 1.0, h('00'))
    assert wire.read(0x2020, 1) == 123456           # loaded from EEPROM at power-on


def test_g15_nvram_error_gives_emcy_ff01(bench):
    sim, wire = bench
    sim.inject_fault('axis1', 'nvram_fault', 0, 0)
    wire.write(0x20C2, 1, 0x81, 2)
    emcy = wire.expect(0x081, 1.0)
    assert emcy[:2] == h('01 FF') and emcy[3:5] == h('08 00')      # Reepsts bit 3
    assert wire.read(0x20C4, 1) == 0x08


# --- SYNC watchdog: 0x1006, Ralarm32 bit 18 "Mancanza Sync", Ralarmreact ----------------------
def test_a_missing_sync_is_alarm_18_with_the_alarm_reaction(bench):
    sim, wire = bench
    node = sim.nodes['axis1']
    wire.write(0x6060, 0, 0xFF, 1)
    wire.write(0x6081, 0, 300, 4)                   # 3 rev/s
    start(wire)
    enable(wire, 0x201, h('FF'))
    wire.send(0x201, h('1F 00 FF'))                 # JOG start
    wire.wait_sw(lambda sw: sw & 0x0100)
    assert wire.write(0x1006, 0, 100000, 4) == h('60 06 10 00 00 00 00 00')    # 100 ms
    wire.drain(0x081)
    for _ in range(6):                              # SYNC every 50 ms: no alarm
        wire.send(0x080, b'')
        last_sync = time.monotonic()
        assert wire.silent(0x081, 0.05)
    emcy = wire.expect(0x081, 1.0)
    alarm_after_s = time.monotonic() - last_sync
    assert 0.1 <= alarm_after_s <= 0.1 + SYNC_CONFIRM_S + 0.05, alarm_after_s
    assert emcy[:2] == h('00 54') and int.from_bytes(emcy[3:7], 'little') == 1 << 18
    assert wire.read(0x222F, 1) == 1 << 18          # Ralarm32 bit 18
    assert wire.read(0x20B8, 1) & 0x0F == 0b0101    # Rcansts red LED: Sync error
    # Ralarmreact -4: not a "non mascherabile" power alarm, so the emergency ramp 0x6085
    ramp_s = vm.hz_from_rps100(300, 3200) / vm.hz_s_from_rps2x10(1000, 3200)
    wire.wait_sw(lambda sw: sw & 0x4F == 0x08, 1.0)  # FAULT at standstill
    assert not node.axis.moving and time.monotonic() - last_sync < 0.1 + ramp_s + 0.2
    # the cause is gone with the next SYNC: the manual's reset procedure works
    wire.send(0x201, h('00 00 FF'))
    wire.send(0x201, h('80 00 FF'))
    assert wire.sw() & 0x4F == 0x08                 # no SYNC yet: cause present, still FAULT
    wire.send(0x080, b'')
    assert wire.sdo('2F 03 10 00 00 00 00 00') == h('60 03 10 00 00 00 00 00')
    wire.send(0x201, h('00 00 FF'))
    wire.send(0x201, h('80 00 FF'))
    wire.wait_sw(lambda sw: sw & 0x4F == 0x40)


def test_the_sync_watchdog_is_off_by_default_and_after_a_reset_communication(bench):
    sim, wire = bench
    start(wire)
    enable(wire)
    assert wire.read(0x1006) == 0
    assert wire.silent(0x081, 0.3)                  # no SYNC, no 0x1006: no alarm
    wire.write(0x1006, 0, 50000, 4)
    wire.send(0x000, h('82 01'))                    # reset communication: 0x1006 = 0 again
    wire.expect(0x701, 1.0, h('00'))
    assert wire.read(0x1006) == 0 and wire.silent(0x081, 0.2)
    assert sim.nodes['axis1'].alarms == 0
