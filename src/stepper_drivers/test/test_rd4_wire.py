"""Rd4Drive + ModbusRtuBus against rd4_sim's RtuLine on a real pty: the node's frames on the
wire, retries and counters, alarms, preset, save.

Expected frames are literals from spec/lika_rd4.md §11.2 where it has them; the others get their
CRC from `crc_modbus` below (the spec's bitwise routine, independent of the code under test).
"""

import time

import pytest
from stepper_drivers.drive import DriveError, Homing, LinkError, Motion, State
from stepper_drivers.tools.processes import wait_for
from stepper_drivers.vendors import rd4
from stepper_drivers.vendors import rd4_map as rm
from stepper_sim.rd4_sim import Rd4Options, Rd4Unit, RtuLine


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
MOTION = Motion(velocity_steps_s=800.0, acceleration_steps_s2=1000.0,
                deceleration_steps_s2=1000.0)


class Rig:
    def __init__(self, tmp_path, units=None, options=None, **drive_params):
        self.frames = []
        tmp_path.mkdir(exist_ok=True)
        units = units or [Rd4Unit('axis1', 1, options=options),
                          Rd4Unit('axis2', 2, 'T48', options=options)]
        self.line = RtuLine(units, tmp_path / 'rd4.pty', baud_switch=0x03,
                            tap=lambda d, frame, t: self.frames.append((d, frame)))
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
        out = [frame for d, frame in self.frames if d == 'rx']
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
    return wait_for(lambda: (lambda s: s if cond(s) else None)(drive.read_state()), timeout_s,
                    what, period_s=0.02)


def test_frames_of_enable_move_jog_stop_preset_and_save_on_the_wire(rig):
    r = rig(watchdog=False, hold_torque=False)
    d = r.drives['axis1']
    d.connect()
    r.sent()
    assert d.read_state().state == State.SWITCH_ON_DISABLED
    assert r.sent() == [POLL]
    d.enable()
    assert r.sent() == [
        f('01 04 00 00 00 04 CRC'),                           # Alarms .. Current position
        f('01 10 00 2B 00 02 04 00 00 00 00 CRC'),            # Target position := 0
        f('01 06 00 2A 00 84 A8 61'),                         # Emergency + Stop high
        f('01 06 00 2A 00 8C A9 A7'), f('01 06 00 2A 00 84 A8 61'),   # Alarm reset edge
        f('01 04 00 00 00 01 31 CA')]                         # Alarms read back: 0
    assert d.read_state().state == State.OPERATION_ENABLED
    r.sent()

    d.move_to(1000, MOTION)
    assert r.sent() == [
        f('01 06 00 0D 03 20 CRC'),                           # Work speed 800 PPS
        f('01 10 00 2B 00 02 04 00 00 03 E8 B0 BA'),          # Target position 1000
        f('01 06 00 2A 00 C4 A9 91')]                         # Start (0 -> 1)
    st = wait_state(d, lambda s: s.target_reached and not s.moving, what='at 1000')
    assert st.position_steps == 1000
    assert r.sent()[-2:] == [POLL, f('01 06 00 2A 00 84 A8 61')]   # Start to 0 when reached
    d.read_state()
    assert r.sent() == [POLL]

    d.set_velocity(-800.0, MOTION)
    assert r.sent() == [f('01 06 00 0C 03 20 48 E1'),         # Jog speed 800 PPS
                        f('01 06 00 2A 00 86 29 A0')]         # Jog -
    d.set_velocity(-800.0, MOTION)
    assert r.sent() == []                                     # nothing new to say
    d.set_velocity(800.0, MOTION)
    assert r.sent() == [f('01 06 00 2A 00 85 69 A1')]         # Jog + (reverses)
    d.set_velocity(0.0, MOTION)
    assert r.sent() == [f('01 06 00 2A 00 84 A8 61')]         # jog released: decelerates
    wait_state(d, lambda s: not s.moving, what='jog stopped')

    d.move_to(-2000, MOTION)
    r.sent()
    wait_state(d, lambda s: s.moving, what='moving')
    d.stop()
    assert r.sent()[-1:] == [f('01 06 00 2A 00 80 A9 A2')]   # Stop low: decelerated stop
    wait_state(d, lambda s: not s.moving and s.status_word & rm.SW_AXIS_RUNNING == 0)
    assert f('01 06 00 2A 00 84 A8 61') in r.sent()           # Stop high again at rest
    assert d.read_state().enabled
    r.sent()

    note = d.start_homing(Homing(35, 0, 0.0, 0.0, 0.0))
    assert 'preset' in note
    assert r.sent() == [f('01 10 00 16 00 02 04 00 00 00 00 72 89'),    # Preset := 0
                        f('01 06 00 2A 08 84 AF A1'), f('01 06 00 2A 00 84 A8 61'),  # bit 11
                        f('01 04 00 02 00 02 D0 0B')]                   # Current position
    assert d.read_state().position_steps == 0
    r.sent()

    d.save_params()
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
    d.connect()
    d.enable()
    assert r.unit().cw == rm.CW_READY | rm.CW_WATCH_DOG_ENABLE | rm.CW_AXIS_TORQUE  # 0x1184
    t_end = time.monotonic() + 1.5
    while time.monotonic() < t_end:            # polled at 20 Hz: the watchdog stays fed
        assert not d.read_state().fault
        time.sleep(0.05)                       # the poll rate under test
    with r.line.lock:
        r.unit().last_frame_at -= 1.5          # as if the master fell silent for 1.5 s
        r.unit().update()
    st = wait_state(d, lambda s: s.fault, what='watch dog alarm')
    assert st.state == State.FAULT and 'Watch dog' in st.fault_text
    assert st.fault_code == rm.ALARM_WATCH_DOG | rm.ALARM_EMERGENCY
    assert d.fault_reset() == ''
    assert d.read_state().state == State.SWITCH_ON_DISABLED
    assert r.unit().cw == rm.CW_EMERGENCY      # reset leaves it disabled, watchdog off


