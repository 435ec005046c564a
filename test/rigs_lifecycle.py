"""The managed (lifecycle) X-PLUS MT node against its simulator: `XplusLifecycle` starts
xplus_mt_lifecycle_node (unconfigured: nothing connected) and calls the standard lifecycle
services as a lifecycle manager does (~/get_state, ~/get_available_transitions, ~/change_state).
"""

from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState
from pymodbus.client import ModbusTcpClient
from rigs_vendors import XplusBench


class XplusLifecycle(XplusBench):
    node_executable = 'xplus_mt_lifecycle_node'
    wait_connected = False

    # ------------------------------------------------------------------ lifecycle services
    def state(self):
        return self.ros.call(GetState, f'{self.node_ns}/get_state', GetState.Request()) \
            .current_state

    def transitions(self):
        r = self.ros.call(GetAvailableTransitions, f'{self.node_ns}/get_available_transitions',
                          GetAvailableTransitions.Request())
        return {t.transition.label for t in r.available_transitions}

    def change(self, transition_id):
        req = ChangeState.Request()
        req.transition.id = transition_id
        return self.ros.call(ChangeState, f'{self.node_ns}/change_state', req,
                             timeout_s=30.0).success

    # ------------------------------------------------------------------------ the drive
    def statusword(self, unit=1):
        """Register 1001 read by a Modbus client of its own (a second client, as an HMI)."""
        c = ModbusTcpClient('127.0.0.1', port=self.port)
        assert c.connect()
        try:
            return c.read_holding_registers(1001, count=1, device_id=unit).registers[0]
        finally:
            c.close()

    def joint_states_within(self, seconds):
        """Whether a joint_states message arrives within `seconds`."""
        return self.message_within('/joint_states', seconds)

    def message_within(self, topic, seconds):
        with self.ros.lock:
            self.ros.latest.pop(topic, None)
        try:
            self.ros.wait_msg(topic, timeout_s=seconds)
            return True
        except AssertionError:
            return False
