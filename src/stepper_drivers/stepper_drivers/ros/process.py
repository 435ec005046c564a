"""The process around a node: shutdown signals, the executor thread, the order of shutdown.

Why the node takes SIGINT and SIGTERM itself, not rclpy: rclpy's handler wakes the executors
and shuts the context down one after the other, from its own thread. An executor woken in
between finds the context still valid, waits again, and nothing wakes it any more: the node
never ends, and its drives are not stopped. rclpy's own timers hide this; this node has none
(its executor sleeps until a command comes: CPU, docs/benchmarks.md). Measured under a CPU load
(scripts/check_signal_race.py): a plain rclpy node without a timer missed SIGTERM in 4 of 300
starts; the same node spun by spin_node, in none of 300.

So the signals are blocked in every thread from the start of the process (`block_shutdown_
signals`, before rclpy.init creates any thread), the executor spins in a thread of its own,
and the main thread waits for a signal with sigwait: a signal is never lost, whenever it comes.
The executor thread wakes the main thread the same way if it ends by itself (an exception in a
callback), and so does a bus owner that ended by an internal error (`DriveNode.on_fatal`): the
node then ends with exit code 1 rather than go on looking alive with drives nobody polls.
Then, in this order: no more commands, every drive stopped (disabled where
disable_on_shutdown), the executor ended, the node destroyed.
"""

from __future__ import annotations

import signal
import sys
import threading

SHUTDOWN_SIGNALS = frozenset({signal.SIGINT, signal.SIGTERM})
# The GIL switch interval of a node process (see spin_node).
GIL_SWITCH_INTERVAL_S = 0.0005
# How long the executor thread may take to end once shut down [s].
EXECUTOR_JOIN_S = 2.0
# How long the service and action callbacks still running may take to answer at shutdown [s]
# (they have their answer once the drives are stopped: the executor only has to send it).
HANDLERS_JOIN_S = 2.0


def block_shutdown_signals() -> None:
    """Block SIGINT and SIGTERM in this thread and in every thread it starts from now on (a
    thread inherits its creator's mask): call first, before rclpy.init."""
    signal.pthread_sigmask(signal.SIG_BLOCK, SHUTDOWN_SIGNALS)


def shutdown_signals_blocked() -> bool:
    return SHUTDOWN_SIGNALS <= signal.pthread_sigmask(signal.SIG_BLOCK, ())


def spin_node(node) -> int:
    """Serve `node` until SIGINT or SIGTERM, then stop its drives and end; returns the exit
    code: 0, or 1 when the node ended itself (`node.on_fatal`: a bus owner failed). Main
    thread only, with the shutdown signals blocked since before rclpy.init
    (block_shutdown_signals)."""
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    if threading.current_thread() is not threading.main_thread() \
            or not shutdown_signals_blocked():
        raise RuntimeError('spin_node: call block_shutdown_signals() first, in the main thread')
    # Every callback only checks and enqueues, or awaits: one thread serves them all, with
    # the shortest publish-to-callback time (4 threads gave 12-120 ms p99 on 2 cores).
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    # The owner threads wait on the bus and then need the GIL back from the executor thread:
    # a short switch interval keeps that hand-over well below a transaction time.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    name = node.get_name()
    failure: list[BaseException] = []
    fatal: list[str] = []
    main = threading.main_thread().ident

    def on_fatal(why: str) -> None:
        fatal.append(why)
        signal.pthread_kill(main, signal.SIGTERM)
    node.on_fatal = on_fatal

    def spin() -> None:
        try:
            executor.spin()
        except ExternalShutdownException:
            pass
        except BaseException as exc:  # noqa: BLE001 - raised again by the main thread
            failure.append(exc)
        finally:
            signal.pthread_kill(main, signal.SIGTERM)   # whatever ended it: the process ends

    node.start_command_executor()
    node.start()
    spinner = threading.Thread(target=spin, name='executor', daemon=True)
    spinner.start()
    try:
        signal.sigwait(SHUTDOWN_SIGNALS)
    finally:
        node.stop_command_executor()        # no new command while the drives stop
        node.shutdown_drives()
        # services and actions still waiting get their answer (the node is shutting down)
        # while the executor still spins
        wait_handlers = getattr(node, 'wait_handlers', None)
        if wait_handlers is not None and not wait_handlers(HANDLERS_JOIN_S):
            print(f'{node.get_name()}: a service or action did not answer within '
                  f'{HANDLERS_JOIN_S:g} s of the shutdown', file=sys.stderr, flush=True)
        executor.shutdown(timeout_sec=1.0)
        spinner.join(EXECUTOR_JOIN_S)
        node.destroy_node()
        import rclpy
        rclpy.try_shutdown()
    if failure:
        raise failure[0]
    if fatal:
        print(f'{name}: ended: {fatal[0]}', file=sys.stderr, flush=True)
        return 1
    return 0
