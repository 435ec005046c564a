"""Drives on the ROS graph: find them by their DriveStatus topics, reach their interfaces.

A drive is known by the base name of its interfaces, `/<node>/<drive>` (docs/interface.md: status,
services and actions live under `~/<drive>/`). Users may name it in full, by its tail
(`xplus_mt_node/axis1`, `axis1`) or by its joint name, as long as that names one drive.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import time
from typing import Any, Callable, Iterable

from .errors import EXIT_NOT_FOUND, EXIT_TIMEOUT, EXIT_USAGE, CliError
from .ros_client import RosClient, command_qos

logger = logging.getLogger(__name__)

STATUS_TYPE = 'stepper_drivers_msgs/msg/DriveStatus'
# Discovery: the set of drives counts as complete once it has not changed for this long (a
# participant on the same host is usually seen within ~0.3 s, on a loaded machine within ~3 s).
DISCOVERY_SETTLE_S = 0.7
DISCOVERY_MIN_S = 1.5     # list/status of every drive: look at least this long
GRAPH_POLL_S = 0.05


@dataclasses.dataclass(frozen=True, order=True)
class DriveRef:
    """One drive on the graph, by the base name of its interfaces ('/xplus_mt_node/axis1')."""

    base: str

    @classmethod
    def from_status_topic(cls, topic: str) -> 'DriveRef':
        return cls(topic[:-len('/status')])

    @property
    def node(self) -> str:
        return self.base.rsplit('/', 1)[0] or '/'

    @property
    def drive(self) -> str:
        return self.base.rsplit('/', 1)[1]

    @property
    def status_topic(self) -> str:
        return self.base + '/status'

    @property
    def label(self) -> str:
        return self.base.lstrip('/')

    def interface(self, name: str) -> str:
        return f'{self.base}/{name}'


def resolve(spec: str, refs: Iterable[DriveRef], joints: dict[DriveRef, str] | None = None
            ) -> DriveRef:
    """The one drive `spec` names: full base, a tail of it ('axis1', 'node/axis1'), or a joint
    name. CliError(EXIT_NOT_FOUND) when none matches, CliError(EXIT_USAGE) when several do."""
    refs = sorted(set(refs))
    key = '/' + spec.strip('/')
    rules: list[Callable[[DriveRef], bool]] = [
        lambda r: r.base == key,
        lambda r: r.base.endswith(key),
        lambda r: joints is not None and joints.get(r) == spec,
    ]
    for rule in rules:
        hits = [r for r in refs if rule(r)]
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1:
            raise CliError(EXIT_USAGE, f"'{spec}' is ambiguous: it names "
                           + ', '.join(r.label for r in hits) + '; give node/drive')
    found = ', '.join(r.label for r in refs) or 'none'
    raise CliError(EXIT_NOT_FOUND, f"drive '{spec}' not found on the ROS graph "
                   f'(ROS_DOMAIN_ID={os.environ.get("ROS_DOMAIN_ID", "0")}; drives found: '
                   f'{found})')


class Graph:
    """An rclpy client node (background executor) with bounded waits on the graph."""

    def __init__(self, discovery_timeout_s: float = 3.0):
        self.discovery_timeout_s = discovery_timeout_s
        self.ros = RosClient(f'stepperctl_{os.getpid()}')
        self.node = self.ros.node
        self._subscribed: set[str] = set()
        self._received: dict[str, float] = {}    # topic -> time.monotonic() of the last message
        self._action_clients: dict[tuple, Any] = {}

    def close(self) -> None:
        self.ros.close()

    # --------------------------------------------------------------------------- discovery
    def drive_refs(self) -> list[DriveRef]:
        """Drives whose status topic has a publisher now."""
        refs = []
        for topic, types in self.node.get_topic_names_and_types():
            if STATUS_TYPE in types and topic.endswith('/status') \
                    and self.node.count_publishers(topic) > 0:
                refs.append(DriveRef.from_status_topic(topic))
        return sorted(refs)

    def discover(self, timeout_s: float | None = None,
                 done: Callable[[list[DriveRef]], bool] | None = None) -> list[DriveRef]:
        """Wait for the drives on the graph, at most timeout_s.

        Without `done`: until the set has not changed for DISCOVERY_SETTLE_S and at least
        DISCOVERY_MIN_S passed (participants show up one by one). With `done(refs)`: as soon as
        it says 'exact', or once it says 'match' and the set settled."""
        timeout_s = self.discovery_timeout_s if timeout_s is None else timeout_s
        t0 = time.monotonic()
        deadline = t0 + timeout_s
        last: list[DriveRef] = []
        changed_at = t0
        while True:
            refs = self.drive_refs()
            now = time.monotonic()
            if refs != last:
                last, changed_at = refs, now
            settled = bool(refs) and now - changed_at >= DISCOVERY_SETTLE_S
            verdict = done(refs) if done else ''
            if verdict == 'exact' or (settled and (verdict == 'match' or (
                    done is None and now - t0 >= DISCOVERY_MIN_S))):
                return refs
            if now >= deadline:
                return refs
            time.sleep(GRAPH_POLL_S)  # the graph has no wait-for-change call in rclpy

    def find(self, spec: str) -> DriveRef:
        """The drive named by spec, waiting for discovery as long as needed (and allowed)."""
        key = '/' + spec.strip('/')

        def verdict(refs: list[DriveRef]) -> str:
            if any(r.base == key for r in refs):
                return 'exact'
            if sum(r.base.endswith(key) for r in refs) == 1:
                return 'match'
            self.subscribe_status(refs)      # a joint name needs the status messages
            return 'match' if list(self.joint_names(refs).values()).count(spec) == 1 else ''
        refs = self.discover(done=verdict)
        return resolve(spec, refs, self.joint_names(refs))

    def joint_names(self, refs: Iterable[DriveRef]) -> dict[DriveRef, str]:
        names = {}
        for r in refs:
            msg = self.latest(r)[0]
            if msg is not None:
                names[r] = msg.joint_name
        return names

    # ------------------------------------------------------------------------------ status
    def subscribe_status(self, refs: Iterable[DriveRef]) -> None:
        from stepper_drivers_msgs.msg import DriveStatus
        for r in refs:
            if r.status_topic not in self._subscribed:
                self._subscribed.add(r.status_topic)
                self._subscribe_timed(DriveStatus, r.status_topic)

    def _subscribe_timed(self, msg_type, topic: str) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        def cb(msg, topic=topic):
            with self.ros.lock:
                self.ros.latest[topic] = msg
                self._received[topic] = time.monotonic()
        self.node.create_subscription(msg_type, topic, cb,
                                      QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    def latest(self, ref: DriveRef) -> tuple[Any, float]:
        """(last status or None, its age in s)."""
        with self.ros.lock:
            msg = self.ros.latest.get(ref.status_topic)
            t = self._received.get(ref.status_topic)
        return msg, (time.monotonic() - t) if t is not None else float('inf')

    def status(self, ref: DriveRef, cond: Callable[[Any], bool] = lambda m: True,
               timeout_s: float = 3.0, newer_than: Any = None, what: str = '') -> Any:
        """The latest status that satisfies cond (and is not `newer_than`), within timeout_s."""
        self.subscribe_status([ref])
        deadline = time.monotonic() + timeout_s
        while True:
            msg, _age = self.latest(ref)
            if msg is not None and msg is not newer_than and cond(msg):
                return msg
            if time.monotonic() >= deadline:
                if msg is None:
                    raise CliError(EXIT_TIMEOUT, f'{ref.label}: no status message within '
                                   f'{timeout_s:g} s (is the node running?)')
                raise CliError(EXIT_TIMEOUT, f'{ref.label}: {what or "status"} not seen within '
                               f'{timeout_s:g} s')
            time.sleep(0.01)  # poll of the subscription callback's result

    # ---------------------------------------------------------------------------- services
    def call(self, ref: DriveRef, name: str, srv_type, request=None, timeout_s: float = 10.0,
             while_waiting: Callable[[], None] | None = None):
        """Call ~/<drive>/<name>; CliError NOT_FOUND when the service is missing, TIMEOUT when
        it does not answer within timeout_s. `while_waiting` runs every 0.1 s meanwhile."""
        srv_name = ref.interface(name)
        client = self.ros._clients.get((srv_type, srv_name))
        if client is None:
            client = self.ros._clients[(srv_type, srv_name)] = \
                self.node.create_client(srv_type, srv_name)
        if not client.wait_for_service(timeout_sec=min(timeout_s, self.discovery_timeout_s)):
            raise CliError(EXIT_NOT_FOUND, f'{ref.label}: service {srv_name} not available')
        future = client.call_async(request if request is not None else srv_type.Request())
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        deadline = time.monotonic() + timeout_s
        while not done.wait(0.1):
            if while_waiting:
                while_waiting()
            if time.monotonic() >= deadline:
                raise CliError(EXIT_TIMEOUT, f'{ref.label}: {name} did not answer within '
                               f'{timeout_s:g} s')
        return future.result()

    def param(self, node: str, name: str, timeout_s: float = 2.0) -> Any:
        """A parameter value of a node, or None when it cannot be read."""
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python
        srv_name = f'{node}/get_parameters'
        client = self.ros._clients.get((GetParameters, srv_name))
        if client is None:
            client = self.ros._clients[(GetParameters, srv_name)] = \
                self.node.create_client(GetParameters, srv_name)
        if not client.wait_for_service(timeout_sec=timeout_s):
            return None
        future = client.call_async(GetParameters.Request(names=[name]))
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout_s) or not future.result().values:
            return None
        return parameter_value_to_python(future.result().values[0])

    # ----------------------------------------------------------------------------- actions
    def action_client(self, ref: DriveRef, name: str, action_type):
        from rclpy.action import ActionClient
        key = (action_type, ref.interface(name))
        if key not in self._action_clients:
            self._action_clients[key] = ActionClient(self.node, action_type, key[1])
        client = self._action_clients[key]
        if not client.wait_for_server(timeout_sec=self.discovery_timeout_s):
            raise CliError(EXIT_NOT_FOUND, f'{ref.label}: action {key[1]} not available')
        return client

    # ------------------------------------------------------------------------------ topics
    def publisher(self, msg_type, topic: str):
        pubs = self.ros._pubs
        if topic not in pubs:
            pubs[topic] = self.node.create_publisher(msg_type, topic, command_qos())
        pub = pubs[topic]
        deadline = time.monotonic() + self.discovery_timeout_s
        while pub.get_subscription_count() == 0:
            if time.monotonic() >= deadline:
                raise CliError(EXIT_NOT_FOUND, f'nobody subscribes to {topic}')
            time.sleep(GRAPH_POLL_S)  # matching has no event in rclpy's Python API
        return pub
