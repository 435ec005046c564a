"""XplusMtDrive against the real X-PLUS MT simulator (pymodbus server on 127.0.0.1, in-process).

Expected values come from the manual (§12 CW sequence, §13 registers) and the simulator's world
(home switch at raw 20000, width 6400); positions are checked against the simulator's exact axis.
"""

import json
import os
import time

import pytest
from stepper_drivers.contract.drive import (
    DriveError,
    Homing,
    HomingState,
    IdentityError,
    LinkError,
    Motion,
    State,
    complete,
    is_operation,
)
from stepper_drivers.vendors.xplus_mt import VENDOR, XplusMtDrive
from stepper_drivers.vendors.xplus_mt import regmap as xm
from stepper_sim.harness import wait_for
from stepper_sim.xplus_mt.sim import XplusMtDriveConfig, XplusMtSim

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
    with pytest.raises(IdentityError) as err:      # not driven: checked again slowly
        drive.connect()
    assert 'LITTLE_ENDIAN_BIG_ENDIAN (1162) reads 1' in str(err.value)
    assert "word_order parameter is 'big'" in str(err.value)
    bus.close()


def test_enable_sets_target_to_actual_and_does_not_move(sim, axis1):
    sim.drives['axis1'].axis.motion.set_position(12_345)
    complete(axis1.enable())
    st = axis1.read_state()
    assert (st.state, st.enabled, st.mode) == (State.OPERATION_ENABLED, True, 'PROFILE POSITION')
    assert st.status_word == 0x0637                       # §12: CW 0x000F -> 0x0637
    assert sim.drives['axis1'].register('TARGET_POSITION') == 12_345
    time.sleep(0.1)                                       # the standstill under test
    assert true_pos(sim) == 12_345
    complete(axis1.disable())
    assert axis1.read_state().state == State.SWITCH_ON_DISABLED


def test_enable_without_high_voltage_names_the_status_word(sim):
    bus, drive = make(sim, name='axis2', unit_id=2)
    drive.connect()
    with pytest.raises(DriveError) as err:
        complete(drive.enable())
    assert 'no high voltage' in str(err.value)
    assert 'READY TO SWITCH ON (statusword 0x0221)' in str(err.value)   # §12: 0x0221
    bus.close()


def test_move_absolute_within_tolerance(sim, axis1):
    complete(axis1.enable())
    complete(axis1.move_to(40_000, FAST))
    seen_moving = wait_for(lambda: axis1.read_state().moving, 1.0)
    assert seen_moving
    st = wait_for(lambda: (lambda s: s if s.target_reached and not s.moving else None)(
        axis1.read_state()), 3.0)
    assert st.position_steps == 40_000
    assert true_pos(sim) == pytest.approx(40_000, abs=0.5)
    assert st.state == State.OPERATION_ENABLED


def test_new_target_during_move_taken_at_once(sim, axis1):
    complete(axis1.enable())
    slow = Motion(60_000, 600_000, 600_000)
    complete(axis1.move_to(60_000, slow))
    wait_for(lambda: axis1.read_state().position_steps > 5_000, 2.0)
    t0 = time.monotonic()
    complete(axis1.move_to(120_000, slow))        # monotonous: no intermediate stop (§13)
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
    complete(axis1.enable())
    motion = Motion(0, 400_000, 400_000)
    complete(axis1.set_velocity(-40_000, motion))
    st = wait_for(lambda: (lambda s: s if s.velocity_steps_s == -40_000 else None)(
        axis1.read_state()), 2.0)
    assert st.mode == 'PROFILE VELOCITY' and st.moving
    p0 = st.position_steps
    wait_for(lambda: axis1.read_state().position_steps < p0 - 2_000, 1.0)
    complete(axis1.set_velocity(60_000, motion))  # on the fly, direction change (§13 PV)
    wait_for(lambda: axis1.read_state().velocity_steps_s == 60_000, 2.0)
    axis1.stop()                                  # Halt (bit 8) with 1072
    st = wait_for(lambda: (lambda s: s if not s.moving else None)(axis1.read_state()), 2.0)
    assert st.state == State.OPERATION_ENABLED and st.velocity_steps_s == 0
    assert sim.drives['axis1'].controlword & 0x0100
    complete(axis1.set_velocity(20_000, motion))  # runs again after the halt
    wait_for(lambda: axis1.read_state().velocity_steps_s == 20_000, 2.0)
    complete(axis1.set_velocity(0, motion))       # 0 = ramp to standstill
    wait_for(lambda: not axis1.read_state().moving, 2.0)


