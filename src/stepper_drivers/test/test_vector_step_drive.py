"""VectorStepDrive against vector_step_sim on the loopback CAN bus, without ROS.

The simulator runs in-process on the real CAN stack (socketcand broker, python-can, canopen); a
third client records the frames, so the tests check what goes over the wire where it matters
(the manual's fault-reset order, raw homing method numbers, the STOP command, no SDO per poll).
"""

import logging
import struct
import threading
import time

import can
import pytest
from stepper_drivers.drive import DriveError, Homing, HomingState, LinkError, Motion, State
from stepper_drivers.protocol.socketcand_broker import SocketcandBroker
from stepper_drivers.tools.processes import wait_for as wait
from stepper_drivers.vendors import vector_step as vs
from stepper_drivers.vendors import vector_step_map as vm
from stepper_sim.vector_step_sim import NodeConfig, VectorStepSim

logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)

MOTION = Motion(velocity_steps_s=32000.0, acceleration_steps_s2=160000.0,
                deceleration_steps_s2=160000.0)


def params(**over):
    p = {spec.name: spec.default for spec in vs.PARAMS}
    p.update({'timeout_s': 0.5, 'steps_per_rev': 3200.0, 'homing.method': 35,
              'heartbeat_timeout_s': 0.5})
    p.update(over)
    return p


