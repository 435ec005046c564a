"""CiA 402 tables and Cia402Walker, checked against the X-PLUS MT manual's T13/T14 and quoted
status words.

The scripted responder below is written from the manual (§12 CW sequence, transitions 2-16),
independently of cia402's own tables: a map (statusword, controlword) -> next statusword.
"""

import time

import pytest
from stepper_drivers.contract.drive import DriveError, HomingState, State, complete
from stepper_drivers.profiles.cia402 import modes as cia402_modes
from stepper_drivers.profiles.cia402 import state_machine as cia402

SOD, RTSO, SO, OE = (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                     State.OPERATION_ENABLED)
QSA, FRA, FAULT = State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE, State.FAULT

# T14: state -> bits 6, 5, 3, 2, 1, 0 (None = x).
T14 = {
    SOD: (1, 1, 0, 0, 0, 0),
    RTSO: (0, 1, 0, 0, 0, 1),
    SO: (0, 1, 0, 0, 1, 1),
    OE: (0, 1, 0, 1, 1, 1),
    QSA: (0, 0, 0, 1, 1, 1),
    FAULT: (0, None, 1, 0, 0, 0),
}
T14_BITS = (6, 5, 3, 2, 1, 0)


def _t14_words(row):
    """Every statusword matching a T14 row: the x bit both ways, bits 4/9/10/12/13/15 mixed in."""
    words = [0]
    for bit, value in zip(T14_BITS, row):
        if value is None:
            words = [w for w0 in words for w in (w0, w0 | 1 << bit)]
        elif value:
            words = [w | 1 << bit for w in words]
    extra = (0, 1 << 4, 1 << 9, 1 << 10 | 1 << 12, 1 << 4 | 1 << 9 | 1 << 13 | 1 << 15)
    return [w | e for w in words for e in extra]


@pytest.mark.parametrize('state', list(T14))
def test_t14_state_bits_decode(state):
    for word in _t14_words(T14[state]):
        assert cia402.decode_state(word) == state, hex(word)


# Status words quoted by the manual (§12 CW sequence; §13 "Register 1085").
QUOTED = {
    0x0221: RTSO, 0x1221: RTSO,            # Shutdown, no HV
    0x0231: RTSO, 0x1231: RTSO,            # Shutdown, HV
    0x0233: SO, 0x1233: SO,                # Switch on
    0x0637: OE, 0x1637: OE, 0x1237: OE,    # Enable operation
    0x201F: FRA,                           # PV following error, 1085 = 2
    0x1218: FAULT,                         # ... after the motor stopped
    0xFFFF: State.UNKNOWN,                 # printed as FRA, a placeholder (A6)
    # derived values a simulator shows (spec §3.5)
    0x0270: SOD, 0x0260: SOD, 0x0617: QSA, 0x0217: QSA, 0x0208: FAULT, 0x0218: FAULT,
}


@pytest.mark.parametrize('word,state', QUOTED.items(), ids=[f'0x{w:04X}' for w in QUOTED])
def test_quoted_statuswords(word, state):
    assert cia402.decode_state(word) == state


def test_describe_names_state_and_hex():
    assert cia402.describe(0x0221) == 'READY TO SWITCH ON (statusword 0x0221)'


# T13: command -> bits 7, 3, 2, 1, 0 (None = X), and the transitions it serves.
T13 = {
    'SHUTDOWN': ((0, None, 1, 1, 0), (2, 6, 8)),
    'SWITCH ON': ((0, None, 1, 1, 1), (3,)),
    'DISABLE VOLTAGE': ((0, None, None, 0, None), (7, 9, 10, 12)),
    'QUICK STOP': ((0, None, 0, 1, None), (7, 10, 11)),
    'DISABLE OPERATION': ((0, 0, 1, 1, 1), (5,)),
    'ENABLE OPERATION': ((0, 1, 1, 1, 1), (4, 16)),
}
T13_BITS = (7, 3, 2, 1, 0)
# §12 transition numbers -> (from, to).
TRANSITION_NUMBERS = {
    2: (SOD, RTSO), 3: (RTSO, SO), 4: (SO, OE), 5: (OE, SO), 6: (SO, RTSO), 7: (RTSO, SOD),
    8: (OE, RTSO), 9: (OE, SOD), 10: (SO, SOD), 11: (OE, QSA), 12: (QSA, SOD), 16: (QSA, OE),
}


