"""rd4_sim against the manual: literal frames over a real pty from an independent client, and
the Control Word / alarm behaviour of one unit on a simulated clock.

The wire tests write byte literals with plain pyserial (no project codec on the client side):
request bytes in, response bytes out, CRC included (manual §7.4.1 and §9, spec §11).
"""

import asyncio
import json
import termios
import time

import pytest
import serial
from stepper_drivers.vendors.rd4 import regmap as rm
from stepper_sim.harness import wait_for
from stepper_sim.rd4.sim import Rd4DriveSim, Rd4Options, RtuLine


def h(text: str) -> bytes:
    return bytes.fromhex(text)


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


class Client:
    """An independent master: raw bytes over pyserial on the pty (parity N: a pty refuses E)."""

    def __init__(self, path, baud):
        self.ser = serial.Serial(path, baud, parity='N', stopbits=1, timeout=1.0)

    def ask(self, frame: bytes, n: int) -> bytes:
        self.ser.reset_input_buffer()
        self.ser.write(frame)
        self.ser.timeout = 1.0
        return self.ser.read(n)

    def silent(self, frame: bytes) -> bytes:
        """Whatever comes back within 100 ms (a 9600-baud reply would take < 30 ms)."""
        self.ser.reset_input_buffer()
        self.ser.write(frame)
        self.ser.timeout = 0.1
        return self.ser.read(64)

    def close(self):
        self.ser.close()


@pytest.fixture
def line(tmp_path):
    """A fresh pty per test: units 1 (T32) and 2 (T48) at the factory 9600 8E1 (dip 01h)."""
    made = []

    def make(*units, **kwargs):
        units = units or (Rd4DriveSim('axis1', 1), Rd4DriveSim('axis2', 2, 'T48'))
        ln = RtuLine(units, tmp_path / 'rd4.pty', **kwargs)
        ln.start()
        made.append(ln)
        return ln
    yield make
    for ln in made:
        ln.stop()


@pytest.fixture
def client(line):
    clients = []

    def make(ln):
        c = Client(ln.link_path, ln.baud)
        clients.append(c)
        return c
    yield make
    for c in clients:
        c.close()


# --------------------------------------------------------------------- manual frame pairs
def _state_g1(u):
    u.set('ACCELERATION', 1000)
    u.set('DECELERATION', 1500)


GOLDEN = [
    # (id, sim state, request, response, check afterwards)
    ('G1 §9.1 FC03 Acceleration + Deceleration', _state_g1,
     '01 03 00 06 00 02 24 0A', '01 03 04 03 E8 05 DC 78 8A', None),
    ('G2 §9.2 Ex.1 FC04 Current position', lambda u: u.motion.set_position(12272),
     '01 04 00 02 00 02 D0 0B', '01 04 04 00 00 2F F0 E7 F0', None),
    ('G3 §9.2 Ex.2 FC04 Alarms', lambda u: setattr(u, 'alarms', 0x0081),
     '01 04 00 00 00 01 31 CA', '01 04 02 00 81 79 50', None),
    ('G4 §9.3 Ex.1 FC06 Acceleration', None,
     '01 06 00 06 05 DC 6B 02', '01 06 00 06 05 DC 6B 02',
     lambda u: u.get('ACCELERATION') == 1500),
    ('G5 §9.3 Ex.2 FC06 Control Word 0x0084', None,
     '01 06 00 2A 00 84 A8 61', '01 06 00 2A 00 84 A8 61',
     lambda u: u.cw == 0x0084 and u.hr[0x2A] == 0x0084),
    ('G6 §9.3 Ex.3 FC06 Control Word 0x0A80', lambda u: u.set('PRESET', 250),
     '01 06 00 2A 0A 80 AF 02', '01 06 00 2A 0A 80 AF 02',
     lambda u: u.saves == 1 and round(u.position) == 250),   # save and (bit 11) preset
    ('G7 §9.4 FC16 Acceleration + Deceleration', None,
     '01 10 00 06 00 02 04 05 DC 03 E8 B2 0D', '01 10 00 06 00 02 A1 C9',
     lambda u: (u.get('ACCELERATION'), u.get('DECELERATION')) == (1500, 1000)),
]


