"""XplusMtDrive against the real X-PLUS MT simulator (pymodbus server on 127.0.0.1, in-process).

Expected values come from the manual (§12 CW sequence, §13 registers) and the simulator's world
(home switch at raw 20000, width 6400); positions are checked against the simulator's exact axis.
"""

import json
import os
import time

import pytest

from stepper_drivers.drive import (DriveError, Homing, HomingState, LinkError, Motion, State)
from stepper_drivers.vendors import xplus_mt_map as xm
from stepper_drivers.vendors.xplus_mt import VENDOR, XplusMtDrive
from stepper_sim.xplus_mt_sim import XplusMtDriveConfig, XplusMtSim
from stepper_drivers.tools.processes import wait_for

FAST = Motion(velocity_steps_s=100_000, acceleration_steps_s2=2_000_000,
              deceleration_steps_s2=2_000_000)


def drives_config():
    return [XplusMtDriveConfig('axis1', unit_id=1, home_switch_steps=20_000.0,
                               home_switch_width_steps=6_400.0, limit_neg_steps=-2_000_000.0,
                               limit_pos_steps=2_000_000.0),
            XplusMtDriveConfig('axis2', unit_id=2, hv_present=False)]


@pytest.fixture
def sim(tmp_path):
    s = XplusMtSim(port=0, drives=drives_config(), storage_dir=str(tmp_path))
    s.start()
    yield s
    s.stop()


def make(sim, name='axis1', unit_id=1, word_order='little', **extra):
    bus = VENDOR.make_bus({'host': '127.0.0.1', 'port': sim.port, 'timeout_s': 0.5})
    bus.open()
    params = {'unit_id': unit_id, 'word_order': word_order, 'homing.method': 19,
              'steps_per_rev': 12800, 'joint_name': name, **extra}
    drive = VENDOR.make_drive(bus, name, params)
    return bus, drive


@pytest.fixture
def axis1(sim):
    bus, drive = make(sim)
    drive.connect()
    yield drive
    drive.close()
    bus.close()


def true_pos(sim, name='axis1'):
    return sim.drives[name].true_position_steps


def test_connect_reads_identity_and_never_enables(sim):
    bus, drive = make(sim)
    ident = drive.connect()
    assert ident['product'] == 'X-PLUS MT'
    assert ident['serial_number'] == '100001'           # sim: 100000 + unit id
    assert ident['software_version'] == '51'            # T15 default
    assert ident['word_order'] == 'little (1162 = 1)'
    assert ident['state'] == 'SWITCH ON DISABLED'
    st = drive.read_state()
    assert (st.state, st.enabled, st.fault, st.status_word) == \
        (State.SWITCH_ON_DISABLED, False, False, 0x0270)
    assert sim.drives['axis1'].controlword == 0         # nothing written to 1040
    bus.close()


def test_word_order_mismatch_is_refused(sim):
    bus, drive = make(sim, word_order='big')
    with pytest.raises(DriveError) as err:
        drive.connect()
    assert 'LITTLE_ENDIAN_BIG_ENDIAN (1162) reads 1' in str(err.value)
    assert "word_order parameter is 'big'" in str(err.value)
    bus.close()


def test_enable_sets_target_to_actual_and_does_not_move(sim, axis1):
    sim.drives['axis1'].axis.motion.set_position(12_345)
    axis1.enable()
    st = axis1.read_state()
    assert (st.state, st.enabled, st.mode) == (State.OPERATION_ENABLED, True, 'PROFILE POSITION')
    assert st.status_word == 0x0637                       # §12: CW 0x000F -> 0x0637
    assert sim.drives['axis1'].register('TARGET_POSITION') == 12_345
    time.sleep(0.1)                                       # the standstill under test
    assert true_pos(sim) == 12_345
    axis1.disable()
    assert axis1.read_state().state == State.SWITCH_ON_DISABLED


def test_enable_without_high_voltage_names_the_status_word(sim):
    bus, drive = make(sim, name='axis2', unit_id=2)
    drive.connect()
    with pytest.raises(DriveError) as err:
        drive.enable()
    assert 'no high voltage' in str(err.value)
    assert 'READY TO SWITCH ON (statusword 0x0221)' in str(err.value)   # §12: 0x0221
    bus.close()