def _matches_t13(cw, bits):
    return all(v is None or bool(cw >> b & 1) == bool(v) for b, v in zip(T13_BITS, bits))


@pytest.mark.parametrize('name', list(T13))
def test_t13_canonical_commands(name):
    value = {'SHUTDOWN': 0x06, 'SWITCH ON': 0x07, 'DISABLE VOLTAGE': 0x00, 'QUICK STOP': 0x02,
             'DISABLE OPERATION': 0x07, 'ENABLE OPERATION': 0x0F}[name]
    assert _matches_t13(value, T13[name][0])
    assert name in cia402.decode_commands(value)
    # every controlword the T13 row allows decodes as that command
    for cw in range(0x100):
        assert (name in cia402.decode_commands(cw)) == _matches_t13(cw, T13[name][0]), hex(cw)


@pytest.mark.parametrize('number', list(TRANSITION_NUMBERS))
def test_transition_table_uses_a_t13_command_for_that_transition(number):
    cw = cia402.TRANSITIONS[TRANSITION_NUMBERS[number]]
    allowed = [bits for bits, numbers in T13.values() if number in numbers]
    assert any(_matches_t13(cw, bits) for bits in allowed), (number, hex(cw))


def test_command_constants():
    assert (cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON, cia402.CW_DISABLE_VOLTAGE,
            cia402.CW_QUICK_STOP, cia402.CW_DISABLE_OPERATION, cia402.CW_ENABLE_OPERATION,
            cia402.CW_FAULT_RESET) == (0x06, 0x07, 0x00, 0x02, 0x07, 0x0F, 0x80)
    assert [cia402.CW_BIT_NEW_SET_POINT, cia402.CW_BIT_CHANGE_SET_IMMEDIATELY,
            cia402.CW_BIT_RELATIVE, cia402.CW_BIT_FAULT_RESET, cia402.CW_BIT_HALT] == \
        [1 << 4, 1 << 5, 1 << 6, 1 << 7, 1 << 8]


def test_set_point_controlwords_match_manual_sequence():
    # §12: "CW = 0x001F or CW = 0x005F (... absolute or relative ...)"
    assert cia402.set_point_controlword(0x000F) == 0x001F
    assert cia402.set_point_controlword(0x000F, relative=True) == 0x005F
    assert cia402.set_point_controlword(0x000F, immediate=True) == 0x003F
    assert cia402.set_point_controlword(0x011F) == 0x001F   # halt and old bits dropped


@pytest.mark.parametrize('current,target,cw', [
    (SOD, OE, 0x06), (RTSO, OE, 0x07), (SO, OE, 0x0F), (QSA, OE, 0x0F), (FAULT, OE, 0x80),
    (OE, SOD, 0x00), (SO, SOD, 0x00), (RTSO, SOD, 0x00), (QSA, SOD, 0x00), (FAULT, SOD, 0x80),
    (OE, SO, 0x07), (OE, RTSO, 0x06), (OE, QSA, 0x02),
    (OE, OE, None), (FRA, OE, None), (State.NOT_READY_TO_SWITCH_ON, OE, None),
])
def test_next_controlword(current, target, cw):
    assert cia402.next_controlword(current, target) == cw


def test_uncommandable_targets_refused_by_name():
    for target in (FAULT, FRA, State.NOT_READY_TO_SWITCH_ON, State.UNKNOWN):
        with pytest.raises(ValueError, match=target.value):
            cia402.next_controlword(SOD, target)
    with pytest.raises(ValueError, match='Illegal state transition from UNKNOWN'):
        cia402.next_state(State.UNKNOWN, OE)