@pytest.mark.parametrize('name, state, request_hex, response_hex, check', GOLDEN,
                         ids=[g[0].split()[0] for g in GOLDEN])
def test_manual_frame_pairs_byte_for_byte(line, client, name, state, request_hex, response_hex,
                                          check):
    ln = line()
    unit = ln.unit('axis1')
    if state:
        with ln.lock:
            state(unit)
    reply = client(ln).ask(h(request_hex), len(h(response_hex)))
    assert reply == h(response_hex), f'{name}: {reply.hex(" ")}'
    if check:
        with ln.lock:
            assert check(unit), name


def test_silence_for_bad_crc_broadcast_other_node_and_garbage(line, client):
    ln = line()
    c = client(ln)
    good = h('01 03 00 06 00 02 24 0A')
    bad_crc = good[:-1] + bytes((good[-1] ^ 0x01,))
    broadcast = h('00 06 00 06 05 DC')
    other = h('05 03 00 06 00 02')
    from stepper_drivers.protocol.modbus_rtu import add_crc  # CRC of the altered frames
    for frame in (bad_crc, add_crc(broadcast), add_crc(other), h('FF 00 13')):
        assert c.silent(frame) == b'', frame.hex(' ')
    with ln.lock:
        assert ln.unit('axis1').get('ACCELERATION') == 1000     # the broadcast did nothing
    # the line is still in step: the next request gets exactly its reply
    assert c.ask(good, 9) == h('01 03 04 03 E8 03 E8 7A FD')
    assert ln.counters['crc_errors'] >= 2 and ln.counters['other_node'] == 1
    assert ln.counters['broadcast'] == 1


def test_garbage_reads_have_a_valid_crc_and_writes_still_act(line, client):
    """Fault 'garbage_reads': another device's words in the next `code` read replies,
    CRC valid (seeded, so reproducible); the writes still reach the unit."""
    import random

    from stepper_drivers.protocol.modbus_rtu import add_crc
    ln = line()
    c = client(ln)
    alarms = h('01 04 00 00 00 01 31 CA')                     # really 0x0040 (power-up)
    with ln.lock:
        assert 'next 2 reads' in ln.unit('axis1').inject('garbage_reads', 2, 5)
    expected = random.Random(5)
    for _ in range(2):
        word = expected.getrandbits(16)
        assert c.ask(alarms, 7) == add_crc(h('01 04 02') + word.to_bytes(2, 'big'))
    assert c.ask(alarms, 7) == add_crc(h('01 04 02 00 40'))   # the budget is used up
    assert c.ask(h('01 06 00 2A 00 84 A8 61'), 8) == h('01 06 00 2A 00 84 A8 61')
    control_word = h('01 03 00 2A 00 01 A5 C2')
    with ln.lock:
        assert ln.unit('axis1').cw == 0x0084                  # the write acted
        ln.unit('axis1').inject('garbage_reads', 0, 1)        # 0: until clear_fault
    expected.seed(1)
    for _ in range(3):
        word = expected.getrandbits(16)
        assert c.ask(control_word, 7) == add_crc(h('01 03 02') + word.to_bytes(2, 'big'))
    with ln.lock:
        ln.unit('axis1').inject('clear_fault', 0, 0)
    assert c.ask(control_word, 7) == add_crc(h('01 03 02 00 84'))


@pytest.mark.parametrize('request_hex, response_hex', [
    ('01 01 00 00 00 01 FD CA', '01 81 01 81 90'),       # FC01: not implemented
    ('01 03 00 2D 00 01 14 03', '01 83 02 C0 F1'),       # beyond the holding map (0x2C)
    ('01 04 00 10 00 01 30 0F', '01 84 02 C2 C1'),       # beyond the input map (0x0F)
    ('01 03 00 00 00 00', '01 83 03 01 31'),             # quantity 0
    ('01 03 00 00 00 7E', '01 83 03 01 31'),             # quantity 126 > 125
    ('01 06 00 2D 00 01', '01 86 02 C3 A1'),             # FC06 beyond the map
    ('01 10 00 2C 00 02 04 00 00 00 01', '01 90 02 CD C1'),   # FC16 across the end
])
def test_exception_responses(line, client, request_hex, response_hex):
    from stepper_drivers.protocol.modbus_rtu import add_crc, crc_ok
    ln = line()
    frame = h(request_hex)
    frame = frame if crc_ok(frame) and len(frame) in (8, 13) else add_crc(frame)
    assert client(ln).ask(frame, 5) == h(response_hex)


