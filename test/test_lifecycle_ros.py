"""The managed (lifecycle) nodes end to end: `<key>_lifecycle_node` against its
simulator, driven through the standard lifecycle services as a lifecycle manager calls them
(~/get_state, ~/get_available_transitions, ~/change_state).
"""

import time

from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState
import pytest
from rigs_lifecycle import XplusLifecycle
from rigs_vendors import Rd4Bench
from rosharness import wait_for
from std_srvs.srv import SetBool

SOD_MASK, SOD = 0x004F, 0x0040          # CiA 402 status word: SWITCH ON DISABLED
STATUS_RATE_HZ = 1.0                    # status_rate_hz: config/xplus_mt.yaml leaves the default


@pytest.fixture
def managed(procs, ros, tmp_path):
    return XplusLifecycle(procs, ros, tmp_path)


def test_configure_activate_deactivate_cleanup_shutdown(managed):
    period_s = 1.0 / 50.0                          # publish_rate_hz of config/xplus_mt.yaml
    assert managed.state().id == State.PRIMARY_STATE_UNCONFIGURED
    assert 'configure' in managed.transitions()
    assert not managed.joint_states_within(5 * period_s)      # nothing before configure

    assert managed.change(Transition.TRANSITION_CONFIGURE)
    assert managed.state().id == State.PRIMARY_STATE_INACTIVE
    managed.node.wait_line('configured: axis1 SWITCH ON DISABLED', 5.0)
    assert not managed.joint_states_within(5 * period_s)      # inactive: nothing published
    status = f'{managed.node_ns}/axis1/status'                # at least once per status period
    assert not managed.message_within(status, 1.5 / STATUS_RATE_HZ)     # when active
    r = managed.call('axis1', 'enable', SetBool.Request(data=True), SetBool)
    assert not r.success and 'not active (lifecycle state inactive)' in r.message
    assert managed.statusword() & SOD_MASK == SOD             # and the drive was not enabled

    assert managed.change(Transition.TRANSITION_ACTIVATE)
    assert managed.state().id == State.PRIMARY_STATE_ACTIVE
    assert managed.joint_states_within(1.0)
    assert managed.message_within(status, 1.5 / STATUS_RATE_HZ)
    managed.enable('axis1')
    managed.command('axis1', 'velocity_command', 3.0)
    managed.status('axis1', lambda m: m.moving, what='running')

    assert managed.change(Transition.TRANSITION_DEACTIVATE)   # stops every drive
    assert managed.state().id == State.PRIMARY_STATE_INACTIVE
    a = managed.fresh_true_steps('axis1')
    time.sleep(0.2)                       # two true-position samples apart: no motion
    assert managed.fresh_true_steps('axis1') == a
    r = managed.call('axis1', 'enable', SetBool.Request(data=True), SetBool)
    assert not r.success and 'not active' in r.message
    assert managed.call('axis1', 'stop').success               # a stop is always taken

    assert managed.change(Transition.TRANSITION_CLEANUP)      # disable_on_shutdown: true
    assert managed.state().id == State.PRIMARY_STATE_UNCONFIGURED
    wait_for(lambda: managed.statusword() & SOD_MASK == SOD, 2.0, 'axis1 disabled')

    assert managed.change(Transition.TRANSITION_CONFIGURE)    # configure again: new owners
    assert managed.change(Transition.TRANSITION_ACTIVATE)
    managed.enable('axis1')
    assert managed.change(Transition.TRANSITION_ACTIVE_SHUTDOWN)
    assert managed.state().id == State.PRIMARY_STATE_FINALIZED
    wait_for(lambda: managed.statusword() & SOD_MASK == SOD, 2.0,
             'axis1 disabled at shutdown')


def test_configure_fails_with_one_line_naming_the_drive_when_it_does_not_answer(managed):
    managed.sim.stop()
    assert not managed.change(Transition.TRANSITION_CONFIGURE)
    assert managed.state().id == State.PRIMARY_STATE_UNCONFIGURED
    managed.node.wait_line('configure failed: axis1: no answer within', 15.0)
    managed.start_sim()                    # and configure works once the drive answers
    assert managed.change(Transition.TRANSITION_CONFIGURE)
    assert managed.state().id == State.PRIMARY_STATE_INACTIVE


class Rd4Lifecycle(Rd4Bench):
    node_executable = 'rd4_lifecycle_node'
    wait_connected = False


def test_rd4_lifecycle_node_keeps_the_plain_nodes_name_and_params(procs, ros, tmp_path):
    bench = Rd4Lifecycle(procs, ros, tmp_path)
    req = ChangeState.Request()
    req.transition.id = Transition.TRANSITION_CONFIGURE
    assert ros.call(ChangeState, '/rd4_node/change_state', req, timeout_s=30.0).success
    req.transition.id = Transition.TRANSITION_ACTIVATE
    assert ros.call(ChangeState, '/rd4_node/change_state', req, timeout_s=30.0).success
    st = bench.status('axis2', lambda m: m.connected)
    assert st.joint_name == 'rd4_joint2'                     # from config/rd4.yaml
    msg = ros.wait_msg('/joint_states', lambda m: len(m.name) == 2)
    assert list(msg.name) == ['rd4_joint1', 'rd4_joint2']