def test_move_absolute_within_tolerance(sim, axis1):
    axis1.enable()
    axis1.move_to(40_000, FAST)
    seen_moving = wait_for(lambda: axis1.read_state().moving, 1.0)
    assert seen_moving
    st = wait_for(lambda: (lambda s: s if s.target_reached and not s.moving else None)(
        axis1.read_state()), 3.0)
    assert st.position_steps == 40_000
    assert true_pos(sim) == pytest.approx(40_000, abs=0.5)
    assert st.state == State.OPERATION_ENABLED


def test_new_target_during_move_taken_at_once(sim, axis1):
    axis1.enable()
    slow = Motion(60_000, 600_000, 600_000)
    axis1.move_to(60_000, slow)
    wait_for(lambda: axis1.read_state().position_steps > 5_000, 2.0)
    t0 = time.monotonic()
    axis1.move_to(120_000, slow)                  # monotonous: no intermediate stop (§13)
    samples = []
    while time.monotonic() - t0 < 4.0:
        st = axis1.read_state()
        samples.append(st)
        if st.target_reached and not st.moving:
            break
    assert samples[-1].position_steps == 120_000
    crossing = [s for s in samples if 55_000 < s.position_steps < 65_000]
    assert crossing and all(s.velocity_steps_s > 50_000 for s in crossing)   # did not stop


def test_velocity_mode_and_halt(sim, axis1):
    axis1.enable()
    motion = Motion(0, 400_000, 400_000)
    axis1.set_velocity(-40_000, motion)
    st = wait_for(lambda: (lambda s: s if s.velocity_steps_s == -40_000 else None)(
        axis1.read_state()), 2.0)
    assert st.mode == 'PROFILE VELOCITY' and st.moving
    p0 = st.position_steps
    wait_for(lambda: axis1.read_state().position_steps < p0 - 2_000, 1.0)
    axis1.set_velocity(60_000, motion)            # on the fly, direction change (§13 PV)
    wait_for(lambda: axis1.read_state().velocity_steps_s == 60_000, 2.0)
    axis1.stop()                                  # Halt (bit 8) with 1072
    st = wait_for(lambda: (lambda s: s if not s.moving else None)(axis1.read_state()), 2.0)
    assert st.state == State.OPERATION_ENABLED and st.velocity_steps_s == 0
    assert sim.drives['axis1'].controlword & 0x0100
    axis1.set_velocity(20_000, motion)            # runs again after the halt
    wait_for(lambda: axis1.read_state().velocity_steps_s == 20_000, 2.0)
    axis1.set_velocity(0, motion)                 # 0 = ramp to standstill
    wait_for(lambda: not axis1.read_state().moving, 2.0)


def test_quick_stop_and_back_to_operation_enabled(sim, axis1):
    axis1.enable()
    axis1.move_to(500_000, Motion(50_000, 500_000, 500_000))
    wait_for(lambda: axis1.read_state().velocity_steps_s > 0, 1.0)
    axis1.stop(quick=True)
    st = wait_for(lambda: (lambda s: s if not s.moving else None)(axis1.read_state()), 2.0)
    assert st.state == State.QUICK_STOP_ACTIVE and st.status_word == 0x0617
    assert true_pos(sim) < 500_000
    axis1.enable()                                # transition 16
    assert axis1.read_state().state == State.OPERATION_ENABLED


def test_homing_on_the_home_switch(sim, axis1):
    axis1.enable()
    homing = Homing(method=19, offset_steps=1_000, speed_search_steps_s=100_000,
                    speed_zero_steps_s=16_000, acceleration_steps_s2=1_000_000)
    with pytest.raises(DriveError, match=r'INPUT_CONFIG \(1088\) = 15 has bit 0'):
        axis1.start_homing(homing)                # factory 1088 = 15: I0 general purpose
    axis1.write_register('1088', 'u16', 14)       # IC0 = 0: I0 = proximity input
    assert axis1.start_homing(homing) == ''
    assert axis1.read_state().homing in (HomingState.RUNNING, HomingState.ATTAINED)
    st = wait_for(lambda: (lambda s: s if s.homing == HomingState.ATTAINED else None)(
        axis1.read_state()), 5.0)
    assert st.homed and st.mode == 'HOMING' and st.position_steps == 1_000
    assert sim.drives['axis1'].axis.raw_position_steps == pytest.approx(20_000, abs=1e-6)
    axis1.move_to(0, FAST)                        # back to profile position at standstill
    st = wait_for(lambda: (lambda s: s if s.target_reached and s.mode == 'PROFILE POSITION'
                           and not s.moving else None)(axis1.read_state()), 3.0)
    assert st.position_steps == 0 and st.homed   # homed stays latched


