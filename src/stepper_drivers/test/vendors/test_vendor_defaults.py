"""A drive made without the node (a script, a benchmark) gets the defaults the node declares and
the docs list: one place, `Vendor.with_defaults` over each vendor's ParamSpecs. No ROS, no link:
the buses are made, not opened.

Before, each drive class repeated its defaults as literals, and some disagreed with the
ParamSpecs: a Vector Step made from partial parameters had its SYNC watchdog (0x1006) off, and
its bus no SYNC and no heartbeat, where the node (and docs/vector_step.md) gives 0.5 s, 0.1 s and
100 ms.
"""

import pytest
from stepper_drivers.vendors import rd4, vector_step, xmind_k, xplus_mt


def spec(vendor, name, scope='drive'):
    return next(p.default for p in vendor.VENDOR.params if p.name == name and p.scope == scope)


def test_vector_step_bus_and_drive_from_partial_params_get_the_documented_watchdogs():
    bus = vector_step.make_bus({'timeout_s': 0.5})
    assert bus.sync_period_s == spec(vector_step, 'can.sync_period_s', 'bus') == 0.1
    assert bus.master_heartbeat_ms == spec(vector_step, 'can.master_heartbeat_ms', 'bus') == 100
    drive = vector_step.make_drive(bus, 'axis1', {'node_id': 3})
    assert drive.sync_timeout_s == spec(vector_step, 'sync_timeout_s') == 0.5
    assert drive.inhibit_100us == round(spec(vector_step, 'tpdo_inhibit_ms') * 10)
    assert drive.event_timer_ms == spec(vector_step, 'tpdo_event_timer_ms')
    assert drive.heartbeat_ms == spec(vector_step, 'heartbeat_period_ms')
    assert drive.steps_per_rev == vector_step.VENDOR.drive_defaults['steps_per_rev']
    assert drive.consumer_heartbeat == 127 << 16 | 10 * 100      # 0x1016:01, 10 periods


def test_vector_step_drive_is_checked_against_what_its_bus_produces():
    """A bus made without SYNC and a drive whose parameters (its own copy of the bus ones) say
    there is: the drive's 0x1006 watchdog would trip 0.5 s after the start. Refused, naming the
    parameter, whatever the drive's params claim."""
    bus = vector_step.make_bus({'timeout_s': 0.5, 'can.sync_period_s': 0.0})
    with pytest.raises(ValueError, match=r'drives\.axis1\.sync_timeout_s: 0\.5 needs the SYNC '
                                         r'of this node \(can\.sync_period_s > 0\)'):
        vector_step.make_drive(bus, 'axis1', {'node_id': 3, 'can.sync_period_s': 0.1})
    drive = vector_step.make_drive(bus, 'axis2', {'node_id': 4, 'sync_timeout_s': 0.0})
    assert drive.sync_timeout_s == 0.0


def test_vector_step_validate_takes_the_bus_defaults():
    """The node's own heartbeat is on by default (node-ID 127): a drive on 127 is refused even
    when the parameters leave can.master_heartbeat_ms out."""
    errors = vector_step.validate({'drives': ['a'], 'drives.a.node_id': 127})
    assert any('drives.a.node_id: 127 is can.master_node_id' in e for e in errors), errors


def test_xplus_mt_drive_from_partial_params():
    bus = xplus_mt.make_bus({'timeout_s': 0.5})
    assert (bus.host, bus.port) == (spec(xplus_mt, 'host', 'bus'), spec(xplus_mt, 'port', 'bus'))
    drive = xplus_mt.make_drive(bus, 'axis1', {'unit_id': 2})
    assert drive.watchdog_ms == spec(xplus_mt, 'watchdog_ms') == 1000    # 1097 armed
    assert drive.word_order == spec(xplus_mt, 'word_order', 'bus')
    assert drive.input_config == spec(xplus_mt, 'input_config')
    # the drive-level host/port ('' / 0: "as the bus") never hide the bus-level defaults
    assert xplus_mt.VENDOR.with_defaults({})['host'] == '127.0.0.1'


def test_rd4_drive_from_partial_params(tmp_path):
    bus = rd4.make_bus({'port': str(tmp_path / 'no_such_tty')})
    assert (bus.baudrate, bus.parity) == (spec(rd4, 'baudrate', 'bus'), spec(rd4, 'parity', 'bus'))
    drive = rd4.make_drive(bus, 'axis1', {'node_id': 5})
    assert drive.watchdog is spec(rd4, 'watchdog') is True
    assert drive.hold_torque is spec(rd4, 'hold_torque')
    assert drive.velocity_source == spec(rd4, 'velocity_source')
    assert drive.steps_per_rev == rd4.VENDOR.drive_defaults['steps_per_rev']


def test_xmind_k_drive_from_partial_params(tmp_path):
    bus = xmind_k.make_bus({'port': str(tmp_path / 'no_such_tty'), 'timeout_s': 0.5})
    drive = xmind_k.make_drive(bus, 'axis1', {'address': 7})
    assert drive.number == 7
    assert drive.steps_per_rev == xmind_k.VENDOR.drive_defaults['steps_per_rev']
    assert drive.busy_poll_s == spec(xmind_k, 'busy_poll_period_s')