def test_holes_and_read_only_registers(line, client):
    from stepper_drivers.protocol.modbus_rtu import add_crc
    ln = line()
    c = client(ln)
    # default: the undocumented 0x1A-0x28 read 0, writes to Offset are acknowledged and ignored
    reply = c.ask(add_crc(h('01 03 00 19 00 02')), 9)
    assert reply[3:7] == h('00 64 00 00')
    assert c.ask(add_crc(h('01 06 00 14 12 34')), 8) == add_crc(h('01 06 00 14 12 34'))
    with ln.lock:
        assert ln.unit('axis1').get('OFFSET') == 0
    ln.stop()
    strict = Rd4Options(hole_policy='exception', ro_write_policy='exception')
    ln = line(Rd4DriveSim('axis1', 1, options=strict))
    c = client(ln)
    assert c.ask(add_crc(h('01 03 00 19 00 02')), 5) == h('01 83 02 C0 F1')
    assert c.ask(add_crc(h('01 06 00 18 00 30')), 5) == h('01 86 02 C3 A1')


def test_out_of_range_write_is_accepted_and_raises_machine_data_not_valid(line, client):
    from stepper_drivers.protocol.modbus_rtu import add_crc
    ln = line()
    c = client(ln)
    c.ask(add_crc(h('01 06 00 2A 00 84')), 8)
    c.ask(add_crc(h('01 06 00 2A 00 8C')), 8)                  # alarm reset edge
    assert c.ask(add_crc(h('01 04 00 00 00 01')), 7)[3:5] == h('00 00')
    frame = add_crc(h('01 06 00 0D 07 D0'))                   # Work speed 2000 > 1600
    assert c.ask(frame, 8) == frame                           # §5.4: no exception
    reply = c.ask(add_crc(h('01 04 00 00 00 02')), 9)
    alarms, status = int.from_bytes(reply[3:5], 'big'), int.from_bytes(reply[5:7], 'big')
    assert alarms == rm.ALARM_MACHINE_DATA_NOT_VALID | rm.ALARM_EMERGENCY
    assert status & rm.SW_ALARM
    wp = c.ask(add_crc(h('01 04 00 09 00 02')), 9)
    assert int.from_bytes(wp[3:7], 'big') == 1 << 12                 # Work speed [0x0D]
    c.ask(add_crc(h('01 06 00 2A 00 84')), 8)
    c.ask(add_crc(h('01 06 00 2A 00 8C')), 8)
    assert c.ask(add_crc(h('01 04 00 00 00 01')), 7)[3:5] == h('00 41')   # still invalid
    c.ask(add_crc(h('01 06 00 0D 06 40')), 8)                 # 1600: valid again
    c.ask(add_crc(h('01 06 00 2A 00 84')), 8)
    c.ask(add_crc(h('01 06 00 2A 00 8C')), 8)
    assert c.ask(add_crc(h('01 04 00 00 00 01')), 7)[3:5] == h('00 00')


def test_node_id_above_247_answers_as_247_and_baud_mismatch_is_silent(line, tmp_path):
    from stepper_drivers.protocol.modbus_rtu import add_crc
    ln = line(Rd4DriveSim('far', 250))
    c = Client(ln.link_path, 9600)
    try:
        reply = c.ask(add_crc(h('F7 04 00 0D 00 01')), 7)
        assert reply[:3] == h('F7 04 02') and int.from_bytes(reply[3:5], 'big') == 250
        c.ser.baudrate = 19200          # the master at another speed than the dip-switch
        assert c.silent(add_crc(h('F7 04 00 0D 00 01'))) == b''
        assert ln.counters['baud_mismatch'] == 1
    finally:
        c.close()