def test_homing_method_refused_and_current_position_method(sim, axis1):
    axis1.enable()
    with pytest.raises(DriveError, match='7 is not a homing method of the X-PLUS MT'):
        axis1.start_homing(Homing(7, 0, 20_000, 1_000, 100_000))
    axis1.write_register('1088', 'u16', 14)
    with pytest.raises(DriveError, match=r'home: homing.speed_search 1019 is outside '
                                         r'HOMING_SPEED_SEARCH_SWITCH \(1052\) range 16001'):
        axis1.start_homing(Homing(19, 0, 1019, 200, 100_000))   # 0.5 rad/s: below 75 rpm
    assert axis1.read_state().mode == 'PROFILE POSITION'       # nothing changed
    axis1.start_homing(Homing(35, -500, 0, 0, 0))   # no speeds needed for 35
    st = wait_for(lambda: (lambda s: s if s.homing == HomingState.ATTAINED else None)(
        axis1.read_state()), 2.0)
    assert st.position_steps == -500 and st.homed


def test_fault_injection_code_text_and_reset(sim, axis1):
    axis1.enable()
    ok, _ = sim.inject_fault('axis1', 'drive_fault', 0x4310)
    assert ok
    st = axis1.read_state()
    assert (st.state, st.fault, st.enabled, st.fault_code) == (State.FAULT, True, False, 0x4310)
    assert st.fault_text == 'Error drive excessive temperature (0x4310)'
    with pytest.raises(DriveError, match='in FAULT.*excessive temperature.*fault_reset first'):
        axis1.enable()
    remaining = axis1.fault_reset()               # cause still present (G15)
    assert 'Error drive excessive temperature (0x4310)' in remaining and 'still' in remaining
    sim.inject_fault('axis1', 'clear_fault', 0x4310)
    assert axis1.fault_reset() == ''
    st = axis1.read_state()
    assert (st.state, st.fault, st.fault_code) == (State.SWITCH_ON_DISABLED, False, 0)
    assert axis1.read_register('1221', 'u16') == 0x4310   # alarm log n°0 code
    axis1.enable()
    assert axis1.read_state().enabled


def test_save_params_writes_the_signature(sim, axis1, tmp_path):
    axis1.write_register('1080', 'u16', 50)       # Current Ratio, storable ('**')
    note = axis1.save_params()
    assert '0x6173' in note and 'SAVE_ALL_PARAMETERS (1260)' in note and '5 s' in note
    with open(os.path.join(tmp_path, 'xplus_mt_unit1.json'), encoding='utf-8') as f:
        stored = json.load(f)
    assert stored['registers']['1080'] == 50


@pytest.mark.parametrize('order', ['little', 'big'])
def test_raw_registers_typed_in_both_word_orders(tmp_path, order):
    s = XplusMtSim(port=0, drives=drives_config()[:1], word_order=order,
                   storage_dir=str(tmp_path))
    s.start()
    try:
        bus, drive = make(s, word_order=order)
        drive.connect()
        drive.write_register('1042', 'i32', -1000)
        assert drive.read_register('0x412', 'i32') == -1000
        assert drive.read_register('1042', 'u32') == 0xFFFF_FC18
        assert s.drives['axis1'].register('TARGET_POSITION') == -1000   # decoded by the sim
        expect = [0xFC18, 0xFFFF] if order == 'little' else [0xFFFF, 0xFC18]
        assert bus.read_registers(1, 1042, 2) == expect    # §11 word order on the wire
        assert drive.read_register('1158', 'u32') == 100_001
        drive.write_register('1040', 'u16', 0x0006)        # raw controlword: SOD -> RTSO
        wait_for(lambda: drive.read_state().state == State.READY_TO_SWITCH_ON, 1.0)
        drive.write_register('1122', 'i16', -2)
        assert drive.read_register('1122', 'u16') == 0xFFFE
        bus.close()
    finally:
        s.stop()


