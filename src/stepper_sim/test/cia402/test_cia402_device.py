"""The simulators' device-side CiA 402 (stepper_sim.cia402.slave) against the manuals' tables.

X-PLUS = rta_xplus_mt_modbus_tcp.txt (§12 "Drive Sub-States", T13, T14, §13 "Register 1001/1040/
1085", "Multi-Set-Point Mode"); AEC = aec_vector_step_canopen_it.txt ([CONTROLWORD],
[STATUSWORD], [MACCHINA A STATI DSP-402 V1.1] "Definizioni transizioni", option code pages).
The engine runs over a real MotionModel on a hand-driven clock; nothing from the driver's
cia402.py is used.
"""

import pytest
from stepper_sim.cia402 import slave as cia
from stepper_sim.cia402.slave import FAULT, FRA, NRTSO, OE, QSA, RTSO, SO, SOD
from stepper_sim.core.motion import MotionModel


class Drive:
    """A drive around the engine: a motion model, option codes, a power stage flag."""

    def __init__(self, profile, state=SOD, options=None):
        self.now_s = 0.0
        self.motion = MotionModel(clock=lambda: self.now_s)
        self.options = dict(options or {})
        self.power_ok = True
        self.calls = []
        self.sm = cia.PowerStateMachine(profile, self, 'test', state)

    def run(self, seconds):
        self.now_s += seconds
        self.motion.update(self.now_s)
        self.sm.settle()

    def cia_allows(self, number):
        return self.power_ok or number != 2

    def cia_moving(self):
        return self.motion.moving

    def cia_option_code(self, transition):
        return self.options[transition]

    def cia_stop(self, ramp, transition):
        self.calls.append((ramp, transition))
        if ramp == cia.CURRENT_OFF:
            self.motion.stop_immediately()
        else:
            self.motion.stop(1000.0 if ramp == cia.SLOW_DOWN_RAMP else 10000.0)

    def cia_leaving(self, number, source, target):
        self.calls.append(('leaving', number))

    def cia_left(self, number, source, target):
        self.calls.append(('left', number))


def walk(profile, state, cw, options=None):
    drive = Drive(profile, state, options)
    drive.sm.apply(cw)
    return drive.sm.state


# T13 and the AEC command table: command -> canonical value, and every X bit flipped.
@pytest.mark.parametrize('name,value,x_bits', [
    (cia.SHUTDOWN, 0x0006, 0x0008), (cia.SWITCH_ON, 0x0007, 0x0008),
    (cia.DISABLE_VOLTAGE, 0x0000, 0x000D), (cia.QUICK_STOP, 0x0002, 0x0009),
    (cia.DISABLE_OPERATION, 0x0007, 0), (cia.ENABLE_OPERATION, 0x000F, 0)])
def test_controlword_commands_follow_t13(name, value, x_bits):
    for x in range(x_bits + 1):
        if x & ~x_bits:
            continue
        assert name in cia.commands(value | x)
        assert name in cia.commands(value | x | 0xFF00)           # bits 8-15 are not in it
        assert cia.commands(value | x | cia.CW_FAULT_RESET) == ()    # bit 7 = 0 in every row


# "Definizioni transizioni" (AEC: value column) and X-PLUS §12 / T13 "Transitions" column.
TRANSITION_ROWS = [
    (SOD, 0x06, RTSO, 2), (RTSO, 0x07, SO, 3), (SO, 0x0F, OE, 4), (OE, 0x07, SO, 5),
    (SO, 0x06, RTSO, 6), (RTSO, 0x00, SOD, 7), (RTSO, 0x02, SOD, 7), (OE, 0x06, RTSO, 8),
    (OE, 0x00, SOD, 9), (SO, 0x00, SOD, 10), (SO, 0x02, SOD, 10), (OE, 0x02, QSA, 11),
    (QSA, 0x00, SOD, 12), (QSA, 0x0F, OE, 16)]


@pytest.mark.parametrize('source,cw,target,number', TRANSITION_ROWS)
def test_transition_table_by_controlword(source, cw, target, number):
    assert cia.next_transition(source, cw) == (target, number)
    # X-PLUS: quick stop option 5, transitions 5/8 current off (§12): at standstill exact
    assert walk(cia.XPLUS_MT, source, cw) == target
    # AEC with 0x605A = 6 (stay in quick stop, so 16 exists), 0x605B = 0, 0x605C = 1
    assert walk(cia.VECTOR_STEP, source, cw, {5: 1, 8: 0, 11: 6}) == target


@pytest.mark.parametrize('state,cw', [(SOD, 0x07), (SOD, 0x0F), (QSA, 0x06), (QSA, 0x07),
                                      (FAULT, 0x06), (FAULT, 0x0F), (FRA, 0x00), (NRTSO, 0x06)])
def test_commands_outside_the_table_change_nothing(state, cw):
    assert walk(cia.XPLUS_MT, state, cw) == state       # spec §3.2 [CiA/R]: ignored