def test_line_timing_delays_the_reply_like_a_19200_line(line, client):
    from stepper_drivers.protocol.modbus_rtu import add_crc
    ln = line(baud_switch=0x04, line_timing=True)         # 19200 8E1 emulated
    c = client(ln)
    request = add_crc(h('01 04 00 00 00 08'))
    expected_s = (8 + 21) * 11 / 19200 + 3.5 * 11 / 19200     # request + t3.5 + reply
    times = []
    for _ in range(5):
        t0 = time.monotonic()
        assert len(c.ask(request, 21)) == 21
        times.append(time.monotonic() - t0)
        time.sleep(0.003)            # the master's own t3.5 before the next request
    assert min(times) >= expected_s - 0.0005, times
    assert sorted(times)[2] < expected_s + 0.008, times


def test_link_faults_corrupt_a_counted_number_of_replies_and_cut_the_pty(line, client):
    from stepper_drivers.protocol.modbus_rtu import add_crc, crc_ok
    ln = line()
    c = client(ln)
    request = add_crc(h('01 04 00 00 00 01'))
    ln.set_link_fault('corrupt_reply', 1)
    bad = c.ask(request, 7)
    assert len(bad) == 7 and bad[:5] == h('01 04 02 00 40') and not crc_ok(bad)
    assert crc_ok(c.ask(request, 7))
    ln.set_link_fault('cut')

    def gone():
        try:
            c.ask(request, 7)
        except (serial.SerialException, termios.error):   # a hung-up pty: tcflush gives EIO
            return True
        return False
    wait_for(gone, 2.0, 'the pty to go away')
    c.close()
    ln.set_link_fault('link_ok')
    wait_for(lambda: ln.counters['pty_opened'] == 2, 2.0, 'a new pty')
    assert crc_ok(client(ln).ask(request, 7))


def test_pymodbus_async_client_interoperates(line):
    from pymodbus.client import AsyncModbusSerialClient
    ln = line()

    async def run():
        c = AsyncModbusSerialClient(ln.link_path, baudrate=9600, parity='N', stopbits=1,
                                    timeout=0.3, retries=0)
        assert await c.connect()
        try:
            r = await c.read_holding_registers(0x06, count=2, device_id=1)
            assert r.registers == [1000, 1000]
            r = await c.read_input_registers(0x0C, count=4, device_id=2)
            assert r.registers == [0x01, 2, 0x0102, 0x0001]
            r = await c.write_register(0x0C, 800, device_id=2)
            assert not r.isError()
        finally:
            c.close()
    asyncio.run(run())
    with ln.lock:
        assert ln.unit('axis2').get('JOG_SPEED') == 800


# ------------------------------------------------------------------ one unit, simulated time
@pytest.fixture
def unit(tmp_path):
    clock = Clock()
    u = Rd4DriveSim('axis1', 1, clock=clock, storage_path=tmp_path / 'axis1.json')
    u.clock_ = clock
    return u


def advance(u, seconds, step=0.01):
    end = u.clock_.t + seconds
    while u.clock_.t < end:
        u.clock_.t = min(end, u.clock_.t + step)
        u.frame_received()
        u.update()


def ready(u, extra=0):
    u.control_word(rm.CW_READY | extra)
    u.control_word(rm.CW_READY | extra | rm.CW_ALARM_RESET)
    u.control_word(rm.CW_READY | extra)
    assert u.alarms == 0


def status(u):
    return u.input_registers()[1]


def test_power_up_is_emergency_until_emergency_high_then_alarm_reset(unit):
    assert unit.alarms == rm.ALARM_EMERGENCY and status(unit) & rm.SW_ALARM
    unit.control_word(rm.CW_ALARM_RESET)          # reset with bit 7 still low: stays
    assert unit.alarms == rm.ALARM_EMERGENCY
    unit.control_word(0)
    ready(unit)
    assert not status(unit) & rm.SW_ALARM