@pytest.mark.parametrize('word,homing', [
    (0x0237, HomingState.RUNNING),      # bits 13/12/10 = 0 0 0: in progress
    (0x0637, HomingState.IDLE),         # 0 0 1: interrupted / not started
    (0x1237, HomingState.RUNNING),      # 0 1 0: attained, target not reached
    (0x1637, HomingState.ATTAINED),     # 0 1 1: success (spec G10)
    (0x2237, HomingState.ERROR),
    (0x2637, HomingState.ERROR),
])
def test_homing_state(word, homing):
    assert cia402.homing_state(word) == homing


# --- Cia402Walker against a scripted responder -------------------------------------------------
HV = {  # (statusword, controlword) -> next statusword; HV present (§12 CW sequence)
    (0x0270, 0x06): 0x0231,
    (0x0231, 0x07): 0x0233, (0x0231, 0x0F): 0x0637, (0x0231, 0x00): 0x0270,
    (0x0231, 0x02): 0x0270,
    (0x0233, 0x0F): 0x0637, (0x0233, 0x06): 0x0231, (0x0233, 0x00): 0x0270,
    (0x0637, 0x07): 0x0233, (0x0637, 0x06): 0x0231, (0x0637, 0x00): 0x0270,
    (0x0637, 0x02): 0x0617,
    (0x0617, 0x0F): 0x0637, (0x0617, 0x00): 0x0270,
}
NO_HV = {(0x0260, 0x06): 0x0221, (0x0221, 0x07): 0x0221, (0x0221, 0x00): 0x0260}


class ScriptedDrive:
    """Statusword responder: applies the table on each controlword write."""

    def __init__(self, sw, table=HV, fault_clears=True, fra_reads=0):
        self.sw, self.table, self.fault_clears = sw, table, fault_clears
        self.fra_reads = fra_reads
        self.cws = []
        self.prev_cw = 0
        self.events = []

    def read(self):
        self.events.append(('r', time.monotonic()))
        if self.sw == 0x201F:
            self.fra_reads -= 1
            if self.fra_reads <= 0:
                self.sw = 0x1218          # FRA -> Fault once the motor stopped
        return self.sw

    def write(self, cw):
        self.events.append(('w', time.monotonic()))
        self.cws.append(cw)
        if self.sw & 0x08 and cw & 0x80 and not self.prev_cw & 0x80:   # T13 "Trans. L/H"
            if self.fault_clears:
                self.sw = 0x0270
        elif not self.sw & 0x08:
            self.sw = self.table.get((self.sw & 0xEFFF, cw & 0x8F), self.sw)
        self.prev_cw = cw


def _device(drive, delay=0.001):
    return cia402.Cia402Walker(drive.read, drive.write, min_delay_s=delay, name='axis1')


@pytest.mark.parametrize('start,cws', [
    (0x0270, [0x06, 0x07, 0x0F]),
    (0x0231, [0x07, 0x0F]),
    (0x0233, [0x0F]),
    (0x0637, []),
    (0x0617, [0x0F]),                               # transition 16
    (0x0218, [0x00, 0x80, 0x00, 0x06, 0x07, 0x0F]),  # fault reset edge, then up
])
def test_path_to_operation_enabled(start, cws):
    drive = ScriptedDrive(start)
    sw = complete(_device(drive).bring_to(OE, timeout_s=1.0, reset_faults=True))
    assert sw == 0x0637
    assert drive.cws == cws


@pytest.mark.parametrize('start,cws', [
    (0x0637, [0x00]), (0x0233, [0x00]), (0x0231, [0x00]), (0x0617, [0x00]), (0x0270, []),
    (0x0218, [0x00, 0x80, 0x00]),
])
def test_path_back_to_switch_on_disabled(start, cws):
    drive = ScriptedDrive(start)
    assert complete(_device(drive).bring_to(SOD, timeout_s=1.0, reset_faults=True)) == 0x0270
    assert drive.cws == cws


