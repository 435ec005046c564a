"""The command topics keep every message (docs/interface.md, "No command is lost on the way in").

With a KEEP_LAST 10 reader history, four publishers bursting 251 velocity commands each, each
ending with 0.0, left the axis running at an older velocity in 4 of about 25 loaded runs of
test_safety_ros (the node's callbacks saw none of the later 0.0s). Discovery does not carry a
reader's history kind, so it is checked here on each vendor's node built in this process.
"""

from __future__ import annotations

import pytest
from rigs_nodes import make_node
from stepper_drivers.vendors.table import KEYS


@pytest.mark.parametrize('key', KEYS)
def test_every_command_subscription_is_reliable_and_keeps_all(offline_rclpy, key):
    from rclpy.qos import HistoryPolicy, ReliabilityPolicy
    node = make_node(key)
    try:
        subs = {s.topic_name: s.qos_profile
                for s in (*node.subscriptions, *node.cmd_node.subscriptions)}
        ns = f'/{key}_node'
        expected = {'/joint_command', f'{ns}/joint_trajectory'}
        for name in node.handles:
            expected |= {f'{ns}/{name}/position_command', f'{ns}/{name}/velocity_command'}
        assert expected <= set(subs), sorted(expected - set(subs))
        for topic in sorted(expected):
            assert subs[topic].history == HistoryPolicy.KEEP_ALL, (topic, subs[topic].history)
            assert subs[topic].reliability == ReliabilityPolicy.RELIABLE, topic
    finally:
        node.destroy_node()


def test_command_topics_are_served_by_the_hidden_companion_node(offline_rclpy):
    node = make_node('xplus_mt')
    try:
        assert node.cmd_node.get_name() == '_xplus_mt_node_commands'    # hidden: leading _
        assert node.cmd_node.get_namespace() == node.get_namespace()
        assert not list(node.cmd_node.services)                # no parameter services
        mine = {s.topic_name for s in node.subscriptions}
        theirs = {s.topic_name for s in node.cmd_node.subscriptions}
        assert '/xplus_mt_node/axis1/position_command' in theirs, theirs
        assert not mine & theirs and '/xplus_mt_node/joint_trajectory' in mine
    finally:
        node.destroy_node()


def test_command_topics_follow_the_nodes_remapping_and_name(offline_rclpy):
    # A launch file's name= is `-r __node:=...`: a global argument that would rename every
    # node of the process; the companion takes none and resolves through the node's rules.
    node = make_node('xplus_mt', '-r', '__node:=arm_drives', '-p', 'drives:=[axis1]', '-r',
                     '/arm_drives/axis1/velocity_command:=/teleop/axis1_velocity')
    try:
        assert node.get_name() == 'arm_drives'
        assert node.cmd_node.get_name() == '_arm_drives_commands'
        theirs = {s.topic_name for s in node.cmd_node.subscriptions}
        assert {'/teleop/axis1_velocity', '/arm_drives/axis1/position_command',
                '/joint_command'} <= theirs, theirs
    finally:
        node.destroy_node()


@pytest.mark.parametrize('key', KEYS)
def test_every_command_callback_takes_the_samples_message_info(offline_rclpy, key):
    """rclpy passes a sample's MessageInfo (its DDS source timestamp) only to a callback that
    takes two arguments: without it a command's age cannot be judged."""
    from rclpy.subscription import Subscription
    node = make_node(key)
    try:
        for s in node.cmd_node.subscriptions:
            assert s._callback_type is Subscription.CallbackType.WithMessageInfo, s.topic_name
    finally:
        node.destroy_node()


def test_a_command_is_judged_by_the_age_of_its_sample(offline_rclpy):
    """Through the subscriptions' own callbacks, with the MessageInfo rclpy would pass: a
    velocity older than command_timeout_s (0.5 s in config/xplus_mt.yaml) and a position older
    than position_command_max_age_s are refused, naming the age and the parameter; a velocity 0
    is not judged by its age; a stamp ahead of this host's clock by more than the bound is
    refused as clocks that disagree. (The drive is not connected: a command that passes the age
    check is refused for that.)"""
    import time

    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64
    node = make_node('xplus_mt', '-p', 'position_command_max_age_s:=0.2')
    try:
        subs = {s.topic_name: s for s in node.cmd_node.subscriptions}
        h = node.handles['axis1']
        joint = h.cfg.joint_name

        def info(age_s):
            return {'source_timestamp': time.time_ns() - round(age_s * 1e9),
                    'received_timestamp': time.time_ns()}

        def refusal(topic, msg, age_s):
            before = h.commands_refused
            subs[topic].callback(msg, info(age_s))
            assert h.commands_refused == before + 1
            return h.last_refusal

        vel, pos = '/xplus_mt_node/axis1/velocity_command', '/xplus_mt_node/axis1/position_command'
        why = refusal(vel, Float64(data=1.0), 0.8)
        assert 'published 0.8' in why and 'command_timeout_s (0.5 s)' in why, why
        assert 'DISCONNECTED' in refusal(vel, Float64(data=1.0), 0.3)
        assert 'DISCONNECTED' in refusal(vel, Float64(data=0.0), 5.0)     # a stop: any age
        why = refusal(pos, Float64(data=1.0), 0.3)
        assert 'published 0.3' in why and 'position_command_max_age_s (0.2 s)' in why, why
        assert 'DISCONNECTED' in refusal(pos, Float64(data=1.0), 0.1)
        why = refusal(vel, Float64(data=1.0), -0.8)
        assert 'ahead of the clock of this host' in why and 'command_timeout_s' in why, why
        js = JointState(name=[joint], velocity=[1.0])
        why = refusal('/joint_command', js, 0.8)
        assert 'stale command' in why and 'command_timeout_s' in why, why
        js = JointState(name=[joint], position=[1.0])
        why = refusal('/joint_command', js, 0.3)
        assert 'stale command' in why and 'position_command_max_age_s' in why, why
        assert 'DISCONNECTED' in refusal('/joint_command', js, 0.0)
    finally:
        node.destroy_node()
