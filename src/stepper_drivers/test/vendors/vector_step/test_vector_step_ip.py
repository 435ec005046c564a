"""VectorStepDrive in interpolated position mode (7) against vector_step_sim, without ROS.

The driver's own bus produces the SYNC (can.sync_period_s = the interpolation period); the test
plays the bus owner: one `interpolation_point` right behind every SYNC it sees on the wire (a
third client records the frames). Real broker, python-can and canopen on both sides.
"""

import logging
import struct
import threading
import time

import can
import pytest
from stepper_drivers.contract.drive import DriveError, State, complete
from stepper_drivers.vendors import vector_step as vs
from stepper_drivers.vendors.vector_step import regmap as vm
from stepper_sim.core.socketcand_broker import SocketcandBroker
from stepper_sim.harness import wait_for as wait
from stepper_sim.vector_step.sim import NodeConfig, VectorStepSim

logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)

PERIOD_S = 0.01
STEP = 40                              # steps per period: 4000 steps/s


class Monitor:
    """Records every frame on the bus and counts the SYNCs."""

    def __init__(self, port):
        self.bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel='can0',
                           tcp_tune=True)
        self.frames: list[tuple[int, bytes]] = []
        self.syncs = 0
        self.cond = threading.Condition()
        self.notifier = can.Notifier(self.bus, [self._on], 0.1)

    def _on(self, msg):
        with self.cond:
            self.frames.append((msg.arbitration_id, bytes(msg.data)))
            if msg.arbitration_id == 0x080:
                self.syncs += 1
                self.cond.notify_all()

    def wait_syncs(self, count):
        with self.cond:
            assert self.cond.wait_for(lambda: self.syncs >= count, 1.0), 'no SYNC'

    def mark(self):
        return len(self.frames)

    def since(self, mark, cob=None):
        return [(c, d) for c, d in self.frames[mark:] if cob is None or c == cob]

    def barrier(self, bus):
        """Every frame the driver's bus sent before is recorded once this one is."""
        start = len(self.frames)
        bus.send(0x7E5, b'barrier')
        wait(lambda: (0x7E5, b'barrier') in self.since(start), what='barrier frame')

    def close(self):
        self.notifier.stop()
        self.bus.shutdown()


class Bench:
    def __init__(self, **over):
        self.broker = SocketcandBroker(port=0, ready_delay_s=0.01)
        self.broker.start()
        self.sim = VectorStepSim([NodeConfig('axis1', 1)], port=self.broker.port,
                                 reboot_delay_s=0.02)
        self.node = self.sim.nodes['axis1']
        self.monitor = Monitor(self.broker.port)
        self.sim.start()
        self.params = {spec.name: spec.default for spec in vs.PARAMS}
        self.params.update({'timeout_s': 0.5, 'steps_per_rev': 3200.0, 'homing.method': 35,
                            'heartbeat_timeout_s': 0.5, 'can.port': self.broker.port,
                            'can.sync_period_s': PERIOD_S, 'node_id': 1, **over})
        self.bus = vs.make_bus(self.params)
        self.bus.open()
        self.drive = vs.make_drive(self.bus, 'axis1', self.params)
        wait(lambda: self.node.nmt_state == 0x7F, what='boot-up')
        complete(self.drive.connect())
        self.due_sync = 0

    def start(self):
        """Enable and start_interpolation; the SYNCs are counted from the start on the wire (the
        second 0x60C1 write): the drive takes an element at each one from then on."""
        complete(self.drive.enable())
        position = complete(self.drive.start_interpolation(PERIOD_S))
        self.monitor.barrier(self.bus)
        frames = self.monitor.since(0)
        trigger = max(i for i, (cob, data) in enumerate(frames)
                      if cob == 0x601 and data[:4] == bytes.fromhex('23 C1 60 02'))
        self.due_sync = 1 + sum(1 for cob, _ in frames[:trigger] if cob == 0x080)
        return position

    def stream(self, points, check=None):
        """The bus owner: point k right behind the (k + 1)-th SYNC since the start (at once when
        that SYNC has gone out already); check(k, point) after each."""
        for k, point in enumerate(points):
            self.monitor.wait_syncs(self.due_sync)
            self.due_sync += 1
            self.drive.interpolation_point(point)
            if check is not None:
                check(k, point)

    def close(self):
        self.bus.close()
        self.monitor.close()
        self.sim.stop()
        self.broker.stop()


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def snap(drive):
    return complete(drive.read_state())