def test_direct_sequence_0x06_to_0x0f():
    # X-PLUS §12: "The direct sequence from CW = 0x0006 to CW = 0x000F can be done"
    assert walk(cia.XPLUS_MT, RTSO, 0x0F) == OE
    assert walk(cia.XPLUS_MT, SOD, 0x0F) == SOD         # Switch On from SOD: no transition


def test_transition_2_needs_the_drives_consent():
    drive = Drive(cia.VECTOR_STEP, SOD, {11: 2})
    drive.power_ok = False                               # AEC: STO, no power stage
    drive.sm.apply(0x06)
    assert drive.sm.state == SOD


# Statusword per state: T14 (X-PLUS) and the AEC [STATUSWORD] state table, mask 0x6F.
@pytest.mark.parametrize('state,xplus,aec', [
    (NRTSO, None, 0x20), (SOD, 0x60, 0x60), (RTSO, 0x21, 0x21), (SO, 0x23, 0x23),
    (OE, 0x27, 0x27), (QSA, 0x07, 0x07), (FRA, 0x0F, 0x2F), (FAULT, 0x08, 0x28)])
def test_statusword_state_bits(state, xplus, aec):
    if xplus is not None:
        sw = cia.state_word(cia.XPLUS_MT, state, voltage_enabled=False)
        assert sw & 0x6F == xplus
    assert cia.state_word(cia.VECTOR_STEP, state, voltage_enabled=False) & 0x6F == aec


def test_statusword_values_the_xplus_manual_quotes():
    xp = cia.XPLUS_MT
    # §12 CW sequence: 0x0221 (no HV), 0x0231, 0x0233; 0x0637 is OE + bit 10 (target reached)
    assert cia.state_word(xp, RTSO, voltage_enabled=False) == 0x0221
    assert cia.state_word(xp, RTSO, voltage_enabled=True) == 0x0231
    assert cia.state_word(xp, SO, voltage_enabled=True) == 0x0233
    assert cia.state_word(xp, OE, voltage_enabled=True) | cia.SW_TARGET_REACHED == 0x0637
    # §13 "Register 1085": FRA 0x201F (Remote and Quick Stop 0; bit 13 is the following error),
    # then Fault 0x1218 (bit 12 zero speed)
    assert cia.state_word(xp, FRA, voltage_enabled=True) | cia.SW_FOLLOWING_ERROR == 0x201F
    assert cia.state_word(xp, FAULT, voltage_enabled=True) | cia.SW_BIT12 == 0x1218
    # AEC: Remote in every state (no exception in the manual)
    assert cia.state_word(cia.VECTOR_STEP, FRA, voltage_enabled=True) & cia.SW_REMOTE


def test_target_reached_shown_per_drive():
    assert not Drive(cia.XPLUS_MT, SO).sm.shows_target_reached()     # 0x0233 quoted
    assert Drive(cia.XPLUS_MT, QSA).sm.shows_target_reached()        # §12 transition 11
    assert Drive(cia.VECTOR_STEP, SO).sm.shows_target_reached()


# Quick stop option code 0x605A (AEC [QUICK STOP OPTION CODE]; CiA 402 transition 12 at the end
# of the ramp for 1/2); the X-PLUS is fixed at 5 (§12 transition 16).
@pytest.mark.parametrize('option,ramp,during,after', [
    (0, cia.CURRENT_OFF, SOD, SOD), (1, cia.SLOW_DOWN_RAMP, QSA, SOD),
    (2, cia.QUICK_STOP_RAMP, QSA, SOD), (5, cia.SLOW_DOWN_RAMP, QSA, QSA),
    (6, cia.QUICK_STOP_RAMP, QSA, QSA)])
def test_quick_stop_option_codes_while_moving(option, ramp, during, after):
    drive = Drive(cia.VECTOR_STEP, OE, {11: option})
    drive.motion.run_velocity(1000.0, 1e9)
    drive.run(0.01)
    drive.sm.apply(0x02)
    assert drive.sm.state == during and (ramp, 11) in drive.calls
    drive.run(5.0)                                       # 1000 Hz at >= 1000 Hz/s: stopped
    assert not drive.motion.moving and drive.sm.state == after
    assert (walk(cia.VECTOR_STEP, QSA, 0x0F, {11: option}) == OE) == (after == QSA)   # 16


def test_xplus_quick_stop_keeps_torque_and_returns_to_oe():
    drive = Drive(cia.XPLUS_MT, OE)
    drive.motion.run_velocity(1000.0, 1e9)
    drive.run(0.01)
    drive.sm.apply(0x02)                                 # transition 11: QSA, on the ramp
    assert drive.sm.state == QSA and drive.calls[-2] == (cia.SLOW_DOWN_RAMP, 11)
    drive.run(5.0)
    assert drive.sm.state == QSA                         # §12 transition 12: never automatic
    drive.sm.apply(0x0F)
    assert drive.sm.state == OE                          # transition 16


