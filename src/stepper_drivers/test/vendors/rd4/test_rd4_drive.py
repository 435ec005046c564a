"""Rd4Drive + ModbusRtuBus against rd4_sim's RtuLine on a real pty: the node's frames on the
wire, retries and counters, alarms, preset, save; the step-wise operations (drive.py contract);
garbage content with a valid CRC, identity, motion refused unless enabled on the wire,
the unit's own watchdog, transport failures.

Expected frames are literals from spec/lika_rd4.md §11.2 where it has them; the others get their
CRC from `crc_modbus` below (the spec's bitwise routine, independent of the code under test).
"""

import socket
import struct
import threading
import time

import pytest
from stepper_drivers.contract.drive import (
    DriveError,
    Homing,
    IdentityError,
    LinkError,
    Motion,
    State,
    complete,
)
from stepper_drivers.protocol import modbus_rtu as rtu
from stepper_drivers.vendors import rd4
from stepper_drivers.vendors.rd4 import regmap as rm
from stepper_sim.harness import wait_for
from stepper_sim.rd4.sim import TICK_S, Rd4DriveSim, Rd4Options, RtuLine


def crc_modbus(data: bytes) -> bytes:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes((crc & 0xFF, crc >> 8))


def f(text: str) -> bytes:
    """A frame from hex; 'CRC' at the end is replaced by the CRC."""
    if text.endswith('CRC'):
        body = bytes.fromhex(text[:-3])
        return body + crc_modbus(body)
    return bytes.fromhex(text)


POLL = f('01 04 00 00 00 08 CRC')
CHECK = f('01 04 00 00 00 02 71 CB')        # Alarms + Status word: enabled, checked on the wire
MOTION = Motion(velocity_steps_s=800.0, acceleration_steps_s2=1000.0,
                deceleration_steps_s2=1000.0)


class Rig:
    def __init__(self, tmp_path, units=None, options=None, line_timing=False, **drive_params):
        self.frames = []
        tmp_path.mkdir(exist_ok=True)
        units = units or [Rd4DriveSim('axis1', 1, options=options),
                          Rd4DriveSim('axis2', 2, 'T48', options=options)]
        self.line = RtuLine(units, tmp_path / 'rd4.pty', baud_switch=0x03,
                            line_timing=line_timing,
                            tap=lambda d, frame, t: self.frames.append((d, frame, t)))
        self.line.start()
        self.bus = rd4.make_bus({'port': str(tmp_path / 'rd4.pty'), 'baudrate': 19200,
                                 'parity': 'N', 'timeout_s': 0.1})
        self.bus.open()
        self.drives = {}
        for u in units:
            params = {'node_id': u.node_id, 'steps_per_rev': 1024.0, **drive_params}
            self.drives[u.name] = rd4.make_drive(self.bus, u.name, params)

    def sent(self):
        """Frames the master wrote since the last call."""
        out = [frame for d, frame, _t in self.frames if d == 'rx']
        self.frames.clear()
        return out

    def unit(self, name='axis1'):
        return self.line.unit(name)

    def close(self):
        self.bus.close()
        self.line.stop()


@pytest.fixture
def rig(tmp_path):
    rigs = []

    def make(**kwargs):
        r = Rig(tmp_path / str(len(rigs)), **kwargs)
        rigs.append(r)
        return r
    yield make
    for r in rigs:
        r.close()


def wait_state(drive, cond, timeout_s=10.0, what='drive state'):
    return wait_for(lambda: (lambda s: s if cond(s) else None)(complete(drive.read_state())),
                    timeout_s, what, period_s=0.02)