def test_fault_on_the_way_raises_without_reset():
    drive = ScriptedDrive(0x0218)
    with pytest.raises(DriveError, match=r'axis1: in FAULT \(statusword 0x0218\)'):
        complete(_device(drive).bring_to(OE, timeout_s=0.5))
    assert drive.cws == []


def test_fault_reset_is_a_rising_edge_then_released():
    drive = ScriptedDrive(0x0218)
    drive.prev_cw = 0x80            # bit 7 left high by someone: a plain 0x80 is no edge
    sw = complete(_device(drive).fault_reset(timeout_s=0.5))
    assert cia402.decode_state(sw) == SOD
    assert drive.cws == [0x00, 0x80, 0x00]


def test_fault_reset_waits_out_fault_reaction_active():
    drive = ScriptedDrive(0x201F, fra_reads=3)
    sw = complete(_device(drive).fault_reset(timeout_s=0.5))
    assert sw == 0x0270
    assert drive.cws == [0x00, 0x80, 0x00]


def test_fault_reset_with_cause_present_returns_fault():
    drive = ScriptedDrive(0x0218, fault_clears=False)
    sw = complete(_device(drive).fault_reset(timeout_s=0.1))
    assert cia402.decode_state(sw) == FAULT
    assert drive.cws[-1] & 0x80 == 0     # bit 7 back to 0


def test_no_high_voltage_sticks_in_ready_to_switch_on():
    drive = ScriptedDrive(0x0260, table=NO_HV)
    with pytest.raises(DriveError) as err:
        complete(_device(drive).bring_to(OE, timeout_s=0.15))
    assert 'stuck in READY TO SWITCH ON (statusword 0x0221) after controlword 0x0007' \
        in str(err.value)


def test_controlword_statusword_delay_respected():
    drive = ScriptedDrive(0x0270)
    complete(_device(drive, delay=0.012).bring_to(OE, timeout_s=1.0))
    gaps = [t2 - t1 for (k1, t1), (k2, t2) in zip(drive.events, drive.events[1:])
            if k1 == 'w' and k2 == 'r']
    assert len(gaps) == 3
    assert min(gaps) >= 0.012


class PpResponder(ScriptedDrive):
    """OE in mode 1: bit 4 up -> bit 12 (set-point acknowledge) up, bit 10 down; bit 4 down ->
    bit 12 down (CiA handshake, §13 "Register 1040" bit 4)."""

    def __init__(self, ack=True):
        super().__init__(0x0637)
        self.ack = ack

    def write(self, cw):
        self.cws.append(cw)
        self.events.append(('w', time.monotonic()))
        if cw & 0x10 and not self.prev_cw & 0x10 and self.ack:
            self.sw = (self.sw | 0x1000) & ~0x0400
        elif not cw & 0x10:
            self.sw &= ~0x1000
        self.prev_cw = cw


def test_set_point_handshake():
    drive = PpResponder()
    dev = _device(drive)
    dev.write(0x000F)
    sw = complete(dev.start_set_point(0x000F, immediate=True))
    assert sw & 0x1000
    assert drive.cws == [0x0F, 0x3F, 0x2F]
    assert drive.sw & 0x1000 == 0


def test_set_point_needs_a_fresh_edge():
    drive = PpResponder()
    dev = _device(drive)
    dev.write(0x001F)               # bit 4 still high from elsewhere
    complete(dev.start_set_point(0x000F, relative=True))
    assert drive.cws == [0x1F, 0x4F, 0x5F, 0x4F]   # bit 6 already stable before the edge


def test_set_point_not_acknowledged():
    drive = PpResponder(ack=False)
    dev = _device(drive)
    dev.write(0x000F)
    with pytest.raises(DriveError, match='bit 12.*0x001F'):
        complete(dev.start_set_point(0x000F, timeout_s=0.05))
    assert drive.cws[-1] == 0x0F