def test_crc_error_is_counted_and_retried_then_link_error(rig):
    r = rig()
    d = r.drives['axis1']
    d.connect()
    r.line.set_link_fault('corrupt_reply', 1)
    st = d.read_state()                        # survives: the retry gets a good reply
    assert st.state == State.SWITCH_ON_DISABLED
    c = r.bus.counters()
    assert (c['crc_errors'], c['retries'], c['errors']) == (1, 1, 1)
    r.line.set_link_fault('corrupt_reply', 2)
    with pytest.raises(LinkError, match='CRC error'):
        d.read_state()
    assert r.bus.counters()['crc_errors'] == 3
    assert d.read_state().state == State.SWITCH_ON_DISABLED   # fault budget used up


def test_no_reply_is_a_timeout_and_an_exception_is_not_retried(rig):
    r = rig(options=Rd4Options(hole_policy='exception'))
    ghost = rd4.make_drive(r.bus, 'ghost', {'node_id': 9})
    t0 = time.monotonic()
    with pytest.raises(LinkError, match='no reply within 0.1 s'):
        ghost.connect()
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
    d.connect()
    r.line.set_link_fault('cut')
    wait_for(lambda: r.line.counters['pty_opened'] == 1 and r.line._master is None, 2.0,
             'pty closed')
    with pytest.raises(LinkError):
        d.read_state()
    r.bus.close()
    with pytest.raises(LinkError, match='cannot open'):
        r.bus.open()
    r.line.set_link_fault('link_ok')
    wait_for(lambda: r.line.counters['pty_opened'] == 2, 2.0, 'pty re-created')
    r.bus.open()
    assert d.connect()['node_id'] == '1'


def test_enable_refused_while_alarm_and_fault_reset_reports_what_remains(rig):
    r = rig()
    d = r.drives['axis1']
    d.connect()
    with r.line.lock:
        r.unit().inject('drive_fault', rm.ALARM_OVERCURRENT, 0)
    st = d.read_state()
    assert st.fault and st.state == State.FAULT and 'Overcurrent' in st.fault_text
    with pytest.raises(DriveError, match='Overcurrent.*fault_reset'):
        d.enable()
    remains = d.fault_reset()
    assert remains.startswith('0x00C0') and 'Overcurrent' in remains
    with r.line.lock:
        r.unit().inject('clear_fault', 0, 0)
    assert d.fault_reset() == ''
    d.enable()
    assert d.read_state().state == State.OPERATION_ENABLED


def test_wrong_parameters_are_named_in_fault_and_refuse_save(rig):
    r = rig()
    d = r.drives['axis1']
    d.connect()
    d.enable()
    d.write_register('WORK_SPEED', 'u16', 2000)       # > 1600: accepted, alarm (§5.4)
    st = d.read_state()
    assert st.fault and 'Work speed [0x0D]' in st.fault_text
    with pytest.raises(DriveError, match='Work speed'):
        d.save_params()
    assert 'Work speed [0x0D]' in d.fault_reset()
    d.write_register('0x0D', 'u16', 1000)
    assert d.fault_reset() == ''


def test_commands_check_the_drives_own_ranges(rig):
    r = rig()
    d = r.drives['axis2']                               # T48: 1066 PPS at most
    d.connect()
    with pytest.raises(DriveError, match='not enabled'):
        d.move_to(10, MOTION)
    d.enable()
    with pytest.raises(DriveError, match='outside the software limits -523263..523263'):
        d.move_to(600000, MOTION)
    r.sent()
    d.move_to(100, Motion(5000.0, 50.0, 20000.0))
    assert r.sent()[:2] == [f('02 10 00 06 00 02 04 00 64 27 10 CRC'),   # 100, 10000 PPS^2
                            f('02 10 00 2B 00 02 04 00 00 00 64 CRC')]   # Work speed: 1066
    with r.line.lock:                                                    # is the default
        assert r.unit('axis2').get('WORK_SPEED') == 1066
    d.set_velocity(-5000.0, MOTION)
    assert r.sent() == [f('02 10 00 06 00 02 04 03 E8 03 E8 CRC'),      # MOTION's ramps
                        f('02 06 00 2A 11 86 CRC')]       # Jog - with Jog speed 1066 as is
    with pytest.raises(DriveError, match='homing.method 19'):
        d.start_homing(Homing(19, 0, 1.0, 1.0, 1.0))


def test_quick_stop_is_emergency_and_enable_recovers(rig):
    r = rig()
    d = r.drives['axis1']
    d.connect()
    d.enable()
    d.set_velocity(1000.0, MOTION)
    wait_state(d, lambda s: s.moving, what='jogging')
    d.stop(quick=True)
    st = d.read_state()
    assert not st.moving and not st.fault and st.state == State.SWITCH_ON_DISABLED
    assert 'Emergency' in st.alarms
    d.enable()
    assert d.read_state().state == State.OPERATION_ENABLED


def test_raw_registers(rig):
    r = rig()
    d = r.drives['axis1']
    d.connect()
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