def test_start_then_a_ramp_followed_within_one_periods_travel(bench):
    d, node = bench.drive, bench.sim.nodes['axis1']
    mark = bench.monitor.mark()
    assert bench.start() == 0
    sdo = [data for _, data in bench.monitor.since(mark, 0x601)]
    for frame in ('2B C0 60 00 00 00 00 00',           # 0x60C0 = 0 linear
                  '2F C2 60 02 FD 00 00 00',           # 0x60C2:02 = 0xFD (ms)
                  '2F C2 60 01 0A 00 00 00',           # 0x60C2:01 = 10
                  '23 C1 60 01 00 00 00 00',           # both buffer elements = position 0
                  '23 C1 60 02 00 00 00 00'):
        assert bytes.fromhex(frame) in sdo, frame
    ramp = [STEP * k for k in range(1, 26)]
    samples = []

    def sample(k, _point):
        with bench.sim.lock:
            node.axis.update()
            samples.append((k, node.axis.motion.target_position_steps, node.axis.position_steps))

    before, mark = bench.bus.transactions, bench.monitor.mark()
    bench.stream(ramp, sample)
    assert bench.bus.transactions - before == len(ramp)          # one frame per point
    s = snap(d)
    assert s.mode == 'INTERPOLATED POSITION (IP active)' and s.enabled
    assert s.status_word & vm.SW_BIT_IP_ACTIVE
    bench.stream([ramp[-1]] * 4)                 # held, reached; then a stop ends the stream
    d.stop()                                     # (else the next SYNCs empty the buffer: FF03)
    wait(lambda: not node.axis.moving, 1.0, 'at rest')
    bench.monitor.barrier(bench.bus)
    # The drive's demand (the element taken at the last SYNC) is one of the points already
    # sent, in their order, and the axis is never more than one period's travel behind it, plus
    # what a SYNC that came early (at worst right behind the one before) left of the last one.
    demands = [demand for _, demand, _ in samples]
    assert demands == sorted(demands) and demands[-1] >= ramp[-4]
    for k, demand, position in samples:
        assert demand in [0] + ramp[:k], (k, demand)
        assert -1e-6 <= demand - position <= 2 * STEP, (k, demand, position)
    points = bench.monitor.since(mark, 0x501)
    assert points[:2] == [(0x501, struct.pack('<Hi', 0x1F, STEP)),
                          (0x501, struct.pack('<Hi', 0x1F, 2 * STEP))]
    assert not bench.monitor.since(mark, 0x601), 'no SDO while streaming'
    s = wait(lambda: (lambda s: s if s.position_steps == ramp[-1] else None)(snap(d)), 1.0,
             'position reported')
    assert s.target_reached and not s.fault and s.enabled and s.mode == 'INTERPOLATED POSITION'
    # on the last point, within a step (a SYNC that came early leaves a slow last segment that
    # the stop cuts short by a fraction of a step)
    assert abs(bench.sim.true_position_steps('axis1') - ramp[-1]) < 1.0


def test_a_point_outside_integer32_is_refused_naming_0x60c1(bench):
    d = bench.drive
    with pytest.raises(DriveError, match='no interpolation running'):
        d.interpolation_point(0)
    bench.start()
    before = bench.bus.transactions
    for value in (2 ** 31, -2 ** 31 - 1):
        with pytest.raises(DriveError, match=r'0x60C1:01 .*-2147483648\.\.2147483647'):
            d.interpolation_point(value)
    assert bench.bus.transactions == before
    d.interpolation_point(STEP)                               # in range: one frame
    assert bench.bus.transactions == before + 1