@pytest.mark.parametrize('cw,number,option,target', [(0x06, 8, 1, RTSO), (0x07, 5, 1, SO)])
def test_shutdown_and_disable_operation_option_ramp(cw, number, option, target):
    # AEC 0x605B / 0x605C = 1: "Slow down on slow down ramp", the state follows at standstill
    drive = Drive(cia.VECTOR_STEP, OE, {number: option})
    drive.motion.run_velocity(1000.0, 1e9)
    drive.run(0.01)
    drive.sm.apply(cw)
    assert drive.sm.state == OE and drive.sm.pending == (target, number)
    assert (cia.SLOW_DOWN_RAMP, number) in drive.calls
    drive.sm.apply(0x00)                                 # ignored while the ramp runs
    drive.run(5.0)
    assert drive.sm.state == target and drive.sm.pending is None
    # option 0 (X-PLUS always, §12 transitions 5/8 "CURRENT OFF"): at once
    drive = Drive(cia.XPLUS_MT, OE)
    drive.motion.run_velocity(1000.0, 1e9)
    drive.run(0.01)
    drive.sm.apply(cw)
    assert drive.sm.state == target and not drive.motion.moving


def test_fault_reaction_and_reset():
    # Transition 13: FRA while the reaction ramp runs, 14 at standstill (AEC [FAULT REACTION
    # OPTION CODE]; X-PLUS §13 "Register 1085" 0x02); commands are ignored meanwhile.
    drive = Drive(cia.VECTOR_STEP, OE)
    drive.motion.run_velocity(1000.0, 1e9)
    drive.run(0.01)
    assert drive.sm.fault(cia.QUICK_STOP_RAMP)
    assert drive.sm.state == FRA and drive.calls[-1] == (cia.QUICK_STOP_RAMP, 13)
    assert not drive.sm.fault(cia.CURRENT_OFF)           # one reaction
    drive.sm.apply(0x0F)
    assert drive.sm.state == FRA
    drive.run(5.0)
    assert drive.sm.state == FAULT
    # Current off (not enabled, or "Disable drive function"): no ramp
    drive = Drive(cia.XPLUS_MT, SO)
    drive.sm.fault(cia.SLOW_DOWN_RAMP)
    assert drive.calls[-1] == (cia.CURRENT_OFF, 13)
    drive.sm.settle()
    assert drive.sm.state == FAULT
    # Transition 15: on the bit 7 rising edge only (T13 "Trans. L/H", AEC "↗")
    assert not drive.sm.fault_reset_edge(0x0080, 0x0080)
    assert drive.sm.fault_reset_edge(0x0080, 0x0000)
    drive.sm.fault_reset()
    assert drive.sm.state == SOD
    assert not drive.sm.fault_reset_edge(0x0080, 0x0000)   # not in FAULT: no reset


# PP handshake (X-PLUS §13 bit 4/5 and Multi-Set-Point; AEC bit 12 "Setpoint acquisito").
def test_set_point_handshake_xplus_ignores_a_set_point_while_moving():
    hs = cia.SetPointHandshake(cia.XPLUS_MT.set_point_buffer)
    assert hs.new_set_point(100.0, busy=False, immediate=False) == hs.START
    assert hs.acknowledged
    hs.released()
    assert not hs.acknowledged
    # bit 5 = 0 while running: "cannot be modified ... until the target position is reached"
    assert hs.new_set_point(200.0, busy=True, immediate=False) == hs.IGNORED
    assert not hs.acknowledged
    # bit 5 = 1: the new target replaces the running one
    assert hs.new_set_point(300.0, busy=True, immediate=True) == hs.START
    assert hs.acknowledged and hs.target_reached(moving=False)


def test_set_point_handshake_aec_buffers_one_set_point():
    hs = cia.SetPointHandshake(cia.VECTOR_STEP.set_point_buffer)
    hs.new_set_point(100.0, busy=False, immediate=False)
    hs.released()
    assert hs.new_set_point(200.0, busy=True, immediate=False) == hs.QUEUED
    assert hs.acknowledged and not hs.target_reached(moving=False)   # one more to run
    assert hs.new_set_point(250.0, busy=True, immediate=False) == hs.QUEUED
    assert hs.take_queued() == 250.0 and hs.target_reached(moving=False)
    hs.new_set_point(300.0, busy=True, immediate=False)
    assert hs.new_set_point(400.0, busy=True, immediate=True) == hs.START   # bit 5: at once
    assert hs.queued is None


# Homing bits 13/12/10 (X-PLUS §13 "Register 1001" Homing table; AEC [STATUSWORD] homing column)
@pytest.mark.parametrize('attained,error,running,moving,bits', [
    (False, False, True, True, 0x0000),            # in progress
    (False, False, False, False, 0x0400),          # interrupted / not started, at rest
    (True, False, False, True, 0x1000),            # attained, still stopping
    (True, False, False, False, 0x1400),           # completed
    (False, True, False, True, 0x2000),            # error, still moving
    (False, True, False, False, 0x2400)])          # error at rest
def test_homing_bits(attained, error, running, moving, bits):
    assert cia.homing_bits(attained=attained, error=error, running=running,
                           moving=moving) == bits