def test_quick_stop_and_back_to_operation_enabled(sim, axis1):
    complete(axis1.enable())
    complete(axis1.move_to(500_000, Motion(50_000, 500_000, 500_000)))
    wait_for(lambda: axis1.read_state().velocity_steps_s > 0, 1.0)
    axis1.stop(quick=True)
    st = wait_for(lambda: (lambda s: s if not s.moving else None)(axis1.read_state()), 2.0)
    assert st.state == State.QUICK_STOP_ACTIVE and st.status_word == 0x0617
    assert true_pos(sim) < 500_000
    complete(axis1.enable())                      # transition 16
    assert axis1.read_state().state == State.OPERATION_ENABLED


def test_homing_on_the_home_switch(sim, axis1):
    complete(axis1.enable())
    homing = Homing(method=19, offset_steps=1_000, speed_search_steps_s=100_000,
                    speed_zero_steps_s=16_000, acceleration_steps_s2=1_000_000)
    with pytest.raises(DriveError, match=r'INPUT_CONFIG \(1088\) = 15 has bit 0'):
        complete(axis1.start_homing(homing))      # factory 1088 = 15: I0 general purpose
    axis1.write_register('1088', 'u16', 14)       # IC0 = 0: I0 = proximity input
    assert complete(axis1.start_homing(homing)) == ''
    assert axis1.read_state().homing in (HomingState.RUNNING, HomingState.ATTAINED)
    st = wait_for(lambda: (lambda s: s if s.homing == HomingState.ATTAINED else None)(
        axis1.read_state()), 5.0)
    assert st.homed and st.mode == 'HOMING' and st.position_steps == 1_000
    assert sim.drives['axis1'].axis.raw_position_steps == pytest.approx(20_000, abs=1e-6)
    complete(axis1.move_to(0, FAST))              # back to profile position at standstill
    st = wait_for(lambda: (lambda s: s if s.target_reached and s.mode == 'PROFILE POSITION'
                           and not s.moving else None)(axis1.read_state()), 3.0)
    assert st.position_steps == 0 and st.homed   # homed stays latched


def test_homing_method_refused_and_current_position_method(sim, axis1):
    complete(axis1.enable())
    with pytest.raises(DriveError, match='7 is not a homing method of the X-PLUS MT'):
        complete(axis1.start_homing(Homing(7, 0, 20_000, 1_000, 100_000)))
    axis1.write_register('1088', 'u16', 14)
    with pytest.raises(DriveError, match=r'home: homing.speed_search 1019 is outside '
                                         r'HOMING_SPEED_SEARCH_SWITCH \(1052\) range 16001'):
        complete(axis1.start_homing(Homing(19, 0, 1019, 200, 100_000)))  # 0.5 rad/s: below 75 rpm
    assert axis1.read_state().mode == 'PROFILE POSITION'       # nothing changed
    complete(axis1.start_homing(Homing(35, -500, 0, 0, 0)))  # no speeds needed for 35
    st = wait_for(lambda: (lambda s: s if s.homing == HomingState.ATTAINED else None)(
        axis1.read_state()), 2.0)
    assert st.position_steps == -500 and st.homed