def test_start_moves_on_the_edge_and_sets_target_reached(unit):
    ready(unit)
    unit.write(0x2B, rm.split32(2000), 0x10)
    unit.control_word(rm.CW_READY | rm.CW_START)
    advance(unit, 0.1)
    assert status(unit) & rm.SW_AXIS_RUNNING
    advance(unit, 3.0)        # 2000 pulses at 1600 PPS, 1000 PPS^2: about 2.85 s
    sw = status(unit)
    assert round(unit.position) == 2000 and sw & rm.SW_TARGET_POSITION_REACHED
    assert not sw & rm.SW_AXIS_RUNNING
    advance(unit, 0.2)
    assert status(unit) & rm.SW_AXIS_IN_POSITION        # Position window time 100 ms
    # Start held high, new target written: nothing moves until Start is written again
    unit.write(0x2B, rm.split32(0), 0x10)
    assert not status(unit) & rm.SW_TARGET_POSITION_REACHED   # cleared by the new target
    advance(unit, 0.2)
    assert round(unit.position) == 2000
    unit.control_word(rm.CW_READY)
    unit.control_word(rm.CW_READY | rm.CW_START)
    advance(unit, 0.2)
    assert unit.position < 2000


def test_position_override_and_stop_bit(unit):
    ready(unit)
    unit.write(0x2B, rm.split32(5000), 0x10)
    unit.control_word(rm.CW_READY | rm.CW_START)
    advance(unit, 1.0)
    unit.write(0x2B, rm.split32(1000), 0x10)
    unit.control_word(rm.CW_READY | rm.CW_START)     # §8.1.1 position override
    advance(unit, 3.0)
    assert round(unit.position) == 1000
    unit.write(0x2B, rm.split32(-3000), 0x10)
    unit.control_word(rm.CW_READY)
    unit.control_word(rm.CW_READY | rm.CW_START)
    advance(unit, 1.0)
    unit.control_word(rm.CW_EMERGENCY | rm.CW_START)          # Stop low: decelerate
    advance(unit, 2.0)
    assert not status(unit) & rm.SW_AXIS_RUNNING and unit.alarms == 0
    assert -3000 < unit.position < 1000


def test_jog_stops_at_the_software_limit_and_both_jog_bits_stop(unit):
    unit.set('POSITIVE_DELTA', 300)
    unit._machine_data_changed()
    ready(unit)
    unit.control_word(rm.CW_READY | rm.CW_JOG_PLUS)
    advance(unit, 2.0)
    assert round(unit.position) == 300 and status(unit) & rm.SW_SW_LIMIT_SWITCH_PLUS
    unit.control_word(rm.CW_READY | rm.CW_JOG_MINUS)
    advance(unit, 0.3)
    assert status(unit) & rm.SW_AXIS_RUNNING
    unit.control_word(rm.CW_READY | rm.CW_JOG)                # both: stop
    advance(unit, 2.0)
    assert not status(unit) & rm.SW_AXIS_RUNNING


def test_jog_is_ignored_while_positioning(unit):
    ready(unit)
    unit.write(0x2B, rm.split32(3000), 0x10)
    unit.control_word(rm.CW_READY | rm.CW_START)
    advance(unit, 0.5)
    unit.control_word(rm.CW_READY | rm.CW_START | rm.CW_JOG_MINUS)
    advance(unit, 4.0)
    assert round(unit.position) == 3000


def test_incremental_jog_steps_one_jog_step_length_per_rising_edge(unit):
    ready(unit)
    mode = rm.CW_READY | rm.CW_INCREMENTAL_JOG
    unit.control_word(mode)
    for _ in range(2):
        unit.control_word(mode | rm.CW_JOG_PLUS)
        advance(unit, 1.0)                      # held: still one step
        unit.control_word(mode)
    assert round(unit.position) == 200          # Jog step length default 100
    unit.control_word(mode | rm.CW_JOG_MINUS)
    advance(unit, 1.0)
    assert round(unit.position) == 100


def test_target_outside_the_limits_raises_target_not_valid(unit):
    ready(unit)
    unit.write(0x2B, rm.split32(600000), 0x10)
    unit.control_word(rm.CW_READY | rm.CW_START)
    assert unit.alarms == rm.ALARM_TARGET_NOT_VALID | rm.ALARM_EMERGENCY
    advance(unit, 0.5)
    assert unit.position == 0
    unit.control_word(rm.CW_READY)
    unit.control_word(rm.CW_READY | rm.CW_ALARM_RESET)
    assert unit.alarms == 0


