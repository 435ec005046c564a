"""What a DriveNode publishes: /joint_states, each drive's status, /diagnostics.

The bus owner threads publish (owner.BusOwner's on_cycle; the poll group's thread for
the owners whose polls it made, owner/poll_group.py): joint_states and the statuses after each poll
cycle of their bus, and /diagnostics when it is due; the executor has no timer and sleeps until a
command comes. A service or action that awaits the publication of a change (DriveNode.published)
is answered here, by the thread that published it.
"""

from __future__ import annotations

import concurrent.futures
import math
import threading
import time
from typing import Any, Mapping, Protocol

from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import ClockType
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from stepper_drivers_msgs.msg import DriveStatus

from ..contract.drive import Vendor
from ..owner import BusOwner
from .handle import DriveHandle
from .joint_state_cdr import JointStateCdr

CLOCK_KIND_CHECK_S = 1.0


def settle(fut: concurrent.futures.Future, value: Any) -> None:
    """Resolve fut with value unless it is resolved already (a timer and the owner may race)."""
    try:
        if not fut.done():
            fut.set_result(value)
    except concurrent.futures.InvalidStateError:
        pass


class PublishingHost(Protocol):
    """What the publishing needs of its node (node.DriveNode): its drives and bus owners, its
    parameters, and the rclpy Node calls below."""

    handles: Mapping[str, DriveHandle]
    bus_owners: list[BusOwner]
    bus_params: Mapping[str, Any]
    vendor: Vendor
    managed: bool            # a lifecycle node: lifecycle publishers
    refusals: int            # of every drive
    context: Any             # the rclpy Context

    def get_name(self) -> str: ...

    def get_clock(self) -> Any: ...

    def create_publisher(self, *args: Any, **kwargs: Any) -> Any: ...

    def create_lifecycle_publisher(self, *args: Any, **kwargs: Any) -> Any: ...