def test_frames_of_enable_move_jog_stop_preset_and_save_on_the_wire(rig):
    r = rig(watchdog=False, hold_torque=False)
    d = r.drives['axis1']
    complete(d.connect())
    r.sent()
    assert complete(d.read_state()).state == State.SWITCH_ON_DISABLED
    assert r.sent() == [POLL]
    complete(d.enable())
    assert r.sent() == [
        f('01 04 00 00 00 04 CRC'),                           # Alarms .. Current position
        f('01 10 00 2B 00 02 04 00 00 00 00 CRC'),            # Target position := 0
        f('01 06 00 2A 00 84 A8 61'),                         # Emergency + Stop high
        f('01 06 00 2A 00 8C A9 A7'), f('01 06 00 2A 00 84 A8 61'),   # Alarm reset edge
        f('01 04 00 00 00 01 31 CA')]                         # Alarms read back: 0
    assert complete(d.read_state()).state == State.OPERATION_ENABLED
    r.sent()

    complete(d.move_to(1000, MOTION))
    assert r.sent() == [
        CHECK,                                                # no alarm: enabled on the wire
        f('01 06 00 0D 03 20 CRC'),                           # Work speed 800 PPS
        f('01 10 00 2B 00 02 04 00 00 03 E8 B0 BA'),          # Target position 1000
        f('01 06 00 2A 00 C4 A9 91')]                         # Start (0 -> 1)
    st = wait_state(d, lambda s: s.target_reached and not s.moving, what='at 1000')
    assert st.position_steps == 1000
    assert r.sent()[-2:] == [POLL, f('01 06 00 2A 00 84 A8 61')]   # Start to 0 when reached
    complete(d.read_state())
    assert r.sent() == [POLL]

    complete(d.set_velocity(-800.0, MOTION))
    assert r.sent() == [CHECK,
                        f('01 06 00 0C 03 20 48 E1'),         # Jog speed 800 PPS
                        f('01 06 00 2A 00 86 29 A0')]         # Jog -
    complete(d.set_velocity(-800.0, MOTION))
    assert r.sent() == []                                     # nothing new to say
    complete(d.set_velocity(800.0, MOTION))
    assert r.sent() == [CHECK, f('01 06 00 2A 00 85 69 A1')]  # Jog + (reverses)
    complete(d.set_velocity(0.0, MOTION))
    assert r.sent() == [f('01 06 00 2A 00 84 A8 61')]         # jog released: decelerates
    wait_state(d, lambda s: not s.moving, what='jog stopped')

    complete(d.move_to(-2000, MOTION))
    r.sent()
    wait_state(d, lambda s: s.moving, what='moving')
    d.stop()
    assert r.sent()[-1:] == [f('01 06 00 2A 00 80 A9 A2')]   # Stop low: decelerated stop
    wait_state(d, lambda s: not s.moving and s.status_word & rm.SW_AXIS_RUNNING == 0)
    assert f('01 06 00 2A 00 84 A8 61') in r.sent()           # Stop high again at rest
    assert complete(d.read_state()).enabled
    r.sent()

    note = complete(d.start_homing(Homing(35, 0, 0.0, 0.0, 0.0)))
    assert 'preset' in note
    assert r.sent() == [CHECK,                                          # enabled, at rest
                        f('01 10 00 16 00 02 04 00 00 00 00 72 89'),    # Preset := 0
                        f('01 06 00 2A 08 84 AF A1'), f('01 06 00 2A 00 84 A8 61'),  # bit 11
                        f('01 04 00 02 00 02 D0 0B')]                   # Current position
    assert complete(d.read_state()).position_steps == 0
    r.sent()

    complete(d.save_params())
    assert r.sent() == [f('01 04 00 00 00 02 71 CB'),                    # standstill, alarms
                        f('01 03 00 00 00 1A C4 01'),                    # machine data
                        f('01 06 00 2A 02 84 A9 01'),                    # Save edge
                        f('01 03 00 2A 00 01 A5 C2'),                    # Control Word echo
                        f('01 06 00 2A 00 84 A8 61'),
                        f('01 03 00 00 00 1A C4 01'),                    # read back
                        f('01 04 00 00 00 01 31 CA')]                    # no Flash error
    with r.line.lock:
        assert r.unit().saves == 1


def test_watchdog_and_hold_torque_bits_and_keep_alive(rig):
    r = rig()                                  # watchdog and hold_torque default on
    d = r.drives['axis1']
    complete(d.connect())
    complete(d.enable())
    assert r.unit().cw == rm.CW_READY | rm.CW_WATCH_DOG_ENABLE | rm.CW_AXIS_TORQUE  # 0x1184
    t_end = time.monotonic() + 1.5
    while time.monotonic() < t_end:            # polled at 20 Hz: the watchdog stays fed
        assert not complete(d.read_state()).fault
        time.sleep(0.05)                       # the poll rate under test
    with r.line.lock:
        r.unit().last_frame_at -= 1.5          # as if the master fell silent for 1.5 s
        r.unit().update()
    st = wait_state(d, lambda s: s.fault, what='watch dog alarm')
    assert st.state == State.FAULT and 'Watch dog' in st.fault_text
    assert st.fault_code == rm.ALARM_WATCH_DOG | rm.ALARM_EMERGENCY
    assert complete(d.fault_reset()) == ''
    assert complete(d.read_state()).state == State.SWITCH_ON_DISABLED
    assert r.unit().cw == rm.CW_EMERGENCY      # reset leaves it disabled, watchdog off


def test_crc_error_is_counted_and_retried_then_link_error(rig):
    r = rig()
    d = r.drives['axis1']
    complete(d.connect())
    r.line.set_link_fault('corrupt_reply', 1)
    st = complete(d.read_state())                        # survives: the retry gets a good reply
    assert st.state == State.SWITCH_ON_DISABLED
    c = r.bus.counters()
    assert (c['crc_errors'], c['retries'], c['errors']) == (1, 1, 1)
    r.line.set_link_fault('corrupt_reply', 2)
    with pytest.raises(LinkError, match='CRC error'):
        complete(d.read_state())
    assert r.bus.counters()['crc_errors'] == 3
    assert complete(d.read_state()).state == State.SWITCH_ON_DISABLED   # fault budget used up


