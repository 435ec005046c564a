#!/usr/bin/env python3
"""Does a node without timers always end on SIGTERM? Counts the starts that did not.

Starts a small rclpy node (one subscription, 20 services, no timer) again and again, sends
SIGTERM at a random moment once it spins, and counts the processes still alive after
--timeout-s. Two ways of spinning it:
  rclpy    rclpy's signal handler and executor.spin() in the main thread (the node before
           process.py): the handler wakes the executor before it shuts the context down, and
           an executor woken in between waits again, for ever.
  process  stepper_drivers.ros.process.spin_node, as every vendor node runs: the signals blocked
           in every thread, sigwait in the main thread.
--load keeps two busy-loop processes running (30 ms of work per 20 and 10 ms of sleep), the
load under which the race shows: without load it is rarely seen.

  scripts/check_signal_race.py --runs 300 --load             both ways, one after the other
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import time


def child(way: str) -> None:
    if way == 'process':
        from stepper_drivers.ros.process import block_shutdown_signals, spin_node
        block_shutdown_signals()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import Float64
    from std_srvs.srv import Trigger
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO if way == 'process' else None)
    node = rclpy.create_node('signal_race')
    node.create_subscription(Float64, 'x', lambda m: None, 10)
    for i in range(20):
        node.create_service(Trigger, f's{i}', lambda req, resp: resp)
    if way == 'process':
        # what spin_node asks of a drive node, with no drives
        for name in ('start_command_executor', 'start', 'stop_command_executor',
                     'shutdown_drives'):
            setattr(node, name, lambda: None)
        print('ready', flush=True)
        spin_node(node)
    else:
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        print('ready', flush=True)
        try:
            executor.spin()
        except Exception:  # noqa: BLE001 - ExternalShutdownException and the like: it ended
            pass
    print('ended', flush=True)


def busy(work_s: float, sleep_s: float) -> None:
    while True:
        t = time.monotonic()
        while time.monotonic() - t < work_s:
            pass
        time.sleep(sleep_s)


def count_hangs(way: str, runs: int, timeout_s: float) -> int:
    hangs = 0
    for i in range(runs):
        p = subprocess.Popen([sys.executable, __file__, '--child', way],
                             stdout=subprocess.PIPE, text=True)
        if p.stdout.readline().strip() != 'ready':
            raise SystemExit(f'{way}: the child did not start')
        time.sleep(random.uniform(0.0, 0.05))
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            hangs += 1
            print(f'{way}: start {i + 1} still running {timeout_s:g} s after SIGTERM',
                  flush=True)
            p.kill()
            p.wait()
    return hangs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--child', choices=('rclpy', 'process'))
    ap.add_argument('--runs', type=int, default=100)
    ap.add_argument('--way', choices=('rclpy', 'process', 'both'), default='both')
    ap.add_argument('--timeout-s', type=float, default=5.0)
    ap.add_argument('--load', action='store_true')
    args = ap.parse_args()
    if args.child:
        child(args.child)
        return
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    hogs = []
    if args.load:
        import multiprocessing
        hogs = [multiprocessing.Process(target=busy, args=a, daemon=True)
                for a in ((0.03, 0.02), (0.03, 0.01))]
        for h in hogs:
            h.start()
    try:
        for way in (('rclpy', 'process') if args.way == 'both' else (args.way,)):
            hangs = count_hangs(way, args.runs, args.timeout_s)
            print(f'{way}: {hangs} of {args.runs} starts did not end within '
                  f'{args.timeout_s:g} s of SIGTERM', flush=True)
    finally:
        for h in hogs:
            h.terminate()


if __name__ == '__main__':
    main()
