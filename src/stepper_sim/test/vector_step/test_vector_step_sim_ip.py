"""vector_step_sim's interpolated position mode (7), driven by an independent canopen master.

No project driver code: canopen for SDO and NMT, raw RxPDO frames on the loopback socketcand
broker, SYNC sent by the test at the interpolation period, a third client recording the wire.
What the manual says [INTERPOLATION DATA RECORD] .. [INTERPOLATION DATA CONFIGURATION] and its
EMCY table: a two-position buffer 0x60C1 (mappable into an RxPDO), movement only once IP is
enabled and both elements are written, one linear segment per SYNC over 0x60C2, FF03 on an empty
buffer, FF04/FF05 on a SYNC too early/late ("VSD[0]==1, VSD[1]==0 fissi").
"""

import logging
import struct
import time

import can
import canopen
import pytest
from stepper_drivers.vendors.vector_step import regmap as vm
from stepper_sim.core.socketcand_broker import SocketcandBroker
from stepper_sim.harness import wait_for as wait
from stepper_sim.vector_step.device import IP_SYNC_PHASE_GAIN, IP_SYNC_TOLERANCE_PERIODS
from stepper_sim.vector_step.sim import NodeConfig, VectorStepSim

logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)
NODE_ID = 7
PERIOD_MS = 10                        # 0x60C2:01 (the longest the manual allows)
PERIOD_S = PERIOD_MS / 1000.0
STEP = 40                             # steps per period in the ramps: 4000 steps/s
CW_IP = 0x1F                          # enable operation + bit 4 "enable ip mode" (CiA 402)
CW_HOLD = 0x0F


class Recorder:
    """A third client on the bus: every frame, in the broker's order."""

    def __init__(self, port):
        self.bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel='can0',
                           tcp_tune=True)
        self.frames: list[tuple[int, bytes]] = []
        self.notifier = can.Notifier(self.bus, [self._on], 0.1)

    def _on(self, msg):
        self.frames.append((msg.arbitration_id, bytes(msg.data)))

    def since(self, mark, cob=None):
        return [(c, d) for c, d in self.frames[mark:] if cob is None or c == cob]

    def close(self):
        self.notifier.stop()
        self.bus.shutdown()


class Master:
    def __init__(self, node, network, sim):
        self.node, self.network, self.sim = node, network, sim
        self.drive = sim.nodes['axis']
        self.due = 0.0

    def cw(self, controlword, mode=7):
        """RxPDO1 (default mapping: controlword, modes of operation)."""
        self.network.send_message(0x200 + NODE_ID, struct.pack('<Hb', controlword, mode))

    def point(self, position, controlword=CW_IP):
        """RxPDO4 as the test maps it: controlword, 0x60C1:01."""
        self.network.send_message(0x500 + NODE_ID, struct.pack('<Hi', controlword, position))

    def sync(self):
        self.network.send_message(0x080, b'')

    def start_clock(self):
        self.due = time.monotonic()

    def next_period(self):
        """Sleep to the next SYNC time (absolute schedule: no drift)."""
        self.due += PERIOD_S
        delay = self.due - time.monotonic()
        if delay > 0:
            time.sleep(delay)

    def statusword(self):
        return self.node.sdo[vm.STATUSWORD].raw

    def position(self):
        return self.sim.true_position_steps('axis')