# --- Step-wise contract (drive.py): the bus is given back between transactions ----------------
def _run_counting(steps, drive):
    """Run a step-wise operation as the bus owner would (sleeping for each yielded delay);
    returns (result, [transactions per step], [delays])."""
    per_step, delays, drive_events = [], [], drive.events
    seen = len(drive_events)
    while True:
        try:
            delay = next(steps)
        except StopIteration as stop:
            per_step.append(len(drive_events) - seen)
            return stop.value, per_step, delays
        per_step.append(len(drive_events) - seen)
        seen = len(drive_events)
        delays.append(delay)
        time.sleep(delay)


def test_bring_to_yields_between_transactions():
    drive = ScriptedDrive(0x0270)
    sw, per_step, delays = _run_counting(_device(drive, delay=0.012).bring_to(OE, 1.0), drive)
    assert sw == 0x0637 and drive.cws == [0x06, 0x07, 0x0F]
    assert max(per_step) <= 2                     # one or two transactions per step
    # after each controlword write the next step waits the 12 ms CW -> SW delay (§13 1001)
    assert sum(1 for d in delays if 0.005 < d <= 0.012) == 3


def test_set_point_handshake_yields_between_transactions():
    drive = PpResponder()
    dev = _device(drive, delay=0.012)
    dev.write(0x000F)
    sw, per_step, _ = _run_counting(dev.start_set_point(0x000F, immediate=True), drive)
    assert sw & 0x1000 and drive.cws == [0x0F, 0x3F, 0x2F]
    assert max(per_step) <= 2


def test_closing_a_step_wise_operation_writes_nothing():
    drive = ScriptedDrive(0x0270)
    steps = _device(drive, delay=0.012).bring_to(OE, 1.0)
    next(steps)                                   # 0x0006 written, waiting for the statusword
    assert drive.cws == [0x06]
    steps.close()                                 # a stop or a link loss cuts it short
    assert drive.cws == [0x06]                    # nothing more went to the drive


# ------------------------------------------------------------------ mode objects (cia402_modes)
@pytest.mark.parametrize('mode, cw, stop', [
    # profile position, velocity, homing: Halt (bit 8) on the enable operation commanded
    (cia402_modes.ProfilePositionMode(), 0x003F, 0x013F),
    (cia402_modes.ProfileVelocityMode(), 0x001F, 0x011F),
    (cia402_modes.HomingMode(), 0x001F, 0x011F),
    # not an enable operation (or unknown): from 0x000F
    (cia402_modes.ProfilePositionMode(), 0x0006, 0x010F),
    (cia402_modes.HomingMode(), None, 0x010F),
    # interpolated position: bit 4 low ends the interpolation (bits 4-6 and 8 low) ...
    (cia402_modes.InterpolatedPositionMode(), 0x001F, 0x000F),
    (cia402_modes.InterpolatedPositionMode(), 0x011F, 0x000F),
    # ... and with bit 4 low already there is none: Halt
    (cia402_modes.InterpolatedPositionMode(), 0x000F, 0x010F),
])
def test_a_mode_s_stop_controlword(mode, cw, stop):
    assert mode.stop_controlword(cw) == stop


@pytest.mark.parametrize('word, started', [
    (0x0437, False),     # bits 13/12/10 = 0/0/1: not started (or interrupted)
    (0x0037, True),      # 0/0/0: in progress
    (0x1437, True),      # 0/1/1: attained
    (0x2037, True),      # 1/0/0: error
])
def test_homing_mode_started_from_bits_13_12_10(word, started):
    assert cia402_modes.HomingMode().started(word) is started


def test_interpolated_position_active_is_statusword_bit_12():
    ip = cia402_modes.InterpolatedPositionMode()
    assert ip.code == 7 and ip.active(0x1037) and not ip.active(0x0037)
