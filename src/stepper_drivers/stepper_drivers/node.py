"""DriveNode: the one ROS layer every vendor node shares (docs/interface.md): a thin adapter.

Each bus has one owner thread (`supervisor.BusSupervisor`, no rclpy) that makes every call into
the vendor code: polls, commands, reconnects, the velocity watchdog and shutdown. This module only
turns ROS into jobs and snapshots into ROS:
- Command subscriptions check a command against the limits and the latest snapshot and enqueue
  it; they never wait. They belong to a hidden companion node (`_<node>_commands`, the pattern of
  tf2_ros's TransformListener) served by an executor thread of its own, whose wait set holds
  nothing else: a command is not delayed by rclpy scanning the node's ~80 services, actions and
  event handlers, nor by a service callback (the command-to-wire goal). One thread serves
  them, so the messages of one topic are handled in the order they arrived.
- Services and actions are async callbacks: they enqueue a job and `await` its result (and then
  the polls they need) without holding an executor thread, so one SingleThreadedExecutor serves
  the node and a stop is never queued behind a homing.
- The owner threads publish joint_states and status after each poll cycle of their bus, and
  /diagnostics when it is due: the executor has no timer and sleeps until a command comes.
- process.py runs the node: signals, the executor thread, the order of shutdown.

One file: DriveNode is one rclpy Node; its interfaces, command checks, publishing and services
share its handles, supervisors and callback groups (the trajectory interface is its own object,
node_trajectory.TrajectoryInterface).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import math
import re
import threading
import time
from typing import Any, Callable

from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import rclpy
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.clock import ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future as RosFuture
from rcl_interfaces.msg import SetParametersResult
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64
from std_srvs.srv import SetBool, Trigger
from stepper_drivers_msgs.action import Home, MoveTo
from stepper_drivers_msgs.msg import DriveStatus
from stepper_drivers_msgs.srv import ReadRegister, WriteRegister

from .drive import (Drive, DriveError, DriveState, Homing, HomingState, Motion, RefusedError,
                    Vendor)
from .joint_state_cdr import JointStateCdr
from .params import BusConfig, DriveConfig, ParameterError, current_values
from .node_trajectory import TrajectoryInterface
from .commands import Command, JobKind
from .supervisor import BusSupervisor, Cancelled, Slot, Superseded

# Position tolerance for "target reached" in a MoveTo action, in steps.
TARGET_TOLERANCE_STEPS = 2
# A MoveTo result is decided on this many consecutive snapshots that agree (standstill).
SETTLED_POLLS = 2
# On shutdown, how long a controlled stop may take before the power stage is disabled anyway.
SHUTDOWN_STOP_TIMEOUT_S = 5.0
# How long a service waits for its job; a job not started by then is dropped.
JOB_TIMEOUT_S = 15.0


# Command topics keep every sample (reliable, KEEP_ALL): a KEEP_LAST reader history fed by
# several writers at once can drop a publisher's last samples (eProsima/Fast-DDS#708), and a
# final 0.0 lost leaves an axis running. Every sample reaches the callback in each publisher's
# order; the bus owner's queue drops stream commands that a newer one replaces before they go.
COMMAND_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)


# A number in a refusal's reason (the command's value, a limit, a code), masked to tell its kind.
_NUMBER = re.compile(r'[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|\b(?:nan|inf)\b')


class CommandRefused(Exception):
    """A command the node does not send to the drive; str() is the reason."""


class DriveHandle:
    """The ROS side of one drive: its configuration, conversion, refusal counters, and the
    owner-side slot (snapshot, link state) of its bus supervisor."""

    def __init__(self, node: 'DriveNode', cfg: DriveConfig, drive: Drive):
        self.node = node
        self.cfg = cfg
        self.name = cfg.name
        self.drive = drive
        self.conv = cfg.conversion
        self.sup: BusSupervisor | None = None   # set when the buses are built
        self.commands_refused = 0
        self.last_refusal = ''
        self.refusal_logged = ''           # the kind of refusal logged last (see refuse)
        self.job_error_logged = ''         # the kind of failed command logged last (owner)
        self.status_key: tuple = ()        # what the last published status said (owner thread)
        self.status_due = 0.0              # time.monotonic() of the next status regardless
        # callers awaiting the publication of a snapshot newer than a change (owner thread)
        self.publish_waiters: list[concurrent.futures.Future] = []

    @property
    def slot(self) -> Slot:
        return self.sup.slots[self.name]

    @property
    def state(self) -> DriveState:
        return self.slot.state

    @property
    def connected(self) -> bool:
        return self.slot.connected

    def param(self, name: str) -> Any:
        return self.node.get_parameter(f'drives.{self.name}.{name}').value

    def motion(self) -> Motion:
        to = self.conv.to_steps
        return Motion(to(self.param('profile_velocity')), to(self.param('profile_acceleration')),
                      to(self.param('profile_deceleration')))

    def homing(self) -> Homing:
        to = self.conv.to_steps
        return Homing(int(self.param('homing.method')),
                      self.conv.to_steps_int(self.param('homing.offset')),
                      to(self.param('homing.speed_search')), to(self.param('homing.speed_zero')),
                      to(self.param('homing.acceleration')))

    @property
    def position(self) -> float:
        return self.conv.from_steps(self.state.position_steps)

    @property
    def velocity(self) -> float:
        return self.conv.from_steps(self.state.velocity_steps_s)


class DriveNode(Node):
    """The plain node: built, connected and publishing from the start. With `managed` (the
    lifecycle variant, lifecycle_node.py) the buses and interfaces wait for on_configure.

    What node_trajectory.TrajectoryInterface uses of it: `handles`, `accepting`, `handling()`,
    `await_future()`, `published()`, `command_qos`, `cmd_group` and the rclpy Node API."""

    command_qos = COMMAND_QOS

    def __init__(self, vendor: Vendor, node_name: str, config_loader: Callable[[Node], BusConfig],
                 managed: bool = False):
        super().__init__(node_name)
        self.vendor = vendor
        self.log = self.get_logger()
        self.cfg = config_loader(self)                       # raises ParameterError
        self.bus_params = self.cfg.params
        self.managed = managed
        # Commands are taken (plain node: always; managed node: while active). A stop is
        # taken in every state: it never moves anything.
        self.accepting = not managed
        self.handles: dict[str, DriveHandle] = {}
        self.supervisors: list[BusSupervisor] = []
        self.by_joint: dict[str, DriveHandle] = {}
        self._interfaces = False
        self._identities: dict[tuple[str, str], str] = {}    # (key, value) -> drive
        self._identity_lock = threading.Lock()
        self._js_lock = threading.Lock()       # joint_states: the owner threads take turns
        self._js_cycled: set[int] = set()
        self._js_due = 0.0
        self._js_cdr: JointStateCdr | None = None     # the joint names, encoded once
        self._js_handles: list[DriveHandle] = []
        self._diag_lock = threading.Lock()     # /diagnostics: the owner threads take turns
        self._diag_due = 0.0
        self._diag_kv: dict[str, dict[str, KeyValue]] = {}     # status name -> key -> KeyValue
        self._refusal_lock = threading.Lock()  # commands and services both count refusals
        self._handlers = 0                     # service and action callbacks running (handling)
        self._handlers_cv = threading.Condition()
        # The command subscriptions' own node: no global arguments (a launch file's
        # `__node:=` would give it this node's name), topics resolved by this node's rules.
        self.cmd_node = rclpy.create_node(
            f'_{self.get_name()}_commands', namespace=self.get_namespace(),
            context=self.context, use_global_arguments=False, start_parameter_services=False,
            enable_rosout=False, parameter_overrides=[
                Parameter('start_type_description_service', value=False)])   # no service
        self._cmd_executor = None
        # called (any thread) when the node cannot go on: a bus owner ended by an internal
        # error; process.spin_node ends the process then
        self.on_fatal: Callable[[str], None] = lambda why: None
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.add_post_set_parameters_callback(self.after_set_parameters)
        if not managed:
            self.build()

    def build(self) -> None:
        """Buses, drives and their owners (not started), and, the first time, the ROS
        interfaces. Nothing is opened or written here: start() does that."""
        self._identities.clear()
        self.supervisors = []
        self._build_buses()
        with self._js_lock:
            self._js_cdr = None
        self.by_joint = {h.cfg.joint_name: h for h in self.handles.values()}
        if not self._interfaces:
            self._make_interfaces()
            self._interfaces = True
        for sup in self.supervisors:
            names = [n for n in self.handles if self.handles[n].sup is sup]
            self.log.info(f'{self.vendor.name} node on {sup.bus.description}: drives '
                          + ', '.join(f'{n} ({self.handles[n].cfg.joint_name})' for n in names))

    def _publisher(self, msg_type, topic: str, qos):
        if self.managed:      # publishes only while active (LifecycleNodeMixin manages it)
            return self.create_lifecycle_publisher(msg_type, topic, qos)
        return self.create_publisher(msg_type, topic, qos)

    def _make_interfaces(self) -> None:
        self.cmd_group = MutuallyExclusiveCallbackGroup()    # ordered, never waits
        self.srv_group = ReentrantCallbackGroup()            # async: awaits, holds no thread
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.joint_pub = self._publisher(JointState, 'joint_states', reliable)
        self.diag_pub = self._publisher(DiagnosticArray, '/diagnostics', 10)
        self._command_subscription(JointState, 'joint_command', self.on_joint_command)
        self.status_pubs = {}
        for h in self.handles.values():
            self._make_drive_interfaces(h)
        self.trajectories = TrajectoryInterface(self)

    # ----------------------------------------------------------------------------------- set-up
    def _drive_bus_params(self, dcfg: DriveConfig) -> dict[str, Any]:
        """The bus parameters of this drive: the bus-level ones, with the drive's own link
        parameters (vendor.drive_bus_params) where it sets them."""
        params = dict(self.bus_params)
        for key in self.vendor.drive_bus_params:
            value = dcfg.params.get(key)
            if value not in (None, '', 0):
                params[key] = value
        return params

    def _build_buses(self) -> None:
        groups: dict[tuple, list[DriveConfig]] = {}
        for dcfg in self.cfg.drives:
            params = self._drive_bus_params(dcfg)
            key = tuple(params.get(k) for k in self.vendor.drive_bus_params)
            groups.setdefault(key, []).append(dcfg)
        for dcfgs in groups.values():
            params = self._drive_bus_params(dcfgs[0])
            try:
                bus = self.vendor.make_bus(params)
            except ValueError as e:
                raise ParameterError(str(e)) from None
            drives = {}
            for dcfg in dcfgs:
                drive_params = {**params, **{k: v for k, v in dcfg.params.items()
                                             if k not in self.vendor.drive_bus_params}}
                try:
                    drive = self.vendor.make_drive(bus, dcfg.name, drive_params)
                except ValueError as e:
                    raise ParameterError(str(e)) from None
                if dcfg.name in self.handles:      # built again (managed: configure again)
                    self.handles[dcfg.name].drive = drive
                else:
                    self.handles[dcfg.name] = DriveHandle(self, dcfg, drive)
                drives[dcfg.name] = drive
            sup = BusSupervisor(
                bus, drives, self.bus_params, on_cycle=self.publish_states,
                on_connected=self._check_identity, on_event=self._on_event,
                # managed: enabled at on_activate, not when the bus is configured
                auto_enable=[] if self.managed else
                [d.name for d in dcfgs if d.params.get('auto_enable')],
                name=bus.description or 'bus', on_failure=self._owner_failed)
            for name in drives:
                self.handles[name].sup = sup
            self.supervisors.append(sup)

    def _command_subscription(self, msg_type, topic: str, callback) -> None:
        """A command topic of this node (its name resolved and remapped as this node's own),
        subscribed by the companion node."""
        self.cmd_node.create_subscription(msg_type, self.resolve_topic_name(topic), callback,
                                          COMMAND_QOS)

    def start_command_executor(self) -> None:
        """Serve the command subscriptions from a thread of their own (see the module doc)."""
        from rclpy.executors import SingleThreadedExecutor
        self._cmd_executor = SingleThreadedExecutor(context=self.context)
        self._cmd_executor.add_node(self.cmd_node)
        threading.Thread(target=_spin_commands, args=(self._cmd_executor,),
                         name='command executor', daemon=True).start()

    def stop_command_executor(self) -> None:
        if self._cmd_executor is not None:
            self._cmd_executor.shutdown(timeout_sec=1.0)
            self._cmd_executor = None

    def destroy_node(self) -> None:
        self.stop_command_executor()
        self.cmd_node.destroy_node()
        super().destroy_node()

    def _make_drive_interfaces(self, h: DriveHandle) -> None:
        ns = f'~/{h.name}/'
        self.status_pubs[h.name] = self.create_publisher(DriveStatus, ns + 'status', 10)
        self._command_subscription(Float64, ns + 'position_command',
                                   lambda m, h=h: self.command_position(h, m.data))
        self._command_subscription(Float64, ns + 'velocity_command',
                                   lambda m, h=h: self.command_velocity(h, m.data))
        srv = [(SetBool, 'enable', self.srv_enable), (Trigger, 'stop', self.srv_stop),
               (Trigger, 'home', self.srv_home), (Trigger, 'fault_reset', self.srv_fault_reset),
               (Trigger, 'save_params', self.srv_save_params),
               (ReadRegister, 'read_register', self.srv_read_register),
               (WriteRegister, 'write_register', self.srv_write_register)]
        for srv_type, name, fn in srv:
            async def callback(req, resp, h=h, fn=fn):
                with self.handling():
                    return await fn(h, req, resp)
            self.create_service(srv_type, ns + name, callback, callback_group=self.srv_group)

        async def move_to(goal, h=h):
            with self.handling():
                return await self.act_move_to(h, goal)

        async def homing(goal, h=h):
            with self.handling():
                return await self.act_home(h, goal)
        ActionServer(self, MoveTo, ns + 'move_to', execute_callback=move_to,
                     goal_callback=lambda _req: GoalResponse.ACCEPT,
                     cancel_callback=lambda _goal: CancelResponse.ACCEPT,
                     callback_group=self.srv_group)
        ActionServer(self, Home, ns + 'homing', execute_callback=homing,
                     goal_callback=lambda _req: GoalResponse.ACCEPT,
                     cancel_callback=lambda _goal: CancelResponse.ACCEPT,
                     callback_group=self.srv_group)

    # ------------------------------------------------------------------- owner-side callbacks
    @property
    def connected(self) -> bool:
        return any(h.connected for h in self.handles.values())

    def _on_event(self, level: str, drive: str, text: str) -> None:
        if self.context.ok():
            # one call site per severity: rclpy refuses two severities from one line
            if level == 'error':
                self.log.error(f'{drive}: {text}')
            elif level == 'warning':
                self.log.warning(f'{drive}: {text}')
            else:
                self.log.info(f'{drive}: {text}')
        else:   # the ROS context is gone (rclpy shut down): print, not through rclpy
            print(f'[{self.get_name()}] {drive}: {text}', flush=True)

    def _owner_failed(self, sup: BusSupervisor, why: str) -> None:
        """Owner thread of `sup`, which ends: its drives are stopped, its bus closed. Their
        statuses say DISCONNECTED with the reason, and the node ends (exit code 1), stopping
        the drives of its other buses: a node that no longer polls or watches some of its
        drives must not go on looking alive (a launch file's respawn restarts it)."""
        try:
            self.publish_states(sup)
        finally:
            self.on_fatal(f'{sup.name}: {why}')

    def _check_identity(self, sup: BusSupervisor, slot: Slot) -> str:
        """Two configured drives that answer with one identity are one device reached twice
        (two unit ids or addresses, two host names): commanding one would move the other."""
        ident = slot.identity
        serial = ident.get('serial_number', '')
        if serial in ('', '0'):
            return ''
        key = ('serial_number', f"{ident.get('product_code', '')}/{serial}")
        with self._identity_lock:
            other = self._identities.setdefault(key, slot.name)
        if other == slot.name:
            return ''
        why = (f'{slot.name} and {other} answer with one identity (serial_number {serial}): '
               f'one device is reached twice; check their address parameters '
               f'({", ".join(self._address_params())})')
        self.handles[other].sup.refuse_drive(other, why)
        return why

    def _address_params(self) -> list[str]:
        names = [s.name for s in self.vendor.params if s.scope == 'drive'
                 and s.name in ('unit_id', 'node_id', 'address', 'host', 'port', 'slave_id')]
        return [f'drives.<name>.{n}' for n in names] or ['the drive addresses']

    # ------------------------------------------------------------------------------ polling
    def lifecycle_state_label(self) -> str:
        return 'active'

    def start(self) -> None:
        for sup in self.supervisors:
            sup.start()

    def publish_states(self, sup: BusSupervisor) -> None:
        """Owner thread, after each poll cycle of its bus, and after a poll that a publish
        waiter awaited (a service or action that changed the drive: `published`): then
        joint_states and that drive's status go out now, whatever is due, and its waiters are
        answered."""
        handles = [self.handles[n] for n in sup.slots]
        waiting = [h for h in handles if h.publish_waiters]
        if not self.context.ok():
            self._answer_publish_waiters(waiting, False)
            return
        stamp = None
        now = time.monotonic()
        if self._joint_states_due(sup, now) or waiting:
            stamp = self._stamp()
            self._publish_joint_states(stamp)
        # A status goes out when something in it changed, and at status_rate_hz otherwise:
        # at 50 Hz the messages of idle drives cost more CPU than polling them.
        counters = None
        for h in handles:
            key = self._status_key(h)
            if key == h.status_key and now < h.status_due and not h.publish_waiters:
                continue
            if counters is None:
                counters = sup.bus.counters()
            if stamp is None:
                stamp = self._stamp()
            self.status_pubs[h.name].publish(self._status_msg(h, stamp, counters))
            h.status_key = key
            h.status_due = now + 1.0 / self.bus_params['status_rate_hz']
        self._answer_publish_waiters(waiting, True)
        if now >= self._diag_due:
            self._publish_diagnostics_due(now)

    @staticmethod
    def _answer_publish_waiters(handles: list[DriveHandle], published: bool) -> None:
        for h in handles:
            waiters, h.publish_waiters = h.publish_waiters, []
            for fut in waiters:
                _settle(fut, published)

    def _publish_diagnostics_due(self, now: float) -> None:
        """/diagnostics from the owner thread that finds it due, not from an executor timer:
        each timer wake-up made rclpy rebuild its wait set over every service, action and
        event handler of the node (3 ms with 8 drives) in the thread that takes the commands
        (the CPU figures in docs/benchmarks.md)."""
        with self._diag_lock:
            if now < self._diag_due:          # another bus's owner was first
                return
            self._diag_due = now + 1.0 / self.bus_params['diagnostics_rate_hz']
            self.publish_diagnostics()

    def _stamp(self) -> TimeMsg:
        """The node clock's now as a message. Without simulated time that is the system
        clock, read directly: rclpy's Clock.now().to_msg() cost 60 us a cycle on the owner's
        cold cache, half of it for a Time object thrown away."""
        clock = self.get_clock()      # a node's clock is ROS_TIME: system time unless ...
        if clock.clock_type != ClockType.ROS_TIME or clock.ros_time_is_active:
            return clock.now().to_msg()            # ... use_sim_time: the /clock topic's time
        ns = time.time_ns()
        return TimeMsg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def _joint_states_due(self, sup: BusSupervisor, now: float) -> bool:
        """One joint_states for the node's drives once every bus that has a connected drive
        finished a cycle (a node with eight drive hosts publishes one message a period, not
        eight), or a period after the last one (a bus whose drives are all lost)."""
        with self._js_lock:
            self._js_cycled.add(id(sup))
            live = {id(s) for s in self.supervisors
                    if any(slot.connected for slot in s.slots.values())}
            if not (self._js_cycled >= live or now >= self._js_due):
                return False
            self._js_cycled = set()
            self._js_due = now + 1.0 / self.bus_params['publish_rate_hz']
            return True

    def _publish_joint_states(self, stamp) -> None:
        """One JointState for every drive of the node, as CDR bytes published raw (encoded
        under _js_lock: owner threads of several buses take turns): rclpy's message path cost
        about 100 us more per message on the owner's cold cache (joint_state_cdr.py; the
        CPU figures in docs/benchmarks.md)."""
        with self._js_lock:
            cdr, handles = self._js_cdr, self._js_handles
            if cdr is None:                      # (build() drops it)
                handles = self._js_handles = list(self.handles.values())
                cdr = self._js_cdr = JointStateCdr([h.cfg.joint_name for h in handles])
            states = [h.slot.state for h in handles]
            self.joint_pub.publish(cdr.encode(
                stamp.sec, stamp.nanosec,
                [h.conv.from_steps(s.position_steps) for h, s in zip(handles, states)],
                [h.conv.from_steps(s.velocity_steps_s) if s.velocity_valid else math.nan
                 for h, s in zip(handles, states)],
                [float(s.effort) for s in states]
                if all(s.effort is not None for s in states) else None))

    def _status_key(self, h: DriveHandle) -> tuple:
        """The status fields that make a new status worth sending (not the link counters)."""
        s = h.state
        return (s, h.slot.connected, h.slot.not_driven, h.commands_refused, h.last_refusal,
                h.sup.watchdog_armed(h.name), h.sup.bus.health())

    def _status_msg(self, h: DriveHandle, stamp, counters: dict[str, int]) -> DriveStatus:
        s = h.state
        m = DriveStatus()
        m.header.stamp = stamp
        m.drive, m.joint_name, m.vendor = h.name, h.cfg.joint_name, self.vendor.name
        m.address = str(h.drive.address)
        m.state = s.state.value
        m.connected = h.connected
        m.enabled, m.moving, m.target_reached = s.enabled, s.moving, s.target_reached
        m.homed = s.homed
        m.homing_state = s.homing.value
        m.mode = s.mode
        m.fault, m.fault_code, m.fault_text = s.fault, s.fault_code & 0xFFFFFFFF, s.fault_text
        m.alarms = list(s.alarms)
        link = h.sup.bus.health()
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
        m.watchdog_armed = h.sup.watchdog_armed(h.name)
        return m

    def publish_diagnostics(self) -> None:
        """Under _diag_lock (an owner thread)."""
        arr = DiagnosticArray()
        arr.header.stamp = self._stamp()
        for sup in self.supervisors:
            names = list(sup.slots)
            link = DiagnosticStatus(name=f'{self.get_name()}: link',
                                    hardware_id=sup.bus.description)
            if len(self.supervisors) > 1:
                link.name += f' {sup.bus.description}'
            lost = [n for n in names if not self.handles[n].connected]
            if not lost:
                link.level, link.message = DiagnosticStatus.OK, 'connected'
            elif len(lost) < len(names):
                link.level = DiagnosticStatus.WARN
                link.message = f'{", ".join(lost)} DISCONNECTED, reconnecting'
            else:
                link.level, link.message = DiagnosticStatus.ERROR, 'DISCONNECTED, reconnecting'
            health = sup.bus.health()
            if health is not None:
                level = DiagnosticStatus.ERROR if health[0] == 'error' else DiagnosticStatus.WARN
                link.message = health[1] if link.level == DiagnosticStatus.OK else \
                    f'{link.message}; {health[1]}'
                link.level = max(link.level, level)
            link.values = self._key_values(link.name, [
                *sup.bus.counters().items(),
                ('reconnects', sum(max(sup.slots[n].reconnects - 1, 0) for n in names))])
            arr.status.append(link)
        for h in self.handles.values():
            s = h.state
            d = DiagnosticStatus(name=f'{self.get_name()}: {h.name}',
                                 hardware_id=f'{self.vendor.name} {h.drive.address}')
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
                  'velocity_watchdog': 'armed' if h.sup.watchdog_armed(h.name) else 'idle',
                  **h.slot.identity}
            d.values = self._key_values(d.name, kv.items())
            arr.status.append(d)
        self.diag_pub.publish(arr)

    def _key_values(self, status: str, items) -> list[KeyValue]:
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

    # ------------------------------------------------------------------------------- commands
    def refuse(self, h: DriveHandle, why: str) -> None:
        """Count every refusal and keep its reason for the status; log the first of a run of
        refusals of one kind (the reason with its numbers masked: a controller streaming set
        points to a drive that is not enabled sends a new value each time, for one reason: a
        warning each flooded the log and /rosout, and the command thread took 2100 refused
        commands/s instead of 6700). A command that passes its checks (`_check_ready`) ends
        the run."""
        kind = _NUMBER.sub('#', why)
        with self._refusal_lock:      # the command executor and the main one both refuse
            if kind != h.refusal_logged:
                self.log.warning(f'{h.name}: command refused: {why}')
                h.refusal_logged = kind
            h.last_refusal = why      # before the count: a status published in between is whole
            h.commands_refused += 1
        raise CommandRefused(why)

    def _check_link(self, h: DriveHandle, what: str, safe: bool = False) -> None:
        """`safe`: a stop, a disable or a read, taken in every lifecycle state."""
        if not self.accepting and not safe:
            self.refuse(h, f'{what}: the node is not active (lifecycle state '
                           f'{self.lifecycle_state_label()}); activate it first')
        if h.slot.not_driven:
            self.refuse(h, f'{what}: drive is not driven: {h.slot.not_driven}')
        if not h.connected:
            self.refuse(h, f'{what}: drive is DISCONNECTED')

    def _check_ready(self, h: DriveHandle, what: str) -> None:
        self._check_link(h, what)
        if h.state.fault:
            self.refuse(h, f'{what}: drive is in FAULT 0x{h.state.fault_code:04X} '
                           f'({h.state.fault_text}); call fault_reset first')
        if not h.state.enabled:
            self.refuse(h, f'{what}: drive is not enabled (state {h.state.state.value}); '
                           'call enable first')
        h.refusal_logged = ''         # taken: the next refusal is news

    def _check_finite(self, h: DriveHandle, what: str, value: float) -> None:
        if not math.isfinite(value):
            self.refuse(h, f'{what} {value} is not a finite number')

    def _check_position(self, h: DriveHandle, what: str, position: float) -> int:
        self._check_finite(h, what, position)
        lo, hi = h.param('min_position'), h.param('max_position')
        if not lo <= position <= hi:
            self.refuse(h, f'{what} {position} is outside min_position..max_position '
                           f'({lo:g}..{hi:g})')
        steps = h.conv.to_steps(position)
        if not math.isfinite(steps) or abs(steps) >= 2 ** 63:
            self.refuse(h, f'{what} {position} is {steps:g} steps: beyond any drive position')
        self._check_ready(h, f'{what} {position}')
        return h.conv.to_steps_int(position)

    def _job_failed(self, h: DriveHandle, what: str, fut: concurrent.futures.Future) -> None:
        """Owner thread, when a queued command ended: a failure goes to the status and
        /diagnostics each time, to the log at the first of a run of one kind (as `refuse`: a
        stream of set points the drive cannot take is one error, not one per set point); one
        the drive took ends the run. Superseded and dropped ones are normal."""
        if fut.cancelled():
            return
        exc = fut.exception()
        if exc is None:
            h.job_error_logged = ''
            return
        if isinstance(exc, (Superseded, Cancelled)):
            return
        msg = f'{what}: {exc}'
        kind = _NUMBER.sub('#', msg)
        if kind != h.job_error_logged:
            self.log.error(f'{h.name}: {msg}')
            h.job_error_logged = kind
        h.slot.last_error = msg

    def command_position(self, h: DriveHandle, position: float) -> None:
        what = 'position_command'
        try:
            steps = self._check_position(h, what, position)
        except CommandRefused:
            return
        motion = h.motion()
        fut = h.sup.submit(h.name, Command.position_stream(
            lambda: h.drive.move_to(steps, motion), f'{what} {position}'), hand_over=True)
        fut.add_done_callback(lambda f: self._job_failed(h, f'{what} {position}', f))

    def command_velocity(self, h: DriveHandle, velocity: float) -> None:
        what = f'velocity_command {velocity}'
        try:
            self._check_finite(h, 'velocity_command', velocity)
            vmax = h.param('max_velocity')
            if abs(velocity) > vmax:
                self.refuse(h, f'{what} exceeds max_velocity ({vmax:g})')
            self._check_ready(h, what)
        except CommandRefused:
            return
        if velocity != 0.0:
            # armed before anything is written: a write whose reply is lost still ran
            h.sup.arm_watchdog(h.name)
        steps_s, motion = h.conv.to_steps(velocity), h.motion()
        fut = h.sup.submit(h.name, Command.velocity_stream(
            lambda: h.drive.set_velocity(steps_s, motion), what, velocity), hand_over=True)
        fut.add_done_callback(lambda f: self._job_failed(h, what, f))

    def on_joint_command(self, msg: JointState) -> None:
        n = len(msg.name)
        for field in ('position', 'velocity'):
            values = getattr(msg, field)
            if values and len(values) != n:
                # executed index by index it would send one joint's value to another
                why = (f'joint_command: {len(values)} {field} values for {n} names '
                       f'{list(msg.name)} (a non-empty array needs one value per name); '
                       'the whole message is refused')
                mine = [self.by_joint[j] for j in msg.name if j in self.by_joint]
                for h in mine:
                    try:
                        self.refuse(h, why)
                    except CommandRefused:
                        pass
                if not mine:
                    self.log.warning(why, throttle_duration_sec=5.0)
                return
        for i, joint in enumerate(msg.name):
            h = self.by_joint.get(joint)
            if h is None:
                self.log.warning(f'joint_command: unknown joint {joint!r} (this node has '
                                 f'{sorted(self.by_joint)})', throttle_duration_sec=5.0)
                continue
            if msg.position and not math.isnan(msg.position[i]):
                self.command_position(h, msg.position[i])
            elif msg.velocity and not math.isnan(msg.velocity[i]):
                self.command_velocity(h, msg.velocity[i])

    # --------------------------------------------------------------- waiting without a thread
    async def await_future(self, fut: concurrent.futures.Future,
                           timeout_s: float | None = None):
        """Await an owner-thread future in an async callback; a job still queued when
        timeout_s passes is dropped (one that started is awaited: it ends by itself)."""
        ros_fut = RosFuture(executor=self.executor)
        ros_fut.add_done_callback(lambda _f: None)    # set_result then wakes the executor
        fut.add_done_callback(lambda _f: ros_fut.set_result(None))
        if timeout_s is not None:
            self.supervisors[0].after(timeout_s, fut.cancel)
        await ros_fut
        if fut.cancelled():
            raise DriveError(f'not started within {timeout_s:g} s: the drive is busy with '
                             'earlier commands')
        return fut.result()

    async def _next_poll(self, h: DriveHandle, timeout_s: float = 2.0) -> bool:
        """Await the next snapshot of h (False: none within timeout_s, or the link is lost).
        Raises Cancelled once the node shuts down: a service or action waiting for its drive
        then answers, rather than loop on polls that will not come."""
        fut: concurrent.futures.Future = concurrent.futures.Future()
        h.sup.wait_poll(h.name, timeout_s, fut.set_result)
        fresh = await self.await_future(fut)
        if not fresh and h.sup.stopping:
            raise Cancelled('the node is shutting down')
        return fresh

    async def published(self, *handles: DriveHandle, timeout_s: float = 2.0) -> bool:
        """Await the next snapshot of each drive and its publication: /joint_states and the
        drive's status that carry it have gone out (False: no snapshot within timeout_s, or
        the link is lost). The drive is polled at once, and its snapshot published at once. A
        service or action that changed a drive answers after this, so a client that reads
        /joint_states after the answer sees the change."""
        futs = []
        for h in handles:
            fut: concurrent.futures.Future = concurrent.futures.Future()

            def polled(fresh: bool, h=h, fut=fut) -> None:   # owner thread, after h's poll
                if fresh:
                    h.publish_waiters.append(fut)
                    self.publish_states(h.sup)     # now, not at the end of the cycle
                else:
                    _settle(fut, False)
            h.sup.wait_poll(h.name, timeout_s, polled)
            h.sup.poll_soon(h.name)
            # no cycle within twice timeout_s (the bus shuts down: at once): not published
            h.sup.after(2 * timeout_s, lambda fut=fut: _settle(fut, False))
            futs.append(fut)
        published = True
        for h, fut in zip(handles, futs):
            published = await self.await_future(fut) and published
            if not published and h.sup.stopping:
                raise Cancelled('the node is shutting down')
        return published

    async def _run_job(self, h: DriveHandle, command: Command) -> Any:
        return await self.await_future(h.sup.submit(h.name, command,
                                              hand_over=command.kind == JobKind.URGENT),
                                 JOB_TIMEOUT_S)

    async def _respond(self, h: DriveHandle, resp, work, ok_message: Callable[[Any], str]):
        """Await work(); fill a success/message response; errors become success=false."""
        try:
            result = await work()
            resp.success, resp.message = True, ok_message(result)
        except (CommandRefused, RefusedError, DriveError) as e:
            resp.success, resp.message = False, f'{h.name}: {e}'
            if not isinstance(e, CommandRefused):
                self.log.warning(resp.message)
        return resp

    # ------------------------------------------------------------------------------- services
    async def srv_enable(self, h: DriveHandle, req, resp):
        async def work():
            self._check_link(h, 'enable' if req.data else 'disable', safe=not req.data)
            if req.data:
                await self._run_job(h, Command.enable(h.drive.enable))
            else:
                await self._run_job(h, Command.disable(h.drive.disable))
            await self.published(h)
            return h.state.state.value
        return await self._respond(h, resp, work, lambda st: f'{h.name}: {st}')

    async def srv_stop(self, h: DriveHandle, req, resp):
        async def work():
            self._check_link(h, 'stop', safe=True)
            await self._run_job(h, Command.stop(h.drive.stop))
            await self.published(h)
        return await self._respond(h, resp, work,
                                   lambda _: f'{h.name}: stopping with the profile deceleration')

    async def run_homing(self, h: DriveHandle, feedback: Callable[[], None] | None = None,
                         cancelled: Callable[[], bool] = lambda: False) -> str:
        self._check_link(h, 'home')
        if h.state.fault:
            self.refuse(h, f'home: drive is in FAULT 0x{h.state.fault_code:04X} '
                           f'({h.state.fault_text}); call fault_reset first')
        homing = h.homing()
        note = await self._run_job(h, Command.homing(lambda: h.drive.start_homing(homing)))
        timeout_s = h.param('homing.timeout_s')
        deadline = self.get_clock().now().nanoseconds * 1e-9 + timeout_s
        fresh = await self._next_poll(h)
        idle_polls = 0         # snapshots in a row that say no homing runs (after its start)
        while True:
            st = h.state.homing
            if st == HomingState.ATTAINED:
                await self.published(h)
                return (f'{h.name}: homed at {h.position:.6g} ({h.state.position_steps} steps)'
                        + (f'; {note}' if note else ''))
            if st == HomingState.ERROR or h.state.fault:
                raise DriveError(f'homing failed (state {h.state.state.value}'
                                 + (f', fault 0x{h.state.fault_code:04X} {h.state.fault_text}'
                                    if h.state.fault else '')
                                 + (f', alarms: {"; ".join(h.state.alarms)}'
                                    if h.state.alarms else '') + ')')
            if not h.connected:
                raise DriveError('homing interrupted: link lost')
            if cancelled():
                await self._stop_quietly(h, 'homing cancelled')
                raise DriveError('homing cancelled; drive stopped')
            # The homing ended without a result: a stop (CiA 402 Halt: "interrupted"), a
            # disable or another mode. Each vendor's start_homing returns once it runs, so
            # IDLE now is no late start; SETTLED_POLLS fresh snapshots decide, as for move_to.
            if st != HomingState.IDLE:
                idle_polls = 0
            elif fresh:
                idle_polls += 1
            if idle_polls >= SETTLED_POLLS:
                raise DriveError(f'homing interrupted before it ended (state '
                                 f'{h.state.state.value}, mode {h.state.mode}): a stop, a '
                                 'disable or a mode change; not homed')
            if self.get_clock().now().nanoseconds * 1e-9 > deadline:
                await self._stop_quietly(h, 'homing timeout')
                raise DriveError(f'homing timed out after {timeout_s:g} s (homing.timeout_s); '
                                 'drive stopped')
            if feedback:
                feedback()
            fresh = await self._next_poll(h, 1.0)

    async def _stop_quietly(self, h: DriveHandle, why: str) -> None:
        try:
            await self._run_job(h, Command.stop(h.drive.stop, f'stop ({why})'))
        except DriveError as e:
            self.log.error(f'{h.name}: stop ({why}) failed: {e}')

    async def srv_home(self, h: DriveHandle, req, resp):
        return await self._respond(h, resp, lambda: self.run_homing(h), lambda msg: msg)

    async def srv_fault_reset(self, h: DriveHandle, req, resp):
        async def work():
            if h.slot.identity_recheck:
                # not driven for its identity: checked again now (a connect, nothing moves)
                try:
                    await self.await_future(h.sup.recheck(h.name))
                except Cancelled:
                    raise
                except DriveError as e:
                    if h.slot.not_driven:
                        raise DriveError(f'still not driven: {h.slot.not_driven}') from None
                    raise DriveError(f'checked again: {e}; DISCONNECTED, reconnecting') from None
                await self.published(h)
                return f'the identity matches again: driven, state {h.state.state.value}'
            self._check_link(h, 'fault_reset')
            remaining = await self._run_job(h, Command.fault_reset(h.drive.fault_reset))
            await self.published(h)
            if remaining:
                raise DriveError(f'fault remains: {remaining}')
            return f'fault cleared, state {h.state.state.value}'
        return await self._respond(h, resp, work, lambda text: f'{h.name}: {text}')

    async def srv_save_params(self, h: DriveHandle, req, resp):
        async def work():
            self._check_link(h, 'save_params')
            return await self._run_job(h, Command.maintenance(h.drive.save_params,
                                                              'save_params'))
        return await self._respond(h, resp, work, lambda note: f'{h.name}: parameters saved'
                                   + (f'; {note}' if note else ''))

    async def srv_read_register(self, h: DriveHandle, req, resp):
        resp.value, resp.text = 0, ''

        async def work():
            self._check_link(h, 'read_register', safe=True)
            value = await self._run_job(h, Command.maintenance(
                lambda: h.drive.read_register(req.address, req.data_type),
                f'read_register {req.address}'))
            if isinstance(value, str):
                resp.text = value
            else:
                resp.value = int(value)
            return value
        return await self._respond(h, resp, work,
                                   lambda v: f'{req.address} ({req.data_type}) = {v}')

    async def srv_write_register(self, h: DriveHandle, req, resp):
        value = req.text if req.data_type.lower() == 'string' else req.value

        async def work():
            if not h.param('allow_raw_write'):
                self.refuse(h, f'write_register {req.address}: raw writes are disabled '
                               f'(set drives.{h.name}.allow_raw_write: true)')
            self._check_link(h, 'write_register')
            await self._run_job(h, Command.raw_write(
                lambda: h.drive.write_register(req.address, req.data_type, value),
                f'write_register {req.address}'))
        return await self._respond(h, resp, work,
                                   lambda _: f'{req.address} ({req.data_type}) := {value}')

    # -------------------------------------------------------------------------------- actions
    async def act_move_to(self, h: DriveHandle, goal_handle):
        result = MoveTo.Result()
        target = goal_handle.request.position
        try:
            steps = self._check_position(h, 'move_to', target)
            motion = h.motion()
            await self._run_job(h, Command.move(lambda: h.drive.move_to(steps, motion),
                                                f'move_to {target}'))
            fb = MoveTo.Feedback()
            settled, last = 0, None
            await self._next_poll(h)
            while True:
                fresh = await self._next_poll(h, 1.0)
                if not fresh and not h.connected:
                    raise DriveError('move aborted: link lost')
                s = h.state
                if s.fault:
                    raise DriveError(f'move aborted: state {s.state.value} {s.fault_text}'.strip())
                if goal_handle.is_cancel_requested:
                    await self._stop_quietly(h, 'move_to cancelled')
                    goal_handle.canceled()
                    result.message, result.final_position = 'cancelled; drive stopped', h.position
                    return result
                # decided on SETTLED_POLLS snapshots in a row that agree: standstill at one
                # position (one snapshot may mix an old position with a new status)
                still = not s.moving and (s.target_reached or abs(
                    s.position_steps - steps) <= TARGET_TOLERANCE_STEPS)
                if fresh:     # a snapshot counts once
                    settled = settled + 1 if still and last == s.position_steps else int(still)
                    last = s.position_steps
                if settled >= SETTLED_POLLS:
                    if abs(s.position_steps - steps) <= TARGET_TOLERANCE_STEPS:
                        break
                    raise DriveError(f'drive stopped at {h.position:.6g}, not at {target:.6g}')
                fb.position, fb.state = h.position, s.state.value
                fb.distance_remaining = target - h.position
                goal_handle.publish_feedback(fb)
            await self.published(h)
            goal_handle.succeed()
            result.success, result.message = True, f'{h.name}: at {h.position:.6g}'
        except (CommandRefused, DriveError) as e:
            goal_handle.abort()
            result.success, result.message = False, f'{h.name}: {e}'
        result.final_position = h.position
        return result

    async def act_home(self, h: DriveHandle, goal_handle):
        result = Home.Result()
        fb = Home.Feedback()

        def feedback():
            fb.homing_state, fb.position = h.state.homing.value, h.position
            goal_handle.publish_feedback(fb)
        try:
            result.message = await self.run_homing(
                h, feedback, lambda: goal_handle.is_cancel_requested)
            result.success = True
            goal_handle.succeed()
        except (CommandRefused, DriveError) as e:
            result.success, result.message = False, f'{h.name}: {e}'
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
            else:
                goal_handle.abort()
        result.final_position = h.position
        return result

    # ----------------------------------------------------------------------------- parameters
    def on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Refuse a run-time change that breaks a rule: the start-up rules (self.cfg.validate,
        pure: no drive or bus is built) on the current values with the changes applied. rclpy
        has checked ranges and read-only already."""
        values = current_values(self)
        values.update((p.name, p.value) for p in params)
        errors = self.cfg.validate(values)
        return SetParametersResult(successful=not errors, reason=errors[0] if errors else '')

    def after_set_parameters(self, params: list[Parameter]) -> None:
        for p in params:
            if p.name in ('publish_rate_hz', 'command_timeout_s', 'status_rate_hz'):
                self.bus_params[p.name] = p.value     # the supervisors read it live
            self.log.info(f'parameter {p.name} := {p.value}')

    # ------------------------------------------------------------------------------- shutdown
    @contextlib.contextmanager
    def handling(self):
        """Around a service or action callback (executor thread): counted, so that the
        shutdown lets it answer before the executor ends (`wait_handlers`)."""
        with self._handlers_cv:
            self._handlers += 1
        try:
            yield
        finally:
            with self._handlers_cv:
                self._handlers -= 1
                self._handlers_cv.notify_all()

    def wait_handlers(self, timeout_s: float) -> bool:
        """After shutdown_drives (the process's main thread): wait until every service and
        action callback has its answer, which the drives' shutdown gave them (the node is
        shutting down); False if some did not within timeout_s. Without this, a client such as
        `ros2 service call .../home` waited for ever on a node that had ended."""
        with self._handlers_cv:
            return self._handlers_cv.wait_for(lambda: self._handlers == 0, timeout_s)

    def shutdown_drives(self) -> None:
        """Stop motion, disable where disable_on_shutdown, close the links. No ROS needed."""
        trajectories = getattr(self, 'trajectories', None)     # (built with the interfaces)
        if trajectories is not None:     # a goal that awaits its run ends with it
            trajectories.follower.stop('the node is shutting down')

        def run(sup: BusSupervisor) -> None:
            disable = [n for n in sup.slots if self.handles[n].param('disable_on_shutdown')]
            sup.shutdown(SHUTDOWN_STOP_TIMEOUT_S, disable)
        threads = [threading.Thread(target=run, args=(sup,)) for sup in self.supervisors]
        for t in threads:                  # every bus stops at once
            t.start()
        for t in threads:
            t.join()


def _settle(fut: concurrent.futures.Future, value: Any) -> None:
    """Resolve fut with value unless it is resolved already (a timer and the owner may race)."""
    try:
        if not fut.done():
            fut.set_result(value)
    except concurrent.futures.InvalidStateError:
        pass


def _spin_commands(executor) -> None:
    from rclpy.executors import ExternalShutdownException, ShutdownException
    try:
        executor.spin()
    except (ExternalShutdownException, ShutdownException):
        pass                          # the process is ending: spin_node stops the drives