@pytest.fixture
def master():
    broker = SocketcandBroker(port=0, ready_delay_s=0.01)
    broker.start()
    sim = VectorStepSim([NodeConfig('axis', NODE_ID)], port=broker.port, reboot_delay_s=0.02)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.1
    network.connect(interface='socketcand', host='127.0.0.1', port=broker.port, channel='can0',
                    tcp_tune=True)
    node = canopen.BaseNode402(NODE_ID, str(vm.eds_path()))
    network.add_node(node)
    recorder = Recorder(broker.port)
    sim.start()
    wait(lambda: sim.nodes['axis'].nmt_state == 0x7F, 5.0, 'boot-up')
    # RxPDO4 = controlword + 0x60C1:01, the manual's mapping procedure [COME MAPPARE UN PDO]
    for index, sub, value in ((0x1403, 1, 0x80000500 + NODE_ID), (0x1403, 2, 0xFE),
                              (0x1603, 0, 0), (0x1603, 1, 0x60400010), (0x1603, 2, 0x60C10120),
                              (0x1603, 0, 2), (0x1403, 1, 0x500 + NODE_ID),
                              (vm.INTERPOLATION_SUBMODE_SELECT, 0, 0),
                              (vm.INTERPOLATION_TIME_PERIOD, 1, PERIOD_MS)):
        entry = node.sdo[index][sub] if index != vm.INTERPOLATION_SUBMODE_SELECT \
            else node.sdo[index]
        entry.raw = value
    node.nmt.state = 'OPERATIONAL'
    m = Master(node, network, sim)
    wait(lambda: m.drive.nmt_state == 0x05, what='OPERATIONAL')
    for controlword in (0x06, 0x07, CW_HOLD):          # mode 7, OPERATION ENABLED
        m.cw(controlword)
    wait(lambda: m.statusword() & 0x6F == 0x27 and node.sdo[vm.MODES_OF_OPERATION_DISPLAY].raw
         == 7, what='OPERATION ENABLED in mode 7')
    m.recorder = recorder
    yield m
    recorder.close()
    network.disconnect()
    sim.stop()
    broker.stop()


def start(m, position=0):
    """Both buffer elements by SDO, then IP enabled (the manual's start condition)."""
    m.node.sdo[vm.INTERPOLATION_DATA_RECORD][1].raw = position
    m.node.sdo[vm.INTERPOLATION_DATA_RECORD][2].raw = position
    m.cw(CW_IP)
    wait(lambda: m.statusword() & vm.SW_BIT_IP_ACTIVE, what='SW bit 12 ip mode active')
    assert m.drive.ip_started


def stream(m, points):
    """One SYNC per period, the next point right behind it (what the bus owner does)."""
    for p in points:
        m.next_period()
        m.sync()
        m.point(p)


def emcy(m, mark):
    return m.recorder.since(mark, 0x080 + NODE_ID)


def test_the_buffer_is_mappable_fifo_and_refuses_a_third_point(master):
    m = master
    node = m.node
    assert node.sdo[0x1603][2].raw == 0x60C10120         # 0x60C1:01 mapped (WMAP)
    with pytest.raises(canopen.SdoAbortedError) as err:  # sub-mode select is not mappable
        node.sdo[0x1603][2].raw = 0x60C00010
    assert err.value.code == vm.ABORT_NOT_MAPPABLE
    node.sdo[vm.INTERPOLATION_DATA_RECORD][1].raw = 5
    m.point(6, CW_HOLD)                                   # RxPDO: the second element
    wait(lambda: node.sdo[vm.INTERPOLATION_DATA_CONFIGURATION][2].raw == 2, what='2 queued')
    assert node.sdo[vm.INTERPOLATION_DATA_CONFIGURATION][1].raw == vm.IP_BUFFER_SIZE
    with pytest.raises(canopen.SdoAbortedError) as err:
        node.sdo[vm.INTERPOLATION_DATA_RECORD][2].raw = 7
    assert err.value.code == vm.ABORT_DEVICE_STATE       # full: the queued points stay
    assert list(m.drive.ip_buffer) == [5, 6]
    node.sdo[vm.INTERPOLATION_DATA_CONFIGURATION][6].raw = vm.IP_BUFFER_CLEAR
    assert node.sdo[vm.INTERPOLATION_DATA_CONFIGURATION][2].raw == 0
    with pytest.raises(canopen.SdoAbortedError):          # access disabled
        node.sdo[vm.INTERPOLATION_DATA_RECORD][1].raw = 5
    node.sdo[vm.INTERPOLATION_DATA_CONFIGURATION][6].raw = vm.IP_BUFFER_ENABLE
    node.sdo[vm.INTERPOLATION_DATA_RECORD][1].raw = 5
    assert node.sdo[vm.INTERPOLATION_DATA_CONFIGURATION][2].raw == 1


def test_motion_starts_only_with_ip_enabled_and_both_elements_written(master):
    m = master
    m.node.sdo[vm.INTERPOLATION_DATA_RECORD][1].raw = 800
    m.cw(CW_IP)
    wait(lambda: m.statusword() & vm.SW_BIT_IP_ACTIVE, what='ip mode active')
    m.start_clock()
    for _ in range(5):                   # one element only: SYNCs move nothing, no alarm
        m.next_period()
        m.sync()
    assert m.statusword() & 0x6F == 0x27       # (an SDO: the SYNCs before are handled)
    assert m.position() == 0.0 and not m.drive.axis.moving and not m.drive.ip_started
    m.node.sdo[vm.INTERPOLATION_DATA_RECORD][2].raw = 800                 # both written
    m.statusword()
    assert m.drive.ip_started and m.position() == 0.0    # ... it moves at the next SYNC
    stream(m, [800, 800])
    wait(lambda: m.position() == 800.0, 1.0, 'at the second element')


