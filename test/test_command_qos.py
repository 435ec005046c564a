"""The command topics keep every message (docs/interface.md, "No command is lost on the way in").

With a KEEP_LAST 10 reader history, four publishers bursting 251 velocity commands each, each
ending with 0.0, left the axis running at an older velocity in 4 of about 25 loaded runs of
test_safety_ros (the node's callbacks saw none of the later 0.0s). Discovery does not carry a
reader's history kind, so it is checked here on each vendor's node built in this process.
"""

from __future__ import annotations

import pytest
from stepper_drivers.vendor_table import KEYS

from test_param_rules import make_node, ros  # noqa: F401 - ros is the fixture make_node needs


@pytest.mark.parametrize('key', KEYS)
def test_every_command_subscription_is_reliable_and_keeps_all(ros, key):
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


def test_command_topics_are_served_by_the_hidden_companion_node(ros):
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


def test_command_topics_follow_the_nodes_remapping_and_name(ros):
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
