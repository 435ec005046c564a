"""process.spin_node, the process around every vendor node: how it ends, and with which code.

Each case is a real process with real rclpy: a small node (no drives) given what spin_node asks
of a drive node, whose `shutdown_drives` prints a line, so the test sees that the drives were
stopped before the process ended. The vendor nodes' own ends (SIGTERM with drives running) are
tested end to end in test_<vendor>_ros.py; the signal race this design closes is measured by
scripts/check_signal_race.py (it needs hundreds of loaded starts to show).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import pytest
from stepper_sim.harness import wait_for

CHILD = textwrap.dedent("""
    import sys, threading
    from stepper_drivers.ros.process import block_shutdown_signals, spin_node
    block_shutdown_signals()
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import Float64
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('process_test')
    how = sys.argv[1]

    def start():
        if how == 'fatal':      # as DriveNode._owner_failed does, from the owner's thread
            threading.Timer(0.2, node.on_fatal, args=('bus 1: bus owner failed: boom',)).start()
        print('ready', flush=True)
    node.start = start
    node.start_command_executor = node.stop_command_executor = lambda: None
    node.shutdown_drives = lambda: print('drives stopped', flush=True)
    if how == 'callback':       # an exception in a callback ends the executor thread
        def boom(msg):
            raise RuntimeError('a bug in a callback')
        node.create_subscription(Float64, 'process_test_boom', boom, 10)
    sys.exit(spin_node(node))
""")


def start(how: str) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, '-c', CHILD, how], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    assert p.stdout.readline().strip() == 'ready'
    return p


def finish(p: subprocess.Popen, timeout_s: float = 10.0) -> tuple[int, str]:
    try:
        out, _ = p.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        p.kill()
        out, _ = p.communicate()
        pytest.fail(f'the process did not end within {timeout_s} s:\n{out}')
    return p.returncode, out


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_a_shutdown_signal_stops_the_drives_and_ends_with_0(sig):
    p = start('signal')
    p.send_signal(sig)
    code, out = finish(p)
    assert code == 0 and out.splitlines() == ['drives stopped'], out


def test_a_failed_bus_owner_ends_the_node_with_1_after_the_drives_stopped():
    code, out = finish(start('fatal'))
    lines = out.splitlines()
    assert code == 1, out
    assert lines[0] == 'drives stopped' and 'bus owner failed: boom' in lines[-1], out


def test_an_exception_in_a_callback_ends_the_node_after_the_drives_stopped():
    import rclpy
    from std_msgs.msg import Float64
    p = start('callback')
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('process_test_client', context=context)
    try:
        pub = node.create_publisher(Float64, 'process_test_boom', 10)
        wait_for(lambda: pub.get_subscription_count() > 0, 10.0, 'the node subscribed')
        pub.publish(Float64(data=1.0))
        code, out = finish(p)
    finally:
        node.destroy_node()          # now, not whenever the garbage collector gets to it
        rclpy.shutdown(context=context)
    assert code == 1 and 'drives stopped' in out and 'a bug in a callback' in out, out
    assert out.index('drives stopped') < out.index('Traceback'), out


PROBE = textwrap.dedent("""
    import rclpy
    rclpy.init()
    node = rclpy.create_node('shm_probe')
    print('up', flush=True)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
""")


def fast_dds_files() -> set[str]:
    return {f for f in os.listdir('/dev/shm') if f.startswith('fastrtps_')}


def test_the_harness_ends_its_processes_so_that_their_shared_memory_goes(tmp_path):
    """Procs.kill_all (every end-to-end test's teardown) asks first: a ROS process that ends on
    SIGINT removes its Fast DDS files from /dev/shm, where a killed one leaves them behind
    (docs/troubleshooting.md: thousands of them stalled the simulators' start)."""
    from rosharness import Procs
    before = fast_dds_files()
    procs = Procs(tmp_path)
    probe = procs.start('probe', [sys.executable, '-c', PROBE])
    probe.wait_line('up')
    mine = fast_dds_files() - before
    assert mine, 'the probe made no Fast DDS files in /dev/shm'
    procs.kill_all()
    assert probe.proc.returncode == 0, probe.output()
    assert not mine & fast_dds_files()

