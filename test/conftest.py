"""Workspace-level fixtures: loopback-only DDS, a private ROS domain, processes, a ROS client,
rclpy for nodes built in this process."""

import os
import pathlib
import socket

import pytest

# Fast DDS discovery must not leave the machine (it multicasts on every interface otherwise).
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
# Every node a test starts checks the writes to its bus owners' slots (owner/slot.py).
os.environ['STEPPER_DRIVERS_CHECK_WRITERS'] = '1'
# Announce participants every 0.3 s instead of 3 s: clients and nodes find each other sooner.
os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(
    pathlib.Path(__file__).resolve().parents[1] / 'config' / 'fastdds_fast_discovery.xml'))

_domain_lock = None


def _reserve_domain() -> None:
    """A private ROS_DOMAIN_ID per test run, reserved by binding a port (as domain_coordinator)."""
    global _domain_lock
    if os.environ.get('ROS_DOMAIN_ID'):
        return
    for domain in range(60, 101):
        s = socket.socket()
        try:
            s.bind(('127.0.0.1', 23000 + domain))
        except OSError:
            s.close()
            continue
        _domain_lock = s
        os.environ['ROS_DOMAIN_ID'] = str(domain)
        return


_reserve_domain()


@pytest.fixture
def procs(tmp_path):
    """Start processes with procs.start(name, args); all are stopped by PID at the end."""
    from rosharness import Procs
    started = Procs(tmp_path)
    yield started
    started.kill_all()


@pytest.fixture
def ros():
    from rosharness import RosClient
    client = RosClient()
    yield client
    client.close()


@pytest.fixture
def offline_rclpy(monkeypatch):
    """rclpy for nodes built in this process (rigs_nodes.make_node), shut down at the end."""
    import rclpy
    # These nodes take part in no graph: a later test that asks the graph for a node of the
    # same name (test_interface_docs) must not find one of these on its way out.
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'OFF')
    rclpy.init(args=['test'])
    yield
    rclpy.try_shutdown()
