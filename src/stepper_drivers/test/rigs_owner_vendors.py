"""One drive of each vendor on its simulator under a BusOwner, no ROS (owner/
test_identity_recheck.py, owner/test_owner_poll_gaps.py): `garble` / `clean` its answers,
`wrong=True` / `make_right` its identity."""

from rigs_owner import SETTINGS, counted
from rigs_vector_step import params as vector_step_params
from rigs_xmind_k import Rig as XmindKRig
from stepper_drivers.owner import BusOwner
from stepper_drivers.vendors import rd4
from stepper_drivers.vendors import vector_step as vs
from stepper_drivers.vendors.xplus_mt import VENDOR as XPLUS_MT
from stepper_sim.core.socketcand_broker import SocketcandBroker
from stepper_sim.harness import wait_for
from stepper_sim.rd4.sim import Rd4DriveSim, RtuLine
from stepper_sim.vector_step.sim import NodeConfig, VectorStepSim
from stepper_sim.xplus_mt.sim import XplusMtDriveConfig, XplusMtSim


class VendorRig:
    """One drive of a vendor on its simulator; `garble` / `clean` the answers, `make_wrong`
    / `make_right` its identity (a well-formed answer naming another device)."""

    name = 'axis1'
    noise = ''             # what the link error of a garbled identity answer names

    def supervise(self):
        self.events = []
        self.bus_owner = BusOwner(self.bus, {self.name: self.drive}, dict(SETTINGS,
                                 reconnect_period_s=0.1),
                                 on_event=lambda *e: self.events.append(e))
        self.calls = counted(self.drive)
        self.bus_owner.start()
        return self.bus_owner.slots[self.name]

    def close(self):
        self.bus_owner.shutdown(0.5)


class XmindK(VendorRig):
    name = 'a1'
    noise = r"01QS,RS.* b'01\?S,RS,D2\\r'"                  # the field's '03?S,RS,D2'
    wrong = r'QS,RS answered B2 = 1600 step/rev'

    def __init__(self, tmp_path, wrong=False):
        self.rig = XmindKRig(tmp_path, sims={'a1': {'address': 1}}, connect=False)
        self.bus, self.drive = self.rig.bus, self.rig.drives['a1']
        if wrong:
            self._rs('B2')

    def _rs(self, value):
        with self.rig.line.lock:
            self.rig.sim().presets['RS'] = value

    def garble(self):
        self.rig.line.set_link_fault('corrupt_reply')        # '?' for the 3rd character

    def clean(self):
        self.rig.line.set_link_fault('link_ok')

    def make_right(self):
        self._rs('D2')

    def close(self):
        super().close()
        self.rig.close()


class Rd4(VendorRig):
    noise = r'FC04 read 4 at 0x0C: CRC error in reply'
    wrong = r'HW Version \[0x0F\] reads HW 1, RD5'

    def __init__(self, tmp_path, wrong=False):
        self.unit = Rd4DriveSim('axis1', 1, hw_version=0x2001 if wrong else 0x0001)
        self.line = RtuLine([self.unit], tmp_path / 'rd4.pty', baud_switch=0x03)
        self.line.start()
        self.bus = rd4.make_bus({'port': str(tmp_path / 'rd4.pty'), 'baudrate': 19200,
                                 'parity': 'N', 'timeout_s': 0.1})
        self.drive = rd4.make_drive(self.bus, 'axis1', {'node_id': 1, 'steps_per_rev': 1024.0})

    def garble(self):
        self.line.set_link_fault('corrupt_reply')            # one byte: the CRC's

    def clean(self):
        self.line.set_link_fault('link_ok')

    def make_right(self):
        with self.line.lock:
            self.unit.hw_version = 0x0001

    def close(self):
        super().close()
        self.line.stop()


class XplusMt(VendorRig):
    noise = r'FC03 read 1 at 1162: not a Modbus TCP header \(protocol id 16128'
    wrong = r'STEP_REVOLUTION \(1081\) reads 200'

    def __init__(self, tmp_path, wrong=False):
        self.sim = XplusMtSim(port=0, drives=[XplusMtDriveConfig(
            'axis1', unit_id=1, registers={1081: 200} if wrong else {})])
        self.sim.start()
        self.bus = XPLUS_MT.make_bus({'host': '127.0.0.1', 'port': self.sim.port,
                                      'timeout_s': 0.3})
        self.drive = XPLUS_MT.make_drive(self.bus, 'axis1', {'unit_id': 1})

    def garble(self):
        self.sim.link.set('corrupt_reply')                    # '?' for the 3rd byte

    def clean(self):
        self.sim.link.set('ok')

    def make_right(self):
        device = self.sim.drives['axis1']
        with device._lock:
            device._regs[1081] = 12800

    def close(self):
        super().close()
        self.sim.stop()


class VectorStep(VendorRig):
    noise = r'gave no valid SDO answer to read 0x1000:00 .*received \[8\] 43 00 3f 00'
    wrong = r'0x1018:02 product code reads 0x00001234'

    def __init__(self, tmp_path, wrong=False):
        self.broker = SocketcandBroker(port=0, ready_delay_s=0.01)
        self.broker.start()
        self.sim = VectorStepSim([NodeConfig('axis1', 1, product_code=0x1234 if wrong
                                             else 0x138E)],
                                 port=self.broker.port, reboot_delay_s=0.02)
        self.sim.start()
        p = vector_step_params(**{'can.port': self.broker.port, 'node_id': 1,
                                  'boot_timeout_s': 0.3})
        self.bus = vs.make_bus(p)
        self.drive = vs.make_drive(self.bus, 'axis1', p)
        wait_for(lambda: self.sim.nodes['axis1'].nmt_state == 0x7F, 5.0, 'booted')

    def garble(self):
        self.sim.inject_fault('axis1', 'corrupt_reply', 0, 0.0)     # SDO answers
        self.sim.inject_fault('axis1', 'reboot', 0, 0.0)   # a boot-up: the driver reconnects

    def clean(self):
        self.sim.inject_fault('axis1', 'link_ok', 0, 0.0)

    def make_right(self):
        with self.sim.lock:
            self.sim.nodes['axis1'].cfg.product_code = 0x138E

    def close(self):
        super().close()
        self.sim.stop()
        self.broker.stop()