def test_no_reply_is_a_timeout_and_an_exception_is_not_retried(rig):
    r = rig(options=Rd4Options(hole_policy='exception'))
    ghost = rd4.make_drive(r.bus, 'ghost', {'node_id': 9})
    t0 = time.monotonic()
    with pytest.raises(LinkError, match='no reply within 0.1 s'):
        complete(ghost.connect())
    assert time.monotonic() - t0 < 1.0
    assert r.bus.counters()['timeouts'] == 2        # first try + 1 retry
    d = r.drives['axis1']
    with pytest.raises(DriveError, match='ILLEGAL DATA ADDRESS') as e:
        d.read_register('0x1A', 'u16')
    assert not isinstance(e.value, LinkError)
    c = r.bus.counters()
    assert (c['exceptions'], c['retries']) == (1, 1)    # the retry was the ghost's


def test_pty_cut_gives_link_error_and_reopen_works(rig):
    r = rig()
    d = r.drives['axis1']
    complete(d.connect())
    r.line.set_link_fault('cut')
    wait_for(lambda: r.line.counters['pty_opened'] == 1 and r.line._master is None, 2.0,
             'pty closed')
    with pytest.raises(LinkError):
        complete(d.read_state())
    r.bus.close()
    with pytest.raises(LinkError, match='cannot open'):
        r.bus.open()
    r.line.set_link_fault('link_ok')
    wait_for(lambda: r.line.counters['pty_opened'] == 2, 2.0, 'pty re-created')
    r.bus.open()
    assert complete(d.connect())['node_id'] == '1'


def test_enable_refused_while_alarm_and_fault_reset_reports_what_remains(rig):
    r = rig()
    d = r.drives['axis1']
    complete(d.connect())
    with r.line.lock:
        r.unit().inject('drive_fault', rm.ALARM_OVERCURRENT, 0)
    st = complete(d.read_state())
    assert st.fault and st.state == State.FAULT and 'Overcurrent' in st.fault_text
    with pytest.raises(DriveError, match='Overcurrent.*fault_reset'):
        complete(d.enable())
    remains = complete(d.fault_reset())
    assert remains.startswith('0x00C0') and 'Overcurrent' in remains
    with r.line.lock:
        r.unit().inject('clear_fault', 0, 0)
    assert complete(d.fault_reset()) == ''
    complete(d.enable())
    assert complete(d.read_state()).state == State.OPERATION_ENABLED


def test_wrong_parameters_are_named_in_fault_and_refuse_save(rig):
    r = rig()
    d = r.drives['axis1']
    complete(d.connect())
    complete(d.enable())
    d.write_register('WORK_SPEED', 'u16', 2000)       # > 1600: accepted, alarm (§5.4)
    st = complete(d.read_state())
    assert st.fault and 'Work speed [0x0D]' in st.fault_text
    with pytest.raises(DriveError, match='Work speed'):
        complete(d.save_params())
    assert 'Work speed [0x0D]' in complete(d.fault_reset())
    d.write_register('0x0D', 'u16', 1000)
    assert complete(d.fault_reset()) == ''


def test_commands_check_the_drives_own_ranges(rig):
    r = rig()
    d = r.drives['axis2']                               # T48: 1066 PPS at most
    complete(d.connect())
    with pytest.raises(DriveError, match='not enabled'):
        complete(d.move_to(10, MOTION))
    complete(d.enable())
    r.sent()
    refused = [
        (lambda: d.move_to(600000, MOTION),
         r'outside the software limits -523263..523263 for Target position \[0x2B-0x2C\]'),
        (lambda: d.move_to(100, Motion(800.0, 50.0, 1000.0)),
         r'acceleration 50 PPS\^2 is outside Acceleration \[0x06\] range 100..10000'),
        (lambda: d.move_to(100, Motion(800.0, 1000.0, 20000.0)),
         r'deceleration 20000 PPS\^2 is outside Deceleration \[0x07\] range 100..10000'),
        (lambda: d.move_to(100, Motion(1067.0, 1000.0, 1000.0)),
         r'velocity 1067 PPS is outside Work speed \[0x0D\] range 1..1066 PPS \(Max. speed '
         r'1066 x Distance per revolution 1024 / 1024'),
        (lambda: d.set_velocity(-5000.0, MOTION),
         r'velocity 5000 PPS is outside Jog speed \[0x0C\] range 1..1066'),
        (lambda: d.set_velocity(float('nan'), MOTION), r'velocity nan PPS is outside Jog speed'),
        (lambda: d.start_homing(Homing(35, 1048577, 0.0, 0.0, 0.0)),
         r'homing.offset = 1048577 pulses is outside Preset \[0x16-0x17\] range '
         r'-1048576..1048576'),
        (lambda: d.start_homing(Homing(19, 0, 1.0, 1.0, 1.0)), 'homing.method 19')]
    for command, text in refused:
        with pytest.raises(DriveError, match=text):
            complete(command())
        assert r.sent() == []                          # refused before anything is written
    complete(d.move_to(100, Motion(1066.0, 100.0, 10000.0)))     # the range's ends are taken
    assert r.sent() == [f('02 04 00 00 00 02 CRC'),
                        f('02 10 00 06 00 02 04 00 64 27 10 CRC'),   # 100, 10000 PPS^2
                        f('02 10 00 2B 00 02 04 00 00 00 64 CRC'),   # Work speed 1066 is
                        f('02 06 00 2A 11 C4 CRC')]                  # the T48 default