def test_start_is_refused_when_disabled_or_with_the_wrong_sync_period():
    bench = Bench()
    try:
        d = bench.drive
        with pytest.raises(DriveError, match='interpolation: the drive is not enabled'):
            complete(d.start_interpolation(PERIOD_S))
        complete(d.enable())
        before = bench.bus.transactions
        with pytest.raises(DriveError, match=r'interpolation period 0.004 s: can.sync_period_s '
                           r'\(0.01 s\) must equal it.*0.001..0.01 s.*0x60C2'):
            complete(d.start_interpolation(0.004))
        assert bench.bus.transactions == before              # nothing sent
        assert bench.sim.nodes['axis1'].mode == vm.MODE_PROFILE_POSITION
    finally:
        bench.close()
    bench = Bench(**{'can.sync_period_s': 0.02})           # outside 0x60C2's 1..10 ms
    try:
        complete(bench.drive.enable())
        with pytest.raises(DriveError, match=r'0.02 s.*0x60C2 interpolation time period: '
                           r'ip_time_units 1..10'):
            complete(bench.drive.start_interpolation(0.02))
    finally:
        bench.close()


def test_underflow_is_a_fault_with_the_manuals_emcy_text(bench):
    d = bench.drive
    bench.start()
    bench.stream([STEP * k for k in range(1, 6)])        # then the owner stops sending
    s = wait(lambda: (lambda s: s if s.fault else None)(snap(d)), 1.0, 'fault')
    assert s.fault_code == vm.EMCY_IP_NO_DATA
    assert s.fault_text == 'interpolation mode: no data to process'
    assert not s.mode.endswith('(IP active)')
    wait(lambda: snap(d).state == State.FAULT, 2.0, 'FAULT at standstill')
    with pytest.raises(DriveError, match=r'interpolation ended by the drive \(FAULT.*EMCY '
                       r'0xFF03: interpolation mode: no data to process'):
        d.interpolation_point(STEP * 6)
    assert complete(d.fault_reset()) == ''
    complete(d.enable())
    assert complete(d.start_interpolation(PERIOD_S)) == snap(d).position_steps
    assert not snap(d).fault


def test_stop_during_interpolation_is_one_frame_and_leaves_ip(bench):
    d, node = bench.drive, bench.sim.nodes['axis1']
    bench.start()
    bench.stream([STEP * k for k in range(1, 13)])
    before, mark = bench.bus.transactions, bench.monitor.mark()
    d.stop()
    assert bench.bus.transactions - before == 1
    bench.monitor.barrier(bench.bus)
    to_drive = [f for f in bench.monitor.since(mark) if f[0] in (0x201, 0x301, 0x401, 0x601)]
    assert to_drive == [(0x301, struct.pack('<Hi', 0x000F, 0))]   # bit 4 low, no SDO
    frames = bench.monitor.since(mark)
    assert not bench.monitor.since(mark + frames.index(to_drive[0]), 0x501)   # no point after
    wait(lambda: not node.axis.moving, 1.0, 'stopped')
    stopped_at = bench.sim.true_position_steps('axis1')
    assert stopped_at < STEP * 12                          # short of the last point
    s = wait(lambda: (lambda s: s if not s.moving else None)(snap(d)), 1.0, 'standstill')
    assert s.enabled and not s.fault and s.mode == 'INTERPOLATED POSITION'
    with pytest.raises(DriveError, match='no interpolation running'):
        d.interpolation_point(STEP * 13)
    time.sleep(3 * PERIOD_S)                               # SYNCs go on: nothing moves
    assert bench.sim.true_position_steps('axis1') == stopped_at
    assert complete(d.start_interpolation(PERIOD_S)) == round(stopped_at)   # again from there
