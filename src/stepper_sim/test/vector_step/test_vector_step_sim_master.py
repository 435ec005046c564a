"""An independent master written with the canopen library alone drives vector_step_sim.

No project driver code: canopen.BaseNode402 + the EDS, through NMT (reset, boot-up, start),
SDO (expedited, segmented), PDO configuration by SDO, the CiA 402 state machine and a profile
position move; then the library's traps that the project driver works around (digest
section 10), shown against the simulator.
"""

import logging
import time

import canopen
import pytest
from stepper_drivers.vendors.vector_step import regmap as vm
from stepper_sim.core.socketcand_broker import SocketcandBroker
from stepper_sim.vector_step.sim import NodeConfig, VectorStepSim

logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)
NODE_ID = 7


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
    sim.start()
    node.nmt.wait_for_bootup(5.0)
    yield node, sim
    network.disconnect()
    sim.stop()
    broker.stop()


def wait(cond, timeout_s=3.0):
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, 'condition not met in time'
        time.sleep(0.005)


def heartbeat_reaches(node, state, timeout_s=1.0):
    """The state of the first heartbeat that shows `state` within timeout_s, else of the last
    one: the library's wait_for_heartbeat returns the next heartbeat, which may have left the
    node before it handled the NMT command just sent."""
    deadline = time.monotonic() + timeout_s
    seen = node.nmt.wait_for_heartbeat(timeout_s)
    while seen != state and time.monotonic() < deadline:
        seen = node.nmt.wait_for_heartbeat(max(deadline - time.monotonic(), 0.01))
    return seen


def test_nmt_sdo_pdo_state_machine_and_a_move(master):
    node, sim = master
    # NMT and SDO
    node.nmt.state = 'RESET COMMUNICATION'
    node.nmt.wait_for_bootup(2.0)
    assert node.sdo[0x1000].raw == 0x00040192
    assert node.sdo[0x1008].raw == 'SMD50.06LIC'             # segmented upload
    assert node.sdo[0x1018][1].raw == 0xBC
    node.sdo[0x1017].raw = 50
    assert heartbeat_reaches(node, 'PRE-OPERATIONAL') == 'PRE-OPERATIONAL'
    # PDO configuration read by SDO; TxPDO1 made periodic so the library's waits work
    node.setup_402_state_machine(read_pdos=True)
    assert [v.index for v in node.tpdo[2]] == [0x6041, 0x6064]
    assert [v.index for v in node.rpdo[2]] == [0x6040, 0x607A]
    node.tpdo[1].event_timer = 10
    node.tpdo[1].save()
    node.rpdo[1]['Modes of operation'].raw = 1   # else the controlword carries mode 0 (trap)
    node.nmt.state = 'OPERATIONAL'
    assert heartbeat_reaches(node, 'OPERATIONAL') == 'OPERATIONAL'
    assert node.tpdo[1].wait_for_reception(1.0)
    assert node.state == 'SWITCH ON DISABLED'
    # State machine by the library: 0x06 -> 0x07 -> 0x0F
    node.state = 'OPERATION ENABLED'
    assert node.state == 'OPERATION ENABLED'
    node.op_mode = 'PROFILED POSITION'
    assert node.op_mode == 'PROFILED POSITION'
    # Profile position move by RxPDO2 with the set-point handshake
    node.sdo['Profile velocity'].raw = 2000                   # 20 rev/s
    node.sdo['Profile acceleration'].raw = 50000
    node.sdo['Profile deceleration'].raw = 50000
    rpdo = node.rpdo[2]
    rpdo['Target position'].raw = 32000
    rpdo['Controlword'].raw = 0x1F
    rpdo.transmit()
    wait(lambda: node.statusword & 0x1000)                    # set-point acknowledged
    rpdo['Controlword'].raw = 0x0F
    rpdo.transmit()
    wait(lambda: node.statusword & 0x0400 and node.tpdo_values[0x6064] == 32000)
    assert sim.true_position_steps('axis') == pytest.approx(32000)
    node.state = 'SWITCH ON DISABLED'
    assert node.statusword & 0x4F == 0x40


def test_library_traps_the_driver_avoids(master):
    node, sim = master
    node.sdo[0x1017].raw = 50
    node.setup_402_state_machine(read_pdos=True)
    # An event-driven TxPDO received twice looks "periodic" to the library (period = interval):
    # its op_mode getter then waits for the next one and times out when nothing changes. With
    # an event timer it is periodic for real.
    node.tpdo[1].event_timer = 10
    node.tpdo[1].save()
    node.nmt.state = 'OPERATIONAL'
    # 0x6502 = 0x00010021 has no bit 6: the op_mode setter refuses interpolated mode outright
    assert node.sdo[0x6502].raw == vm.SUPPORTED_DRIVE_MODES_VALUE
    with pytest.raises(TypeError):
        node.op_mode = 'INTERPOLATED POSITION'
    # mode -1 (JOG) has no name in the library: write 0x6060 raw, read 0x6061 raw
    node.sdo[0x6060].raw = -1
    wait(lambda: node.tpdo_values.get(0x6061) == -1)
    with pytest.raises(KeyError):
        node.op_mode                                           # noqa: B018 - the getter raises
    assert node.sdo[0x6061].raw == -1
    # 0x6060 is write-only: reading it aborts 0x06010001
    with pytest.raises(canopen.SdoAbortedError) as err:
        node.sdo[0x6060].raw       # noqa: B018 - the read is the test: it must abort
    assert err.value.code == 0x06010001
    # AEC homing methods are raw numbers: -1 is "BLS, negative direction", not the library's
    node.sdo[0x6098].raw = -1
    assert node.sdo[0x2052][1].raw == -1                       # Rhmode mirrors it