def test_fault_injection_code_text_and_reset(sim, axis1):
    complete(axis1.enable())
    ok, _ = sim.inject_fault('axis1', 'drive_fault', 0x4310)
    assert ok
    st = axis1.read_state()
    assert (st.state, st.fault, st.enabled, st.fault_code) == (State.FAULT, True, False, 0x4310)
    assert st.fault_text == 'Error drive excessive temperature (0x4310)'
    with pytest.raises(DriveError, match='in FAULT.*excessive temperature.*fault_reset first'):
        complete(axis1.enable())
    remaining = complete(axis1.fault_reset())     # cause still present (G15)
    assert 'Error drive excessive temperature (0x4310)' in remaining and 'still' in remaining
    sim.inject_fault('axis1', 'clear_fault', 0x4310)
    assert complete(axis1.fault_reset()) == ''
    st = axis1.read_state()
    assert (st.state, st.fault, st.fault_code) == (State.SWITCH_ON_DISABLED, False, 0)
    assert axis1.read_register('1221', 'u16') == 0x4310   # alarm log n°0 code
    complete(axis1.enable())
    assert axis1.read_state().enabled


def test_save_params_writes_the_signature(sim, axis1, tmp_path):
    axis1.write_register('1080', 'u16', 50)       # Current Ratio, storable ('**')
    note = complete(axis1.save_params())
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
        assert bus.read_holding_registers(1, 1042, 2) == expect  # §11 word order on the wire
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
    (lambda d: complete(d.move_to(1000, FAST)), 'move_to: drive is in SWITCH ON DISABLED'),
])
def test_refusals_name_the_register(sim, axis1, call, message):
    transactions = axis1.bus.transactions
    with pytest.raises(DriveError, match=message):
        call(axis1)
    assert axis1.bus.transactions - transactions <= 1    # refused before writing anything
    assert axis1.bus.counters()['exceptions'] == 0


def test_motion_ranges_checked_before_sending(sim, axis1):
    complete(axis1.enable())
    with pytest.raises(DriveError, match=r'acceleration 1000 is outside PROFILE_ACCELERATION '
                                         r'\(1046\) range 2000..10000000'):
        complete(axis1.move_to(1000, Motion(10_000, 1_000, 10_000)))
    with pytest.raises(DriveError, match=r'900000 is outside TARGET_VELOCITY \(1048\)'):
        complete(axis1.set_velocity(900_000, FAST))


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


def test_an_idle_drive_gives_its_snapshot_again_and_a_change_a_new_one(sim, axis1):
    """Polls that read the same words give the last snapshot again, not a new decode; a new
    position, an enable, a disable each give a new snapshot that says so."""
    axis1.read_state()
    idle = axis1.read_state()                # (the position before is now the same too)
    assert axis1.read_state() is idle and axis1.read_state() is idle
    sim.drives['axis1'].axis.motion.set_position(1_000)
    moved = axis1.read_state()
    assert moved is not idle and moved.position_steps == 1_000 and idle.position_steps == 0
    complete(axis1.enable())
    assert axis1.read_state().state == State.OPERATION_ENABLED
    complete(axis1.disable())
    st = axis1.read_state()
    assert st.state == State.SWITCH_ON_DISABLED and not st.alarms      # no "possible STO"
    assert axis1.read_state() is axis1.read_state()


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
    ({'watchdog_ms': 50}, 'drives.axis1.watchdog_ms: 50 (allowed: 0 = off, or 100..32000 ms'),
    ({'watchdog_ms': 200, 'publish_rate_hz': 20.0},
     'drives.axis1.watchdog_ms: 200 ms is less than 5 poll periods at publish_rate_hz 20 (the '
     'polls feed the drive watchdog); allowed: >= 250 ms, or 0 = off'),
    ({'input_config': 0x90}, 'drives.axis1.input_config: 144 (allowed: -1 = leave the drive as '
                             'it is, or INPUT_CONFIG (1088) 0x0000..0x008F)'),
    ({'homing.method': 19, 'input_config': 15},
     'drives.axis1.homing.method: 19 needs the home switch on I0, but drives.axis1.input_config '
     '15 has bit 0 = 1'),
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
    specs = {(p.scope, p.name): p for p in VENDOR.params}
    assert (specs['bus', 'host'].default, specs['bus', 'port'].default,
            specs['bus', 'word_order'].choices) == ('127.0.0.1', 502, ('little', 'big'))
    assert specs['drive', 'unit_id'].max_value == 255
    # a drive on a host of its own ('' and 0: as the bus-level parameter)
    assert VENDOR.drive_bus_params == ('host', 'port')
    assert (specs['drive', 'host'].default, specs['drive', 'port'].default) == ('', 0)
    assert (specs['drive', 'watchdog_ms'].default, specs['drive', 'input_config'].default) == \
        (1000, -1)
    assert isinstance(VENDOR.make_drive(VENDOR.make_bus({}), 'x', {}), XplusMtDrive)