def test_quick_stop_is_emergency_and_enable_recovers(rig):
    r = rig()
    d = r.drives['axis1']
    complete(d.connect())
    complete(d.enable())
    complete(d.set_velocity(1000.0, MOTION))
    wait_state(d, lambda s: s.moving, what='jogging')
    d.stop(quick=True)
    st = complete(d.read_state())
    assert not st.moving and not st.fault and st.state == State.SWITCH_ON_DISABLED
    assert 'Emergency' in st.alarms
    complete(d.enable())
    assert complete(d.read_state()).state == State.OPERATION_ENABLED


def test_raw_registers(rig):
    r = rig()
    d = r.drives['axis1']
    complete(d.connect())
    assert d.read_register('ir:0x0D', 'u16') == 1
    assert d.read_register('hr:0x08', 'u32') == 523263
    assert d.read_register('ACCELERATION', 'u16') == 1000
    with pytest.raises(DriveError, match='low word of Positive delta'):
        d.read_register('0x09', 'u16')
    with pytest.raises(DriveError, match='read-only'):
        d.write_register('GEAR_RATIO', 'u16', 48)
    with pytest.raises(DriveError, match='outside the RD4 map'):
        d.read_register('ir:0x10', 'u16')
    d.write_register('CONTROL_WORD', 'u16', 0x0084)
    assert d.cw == 0x0084
    d.write_register('hr:0x16', 'i32', -500)
    assert d.read_register('PRESET', 'i32') == -500
    assert d.limits == (-500 - 523263, -500 + 523263)   # cache refreshed after a raw write


def test_vendor_parameters_are_checked_with_one_line(tmp_path):
    bad = [({'port': 'x', 'baudrate': 4800}, 'baudrate: 4800 is not an RD4 baud rate'),
           ({'port': 'x', 'baudrate': 14400},
            r'^parameter baudrate: 14400 is not an RD4 baud rate \(allowed: 9600, 19200; '
            r'§4.4.2 dip-switch\)$'),
           ({'port': 'x', 'baudrate': 'fast'}, r"^parameter baudrate: 'fast' is not a number "
                                               r'\(allowed: 9600, 19200\)$'),
           ({'port': 'x', 'retries': 9}, 'parameter timeout_s/retries'),
           ({'port': 'x', 'parity': 'N', 'stopbits': 1}, 'stopbits: 1 with parity N'),
           ({'port': ''}, "port: ''")]
    for params, text in bad:
        with pytest.raises(ValueError, match=text):
            rd4.make_bus(params)
    bus = rd4.make_bus({'port': str(tmp_path / 'nothing'), 'baudrate': 19200, 'parity': 'E'})
    assert bus.stopbits == 1 and bus.description.endswith('19200 8E1')
    with pytest.raises(LinkError, match=r'cannot open .*nothing at 19200 baud 8E1'):
        bus.open()
    for params, text in [({'homing.method': 19}, 'drives.a.homing.method: 19'),
                         ({'node_id': 0}, 'drives.a.node_id: 0'),
                         ({'publish_rate_hz': 2.0}, 'publish_rate_hz >= 5')]:
        with pytest.raises(ValueError, match=text):
            rd4.make_drive(bus, 'a', params)


# ------------------------------------------------------------------------ step-wise operations
def frames_per_step(r, result):
    """Run a step-wise result by hand: the frames the master sent in each step, and the value."""
    counts = []
    while True:
        try:
            next(result)
        except StopIteration as stop:
            counts.append(len(r.sent()))
            return counts, stop.value
        counts.append(len(r.sent()))