def test_linear_interpolation_follows_the_points_one_period_apart(master):
    m = master
    start(m)
    mark = len(m.recorder.frames)
    ramp = [STEP * k for k in range(1, 21)]
    m.start_clock()
    samples = []
    for k, p in enumerate(ramp):
        m.next_period()
        m.sync()
        m.point(p)
        with m.sim.lock:                 # the drive's demand and position at one instant
            m.drive.axis.update()
            samples.append((k, m.drive.axis.motion.target_position_steps,
                            m.drive.axis.position_steps))
    stream(m, [ramp[-1]] * 4)                                    # hold the last point
    wait(lambda: not m.drive.axis.moving, 1.0, 'at rest')
    assert m.position() == ramp[-1]                              # exactly on the last point
    sw = m.statusword()
    assert sw & 0x6F == 0x27 and sw & vm.SW_BIT_IP_ACTIVE and sw & (1 << 10)   # target reached
    assert not emcy(m, mark)
    # Bytes on the wire: RxPDO4 = controlword 0x001F, 0x60C1:01 (INTEGER32 LE)
    sent = m.recorder.since(mark, 0x500 + NODE_ID)
    assert sent[:2] == [(0x507, bytes.fromhex('1F00 28000000')),
                        (0x507, bytes.fromhex('1F00 50000000'))]
    # Two elements queued at the start (both the start position): ramp[k], sent behind the
    # (k + 1)-th SYNC, is taken two SYNCs later (the drive's demand) and reached one period
    # after that. The demand is a point already sent, in order, never ramp[k] itself; the axis
    # is at most one period's travel behind it, plus what a SYNC that came early left of the
    # segment before.
    demands = [demand for _, demand, _ in samples]
    assert demands == sorted(demands) and demands[-1] >= ramp[-4]
    for k, demand, position in samples:
        assert demand in [0] + ramp[:k - 1], (k, demand)
        assert -1e-6 <= demand - position <= 2 * STEP, (k, demand, position)


def test_underflow_is_emcy_ff03_and_a_fault(master):
    m = master
    start(m)
    m.start_clock()
    stream(m, [STEP * k for k in range(1, 11)])
    mark = len(m.recorder.frames)
    for _ in range(2):                   # the two queued points are still run
        m.next_period()
        m.sync()
    assert m.statusword() & 0x6F == 0x27 and not emcy(m, mark)
    m.next_period()
    m.sync()                             # nothing left: "Mancanza dati da elaborare"
    frames = wait(lambda: emcy(m, mark), 1.0, 'EMCY')
    # code 0xFF03 LE, error register 0x01 (generic), VSD[0] = 1, VSD[1] = 0 [PRE-DEFINED ...]
    assert frames == [(0x087, bytes.fromhex('03FF01 0100 000000'))]
    wait(lambda: m.statusword() & 0x4F == 0x08, 2.0, 'FAULT')   # quick-stop ramp, then FAULT
    assert m.node.sdo[vm.ERROR_CODE].raw == 0xFF03
    assert m.node.sdo[vm.PRE_DEFINED_ERROR_FIELD][1].raw == 0x0001FF03
    assert not m.drive.axis.moving and not m.statusword() & vm.SW_BIT_IP_ACTIVE
    assert m.node.sdo[vm.INTERPOLATION_DATA_CONFIGURATION][2].raw == 0     # buffer emptied
    # the manual's fault reset: 0x1003:00 = 0, then bit 7
    m.node.sdo[vm.PRE_DEFINED_ERROR_FIELD][0].raw = 0
    m.cw(0x00)
    m.cw(0x80)
    wait(lambda: m.statusword() & 0x4F == 0x40, 1.0, 'SWITCH ON DISABLED')


