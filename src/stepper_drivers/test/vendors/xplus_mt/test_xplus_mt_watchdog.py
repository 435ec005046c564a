"""The X-PLUS MT drive-side watchdog (register 1097) armed by the driver, against the simulator.

§13 "Register 1097": a value other than 0 is the timeout in ms (100÷32000); when the drive
"does not receive any read or write message before the timeout", it goes to Fault (current off,
§12 transitions 13-14). The driver arms it at connect (parameter watchdog_ms) and its polls feed
it, so a master that dies leaves no axis running.
"""

import json
import time

import pytest
from stepper_drivers.contract.drive import Motion, State, complete
from stepper_drivers.vendors.xplus_mt import VENDOR
from stepper_sim.harness import wait_for
from stepper_sim.xplus_mt.sim import XplusMtDriveConfig, XplusMtSim

RUN = Motion(velocity_steps_s=0, acceleration_steps_s2=400_000, deceleration_steps_s2=400_000)
WATCHDOG_MS = 300
POLL_S = 0.02                    # the node's default publish_rate_hz 50


@pytest.fixture
def sim(tmp_path):
    s = XplusMtSim(port=0, drives=[XplusMtDriveConfig('axis1')], storage_dir=str(tmp_path))
    s.start()
    yield s
    s.stop()


def connect(sim, watchdog_ms=WATCHDOG_MS):
    bus = VENDOR.make_bus({'host': '127.0.0.1', 'port': sim.port, 'timeout_s': 0.5})
    bus.open()
    drive = VENDOR.make_drive(bus, 'axis1', {'unit_id': 1, 'watchdog_ms': watchdog_ms})
    return bus, drive, drive.connect()


def run_and_poll(drive, duration_s):
    """Enable, run at 40000 Hz, and poll like the node for duration_s; the last state."""
    complete(drive.enable())
    complete(drive.set_velocity(40_000, RUN))
    deadline = time.monotonic() + duration_s
    while time.monotonic() < deadline:
        st = drive.read_state()
        time.sleep(POLL_S)
    return st


def test_connect_arms_the_watchdog(sim):
    dev = sim.drives['axis1']
    assert dev.register('COUNTER_WATCHDOG') == 0                 # power-on value (App.1)
    bus, _, ident = connect(sim)
    assert dev.register('COUNTER_WATCHDOG') == WATCHDOG_MS
    assert ident['watchdog'] == '300 ms (1097)'
    bus.close()


def test_polls_feed_it_and_a_dead_master_leaves_the_axis_stopped(sim):
    dev = sim.drives['axis1']
    bus, drive, _ = connect(sim)
    st = run_and_poll(drive, 3 * WATCHDOG_MS / 1000.0)             # fed: no fault meanwhile
    assert (st.state, st.velocity_steps_s) == (State.OPERATION_ENABLED, 40_000)
    bus.close()                                                    # the master dies
    died = time.monotonic()
    # it ran on by itself until the watchdog ran out ...
    time.sleep(0.8 * WATCHDOG_MS / 1000.0)
    assert dev.axis.velocity_hz == 40_000 and dev.state == 'OPERATION ENABLED'
    # ... then the drive went to Fault, current off: the axis stops by itself
    wait_for(lambda: dev.axis.velocity_hz == 0, 1.0, 'the watchdog stop')
    stopped_after_s = time.monotonic() - died
    # bound: the timeout, one simulator tick, the poll period of this wait, scheduling slack
    # (current off: no ramp)
    assert stopped_after_s <= WATCHDOG_MS / 1000.0 + sim.tick_s + 0.01 + 0.05, stopped_after_s
    assert dev.state == 'FAULT' and dev.alarm_log[0][1] == dev.config.watchdog_error_code
    # the master comes back: it sees the fault, and only a fault reset clears it
    bus.open()
    drive.connect()
    st = drive.read_state()
    assert st.fault and not st.moving and st.state == State.FAULT
    assert complete(drive.fault_reset()) == ''
    bus.close()


def test_watchdog_off_keeps_the_axis_running_without_a_master(sim):
    dev = sim.drives['axis1']
    bus, drive, ident = connect(sim, watchdog_ms=0)
    assert ident['watchdog'] == 'off (1097 = 0)' and dev.register('COUNTER_WATCHDOG') == 0
    run_and_poll(drive, 0.1)
    bus.close()
    time.sleep(2 * WATCHDOG_MS / 1000.0)                            # the silence under test
    assert dev.axis.velocity_hz == 40_000 and dev.state == 'OPERATION ENABLED'


def test_orderly_close_disarms_it_so_a_holding_drive_stays_enabled(sim):
    """disable_on_shutdown false: the node stops but leaves the drive enabled on purpose."""
    dev = sim.drives['axis1']
    bus, drive, _ = connect(sim)
    complete(drive.enable())
    drive.close()
    assert dev.register('COUNTER_WATCHDOG') == 0
    bus.close()
    time.sleep(2 * WATCHDOG_MS / 1000.0)                            # the silence under test
    assert dev.state == 'OPERATION ENABLED'


def test_save_params_stores_it_off_and_keeps_it_armed(sim, tmp_path):
    """Stored armed, the watchdog would fault every drive powered up without a master."""
    dev = sim.drives['axis1']
    bus, drive, _ = connect(sim)
    note = complete(drive.save_params())
    assert 'COUNTER_WATCHDOG (1097) was stored as 0' in note
    with open(tmp_path / 'xplus_mt_unit1.json', encoding='utf-8') as f:
        assert json.load(f)['registers']['1097'] == 0
    assert dev.register('COUNTER_WATCHDOG') == WATCHDOG_MS          # still armed in RAM
    bus.close()