def test_every_step_is_one_transaction_and_a_stop_goes_between_the_reads_of_a_poll(rig):
    r = rig(watchdog=False, hold_torque=False)
    d = r.drives['axis1']
    counts, identity = frames_per_step(r, d.connect())
    assert counts == [1, 1, 1] and identity['product'] == 'RD4 ROTADRIVE T32'
    counts, _ = frames_per_step(r, d.enable())              # from the power-up Emergency
    assert counts == [1, 1, 1, 1, 1, 1]
    counts, _ = frames_per_step(r, d.move_to(500, MOTION))
    assert counts == [1, 1, 1, 1]                   # check, Work speed, Target position, Start
    counts, _ = frames_per_step(r, d.set_velocity(-800.0, MOTION))
    assert counts == [1, 1, 1]                      # check, Jog speed, Jog -
    assert d.stop() is None and len(r.sent()) == 1  # plain: one transaction, no step
    wait_state(d, lambda s: not s.moving, what='stopped')
    complete(d.read_state())
    r.sent()
    counts, note = frames_per_step(r, d.start_homing(Homing(35, 0, 0.0, 0.0, 0.0)))
    assert counts == [1, 1, 1, 1, 1] and 'preset' in note
    counts, _ = frames_per_step(r, d.save_params())
    assert max(counts) == 1 and sum(counts) == 7, counts

    # Machine data not valid: a poll is two FC04 (20.6 + 13.7 ms of line at 19200). A stop
    # given between the poll's steps reaches the wire after the first one, not after both.
    d.write_register('WORK_SPEED', 'u16', 2000)
    r.sent()
    poll = d.read_state()
    next(poll)
    assert r.sent() == [POLL]
    d.stop()
    assert r.sent() == [f('01 06 00 2A 00 80 CRC')]
    st = complete(poll)
    assert r.sent() == [f('01 04 00 09 00 02 CRC')]           # Wrong parameters list
    assert 'Work speed [0x0D]' in st.fault_text


# ------------------------------------------------------------------------------ garbage content
def cw_writes(frames):
    """Values written to Control Word [0x2A] (FC06, or FC16 covering it), in order."""
    out = []
    for fr in frames:
        address = int.from_bytes(fr[2:4], 'big')
        if fr[1] == 0x06 and address == 0x2A:
            out.append(int.from_bytes(fr[4:6], 'big'))
        elif fr[1] == 0x10 and address <= 0x2A < address + int.from_bytes(fr[4:6], 'big'):
            i = 7 + 2 * (0x2A - address)
            out.append(int.from_bytes(fr[i:i + 2], 'big'))
    return out


def run_all(ops):
    """Run each operation, counting the outcomes (garbage makes most of them fail)."""
    outcomes = {}
    for op in ops:
        try:
            complete(op())
            kind = 'ok'
        except (IdentityError, LinkError, DriveError) as e:
            kind = type(e).__name__
        outcomes[kind] = outcomes.get(kind, 0) + 1
    return outcomes


def test_garbage_replies_never_make_the_driver_write_an_uncommanded_control_word(rig):
    """Another device answers at node 1 (valid CRC, its own register contents), while the real
    unit still takes the writes. The driver reconnects, polls and is told to stop, over and
    over: the only Control Word it ever writes is the stop it was told to send; nothing
    moves, saves or presets (the user's case: 0x2A := 0x6B8E, Jog - + Save + Counting preset,
    and 59 rad on an axis never enabled)."""
    r = rig(watchdog=False, hold_torque=False)
    d = r.drives['axis1']
    complete(d.connect())
    unit = r.unit()
    with r.line.lock:
        start_steps, start_offset = unit.position, unit.get('OFFSET')
        unit.inject('garbage_reads', 0, 9)               # every read, seed 9
    r.sent()
    outcomes = run_all([d.connect, d.read_state, d.read_state, d.stop] * 40)
    sent = r.sent()
    assert cw_writes(sent) == [rm.CW_EMERGENCY] * 40      # 0x0080: Stop low, nothing else
    assert all(fr[1] in (0x03, 0x04) or cw_writes([fr]) for fr in sent), 'other writes'
    # every connect refused; nearly every poll implausible (LinkError: the node reconnects)
    assert outcomes['IdentityError'] == 40 and outcomes['LinkError'] >= 70, outcomes
    with r.line.lock:
        assert unit.position == start_steps and not unit.motion.moving
        assert unit.get('OFFSET') == start_offset and unit.saves == 0

    # Enabled and at a target: what garbage may make it write is its own intent only.
    with r.line.lock:
        unit.inject('clear_fault', 0, 0)
    complete(d.connect())
    complete(d.enable())
    complete(d.move_to(300, MOTION))
    wait_state(d, lambda s: s.target_reached and not s.moving, what='at 300')
    complete(d.read_state())
    with r.line.lock:
        unit.inject('garbage_reads', 0, 10)
    r.sent()
    outcomes = run_all([d.connect, d.read_state, d.read_state, d.stop,
                        lambda: d.move_to(0, MOTION), d.fault_reset] * 30)
    sent = r.sent()
    # stop: 0x0080; Start back to 0 or Stop high again: 0x0084; fault_reset, when the garbage
    # reads as a plausible alarm, its own Alarm reset edge 0x0088: nothing else, ever.
    commanded = {rm.CW_EMERGENCY, rm.CW_READY, rm.CW_EMERGENCY | rm.CW_ALARM_RESET}
    assert set(cw_writes(sent)) <= commanded, [hex(cw) for cw in cw_writes(sent)]
    assert all(fr[1] in (0x03, 0x04) or cw_writes([fr]) for fr in sent), 'other writes'
    with r.line.lock:
        assert round(unit.position) == 300 and unit.saves == 0
    assert outcomes.get('ok', 0) <= 30, outcomes        # the stops only


