"""A small rclpy client with a background executor: bounded waits for messages and services.

stepperctl talks to the nodes through it (cli/graph.py); tests, the demo and the benchmarks use
it too. rclpy is imported when a client is made, so `wait_for` imports without ROS.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

# How long one spin_once waits for work: also how soon close() ends the spin thread.
SPIN_PERIOD_S = 0.05


def wait_for(cond: Callable[[], Any], timeout_s: float = 5.0, what: str = 'condition',
             period_s: float = 0.01) -> Any:
    """Poll cond until it returns something truthy; fail naming `what` after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {timeout_s} s waiting for {what}')
        time.sleep(period_s)


def command_qos():
    """What the clients publish commands with: KEEP_ALL, RELIABLE, as the nodes subscribe."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)


class RosClient:
    """One rclpy node with a background executor (stepperctl, tests, demo, benchmarks)."""

    def __init__(self, name: str = 'test_client'):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        # Single-threaded: every callback runs inside _spin's spin_once, so once that thread is
        # joined nothing can touch an entity. (MultiThreadedExecutor.shutdown in the jazzy wheels
        # does not wait for its pool: a late task triggers a destroyed guard condition.)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        # Our own spin loop, so close() can stop it and join the thread *before* the executor is
        # shut down: executor.shutdown() under a running spin() destroys a guard condition the spin
        # thread may still trigger (rclpy InvalidHandle 'cannot use Destroyable').
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        self.latest: dict[str, Any] = {}
        self.history: dict[str, list] = {}
        self.lock = threading.Lock()
        self._pubs: dict[str, Any] = {}
        self._clients: dict[tuple, Any] = {}

    def subscribe(self, msg_type, topic: str, keep: bool = False) -> None:
        """Remember the latest message on topic (and all of them if keep)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        def cb(msg, topic=topic):
            with self.lock:
                self.latest[topic] = msg
                if keep:
                    self.history.setdefault(topic, []).append(msg)
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(msg_type, topic, cb, qos)

    def wait_msg(self, topic: str, cond: Callable[[Any], bool] = lambda m: True,
                 timeout_s: float = 10.0, what: str = '') -> Any:
        def check():
            with self.lock:
                m = self.latest.get(topic)
            return m if m is not None and cond(m) else None
        return wait_for(check, timeout_s, what or f'a message on {topic}')

    def call(self, srv_type, name: str, request=None, timeout_s: float = 10.0):
        """Call a service and wait for the answer (clients are kept: destroying one while the
        executor waits on it makes rclpy log 'cannot use Destroyable')."""
        key = (srv_type, name)
        client = self._clients.get(key)
        if client is None:
            client = self._clients[key] = self.node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise AssertionError(f'service {name} not available within {timeout_s} s')
        future = client.call_async(request if request is not None else srv_type.Request())
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout_s):
            raise AssertionError(f'service {name} did not answer within {timeout_s} s')
        return future.result()

    def in_spin(self, fn: Callable, *args, timeout_s: float = 5.0, **kwargs) -> Any:
        """Run fn in the spin thread and return its result.

        rclpy's ActionClient (jazzy 7.1) sends a goal, cancel or result request *before* it
        registers the sequence number; called from another thread while the executor spins, a
        quick answer is taken first and dropped ('Ignoring unexpected goal response') and the
        future never completes. Calling send_goal_async, cancel_goal_async and get_result_async
        through here makes send + register atomic for the executor."""
        task = self.executor.create_task(fn, *args, **kwargs)
        done = threading.Event()
        task.add_done_callback(lambda _t: done.set())
        if not done.wait(timeout_s):
            raise TimeoutError(f'{getattr(fn, "__name__", fn)} did not run within {timeout_s} s '
                               '(is the spin thread alive?)')
        return task.result()

    def publish(self, msg_type, topic: str, msg) -> None:
        """Publish msg once a subscriber is there. KEEP_ALL, RELIABLE (the nodes' command QoS):
        a reliable writer that keeps the last 10 drops the oldest one not yet acknowledged, so
        one of 200 commands published back to back on a loaded machine never arrived."""
        if topic not in self._pubs:
            self._pubs[topic] = self.node.create_publisher(msg_type, topic, command_qos())
            wait_for(lambda: self._pubs[topic].get_subscription_count() > 0, 10.0,
                     f'a subscriber on {topic}')
        self._pubs[topic].publish(msg)

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=SPIN_PERIOD_S)

    def close(self) -> None:
        """Stop the spin thread, then the executor, then the node (the only safe order)."""
        self._stop.set()
        self.thread.join(timeout=5)
        if self.thread.is_alive():
            # still inside rclpy's wait: destroying the node it waits on ends the process with
            # a segmentation fault (seen in CI); the node and its context go with the process
            return
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)