def test_emergency_low_stops_at_once_and_latches(unit):
    ready(unit)
    unit.control_word(rm.CW_READY | rm.CW_JOG_PLUS)
    advance(unit, 1.0)
    at = unit.position
    unit.control_word(rm.CW_STOP)               # bit 7 low
    advance(unit, 0.5)
    assert unit.position == at and unit.alarms == rm.ALARM_EMERGENCY
    assert not status(unit) & rm.SW_AXIS_ENABLED


def test_watchdog_trips_after_one_second_without_a_frame(unit):
    ready(unit, rm.CW_WATCH_DOG_ENABLE)
    unit.control_word(rm.CW_READY | rm.CW_WATCH_DOG_ENABLE | rm.CW_JOG_PLUS)
    advance(unit, 2.0)                          # frames keep it fed (advance feeds it)
    assert unit.alarms == 0
    unit.clock_.t += 0.9
    unit.update()
    assert unit.alarms == 0
    unit.clock_.t += 0.2
    unit.update()
    assert unit.alarms == rm.ALARM_WATCH_DOG | rm.ALARM_EMERGENCY
    assert not unit.motion.moving


def test_injected_alarm_needs_its_cause_gone_before_reset(unit):
    ready(unit)
    unit.inject('drive_fault', rm.ALARM_OVERTEMPERATURE, 0)
    assert unit.alarms == rm.ALARM_OVERTEMPERATURE | rm.ALARM_EMERGENCY
    unit.control_word(rm.CW_READY | rm.CW_ALARM_RESET)
    unit.control_word(rm.CW_READY)
    assert unit.alarms & rm.ALARM_OVERTEMPERATURE
    unit.inject('clear_fault', 0, 0)
    unit.control_word(rm.CW_READY | rm.CW_ALARM_RESET)
    assert unit.alarms == 0
    unit.inject('drive_fault', rm.ALARM_FLASH_MEMORY_ERROR, 0)
    unit.inject('clear_fault', 0, 0)
    unit.control_word(rm.CW_READY)
    unit.control_word(rm.CW_READY | rm.CW_ALARM_RESET)
    assert unit.alarms & rm.ALARM_FLASH_MEMORY_ERROR     # §8.1.2: cannot be restored


def test_preset_applies_on_bit_11_edge_by_default_or_on_write(unit, tmp_path):
    ready(unit)
    unit.write(0x16, rm.split32(-500), 0x10)
    assert unit.position == 0                               # stored, not applied
    unit.control_word(rm.CW_READY | rm.CW_PERFORM_COUNTING_PRESET)
    assert unit.position == -500 and unit.limits == (-500 - 523263, -500 + 523263)
    assert unit.get('OFFSET') == 500                        # real position - preset
    eager = Rd4DriveSim('b', 2, clock=Clock(), options=Rd4Options(preset_on_write=True))
    eager.write(0x16, rm.split32(1234), 0x10)
    assert eager.position == 1234


def test_save_persists_and_load_defaults_does_not(unit, tmp_path):
    ready(unit)
    unit.write(0x06, [2500], 0x06)
    unit.write(0x16, rm.split32(100), 0x10)
    unit.control_word(rm.CW_READY | rm.CW_PERFORM_COUNTING_PRESET)
    unit.control_word(rm.CW_READY | rm.CW_SAVE_PARAMETERS)
    stored = json.loads((tmp_path / 'axis1.json').read_text())
    assert stored['values']['ACCELERATION'] == 2500 and stored['values']['PRESET'] == 100
    unit.control_word(rm.CW_READY | rm.CW_LOAD_DEFAULT_PARAMETERS)
    assert unit.get('ACCELERATION') == 1000
    again = Rd4DriveSim('axis1', 1, clock=Clock(), storage_path=tmp_path / 'axis1.json')
    assert again.get('ACCELERATION') == 2500 and again.get('OFFSET') == -100
    assert again.position == 100          # the absolute reference survives the power cycle
    assert again.alarms == rm.ALARM_EMERGENCY


def test_current_velocity_register_updates_once_per_second(unit):
    ready(unit)
    unit.control_word(rm.CW_READY | rm.CW_JOG_PLUS)
    advance(unit, 0.5)
    assert unit.input_registers()[4] == 0
    advance(unit, 2.1)
    assert unit.input_registers()[4] == 1600