# --- Step-wise operations (drive.py contract) -------------------------------------------------
def run_steps(result, bus):
    """Run a step-wise result as the bus owner does (sleeping each yielded delay); returns
    (value, transactions of each step)."""
    assert is_operation(result), 'not step-wise'
    per_step, seen = [], bus.transactions
    while True:
        try:
            delay = next(result)
        except StopIteration as stop:
            per_step.append(bus.transactions - seen)
            return stop.value, per_step
        per_step.append(bus.transactions - seen)
        seen = bus.transactions
        time.sleep(delay)


def test_operations_give_the_bus_back_between_transactions(sim, axis1):
    bus = axis1.bus
    homing = Homing(method=35, offset_steps=0, speed_search_steps_s=100_000,
                    speed_zero_steps_s=16_000, acceleration_steps_s2=1_000_000)
    # strict simulator: a mode change reads the state in 3 FC03 (holes refused), one step
    for name, op, most in [
            ('enable', lambda: axis1.enable(), 2),
            ('move_to', lambda: axis1.move_to(5_000, FAST), 2),
            ('move_to again', lambda: axis1.move_to(0, FAST), 2),
            ('set_velocity', lambda: axis1.set_velocity(20_000, FAST), 3),
            ('set_velocity again', lambda: axis1.set_velocity(-20_000, FAST), 2),
            ('set_velocity 0', lambda: axis1.set_velocity(0, FAST), 2),
            ('start_homing', lambda: axis1.start_homing(homing), 3),
            ('disable', lambda: axis1.disable(), 2)]:
        _, per_step = run_steps(op(), bus)
        assert max(per_step) <= most, (name, per_step)
        if name == 'move_to again':
            # same mode: state and mode in one FC03 (1001..1002), then target & profile in one
            # FC16 (the deceleration 1072 is as this connection wrote it)
            assert per_step[:2] == [1, 1], per_step
        if name in ('move_to', 'move_to again', 'set_velocity 0'):
            wait_for(lambda: (lambda st: not st.moving and (
                st.target_reached or st.mode == 'PROFILE VELOCITY'))(axis1.read_state()),
                2.0, 'standstill')
    sim.inject_fault('axis1', 'drive_fault', 0x4310)
    sim.inject_fault('axis1', 'clear_fault', 0x4310)
    note, per_step = run_steps(axis1.fault_reset(), bus)
    assert note == '' and max(per_step) <= 2
    assert axis1.read_state().state == State.SWITCH_ON_DISABLED


def fc16_addresses(bus, monkeypatch):
    """The start address of every FC16 the drive sends from now on (the real write runs)."""
    sent = []
    write = bus.write_registers

    def recorded(unit, address, words):
        sent.append(address)
        return write(unit, address, words)
    monkeypatch.setattr(bus, 'write_registers', recorded)
    return sent