def test_a_sync_too_late_is_emcy_ff05(master):
    m = master
    start(m)
    m.start_clock()
    stream(m, [STEP, 2 * STEP])
    mark = len(m.recorder.frames)
    late_s = (IP_SYNC_TOLERANCE_PERIODS + 1.5) * PERIOD_S      # half a period beyond it
    time.sleep(PERIOD_S + late_s)
    m.sync()
    frames = wait(lambda: emcy(m, mark), 1.0, 'EMCY')
    assert frames == [(0x087, struct.pack('<HB', vm.EMCY_IP_SYNC_LATE, 1) +
                       b'\x01\x00\x00\x00\x00')]            # VSD[0] = 1, VSD[1] = 0
    wait(lambda: m.statusword() & 0x4F == 0x08, 2.0, 'FAULT')
    assert m.node.sdo[vm.ERROR_CODE].raw == 0xFF05


def test_syncs_at_half_the_period_drift_off_the_grid_ff04(master):
    """A master with the wrong period (5 ms for 10 ms): each SYNC comes 5 ms early on the grid
    the drive follows, which moves by IP_SYNC_PHASE_GAIN of that; the error grows to the
    tolerance within a few SYNCs. One SYNC late and the next on time would not."""
    m = master
    start(m)
    mark = len(m.recorder.frames)
    error_s, expected_count = 0.0, 1
    while error_s > -IP_SYNC_TOLERANCE_PERIODS * PERIOD_S:      # the grid's own arithmetic
        error_s = (1 - IP_SYNC_PHASE_GAIN) * error_s - PERIOD_S / 2
        expected_count += 1
    count = 0
    m.due = time.monotonic()
    while not emcy(m, mark) and count < 3 * expected_count:
        m.due += PERIOD_S / 2
        time.sleep(max(m.due - time.monotonic(), 0.0))
        m.sync()
        m.point(0)                       # no underflow: a point per SYNC
        count += 1
    frames = wait(lambda: emcy(m, mark), 1.0, 'EMCY')
    assert frames == [(0x087, struct.pack('<HB', vm.EMCY_IP_SYNC_EARLY, 1) +
                       b'\x01\x00\x00\x00\x00')]
    assert expected_count - 2 <= count <= expected_count + 2, (count, expected_count)
    wait(lambda: m.statusword() & 0x4F == 0x08, 2.0, 'FAULT')
    assert vm.emcy_text(vm.EMCY_IP_SYNC_EARLY) == 'interpolation alarm: SYNC too early'


def test_bit_4_low_or_a_mode_change_ends_the_interpolated_motion(master):
    m = master
    start(m)
    m.start_clock()
    stream(m, [STEP * k for k in range(1, 21)])
    m.cw(CW_HOLD)                        # bit 4 = 0: IP off, stop on the stop ramp (0x605D)
    m.statusword()                       # barrier: handled (between two points the axis rests)
    wait(lambda: not m.drive.axis.moving, 2.0, 'stopped')
    stopped_at = m.position()
    assert STEP * 16 <= stopped_at < STEP * 20           # stopped on the way, short of the end
    sw = m.statusword()
    assert sw & 0x6F == 0x27 and not sw & vm.SW_BIT_IP_ACTIVE
    assert m.node.sdo[vm.INTERPOLATION_DATA_CONFIGURATION][2].raw == 0
    mark = len(m.recorder.frames)
    for p in (100000, 100000):           # points (bit 4 low) and SYNCs: nothing moves
        m.next_period()
        m.sync()
        m.point(p, CW_HOLD)
    # Enabled again with the buffer full, but filled through sub 1 only: "entrambi gli elementi"
    # read as sub-indexes 1 and 2, so nothing starts (a third point is refused: buffer full)
    m.cw(CW_IP)
    stream(m, [100000])
    m.statusword()                        # barrier: the sim has handled every frame before
    assert m.position() == stopped_at and not emcy(m, mark)
    # a new start, then a mode change while moving: Abort on the emergency ramp [MODES OF ...]
    m.cw(CW_HOLD)
    start(m, int(stopped_at))
    m.start_clock()
    stream(m, [int(stopped_at) + STEP * k for k in range(1, 21)])
    m.cw(CW_HOLD, mode=1)
    m.statusword()                        # barrier: the mode change is handled
    wait(lambda: not m.drive.axis.moving, 2.0, 'stopped')
    assert m.node.sdo[vm.MODES_OF_OPERATION_DISPLAY].raw == 1 and m.statusword() & 0x6F == 0x27
    assert not m.drive.ip_started and not emcy(m, mark)