def test_a_control_word_read_at_connect_is_never_written_back(rig):
    """The unit's Control Word register holds another master's word (Start, Jog -, Save,
    Counting preset, outputs): connect only reads it; stop writes the driver's own word."""
    r = rig(watchdog=False, hold_torque=False)
    d = r.drives['axis1']
    with r.line.lock:
        r.unit().hr[0x2A] = 0x6BCE
    identity = complete(d.connect())
    assert complete(d.read_state()).state == State.SWITCH_ON_DISABLED
    r.sent()
    d.stop()
    assert r.sent() == [f('01 06 00 2A 00 80 CRC')]
    assert identity['control_word'] == '0x6BCE (not enabled by this node)'
    with pytest.raises(DriveError, match='not enabled; call enable first'):
        complete(d.move_to(100, MOTION))
    assert r.sent() == []


def test_reconnect_keeps_the_intent_only_while_the_unit_holds_the_last_word(rig):
    r = rig()
    d = r.drives['axis1']
    complete(d.connect())
    complete(d.enable())
    complete(d.connect())                                  # a reconnect after a short loss
    assert complete(d.read_state()).state == State.OPERATION_ENABLED
    with r.line.lock:                                      # power cycled meanwhile
        r.unit().control_word(0x0000)
    identity = complete(d.connect())
    assert identity['control_word'] == '0x0000 (not enabled by this node)'
    st = complete(d.read_state())
    assert st.state == State.SWITCH_ON_DISABLED and not st.enabled
    with pytest.raises(DriveError, match='not enabled'):
        complete(d.set_velocity(100.0, MOTION))


# ------------------------------------------------------------------------------- identity
def unit_with(hw_version=0x0001, **changes):
    """A simulated unit with attributes, or holding registers (hr_<hex address>), changed."""
    def make():
        u = Rd4DriveSim('axis1', 1, hw_version=hw_version)
        for key, value in changes.items():
            if key.startswith('hr_'):
                u.hr[int(key[3:], 16)] = value
            else:
                setattr(u, key, value)
        return u
    return make


@pytest.mark.parametrize('make, text', [
    (unit_with(hw_version=0x2001), r'HW Version \[0x0F\] reads HW 1, RD5, Modbus'),
    (unit_with(hw_version=0x0201), r'HW Version \[0x0F\] reads HW 1, RD4, CANopen'),
    (unit_with(hw_version=0x0071), r'HW Version .* bits 4-6 clear'),
    (unit_with(switch_node_id=5), r'Dip-switch node ID \[0x0D\] reads 5, expected 1'),
    (unit_with(hr_18=7), r'Gear ratio \[0x18\] reads 7, expected 32 \(T32\) or 48'),
    (unit_with(hr_0D=2000), r'Work speed \[0x0D\] reads 2000, outside 1..1600 and Wrong '
                            r'parameters list \[0x09-0x0A\] = 0x00000000 does not list it'),
    (unit_with(hr_00=0), r'Distance per revolution \[0x00\] reads 0, outside 1..1024')])
def test_connect_refuses_a_device_that_is_plainly_not_an_rd4(rig, make, text):
    r = rig(units=[make()])
    d = r.drives['axis1']
    with pytest.raises(IdentityError, match=rf'axis1: node 1 is not .*{text}'):
        complete(d.connect())
    assert all(fr[1] in (0x03, 0x04) for fr in r.sent())   # it wrote nothing