def test_deceleration_is_written_only_when_it_changes(sim, axis1, monkeypatch):
    """A stream of set points with one profile: 1072 (not contiguous with 1042..1047) goes
    once per value and connection; a lost reply, a raw write and a reconnect forget it."""
    complete(axis1.enable())
    sent = fc16_addresses(axis1.bus, monkeypatch)
    slower = Motion(FAST.velocity_steps_s, FAST.acceleration_steps_s2, 1_000_000)

    def moves(target, motion=FAST):
        del sent[:]
        complete(axis1.move_to(target, motion))
        return list(sent)
    assert moves(1_000) == [1042, 1072]
    assert moves(2_000) == [1042]
    assert moves(3_000, slower) == [1042, 1072]
    assert sim.drives['axis1'].register('PROFILE_DECELERATION') == 1_000_000
    assert moves(4_000, slower) == [1042]
    axis1.write_register('1072', 'i32', 1_000_000)          # a raw write: anything may change
    assert moves(5_000, slower) == [1042, 1072]
    sim.inject_fault('axis1', 'lose_write_reply', 1072, 0)  # takes effect, the reply is lost
    with pytest.raises(LinkError):
        moves(6_000)
    assert sim.drives['axis1'].register('PROFILE_DECELERATION') == FAST.deceleration_steps_s2
    assert moves(7_000) == [1042, 1072]          # unknown after the lost reply: sent again
    axis1.connect()
    assert moves(8_000) == [1042, 1072]


def test_stop_is_one_read_and_one_write(sim, axis1):
    complete(axis1.enable())
    complete(axis1.set_velocity(40_000, FAST))
    before = axis1.bus.transactions
    assert not is_operation(axis1.stop())               # the urgent path: never step-wise
    assert axis1.bus.transactions - before == 2
    assert sim.drives['axis1'].controlword & 0x0100  # Halt


def test_cut_short_move_leaves_no_write_behind(sim, axis1):
    complete(axis1.enable())
    steps = axis1.move_to(40_000, FAST)
    next(steps)                                     # enabled/mode read, nothing written yet
    cw = sim.drives['axis1'].controlword
    steps.close()                                   # a stop or a link loss cut it short
    assert sim.drives['axis1'].controlword == cw
    assert sim.drives['axis1'].register('TARGET_POSITION') == 0   # enable's target = actual
    time.sleep(0.05)                                # the standstill under test
    assert true_pos(sim) == 0


# --- Representable ranges: checked before anything is read or written ------------------------
@pytest.mark.parametrize('call,message', [
    (lambda d: d.move_to(2**31, FAST), r'move_to: target 2147483648 is outside TARGET_POSITION '
                                       r'\(1042\) range -2147483648..2147483647'),
    (lambda d: d.move_to(float('nan'), FAST), r'move_to: target nan is not a number for '
                                              r'TARGET_POSITION \(1042\)'),
    (lambda d: d.move_to(0, Motion(900_000, 1e6, 1e6)),
     r'move_to: velocity 900000 is outside PROFILE_VELOCITY \(1044\) range 0..800000 Hz'),
    (lambda d: d.move_to(0, Motion(1e4, 1e6, 2e7)),
     r'move_to: deceleration 20000000 is outside PROFILE_DECELERATION \(1072\)'),
    (lambda d: d.set_velocity(float('inf'), FAST), r'set_velocity: inf is not a number for '
                                                   r'TARGET_VELOCITY \(1048\)'),
    (lambda d: d.set_velocity(-800_001, FAST), r'-800001 is outside TARGET_VELOCITY \(1048\)'),
    (lambda d: d.start_homing(Homing(35, 2**31, 0, 0, 0)),
     r'home: homing.offset 2147483648 is outside HOMING_OFFSET \(1058\)'),
    (lambda d: d.start_homing(Homing(19, 0, 20_000, 16_001, 1e6)),
     r'home: homing.speed_zero 16001 is outside HOMING_SPEED_SEARCH_ZERO \(1054\) range '
     r'0..16000 Hz'),
    (lambda d: d.start_homing(Homing(19, 0, 20_000, 1_000, 1_000)),
     r'home: homing.acceleration 1000 is outside HOMING_ACCELERATION \(1056\)'),
])
def test_motion_outside_the_registers_is_refused_before_any_transaction(
        sim, axis1, call, message):
    complete(axis1.enable())
    before = axis1.bus.transactions
    with pytest.raises(DriveError, match=message):
        complete(call(axis1))
    assert axis1.bus.transactions == before