class StatePublisher:
    """The publishers of `node` and what they last sent; every publish runs in an owner
    thread. Built with the node (no ROS entity); `create_publishers` and `add_drive` make the
    publishers with the node's interfaces."""

    def __init__(self, node: PublishingHost):
        self.node = node
        self._js_lock = threading.Lock()       # joint_states: the owner threads take turns
        self._js_cycled: set[int] = set()
        self._js_due = 0.0
        self._js_cdr: JointStateCdr | None = None     # the joint names, encoded once
        self._js_handles: list[DriveHandle] = []
        self._sup_handles: dict[BusOwner, list[DriveHandle]] = {}   # a bus' drives
        # a bus' (node.refusals, link health) at its last look at the status keys, and its
        # drives' next status due then (publish_states)
        self._statuses_seen: dict[BusOwner, tuple] = {}
        self._status_due_min: dict[BusOwner, float] = {}
        self._context_live = True              # until rclpy's context shuts down
        # (handles, their states, positions, velocities, efforts) of the last joint_states:
        # the values again while the states are equal (idle drives)
        self._js_values: tuple = ((), (), (), (), None)
        self._diag_lock = threading.Lock()     # /diagnostics: the owner threads take turns
        self._diag_due = 0.0
        self._diag_kv: dict[str, dict[str, KeyValue]] = {}     # status name -> key -> KeyValue
        # drive name -> (what its DiagnosticStatus is made of, the status): sent again as is
        self._diag_drive: dict[str, tuple[tuple, DiagnosticStatus]] = {}
        self.status_pubs = {}
        self._sim_time = False                 # the node's clock runs on /clock (stamp_pair)
        self._clock_kind_due = 0.0

    def create_publishers(self) -> None:
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.joint_pub = self._publisher(JointState, 'joint_states', reliable)
        self.diag_pub = self._publisher(DiagnosticArray, '/diagnostics', 10)
        # publish_states stops at the context's shutdown (rclpy.shutdown, a signal): a flag
        # set by its callback, not Context.ok(), which took 30 us a cycle
        self._context_live = self.node.context.ok()
        self.node.context.on_shutdown(self._context_shut_down)

    def _context_shut_down(self) -> None:
        self._context_live = False

    def add_drive(self, h: DriveHandle, ns: str) -> None:
        """The status publisher of drive h, under the namespace ns (`~/<drive>/`)."""
        self.status_pubs[h.name] = self._publisher(DriveStatus, ns + 'status', 10)

    def drives_rebuilt(self) -> None:
        """The node built its drives again: the joint names are encoded anew."""
        with self._js_lock:
            self._js_cdr = None
            self._sup_handles = {}
            self._statuses_seen = {}

    def _publisher(self, msg_type, topic: str, qos):
        if self.node.managed:      # publishes only while active (LifecycleNodeMixin manages it)
            return self.node.create_lifecycle_publisher(msg_type, topic, qos)
        return self.node.create_publisher(msg_type, topic, qos)

    def publish_states(self, bus_owner: BusOwner) -> None:
        """Owner thread, after each poll cycle of its bus, and after a poll that a publish
        waiter awaited (a service or action that changed the drive: `DriveNode.published`): then
        joint_states and that drive's status go out now, whatever is due, and its waiters are
        answered."""
        handles = self._sup_handles.get(bus_owner)
        if handles is None:
            handles = [self.node.handles[n] for n in bus_owner.slots]
            self._sup_handles[bus_owner] = handles
        waiting = [h for h in handles if h.publish_waiters]
        if not self._context_live:
            self._answer_publish_waiters(waiting, False)
            return
        stamp = pair = None
        now = time.monotonic()
        if self._joint_states_due(bus_owner, now) or waiting:
            pair = self.stamp_pair()
            self._publish_joint_states(*pair)
        # A status goes out when something in it changed, and at status_rate_hz otherwise:
        # at 50 Hz the messages of idle drives cost more CPU than polling them. Nothing in
        # them changed (no status key to build) after a cycle the owner calls unchanged, with
        # no refusal and the same link health since the last one, until a status is due.
        health = bus_owner.bus.health()
        refusals = self.node.refusals          # before the keys: a refusal after is seen next
        seen = self._statuses_seen.get(bus_owner)
        if bus_owner.cycle_unchanged and not waiting and seen is not None \
                and seen == (refusals, health) and now < self._status_due_min[bus_owner]:
            if now >= self._diag_due:
                self._publish_diagnostics_due(now)
            return
        counters = None
        for h in handles:
            # the status fields that make a new status worth sending (not the link counters)
            slot = h.slot
            key = (slot.state, slot.connected, slot.not_driven, h.commands_refused,
                   h.last_refusal, slot.velocity_deadline is not None, health)
            if key == h.status_key and now < h.status_due and not h.publish_waiters:
                continue
            if counters is None:
                counters = bus_owner.bus.counters()
            if stamp is None:
                pair = pair or self.stamp_pair()
                stamp = TimeMsg(sec=pair[0], nanosec=pair[1])
            self.status_pubs[h.name].publish(self._status_msg(h, stamp, counters))
            h.status_key = key
            h.status_due = now + 1.0 / self.node.bus_params['status_rate_hz']
        self._statuses_seen[bus_owner] = (refusals, health)
        self._status_due_min[bus_owner] = min(h.status_due for h in handles)
        self._answer_publish_waiters(waiting, True)
        if now >= self._diag_due:
            self._publish_diagnostics_due(now)

    @staticmethod
    def _answer_publish_waiters(handles: list[DriveHandle], published: bool) -> None:
        for h in handles:
            waiters, h.publish_waiters = h.publish_waiters, []
            for fut in waiters:
                settle(fut, published)

    def _publish_diagnostics_due(self, now: float) -> None:
        """/diagnostics from the owner thread that finds it due, not from an executor timer:
        each timer wake-up made rclpy rebuild its wait set over every service, action and
        event handler of the node (3 ms with 8 drives) in the thread that takes the commands
        (the CPU figures in docs/benchmarks.md)."""
        with self._diag_lock:
            if now < self._diag_due:          # another bus's owner was first
                return
            self._diag_due = now + 1.0 / self.node.bus_params['diagnostics_rate_hz']
            self.publish_diagnostics()

    def stamp(self) -> TimeMsg:
        """The node clock's now as a message."""
        sec, nanosec = self.stamp_pair()
        return TimeMsg(sec=sec, nanosec=nanosec)

    def stamp_pair(self) -> tuple[int, int]:
        """The node clock's now as (sec, nanosec). Without simulated time that is the system
        clock, read directly: rclpy's Clock.now().to_msg() cost 60 us a cycle on the owner's
        cold cache, half of it for a Time object thrown away; the joint_states, encoded by
        hand, need no message at all. Whether the clock runs on simulated time is looked up
        once per CLOCK_KIND_CHECK_S (25 us a look: use_sim_time set at run time takes effect
        within that)."""
        clock = self.node.get_clock()      # a node's clock is ROS_TIME: system time unless ...
        now = time.monotonic()
        if now >= self._clock_kind_due:
            self._sim_time = clock.clock_type != ClockType.ROS_TIME or clock.ros_time_is_active
            self._clock_kind_due = now + CLOCK_KIND_CHECK_S
        if self._sim_time:
            ns = clock.now().nanoseconds           # ... use_sim_time: the /clock topic's time
        else:
            ns = time.time_ns()
        return ns // 1_000_000_000, ns % 1_000_000_000

    def _joint_states_due(self, bus_owner: BusOwner, now: float) -> bool:
        """One joint_states for the node's drives once every bus that has a connected drive
        finished a cycle (a node with eight drive hosts publishes one message a period, not
        eight), or a period after the last one (a bus whose drives are all lost)."""
        with self._js_lock:
            bus_owners = self.node.bus_owners
            if len(bus_owners) > 1:
                self._js_cycled.add(id(bus_owner))
                live = {id(s) for s in bus_owners
                        if any(slot.connected for slot in s.slots.values())}
                if not (self._js_cycled >= live or now >= self._js_due):
                    return False
            self._js_cycled = set()
            self._js_due = now + 1.0 / self.node.bus_params['publish_rate_hz']
            return True

    def _publish_joint_states(self, sec: int, nanosec: int) -> None:
        """One JointState for every drive of the node, as CDR bytes published raw (encoded
        under _js_lock: owner threads of several buses take turns): rclpy's message path cost
        about 100 us more per message on the owner's cold cache (joint_state_cdr.py; the
        CPU figures in docs/benchmarks.md)."""
        with self._js_lock:
            cdr, handles = self._js_cdr, self._js_handles
            if cdr is None:                      # (build() drops it)
                handles = self._js_handles = list(self.node.handles.values())
                cdr = self._js_cdr = JointStateCdr([h.cfg.joint_name for h in handles])
            states = [h.slot.state for h in handles]
            last = self._js_values
            if last[0] is not handles or last[1] != states:
                last = self._js_values = (
                    handles, states,
                    [h.conv.from_steps(s.position_steps) for h, s in zip(handles, states)],
                    [h.conv.from_steps(s.velocity_steps_s) if s.velocity_valid else math.nan
                     for h, s in zip(handles, states)],
                    [float(s.effort) for s in states]
                    if all(s.effort is not None for s in states) else None)
            self.joint_pub.publish(cdr.encode(sec, nanosec, *last[2:]))

    def _status_msg(self, h: DriveHandle, stamp, counters: dict[str, int]) -> DriveStatus:
        s = h.state
        m = DriveStatus()
        m.header.stamp = stamp
        m.drive, m.joint_name, m.vendor = h.name, h.cfg.joint_name, self.node.vendor.name
        m.address = str(h.drive.address)
        m.state = s.state.value
        m.connected = h.connected
        m.enabled, m.moving, m.target_reached = s.enabled, s.moving, s.target_reached
        m.homed = s.homed
        m.homing_state = s.homing.value
        m.mode = s.mode
        m.fault, m.fault_code, m.fault_text = s.fault, s.fault_code & 0xFFFFFFFF, s.fault_text
        m.alarms = list(s.alarms)
        link = h.bus_owner.bus.health()
        if link is not None:
            m.alarms.append(link[1])
        m.status_word = s.status_word & 0xFFFFFFFF
        m.position_steps = int(s.position_steps)
        m.velocity_steps_s = float(s.velocity_steps_s)
        m.velocity_valid, m.position_estimated = s.velocity_valid, s.position_estimated
        m.position, m.velocity = h.position, h.velocity
        m.link_transactions = counters.get('transactions', 0) & 0xFFFFFFFF
        m.link_errors = counters.get('errors', 0) & 0xFFFFFFFF
        m.link_reconnects = max(h.slot.reconnects - 1, 0)
        m.commands_refused, m.last_refusal = h.commands_refused, h.last_refusal
        m.not_driven = h.slot.not_driven
        m.watchdog_armed = h.bus_owner.watchdog_armed(h.name)
        return m

    def publish_diagnostics(self) -> None:
        """Under _diag_lock (an owner thread)."""
        arr = DiagnosticArray()
        arr.header.stamp = self.stamp()
        for bus_owner in self.node.bus_owners:
            names = list(bus_owner.slots)
            link = DiagnosticStatus(name=f'{self.node.get_name()}: link',
                                    hardware_id=bus_owner.bus.description)
            if len(self.node.bus_owners) > 1:
                link.name += f' {bus_owner.bus.description}'
            lost = [n for n in names if not self.node.handles[n].connected]
            if not lost:
                link.level, link.message = DiagnosticStatus.OK, 'connected'
            elif len(lost) < len(names):
                link.level = DiagnosticStatus.WARN
                link.message = f'{", ".join(lost)} DISCONNECTED, reconnecting'
            else:
                link.level, link.message = DiagnosticStatus.ERROR, 'DISCONNECTED, reconnecting'
            health = bus_owner.bus.health()
            if health is not None:
                level = DiagnosticStatus.ERROR if health[0] == 'error' else DiagnosticStatus.WARN
                link.message = health[1] if link.level == DiagnosticStatus.OK else \
                    f'{link.message}; {health[1]}'
                link.level = max(link.level, level)
            link.values = self.key_values(link.name, [
                *bus_owner.bus.counters().items(),
                ('reconnects', sum(max(bus_owner.slots[n].reconnects - 1, 0) for n in names))])
            arr.status.append(link)
        for h in self.node.handles.values():
            s = h.state
            key = (h.drive, s, h.slot.not_driven, h.connected, h.slot.last_error,
                   h.commands_refused, h.last_refusal, h.bus_owner.watchdog_armed(h.name),
                   h.slot.identity)
            last = self._diag_drive.get(h.name)
            if last is not None and last[0] == key:
                arr.status.append(last[1])
                continue
            d = DiagnosticStatus(name=f'{self.node.get_name()}: {h.name}',
                                 hardware_id=f'{self.node.vendor.name} {h.drive.address}')
            if h.slot.not_driven:
                d.level, d.message = DiagnosticStatus.ERROR, f'not driven: {h.slot.not_driven}'
            elif not h.connected:
                d.level, d.message = DiagnosticStatus.ERROR, 'DISCONNECTED'
            elif s.fault:
                d.level = DiagnosticStatus.ERROR
                d.message = f'FAULT 0x{s.fault_code:04X}: {s.fault_text}'
            elif s.alarms or h.slot.last_error:
                d.level = DiagnosticStatus.WARN
                d.message = '; '.join(s.alarms) or h.slot.last_error
            else:
                d.level, d.message = DiagnosticStatus.OK, s.state.value
            kv = {'state': s.state.value, 'joint': h.cfg.joint_name, 'enabled': s.enabled,
                  'moving': s.moving, 'homed': s.homed, 'mode': s.mode,
                  'position': f'{h.position:.6g}', 'position_steps': s.position_steps,
                  'status_word': f'0x{s.status_word:04X}', 'fault_code': f'0x{s.fault_code:04X}',
                  'fault_text': s.fault_text, 'commands_refused': h.commands_refused,
                  'last_refusal': h.last_refusal,
                  'velocity_watchdog': 'armed' if h.bus_owner.watchdog_armed(h.name) else 'idle',
                  **h.slot.identity}
            d.values = self.key_values(d.name, kv.items())
            self._diag_drive[h.name] = (key, d)
            arr.status.append(d)
        self.diag_pub.publish(arr)

    def key_values(self, status: str, items) -> list[KeyValue]:
        """KeyValues for (key, value) items, reusing those whose value is unchanged since the
        last message (under _diag_lock). Built anew, the ~200 of 8 drives took 3.7 ms per
        message."""
        cache = self._diag_kv.setdefault(status, {})
        out = []
        for k, v in items:
            v = str(v)
            kv = cache.get(k)
            if kv is None or kv.value != v:
                kv = cache[k] = KeyValue(key=k, value=v)    # new: a published one stays as sent
            out.append(kv)
        return out