def test_identity_baud_register_garbage_and_missing_registers(rig):
    r = rig(units=[Rd4DriveSim('axis1', 1)])
    d = r.drives['axis1']
    with r.line.lock:
        r.unit().baud_switch = 0x01                       # says 9600 8E1, answers at 19200
    with pytest.raises(IdentityError, match=r'Dip-switch baud rate \[0x0C\] reads 01h = 9600 '
                                            r'8E1, but it answers at 19200 baud'):
        complete(d.connect())
    with r.line.lock:
        r.unit().baud_switch = 0x03
        r.unit().inject('garbage_reads', 0, 1)
    with pytest.raises(IdentityError, match='is not the configured RD4: HW Version'):
        complete(d.connect())
    with r.line.lock:
        r.unit().inject('clear_fault', 0, 0)
    complete(d.connect())

    class NotAnRd4(Rd4DriveSim):
        """Another Modbus device: no input registers at all."""
        def handle(self, request, frame):
            if request.function_code == rtu.FC_READ_INPUT_REGISTERS:
                raise rtu.ModbusExceptionError(request.function_code, rtu.ILLEGAL_DATA_ADDRESS)
            return super().handle(request, frame)
    other = rig(units=[NotAnRd4('axis1', 1)]).drives['axis1']
    with pytest.raises(IdentityError, match=r'has no Dip-switch baud rate \[0x0C\] .. HW '
                                            r'Version \[0x0F\] \(FC04\) .*ILLEGAL DATA '
                                            r'ADDRESS.*not an RD4'):
        complete(other.connect())


def test_out_of_range_machine_data_the_unit_lists_as_wrong_is_still_an_rd4(rig):
    u = Rd4DriveSim('axis1', 1)
    u.write(rm.HR['WORK_SPEED'].address, [2000], rtu.FC_WRITE_SINGLE_REGISTER)  # §5.4: alarm
    r = rig(units=[u])
    d = r.drives['axis1']
    identity = complete(d.connect())
    assert identity['product'] == 'RD4 ROTADRIVE T32'
    st = complete(d.read_state())
    assert st.fault and 'Work speed [0x0D]' in st.fault_text


# ------------------------------------------------------------------- enabled, on the wire
def test_motion_and_preset_need_the_unit_enabled_on_the_wire(rig):
    r = rig(watchdog=False, hold_torque=False)
    d = r.drives['axis1']
    complete(d.connect())
    complete(d.enable())
    assert complete(d.read_state()).enabled
    with r.line.lock:                    # an alarm the driver has not polled yet
        r.unit().inject('drive_fault', rm.ALARM_OVERTEMPERATURE, 0)
    r.sent()
    for op in (lambda: d.move_to(100, MOTION), lambda: d.set_velocity(500.0, MOTION),
               lambda: d.start_homing(Homing(35, 0, 0.0, 0.0, 0.0))):
        with pytest.raises(DriveError, match=r'not enabled: Alarms register \[0x00\] = 0x0140 '
                                             r'\(Emergency, Overtemperature\); call fault_reset'):
            complete(op())
        assert r.sent() == [CHECK]                        # the check only, nothing written
    with r.line.lock:
        r.unit().inject('clear_fault', 0, 0)
    assert complete(d.fault_reset()) == ''
    complete(d.enable())
    with r.line.lock:                    # someone else's Emergency low (another master)
        r.unit().control_word(rm.CW_STOP)
    with pytest.raises(DriveError, match=r'Alarms register \[0x00\] = 0x0040 \(Emergency\); '
                                         'call enable'):
        complete(d.move_to(100, MOTION))
    with r.line.lock:
        assert not r.unit().motion.moving and round(r.unit().position) == 0


def test_a_fresh_poll_lets_the_motion_frames_go_first_a_stale_one_costs_the_check(rig):
    """Within state_fresh_s of a poll that found no alarm (the bus owner sets its poll period),
    a motion's first frame is its own; a stale snapshot, or a stop, disable or enable since,
    costs the FC04 check first."""
    r = rig(watchdog=False, hold_torque=False)
    d = r.drives['axis1']
    complete(d.connect())
    complete(d.enable())
    d.state_fresh_s = 0.3
    complete(d.read_state())
    r.sent()
    complete(d.move_to(500, MOTION))
    assert r.sent() == [f('01 06 00 0D 03 20 CRC'),                     # Work speed first
                        f('01 10 00 2B 00 02 04 00 00 01 F4 CRC'),      # Target position 500
                        f('01 06 00 2A 00 C4 A9 91')]                   # Start
    wait_state(d, lambda s: not s.moving and s.position_steps == 500, what='at 500')
    r.sent()
    complete(d.move_to(600, MOTION))                 # (wait_state polled: still fresh)
    assert r.sent()[0] == f('01 10 00 2B 00 02 04 00 00 02 58 CRC')     # Target position 600
    wait_state(d, lambda s: not s.moving and s.position_steps == 600, what='at 600')
    time.sleep(0.35)                                 # stale: older than state_fresh_s
    r.sent()
    complete(d.move_to(700, MOTION))
    assert r.sent()[0] == CHECK
    wait_state(d, lambda s: not s.moving and s.position_steps == 700, what='at 700')
    d.stop()                                         # a stop since the poll: checked again
    r.sent()
    complete(d.set_velocity(300.0, MOTION))
    assert r.sent()[0] == CHECK
    d.stop()
    wait_state(d, lambda s: not s.moving, what='jog stopped')
    complete(d.disable())                            # disabled: refused, nothing written
    r.sent()
    with pytest.raises(DriveError, match='not enabled'):
        complete(d.move_to(100, MOTION))
    assert r.sent() == []
    complete(d.enable())                             # enabled again, no poll since: checked
    r.sent()
    complete(d.move_to(100, MOTION))
    assert r.sent()[0] == CHECK
    # an alarm the last poll saw: checked on the wire (and refused there)
    wait_state(d, lambda s: not s.moving, what='at 100')
    with r.line.lock:
        r.unit().inject('drive_fault', rm.ALARM_OVERTEMPERATURE, 0)
    complete(d.read_state())
    r.sent()
    with pytest.raises(DriveError, match='Overtemperature'):
        complete(d.move_to(200, MOTION))
    assert r.sent() == [CHECK]