def test_motion_needs_the_drive_enabled_on_the_wire(sim, axis1):
    complete(axis1.enable())
    sim.drives['axis1'].inject('hv_off', 0, 0.0)      # the drive faults behind the driver's back
    for call in (lambda: axis1.move_to(1_000, FAST), lambda: axis1.set_velocity(1_000, FAST),
                 lambda: axis1.start_homing(Homing(35, 0, 0, 0, 0))):
        with pytest.raises(DriveError, match=r'drive is in FAULT .* not OPERATION ENABLED'):
            complete(call())
    assert sim.drives['axis1'].controlword == 0x000F  # nothing was commanded


# --- Identity (drive.IdentityError: not driven, checked again on the slow back-off) -----------
@pytest.mark.parametrize('registers,message', [
    ({1081: 200}, r'STEP_REVOLUTION \(1081\) reads 200; an X-PLUS MT has 12800 only'),
    ({1162: 7}, r'LITTLE_ENDIAN_BIG_ENDIAN \(1162\) reads 7; an X-PLUS MT holds 1 \(little\) or '
                r'0 \(big\)'),
])
def test_a_device_that_is_not_an_xplus_mt_is_refused(tmp_path, registers, message):
    s = XplusMtSim(port=0, drives=[XplusMtDriveConfig('axis1', registers=registers)])
    s.start()
    try:
        bus, drive = make(s)
        with pytest.raises(IdentityError, match=message):
            drive.connect()
        dev = s.drives['axis1']
        assert (dev.controlword, dev.register('COUNTER_WATCHDOG')) == (0, 0)   # nothing written
        bus.close()
    finally:
        s.stop()


def test_another_modbus_device_is_not_an_xplus_mt():
    """A plain pymodbus server (registers 0..99) where the X-PLUS MT was configured."""
    import asyncio
    import threading

    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    loop = asyncio.new_event_loop()
    started = threading.Event()
    holder = {}

    async def serve():
        holder['server'] = server = ModbusTcpServer(
            SimDevice(id=1, simdata=[SimData(address=0, count=100, values=0,
                                             datatype=DataType.REGISTERS)]),
            address=('127.0.0.1', 0))
        await server.serve_forever(background=True)
        holder['port'] = server.transport.sockets[0].getsockname()[1]
        started.set()
        await server.serving

    thread = threading.Thread(target=loop.run_until_complete, args=(serve(),), daemon=True)
    thread.start()
    assert started.wait(5)
    try:
        bus = VENDOR.make_bus({'host': '127.0.0.1', 'port': holder['port'], 'timeout_s': 0.5})
        bus.open()
        drive = VENDOR.make_drive(bus, 'axis1', {'unit_id': 1})
        with pytest.raises(IdentityError, match=r'LITTLE_ENDIAN_BIG_ENDIAN \(1162\): the '
                                                r'device at unit 1 has no such register '
                                                r'.*exception 0x02.*not an X-PLUS MT'):
            drive.connect()
        bus.close()
    finally:
        asyncio.run_coroutine_threadsafe(holder['server'].shutdown(), loop).result(5)
        thread.join(5)


def test_input_config_bit_7_on_a_b4_is_refused_as_identity(tmp_path):
    s = XplusMtSim(port=0, drives=[XplusMtDriveConfig('axis1', model='B4')])
    s.start()
    try:
        bus, drive = make(s, input_config=0x8E)     # IC7 (STO status) exists on the S4 only
        with pytest.raises(IdentityError, match=r'drives.axis1.input_config: the drive refuses '
                                                r'142 in INPUT_CONFIG \(1088\)'):
            drive.connect()
        bus.close()
    finally:
        s.stop()


