"""What the node publishes, and from which thread (its CPU cost: docs/benchmarks.md).

The owner threads publish joint_states, status and /diagnostics; the executor has no timer, so
it sleeps until a command, a service call or an action comes (each wake-up of rclpy's executor
rebuilds its wait set over every service, action and event handler: 3 ms with 8 drives).
Nodes are built in this process (not started: no bus is opened).
"""

from __future__ import annotations

import time

import pytest
from rigs_nodes import make_node
from stepper_drivers.vendors.table import KEYS


@pytest.mark.parametrize('key', KEYS)
def test_the_executor_has_no_periodic_work(offline_rclpy, key):
    node = make_node(key)
    try:
        assert [t.timer_period_ns for t in node.timers] == []
    finally:
        node.destroy_node()


def test_stamps_are_the_system_time_or_the_simulated_time(offline_rclpy):
    node = make_node('xplus_mt')
    try:
        before = time.time_ns()
        stamp = node.publishing.stamp()
        after = time.time_ns()
        assert before <= stamp.sec * 10**9 + stamp.nanosec <= after
    finally:
        node.destroy_node()
    node = make_node('xplus_mt', '-p', 'use_sim_time:=true')
    try:
        stamp = node.publishing.stamp()    # no /clock yet: simulated time is 0
        assert (stamp.sec, stamp.nanosec) == (0, 0)
    finally:
        node.destroy_node()


def test_diagnostics_values_are_reused_only_while_unchanged(offline_rclpy):
    node = make_node('xplus_mt')
    try:
        first = node.publishing.key_values('n: axis1', [('state', 'READY'), ('position', 0.5)])
        second = node.publishing.key_values('n: axis1', [('state', 'READY'), ('position', 0.75)])
        assert second[0] is first[0]                      # unchanged: the same KeyValue
        assert second[1] is not first[1] and second[1].value == '0.75'
        assert first[1].value == '0.5'                    # a published one stays as sent
        other = node.publishing.key_values('n: axis2', [('state', 'FAULT')])
        assert other[0].value == 'FAULT' and other[0] is not first[0]
    finally:
        node.destroy_node()