class Monitor:
    """Records every frame on the bus (a third client)."""

    def __init__(self, port):
        self.bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel='can0',
                           tcp_tune=True)
        self.frames: list[tuple[int, bytes]] = []
        self.notifier = can.Notifier(self.bus, [self._on], 0.1)

    def _on(self, msg):
        self.frames.append((msg.arbitration_id, bytes(msg.data)))

    def send(self, cob: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def mark(self) -> int:
        return len(self.frames)

    def since(self, mark, cob=None):
        return [(c, d) for c, d in self.frames[mark:] if cob is None or c == cob]

    def wait_seen(self, mark, frame, timeout_s=5.0):
        """The notifier thread records asynchronously: wait for a frame instead of racing it."""
        wait(lambda: frame in self.since(mark), timeout_s, f'frame {frame} on the bus')
        return self.since(mark)

    def catch_up(self, node_id=1, timeout_s=5.0):
        """Wait until two heartbeats of a node arrive after this call; the broker forwards in
        order, so every frame sent before the call has then been recorded (for 'not sent')."""
        start = len(self.frames)
        wait(lambda: len(self.since(start, 0x700 + node_id)) >= 2, timeout_s, 'heartbeats')

    def close(self):
        self.notifier.stop()
        self.bus.shutdown()


class Bench:
    def __init__(self, tmp_path):
        self.broker = SocketcandBroker(port=0, ready_delay_s=0.01)
        self.broker.start()
        self.sim = VectorStepSim([NodeConfig('axis1', 1, limit_neg_steps=-3200.0),
                                  NodeConfig('axis2', 2)], port=self.broker.port,
                                 reboot_delay_s=0.02, storage_dir=str(tmp_path))
        self.monitor = Monitor(self.broker.port)
        self.sim.start()
        self.bus = vs.make_bus(params(**{'can.port': self.broker.port}))
        self.bus.open()
        self.drives = {name: vs.make_drive(self.bus, name, params(
            node_id=node_id, **{'can.port': self.broker.port}))
            for name, node_id in (('axis1', 1), ('axis2', 2))}
        for node in self.sim.nodes.values():      # both booted
            wait(lambda node=node: node.nmt_state == 0x7F)

    def connect(self, *names):
        for name in names or self.drives:
            self.drives[name].connect()
        return self.drives[names[0]] if len(names) == 1 else self.drives

    def close(self):
        self.bus.close()
        self.monitor.close()
        self.sim.stop()
        self.broker.stop()


def settle(drive, timeout_s=5.0):
    return wait(lambda: (lambda s: s if not s.moving else None)(drive.read_state()), timeout_s,
                'standstill')


@pytest.fixture
def bench(tmp_path):
    b = Bench(tmp_path)
    yield b
    b.close()


def test_connect_configures_the_node_and_reads_state_from_pdos_only(bench):
    d = bench.connect('axis1')
    node = bench.sim.nodes['axis1']
    assert d.address == 1
    assert node.nmt_state == 0x05                                    # started
    assert node._stored(vm.PRODUCER_HEARTBEAT_TIME) == 100
    for number, entries in enumerate(vm.DRIVER_TPDOS, 1):
        mapping = vm.TPDO_MAPPING + number - 1
        assert node._stored(mapping, 0) == len(entries)
        assert [node._stored(mapping, k) for k in range(1, len(entries) + 1)] == \
            [vm.mapping_entry(*e) for e in entries]
    assert node._stored(vm.TPDO_COMMUNICATION + 1, 5) == 100         # TxPDO2 event timer
    assert node._stored(vm.RPDO_MAPPING + 2, 1) == vm.mapping_entry(vm.CONTROLWORD, 0, 16)
    assert node._stored(vm.RPDO_COMMUNICATION + 3, 1) & vm.PDO_INVALID   # RxPDO4 off
    mark = bench.monitor.mark()
    for _ in range(20):
        s = d.read_state()
    assert s.state == State.SWITCH_ON_DISABLED and not s.enabled and s.mode == 'PROFILE POSITION'
    bench.monitor.catch_up()
    assert not bench.monitor.since(mark, 0x601), 'read_state() must not use SDO'


def test_identity(bench):
    identity = bench.connect('axis1').connect()
    assert identity['vendor_id'] == '0x000000BC'
    assert identity['product_code'].endswith('(SMD5006)')
    assert identity['device_name'] == 'SMD50.06LIC' and identity['Rstpres'] == '16'


def test_enable_keeps_the_position_then_moves_and_changes_target_immediately(bench):
    d = bench.connect('axis1')
    before = bench.sim.true_position_steps('axis1')
    d.enable()
    s = d.read_state()
    assert s.state == State.OPERATION_ENABLED and s.enabled and not s.moving
    assert bench.sim.true_position_steps('axis1') == before
    d.move_to(6400, MOTION)
    s = settle(d)
    assert s.position_steps == 6400 and s.target_reached
    assert bench.sim.true_position_steps('axis1') == pytest.approx(6400)
    d.move_to(64000, MOTION)
    wait(lambda: d.read_state().position_steps > 9000, what='moving')
    d.move_to(1000, MOTION)                       # bit 5: change set immediately
    s = settle(d)
    assert s.position_steps == 1000


def test_jog_reverses_and_stops_on_bit_4(bench):
    d = bench.connect('axis1')
    d.enable()
    d.set_velocity(6400.0, MOTION)                # 2 rev/s
    s = wait(lambda: (lambda s: s if s.velocity_steps_s == 6400.0 else None)(d.read_state()))
    assert s.mode == 'AEC VELOCITY (JOG)' and s.moving
    d.set_velocity(-3200.0, MOTION)
    wait(lambda: d.read_state().velocity_steps_s == -3200.0, what='reversed')
    mark = bench.monitor.mark()
    d.set_velocity(0.0, MOTION)
    s = settle(d)
    assert s.enabled and s.velocity_steps_s == 0.0
    bench.monitor.catch_up()
    assert not bench.monitor.since(mark, 0x601), 'JOG stop is the controlword, not an SDO'


def test_stop_in_profile_position_uses_the_rcmdwr_stop_bit(bench):
    d = bench.connect('axis1')
    d.enable()
    d.move_to(320000, MOTION)
    wait(lambda: d.read_state().position_steps > 3000, what='moving')
    mark = bench.monitor.mark()
    d.stop()
    bench.monitor.wait_seen(mark, (0x601, bytes.fromhex('2B 3B 20 01 08 00 00 00')))
    s = settle(d)
    assert s.enabled and s.position_steps < 320000


def test_homing_on_bls_writes_the_raw_method_and_forces_the_offset(bench):
    d = bench.connect('axis1')
    d.enable()
    mark = bench.monitor.mark()
    note = d.start_homing(Homing(-1, 500, 6400.0, 1600.0, 64000.0))
    assert 'BLS, negative direction' in note
    bench.monitor.wait_seen(mark, (0x601, bytes.fromhex('2F 98 60 00 FF 00 00 00')))
    assert d.read_state().homing == HomingState.RUNNING
    s = wait(lambda: (lambda s: s if s.homing != HomingState.RUNNING else None)(
        d.read_state()), 10.0, 'homing result')
    assert s.homing == HomingState.ATTAINED and s.homed and s.mode == 'HOMING'
    raw = bench.sim.nodes['axis1'].axis.raw_position_steps
    assert s.position_steps == pytest.approx(500 + (raw + 3200), abs=1)   # BLS edge reads 500
    d.move_to(3000, MOTION)                       # away from the BLS it stopped on
    assert settle(d).position_steps == 3000


def test_homing_error_shows_the_emcy_text(bench):
    d = bench.connect('axis2')
    d.enable()
    d.write_register('0x2020:1', 'u32', 800)      # Rhmaxspc
    d.start_homing(Homing(-1, 0, 16000.0, 1600.0, 160000.0))
    s = wait(lambda: (lambda s: s if s.homing == HomingState.ERROR else None)(d.read_state()),
             5.0, 'homing error')
    assert not s.fault and s.enabled
    assert any('EMCY 0xFF02' in a and 'maximum travel for home exceeded' in a
               for a in s.alarms), s.alarms


def test_fault_emcy_text_and_the_manuals_reset_order(bench):
    d = bench.connect('axis1')
    d.enable()
    bench.sim.inject_fault('axis1', 'drive_fault', 1 << 6, 0)
    s = wait(lambda: (lambda s: s if s.state == State.FAULT else None)(d.read_state()))
    assert s.fault and s.fault_code == 0x5400
    assert 'power stage' in s.fault_text and 'over-temperature' in s.fault_text
    with pytest.raises(DriveError, match='call fault_reset first'):
        d.enable()
    remaining = d.fault_reset()                   # cause still present
    assert '0x5400' in remaining and 'over-temperature' in remaining
    bench.sim.inject_fault('axis1', 'clear_fault', 0, 0)
    mark = bench.monitor.mark()
    assert d.fault_reset() == ''
    bench.monitor.catch_up()
    frames = bench.monitor.since(mark)
    clear = frames.index((0x601, bytes.fromhex('2F 03 10 00 00 00 00 00')))
    edge = next(i for i, (cob, data) in enumerate(frames) if cob in (0x201, 0x301) and
                data[:2] == b'\x80\x00')
    assert clear < edge, 'the manual clears 0x1003:00 before the reset'
    s = d.read_state()
    assert s.state == State.SWITCH_ON_DISABLED and not s.fault
    d.enable()


def test_start_up_with_the_power_stage_blocked(bench):
    bench.sim.inject_fault('axis2', 'power_stage_blocked', 0, 0)
    d = bench.connect('axis2')                    # connect succeeds
    assert d.read_state().state == State.SWITCH_ON_DISABLED
    with pytest.raises(DriveError) as err:
        d.enable()
    assert 'SWITCH ON DISABLED' in str(err.value) and 'power stage is blocked' in str(err.value)
    assert 'STO' in str(err.value)
    bench.sim.inject_fault('axis2', 'power_stage_ok', 0, 0)
    d.enable()
    assert d.read_state().enabled


def test_save_params_is_verified(bench, tmp_path):
    d = bench.connect('axis1')
    d.write_register('0x2020:1', 'u32', 424242)
    note = d.save_params()
    assert 'Reepsts 0' in note
    assert '424242' in (tmp_path / 'vector_step_node1.json').read_text()
    bench.sim.inject_fault('axis1', 'nvram_fault', 0, 0)
    with pytest.raises(DriveError, match='Reepsts 0x0008'):
        d.save_params()


@pytest.mark.parametrize('address, data_type, expected', [
    ('0x1001:0', 'u8', 0), ('0x6061:0', 'i8', 1), ('0x6041', 'u16', 0x0670),
    ('0x605A:0', 'i16', 2), ('0x1000:0', 'u32', 0x00040192), ('0x6064:0', 'i32', 0),
    ('0x202A', 'u32', 1234567890), ('0x6505:0', 'string', 'www.aec-smd.it'),
    ('0x1008:00', 'string', 'SMD50.06LIC'),
])
def test_typed_register_reads(bench, address, data_type, expected):
    d = bench.connect('axis1')
    assert d.read_register(address, data_type) == expected


def test_typed_register_writes_and_errors(bench):
    d = bench.connect('axis1')
    d.write_register('0x6098:0', 'i8', -3)
    assert d.read_register('0x6098:0', 'i8') == -3 and d.read_register('0x2052', 'i16') == -3
    d.write_register('0x605A:0', 'i16', 6)
    assert d.read_register('0x605A:0', 'i16') == 6
    d.write_register('0x2020:1', 'u32', 0xDEADBE)
    assert d.read_register('0x2020:1', 'u32') == 0xDEADBE
    d.write_register('0x6504:0', 'string', 'stepper_drivers test rig')    # segmented download
    assert d.read_register('0x6504:0', 'string') == 'stepper_drivers test rig'
    with pytest.raises(DriveError, match='answered 4 byte'):
        d.read_register('0x6064:0', 'i16')
    with pytest.raises(DriveError, match='0x06010002'):
        d.write_register('0x1000:0', 'u32', 1)
    with pytest.raises(DriveError, match='0x06010001'):
        d.read_register('0x6060:0', 'i8')
    with pytest.raises(DriveError, match='0x06090030'):
        d.write_register('0x6083:0', 'u32', 0)                        # below min 1
    with pytest.raises(DriveError, match='out of range'):
        d.write_register('0x6098:0', 'i8', 200)
    with pytest.raises(DriveError, match='index:subindex'):
        d.read_register('Rposact', 'i32')


def test_parse_address():
    assert vs.parse_address('0x6041:0') == (0x6041, 0)
    assert vs.parse_address('1A00:02') == (0x1A00, 2)
    assert vs.parse_address('0x20C2') == (0x20C2, 1)        # AEC register: sub 1
    assert vs.parse_address('6064') == (0x6064, 0)


def test_a_reboot_and_a_heartbeat_loss_are_link_errors(bench):
    d = bench.connect('axis1')
    d.enable()
    bench.sim.inject_fault('axis1', 'reboot', 0, 0)
    with pytest.raises(LinkError, match='boot-up seen'):
        wait(lambda: d.read_state() and False, 2.0)
    bench.bus.close()                             # what the node layer does: close, open
    bench.bus.open()
    d.connect()
    assert d.read_state().state == State.SWITCH_ON_DISABLED
    bench.sim.inject_fault('axis1', 'cut', 0, 0)
    t0 = time.monotonic()
    with pytest.raises(LinkError, match='heartbeat lost'):
        wait(lambda: d.read_state() and False, 2.0)
    assert 0.4 < time.monotonic() - t0 < 1.0


def test_a_node_put_in_nmt_stopped_is_recovered(bench):
    d = bench.connect('axis1')
    bench.monitor.bus.send(can.Message(arbitration_id=0x000, data=b'\x02\x01',
                                       is_extended_id=False))        # NMT stop node 1
    with pytest.raises(LinkError, match='NMT state 0x04'):
        wait(lambda: d.read_state() and False, 2.0)
    bench.bus.close()
    bench.bus.open()
    d.connect()                                   # no SDO in STOPPED: a reset reaches it
    assert bench.sim.nodes['axis1'].nmt_state == 0x05
    assert d.read_state().state == State.SWITCH_ON_DISABLED


def test_two_nodes_on_one_bus(bench):
    drives = bench.connect()
    for d in drives.values():
        d.enable()
    drives['axis2'].move_to(-8000, MOTION)
    assert settle(drives['axis2']).position_steps == -8000
    assert drives['axis1'].read_state().position_steps == 0
    assert bench.sim.true_position_steps('axis2') == pytest.approx(-8000)


def test_parameters_are_checked(bench):
    with pytest.raises(ValueError, match=r'drives\.bad\.homing\.method: 19'):
        vs.make_drive(bench.bus, 'bad', params(node_id=9, **{'homing.method': 19}))
    with pytest.raises(ValueError, match=r"node_id: 1 is already the node-ID of drive 'axis1'"):
        vs.make_drive(bench.bus, 'other', params(node_id=1))
    with pytest.raises(ValueError, match='can.bitrate: 100000'):
        vs.make_drive(bench.bus, 'rate', params(node_id=10, **{'can.bitrate': 100000}))
    with pytest.raises(ValueError, match='heartbeat_timeout_s'):
        vs.make_drive(bench.bus, 'hb', params(node_id=11, heartbeat_timeout_s=0.05))


def test_missing_node_fails_fast_with_a_link_error(bench):
    d = vs.make_drive(bench.bus, 'ghost', params(node_id=33, **{'can.port': bench.broker.port}))
    t0 = time.monotonic()
    with pytest.raises(LinkError, match='no answer'):
        d.connect()
    assert time.monotonic() - t0 < 3.0


def test_any_python_can_interface_works(tmp_path):
    """Nothing is tied to socketcand: the same driver and simulator on python-can's in-process
    'virtual' interface (what a user with hardware changes: can.interface, can.channel)."""
    sim = VectorStepSim([NodeConfig('axis1', 4)], interface='virtual', channel='vs_test',
                        reboot_delay_s=0.02)
    sim.start()
    bus = vs.make_bus(params(**{'can.interface': 'virtual', 'can.channel': 'vs_test'}))
    try:
        bus.open()
        assert bus.description == 'CAN virtual vs_test 125 kbit/s'
        d = vs.make_drive(bus, 'axis1', params(node_id=4, **{'can.interface': 'virtual'}))
        wait(lambda: sim.nodes['axis1'].nmt_state == 0x7F)
        d.connect()
        d.enable()
        d.move_to(-1600, MOTION)
        assert settle(d).position_steps == -1600
    finally:
        bus.close()
        sim.stop()


def test_a_snapshot_waits_for_the_rest_of_a_statusword_burst(bench, monkeypatch):
    """The monitor plays node 1 (the simulator's link is cut). 'Homing attained' comes first in
    TxPDO1; Rstsflg's homed bit, the position and the velocity follow in the other TxPDOs of the
    same burst. read_state() must not mix the new statusword with the old values."""
    d = bench.connect('axis1')
    bench.sim.nodes['axis1'].link_cut = True
    moving, attained, other = 0x0337, 0x1637, 0x0637

    def burst(sw, position, velocity, rstsflg, cobs=(0x181, 0x281, 0x381, 0x481)):
        frames = {0x181: struct.pack('<Hb', sw, vm.MODE_HOMING),
                  0x281: struct.pack('<Hi', sw, position),
                  0x381: struct.pack('<Hi', sw, velocity),
                  0x481: struct.pack('<HHB', sw, rstsflg, 0)}
        bench.monitor.send(0x701, b'\x05')              # heartbeat: OPERATIONAL
        for cob in cobs:
            bench.monitor.send(cob, frames[cob])

    def newest_statusword(sw):
        wait(lambda: d._values().get(vm.STATUSWORD) == sw, what=f'statusword 0x{sw:04X}')

    burst(moving, 1000, -100, 0)
    wait(lambda: d.read_state().position_steps == 1000, what="the monitor's TxPDOs")
    monkeypatch.setattr(vs, 'BURST_WAIT_S', 5.0)        # no race with a loaded machine
    burst(attained, 500, 0, vm.RSTSFLG_HOMED, cobs=(0x181,))
    newest_statusword(attained)
    got = {}
    reader = threading.Thread(target=lambda: got.update(state=d.read_state()))
    reader.start()
    reader.join(0.3)
    assert reader.is_alive(), 'read_state() returned in the middle of a burst'
    burst(attained, 500, 0, vm.RSTSFLG_HOMED, cobs=(0x281, 0x381, 0x481))
    reader.join(5.0)
    s = got['state']
    assert s.homed and s.position_steps == 500 and s.velocity_steps_s == 0.0
    # a frame of a burst lost: one bounded wait, then no wait per poll until the next change
    monkeypatch.setattr(vs, 'BURST_WAIT_S', 0.3)
    burst(other, 500, 0, vm.RSTSFLG_HOMED, cobs=(0x181, 0x281, 0x381))
    newest_statusword(other)
    start = time.monotonic()
    assert d.read_state().status_word == other
    assert time.monotonic() - start >= 0.3
    bench.monitor.send(0x701, b'\x05')
    start = time.monotonic()
    assert d.read_state().status_word == other
    assert time.monotonic() - start < 0.3