# --- Input Config (1088): a factory drive homes on its switch ---------------------------------
def test_input_config_written_at_connect_lets_a_factory_drive_home(sim, tmp_path):
    bus, drive = make(sim, input_config=14)
    assert sim.drives['axis1'].register('INPUT_CONFIG') == 15     # factory: I0 general purpose
    ident = drive.connect()
    assert ident['input_config'] == '0x000E (1088)'
    assert sim.drives['axis1'].register('INPUT_CONFIG') == 14
    complete(drive.enable())
    homing = Homing(method=19, offset_steps=0, speed_search_steps_s=100_000,
                    speed_zero_steps_s=16_000, acceleration_steps_s2=1_000_000)
    complete(drive.start_homing(homing))
    st = wait_for(lambda: (lambda s: s if s.homing == HomingState.ATTAINED else None)(
        drive.read_state()), 5.0, 'homing attained')
    assert st.homed and sim.drives['axis1'].axis.raw_position_steps == pytest.approx(20_000)
    assert not os.path.exists(tmp_path / 'xplus_mt_unit1.json')   # RAM only ...
    complete(drive.save_params())                                  # ... until asked
    with open(tmp_path / 'xplus_mt_unit1.json', encoding='utf-8') as f:
        assert json.load(f)['registers']['1088'] == 14
    bus.close()


def test_input_config_minus_one_leaves_the_drive_alone(sim):
    bus, drive = make(sim, input_config=-1)
    transactions = bus.transactions
    assert drive.connect()['input_config'] == '0x000F (1088)'
    assert sim.drives['axis1'].register('INPUT_CONFIG') == 15
    # 1162, 1152..1159, 1081..1097, 1097 := watchdog, 1001: no write of 1088
    assert bus.transactions - transactions == 5
    bus.close()


# --- Several drive hosts: each X-PLUS MT is its own Modbus TCP server -------------------------
def test_drives_on_two_hosts_each_get_their_own_bus(tmp_path):
    sims = [XplusMtSim(port=0, drives=[XplusMtDriveConfig('axis1')]) for _ in range(2)]
    for s in sims:
        s.start()
    try:
        bus_params = {'host': '127.0.0.1', 'port': sims[0].port, 'timeout_s': 0.5,
                      'word_order': 'little', 'publish_rate_hz': 50.0}
        drive_params = {'left': {'unit_id': 1, 'host': '', 'port': 0},
                        'right': {'unit_id': 1, 'host': '127.0.0.1', 'port': sims[1].port}}
        buses, drives = {}, {}
        for name, params in drive_params.items():
            # what the node does with Vendor.drive_bus_params: '' / 0 = as the bus level
            link = {**bus_params, **{k: params[k] for k in VENDOR.drive_bus_params
                                     if params[k]}}
            key = tuple(link[k] for k in VENDOR.drive_bus_params)
            if key not in buses:
                buses[key] = VENDOR.make_bus(link)
                buses[key].open()
            drives[name] = VENDOR.make_drive(buses[key], name, {**bus_params, **params})
        assert len(buses) == 2
        for d in drives.values():
            d.connect()
            complete(d.enable())
        complete(drives['left'].move_to(3_000, FAST))
        complete(drives['right'].move_to(-7_000, FAST))
        for d, s, target in ((drives['left'], sims[0], 3_000),
                             (drives['right'], sims[1], -7_000)):
            wait_for(lambda d=d: (lambda st: st.target_reached and not st.moving)(d.read_state()),
                     3.0, 'target reached')
            assert s.drives['axis1'].true_position_steps == pytest.approx(target, abs=0.5)
        for b in buses.values():
            b.close()
    finally:
        for s in sims:
            s.stop()


@pytest.mark.parametrize('params,message', [
    ({'host': '', 'port': 502}, "host: '' (allowed: an IP address or host name"),
    ({'host': '10.0.0.5', 'port': 0}, 'port: 0 (allowed: a TCP port 1..65535)'),
])
def test_make_bus_refuses_an_unusable_link(params, message):
    with pytest.raises(ValueError) as err:
        VENDOR.make_bus(params)
    assert str(err.value).startswith(message)