# -------------------------------------------------------------------- the unit's own watchdog
def test_unit_watchdog_stops_a_jog_one_second_after_the_master_falls_silent(rig):
    """The step-wise polls keep the 1 s watchdog fed; when the master stops (a killed node) the
    unit stops the jog with the Watch dog alarm 1 s after the last frame (§8.1.1 bit 8)."""
    r = rig()                                              # watchdog and hold torque on
    d = r.drives['axis1']
    complete(d.connect())
    complete(d.enable())
    unit = r.unit()
    assert unit.cw & rm.CW_WATCH_DOG_ENABLE
    complete(d.set_velocity(1000.0, MOTION))
    end = time.monotonic() + 1.5 * rm.WATCH_DOG_TIMEOUT_S
    while time.monotonic() < end:                          # polled at the node's 10 Hz
        st = complete(d.read_state())
        assert st.moving and not st.fault
        time.sleep(0.1)
    last_rx = max(t for direction, _frame, t in r.frames if direction == 'rx')
    wait_for(lambda: unit.alarms & rm.ALARM_WATCH_DOG, 2 * rm.WATCH_DOG_TIMEOUT_S,
             'Watch dog alarm', period_s=0.002)
    tripped_after_s = time.monotonic() - last_rx
    with r.line.lock:
        assert not unit.motion.moving and unit.motion.velocity_hz == 0.0
    # Never before 1 s; at most one model tick (TICK_S) and a little scheduling late.
    assert rm.WATCH_DOG_TIMEOUT_S <= tripped_after_s <= rm.WATCH_DOG_TIMEOUT_S + TICK_S + 0.1
    st = complete(d.read_state())
    assert st.fault and 'Watch dog' in st.fault_text and not st.moving


# ------------------------------------------------------------------------ transport failures
def test_transport_failures_are_one_line_link_errors(tmp_path):
    server = socket.socket()
    server.bind(('127.0.0.1', 0))
    server.listen(1)

    def reset_after_request():
        conn, _ = server.accept()
        conn.recv(64)
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack('ii', 1, 0))
        conn.close()                                      # RST: ConnectionResetError
    threading.Thread(target=reset_after_request, daemon=True).start()
    bus = rd4.make_bus({'port': f'socket://127.0.0.1:{server.getsockname()[1]}',
                        'baudrate': 19200, 'parity': 'N', 'timeout_s': 0.5})
    bus.open()
    try:
        with pytest.raises(LinkError, match=r'unit 1: FC04 read 8 at 0x00: .*reset by peer'):
            bus.read_input_registers(1, 0, 8)
    finally:
        bus.close()
        server.close()

    line = RtuLine([Rd4DriveSim('axis1', 1)], tmp_path / 'rd4.pty', baud_switch=0x03)
    line.start()
    try:
        bus = rd4.make_bus({'port': str(tmp_path / 'rd4.pty'), 'baudrate': 19200,
                            'parity': 'N'})
        bus.open()
        bus._serial.close()                               # the port closed under pyserial
        with pytest.raises(LinkError, match='FC04 read 8 at 0x00: TypeError') as e:
            bus.read_input_registers(1, 0, 8)
        assert '\n' not in str(e.value)
    finally:
        bus.close()
        line.stop()


def test_a_polled_position_is_dated_when_the_unit_took_it_not_when_the_poll_ended(rig):
    """With the line's timing, the request of the state block (FC04, 8 bytes) takes 4.6 ms and
    its reply (8 registers, 21 bytes) 11 ms at 19200 baud: the position was true after the
    request was out and at least the reply's transmission before the poll ended."""
    drive = rig(line_timing=True).drives['axis1']
    complete(drive.connect())
    request_s = rtu.frame_time_s(8, 19200)
    reply_s = rtu.frame_time_s(5 + 2 * rm.STATE_BLOCK[1], 19200)
    for _ in range(3):
        asked = time.monotonic()
        state = complete(drive.read_state())
        done = time.monotonic()
        assert state.measured_at_s is not None
        assert asked + request_s <= state.measured_at_s <= done - reply_s, \
            (asked, state.measured_at_s, done)