@pytest.mark.parametrize('call,message', [
    (lambda d: d.read_register('1003', 'u16'), 'register 1003 is not in the X-PLUS MT'),
    (lambda d: d.read_register('1005', 'u16'),
     r'register 1005 is the second word of POSITION_ACTUAL_VALUE \(1004\)'),
    (lambda d: d.read_register('1042', 'u16'), r'TARGET_POSITION \(1042\) is i32'),
    (lambda d: d.read_register('abc', 'u16'), "'abc' is not a number"),
    (lambda d: d.read_register('1001', 'f32'), 'unknown data type'),
    (lambda d: d.write_register('1001', 'u16', 1), r'STATUS_WORD \(1001\) is read-only'),
    (lambda d: d.write_register('1080', 'u16', 200),
     r'200 is outside CURRENT_RATIO \(1080\) range 0..120 %'),
    (lambda d: d.write_register('1260', 'u16', 5),
     r'5 is outside SAVE_ALL_PARAMETERS \(1260\) range one of 0x6173, 0x1111'),
    (lambda d: d.write_register('1041', 'i16', 2), r'MODE_OF_OPERATION \(1041\)'),
    (lambda d: d.write_register('1162', 'u16', 0), r'LITTLE_ENDIAN_BIG_ENDIAN \(1162\)'),
    (lambda d: d.write_register('1080', 'u16', -1), 'out of range for u16'),
    (lambda d: d.move_to(1000, FAST), 'move_to: drive is in SWITCH ON DISABLED'),
])
def test_refusals_name_the_register(sim, axis1, call, message):
    transactions = axis1.bus.transactions
    with pytest.raises(DriveError, match=message):
        call(axis1)
    assert axis1.bus.transactions - transactions <= 1    # refused before writing anything
    assert axis1.bus.counters()['exceptions'] == 0


def test_motion_ranges_checked_before_sending(sim, axis1):
    axis1.enable()
    with pytest.raises(DriveError, match=r'acceleration 1000 is outside PROFILE_ACCELERATION '
                                         r'\(1046\) range 2000..10000000'):
        axis1.move_to(1000, Motion(10_000, 1_000, 10_000))
    with pytest.raises(DriveError, match=r'900000 is outside TARGET_VELOCITY \(1048\)'):
        axis1.set_velocity(900_000, FAST)


@pytest.mark.parametrize('strict,per_poll', [(True, 3), (False, 1)])
def test_read_state_transactions(tmp_path, strict, per_poll):
    s = XplusMtSim(port=0, drives=drives_config()[:1], strict=strict)
    s.start()
    try:
        bus, drive = make(s)
        drive.connect()
        drive.read_state()               # the first poll finds out whether holes are readable
        before = bus.transactions
        for _ in range(5):
            drive.read_state()
        assert bus.transactions - before == 5 * per_poll
        bus.close()
    finally:
        s.stop()


def test_link_loss_raises_link_error(sim, axis1):
    sim.inject_fault('axis1', 'no_reply')
    with pytest.raises(LinkError, match=r'127.0.0.1:\d+ unit 1: FC03 .*no answer within 0.5 s'):
        axis1.read_state()
    sim.inject_fault('axis1', 'link_ok')


@pytest.mark.parametrize('params,message', [
    ({'homing.method': 7}, 'drives.axis1.homing.method: 7 is not a homing method of the X-PLUS '
                           'MT (allowed: 3, 4, 5, 6, 19, 20, 21, 22, 35, 37)'),
    ({'unit_id': 300}, 'drives.axis1.unit_id: 300 is not a Modbus unit id (allowed: 0..255)'),
    ({'steps_per_rev': 200.0}, 'drives.axis1.steps_per_rev: 200 is not the X-PLUS MT'),
    ({'word_order': 'middle'}, "word_order: 'middle' is not a word order"),
])
def test_make_drive_refuses_bad_parameters(params, message):
    bus = VENDOR.make_bus({'host': '127.0.0.1', 'port': 1502, 'timeout_s': 0.5})
    base = {'unit_id': 1, 'word_order': 'little', 'homing.method': 35, 'steps_per_rev': 12800.0}
    with pytest.raises(ValueError) as err:
        VENDOR.make_drive(bus, 'axis1', {**base, **params})
    assert str(err.value).startswith(message)
    assert '\n' not in str(err.value)


def test_vendor_description():
    assert VENDOR.name == 'X-PLUS MT'
    assert VENDOR.drive_defaults['steps_per_rev'] == xm.STEPS_PER_REV
    specs = {p.name: p for p in VENDOR.params}
    assert (specs['host'].scope, specs['port'].default, specs['word_order'].choices) == \
        ('bus', 502, ('little', 'big'))
    assert (specs['unit_id'].scope, specs['unit_id'].max_value) == ('drive', 255)
    assert isinstance(VENDOR.make_drive(VENDOR.make_bus({}), 'x', {}), XplusMtDrive)
