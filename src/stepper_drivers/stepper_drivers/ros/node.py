"""DriveNode: the one ROS layer every vendor node shares (docs/interface.md): a thin adapter.

Each bus has one owner thread (`owner.BusOwner`, no rclpy) that makes every call into
the vendor code: polls, commands, reconnects, the velocity watchdog and shutdown; a node with
several links that poll without blocking (X-PLUS MT hosts) lends their idle periodic polls to one
thread (`poll_group.PollGroup`). This module only turns ROS into jobs and snapshots into ROS:
- Command subscriptions check a command against the limits and the latest snapshot and enqueue
  it; they never wait. They belong to a hidden companion node (`_<node>_commands`, the pattern of
  tf2_ros's TransformListener) served by an executor thread of its own, whose wait set holds
  nothing else: a command is not delayed by rclpy scanning the node's ~80 services, actions and
  event handlers, nor by a service callback (the command-to-wire goal). One thread serves
  them, so the messages of one topic are handled in the order they arrived.
- Services and actions are async callbacks: they enqueue a job and `await` its result (and then
  the polls they need) without holding an executor thread, so one SingleThreadedExecutor serves
  the node and a stop is never queued behind a homing (node_services.DriveServices).
- The owner threads (or the poll group) publish joint_states and status after each poll cycle
  of their bus, and /diagnostics when it is due: the executor has no timer and sleeps until a
  command comes (node_publishing.StatePublisher).
- process.py runs the node: signals, the executor thread, the order of shutdown.

DriveNode is one rclpy Node. This module holds its construction, parameters, command topics and
their checks, the bus_owners' callbacks, the awaiting of owner-thread futures and the shutdown.
The services and actions, the publishing and the trajectory interface are objects of their own
(node_services, node_publishing, node_trajectory), each created by the node and given it; they
use only its public members (DriveNode's docstring lists which).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import math
import re
import threading
import time
from typing import Any, Callable

from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future as RosFuture
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

from ..contract.drive import Drive, DriveError, DriveState, Homing, Motion, Vendor
from ..owner import BusOwner, Cancelled, Slot, Superseded
from ..owner.commands import Command, CommandRefused
from ..owner.poll_group import PollGroup
from .params import BusConfig, DriveConfig, ParameterError, current_values
from .publishing import StatePublisher, settle
from .services import DriveServices
from .trajectory_interface import TrajectoryInterface

# On shutdown, how long a controlled stop may take before the power stage is disabled anyway.
SHUTDOWN_STOP_TIMEOUT_S = 5.0


# Command topics keep every sample (reliable, KEEP_ALL): a KEEP_LAST reader history fed by
# several writers at once can drop a publisher's last samples (eProsima/Fast-DDS#708), and a
# final 0.0 lost leaves an axis running. Every sample reaches the callback in each publisher's
# order; the bus owner's queue drops stream commands that a newer one replaces before they go.
COMMAND_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)


# A streamed command is judged by its age: the DDS source timestamp of its sample (the
# publisher's system clock when it published; every sample carries it, rclpy hands it to a
# callback that takes a second argument, MessageInfo) against this host's system clock. A sample
# can reach the node seconds after it was published: a node stalled by the machine reads its
# socket's backlog when it resumes, and a reliable writer resends a sample it was not
# acknowledged for after its next heartbeat.
SOURCE_TIMESTAMP = 'source_timestamp'


def sample_age_s(info: dict | None) -> float | None:
    """How long ago the sample was published [s] (negative: the publisher's clock is ahead of
    this one's); None where the middleware gives no source timestamp."""
    stamp_ns = (info or {}).get(SOURCE_TIMESTAMP) or 0
    if stamp_ns <= 0:
        return None
    return (time.time_ns() - stamp_ns) * 1e-9


# A number in a refusal's reason (the command's value, a limit, a code), masked to tell its kind.
_NUMBER = re.compile(r'[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|\b(?:nan|inf)\b')


class DriveHandle:
    """The ROS side of one drive: its configuration, conversion, refusal counters, and the
    owner-side slot (snapshot, link state) of its bus bus owner."""

    def __init__(self, node: 'DriveNode', cfg: DriveConfig, drive: Drive):
        self.node = node
        self.cfg = cfg
        self.name = cfg.name
        self.drive = drive
        self.conv = cfg.conversion
        self._sup: BusOwner | None = None   # set when the buses are built
        self.slot: Slot | None = None            # its slot in that bus owner (with it)
        self.commands_refused = 0
        self.last_refusal = ''
        self.refusal_logged = ''           # the kind of refusal logged last (see refuse)
        self.job_error_logged = ''         # the kind of failed command logged last (owner)
        self.status_key: tuple = ()        # what the last published status said (owner thread)
        self.status_due = 0.0              # time.monotonic() of the next status regardless
        # callers awaiting the publication of a snapshot newer than a change (owner thread)
        self.publish_waiters: list[concurrent.futures.Future] = []
        # (steps, slot, slot.submitted, slot.reconnects) of the last target the drive confirmed
        # (set by the owner thread in one assignment, read by the command thread): see _holds
        self.held_target: tuple | None = None
        # (that tuple, the job's future) of the last position job submitted (command thread)
        self.pending_target: tuple | None = None
        self.stream_t = -math.inf          # time.monotonic() of the last joint_command position

    @property
    def bus_owner(self) -> BusOwner | None:
        return self._sup

    @bus_owner.setter
    def bus_owner(self, bus_owner: BusOwner | None) -> None:
        self._sup = bus_owner
        self.slot = None if bus_owner is None else bus_owner.slots[self.name]

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

    What its parts use of it, besides the rclpy Node API:
    - node_trajectory.TrajectoryInterface: `by_joint`, `accepting`, `lifecycle_state_label()`,
      `handling()`, `await_future()`, `published()`, `bus_owners`, `log`, `command_qos`,
      `cmd_group`, `srv_group`.
    - node_services.DriveServices: `refuse()`, `check_link()`, `check_position()`,
      `await_future()`, `published()`, `handling()`, `srv_group`, `log`.
    - node_publishing.StatePublisher: `handles`, `bus_owners`, `bus_params`, `vendor`,
      `managed` (a lifecycle publisher then)."""

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
        self.bus_owners: list[BusOwner] = []
        self.poll_group: PollGroup | None = None
        self.by_joint: dict[str, DriveHandle] = {}
        self._interfaces = False
        self._identities: dict[tuple[str, str], str] = {}    # (key, value) -> drive
        self._identity_lock = threading.Lock()
        # what the owner threads publish (its publishers come with the interfaces)
        self.publishing = StatePublisher(self)
        self._refusal_lock = threading.Lock()  # commands and services both count refusals
        self._foreign_joints: set[str] = set()   # joint_command names told (command thread)
        self.refusals = 0                      # of every drive (under _refusal_lock)
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
        self.bus_owners = []
        self._build_buses()
        self.publishing.drives_rebuilt()
        self.by_joint = {h.cfg.joint_name: h for h in self.handles.values()}
        if not self._interfaces:
            self._make_interfaces()
            self._interfaces = True
        for bus_owner in self.bus_owners:
            names = [n for n in self.handles if self.handles[n].bus_owner is bus_owner]
            self.log.info(f'{self.vendor.name} node on {bus_owner.bus.description}: drives '
                          + ', '.join(f'{n} ({self.handles[n].cfg.joint_name})' for n in names))

    def _make_interfaces(self) -> None:
        self.cmd_group = MutuallyExclusiveCallbackGroup()    # ordered, never waits
        self.srv_group = ReentrantCallbackGroup()            # async: awaits, holds no thread
        self.publishing.create_publishers()
        self._command_subscription(JointState, 'joint_command', self.on_joint_command)
        self.drive_services = DriveServices(self)
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
            bus_owner = BusOwner(
                bus, drives, self.bus_params, on_cycle=self.publishing.publish_states,
                on_connected=self._on_connected, on_event=self._on_event,
                # managed: enabled at on_activate, not when the bus is configured
                auto_enable=[] if self.managed else
                [d.name for d in dcfgs if d.params.get('auto_enable')],
                name=bus.description or 'bus', on_failure=self._owner_failed)
            for name in drives:
                self.handles[name].bus_owner = bus_owner
            self.bus_owners.append(bus_owner)
        # several links that can poll without blocking (X-PLUS MT hosts): one thread polls
        # the idle ones (poll_group.py)
        self.poll_group = None
        if len(self.bus_owners) > 1 and all(s.bus.nonblocking_polls for s in self.bus_owners):
            self.poll_group = PollGroup(self.bus_owners, on_event=self._on_event)

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
        self.publishing.add_drive(h, ns)
        # two arguments: rclpy passes the sample's MessageInfo (its source timestamp)
        self._command_subscription(
            Float64, ns + 'position_command',
            lambda m, info, h=h: self.command_position(h, m.data, sample_age_s(info)))
        self._command_subscription(
            Float64, ns + 'velocity_command',
            lambda m, info, h=h: self.command_velocity(h, m.data, sample_age_s(info)))
        self.drive_services.add_drive(h, ns)

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

    def _owner_failed(self, bus_owner: BusOwner, why: str) -> None:
        """Owner thread of `bus_owner`, which ends: its drives are stopped, its bus closed. Their
        statuses say DISCONNECTED with the reason, and the node ends (exit code 1), stopping
        the drives of its other buses: a node that no longer polls or watches some of its
        drives must not go on looking alive (a launch file's respawn restarts it)."""
        try:
            self.publishing.publish_states(bus_owner)
        finally:
            self.on_fatal(f'{bus_owner.name}: {why}')

    def _on_connected(self, bus_owner: BusOwner, slot: Slot) -> str:
        """Owner thread, a drive connected: its identity checked, then what its bus must check
        before it starts drives together (Bus.group_start_check: the X-MIND K line probe of
        broadcast_start), queued once as a MAINTENANCE job of this drive; its result is logged.
        Until it ran, group starts fall back to per-drive starts."""
        why = self._check_identity(bus_owner, slot)
        check = None if why else bus_owner.bus.group_start_check()
        if check is not None:
            def probed(fut: concurrent.futures.Future, name: str = slot.name) -> None:
                exc = fut.exception()
                self._on_event('warning' if exc is not None else 'info', name,
                               f'line probe failed, no group starts: {exc}' if exc is not None
                               else fut.result())
            self._on_event('info', slot.name, 'line probe for drives of no node '
                           '(broadcast_start) queued')
            bus_owner.submit(slot.name, Command.maintenance(check, 'line probe')) \
                .add_done_callback(probed)
        return why

    def _check_identity(self, bus_owner: BusOwner, slot: Slot) -> str:
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
        self.handles[other].bus_owner.refuse_drive(other, why)
        return why

    def _address_params(self) -> list[str]:
        names = [s.name for s in self.vendor.params if s.scope == 'drive'
                 and s.name in ('unit_id', 'node_id', 'address', 'host', 'port', 'slave_id')]
        return [f'drives.<name>.{n}' for n in names] or ['the drive addresses']

    # ------------------------------------------------------------------------------ polling
    def lifecycle_state_label(self) -> str:
        return 'active'

    def start(self) -> None:
        for bus_owner in self.bus_owners:
            bus_owner.start()
        if self.poll_group is not None:
            self.poll_group.start()

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
            self.refusals += 1        # after: StatePublisher.publish_states reads it first
        raise CommandRefused(why)

    def check_link(self, h: DriveHandle, what: str, safe: bool = False) -> None:
        """`safe`: a stop, a disable or a read, taken in every lifecycle state."""
        if not self.accepting and not safe:
            self.refuse(h, f'{what}: the node is not active (lifecycle state '
                           f'{self.lifecycle_state_label()}); activate it first')
        if h.slot.not_driven:
            self.refuse(h, f'{what}: drive is not driven: {h.slot.not_driven}')
        if not h.connected:
            self.refuse(h, f'{what}: drive is DISCONNECTED')

    def _check_ready(self, h: DriveHandle, what: str, taken: bool = True) -> None:
        """`taken`: the command passed its last check here, which ends a run of refusals
        (False: a check follows, which ends it itself)."""
        self.check_link(h, what)
        if h.state.fault:
            self.refuse(h, f'{what}: drive is in FAULT 0x{h.state.fault_code:04X} '
                           f'({h.state.fault_text}); call fault_reset first')
        if not h.state.enabled:
            self.refuse(h, f'{what}: drive is not enabled (state {h.state.state.value}); '
                           'call enable first')
        if taken:
            h.refusal_logged = ''     # taken: the next refusal is news

    def _check_finite(self, h: DriveHandle, what: str, value: float) -> None:
        if not math.isfinite(value):
            self.refuse(h, f'{what} {value} is not a finite number')

    def _check_age(self, h: DriveHandle, what: str, age_s: float | None, bound_s: float,
                   parameter: str) -> None:
        """Refuse a streamed command published more than bound_s before it arrived, or
        stamped more than bound_s ahead of this host's clock (the two clocks disagree, so its
        age cannot be told). No age (no source timestamp): taken."""
        if age_s is None or bound_s <= 0.0:
            return
        if age_s > bound_s:
            self.refuse(h, f'{what} was published {age_s:.3f} s before it arrived, more than '
                           f'{parameter} ({bound_s:g} s): a stale command, not sent')
        if age_s < -bound_s:
            self.refuse(h, f'{what} is stamped {-age_s:.3f} s ahead of the clock of this host, '
                           f'more than {parameter} ({bound_s:g} s): its age cannot be told; '
                           'synchronise the clocks of the hosts (chrony, PTP)')

    def check_position(self, h: DriveHandle, what: str, position: float,
                       taken: bool = True) -> int:
        self._check_finite(h, what, position)
        lo, hi = h.param('min_position'), h.param('max_position')
        if not lo <= position <= hi:
            self.refuse(h, f'{what} {position} is outside min_position..max_position '
                           f'({lo:g}..{hi:g})')
        steps = h.conv.to_steps(position)
        if not math.isfinite(steps) or abs(steps) >= 2 ** 63:
            self.refuse(h, f'{what} {position} is {steps:g} steps: beyond any drive position')
        self._check_ready(h, f'{what} {position}', taken)
        return h.conv.to_steps_int(position)

    def _job_failed(self, h: DriveHandle, what: str, fut: concurrent.futures.Future) -> None:
        """When a queued command ended (the owner thread; the submitting one when it ended
        before its callback was added, or was refused at once): a failure goes to the status and
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
        h.bus_owner.report_error(h.name, msg)

    def command_position(self, h: DriveHandle, position: float,
                         age_s: float | None = None, stream: bool = False) -> None:
        """A position_command, or with `stream` a joint_command position, published age_s
        ago. A target the drive already took, with no job for the drive since and its snapshot
        moving or standing there, is not sent again: a ros2_control hold streams one target
        100 times a second. A stream's first position must be near the joint (`_check_start`)."""
        what = 'joint_command position' if stream else 'position_command'
        try:
            self._check_age(h, f'{what} {position}', age_s,
                            self.bus_params['position_command_max_age_s'],
                            'position_command_max_age_s')
            steps = self.check_position(h, what, position, taken=not stream)
            if stream:
                self._check_start(h, what, position)
                h.refusal_logged = ''     # taken: the next refusal is news
        except CommandRefused:
            return
        if stream:
            h.stream_t = time.monotonic()
        if self._holds(h, steps):
            return
        motion = h.motion()
        fut = h.bus_owner.submit(h.name, Command.position_stream(
            lambda: h.drive.move_to(steps, motion), f'{what} {position}'), hand_over=True)
        target = (steps, h.slot, getattr(fut, 'submitted', None), h.slot.reconnects)
        h.pending_target = (target, fut)
        fut.add_done_callback(lambda f: self._position_done(h, f'{what} {position}', f, target))

    def _check_start(self, h: DriveHandle, what: str, position: float) -> None:
        """A joint_command position that starts a stream (none for command_timeout_s) must be
        within joint_command_max_start_offset of where the joint stands: ros2_control's older
        topic plugin sends 0.0 (or the URDF's initial_value) before a controller writes."""
        if time.monotonic() - h.stream_t <= self.bus_params['command_timeout_s']:
            return
        bound = h.param('joint_command_max_start_offset')
        actual = h.position
        if abs(position - actual) > bound:
            self.refuse(h, f'{what} {position:g} for joint {h.cfg.joint_name!r} starts a stream '
                           f'{abs(position - actual):g} from where the joint stands ({actual:g}), '
                           f'more than drives.{h.name}.joint_command_max_start_offset '
                           f'({bound:g}): not sent; command the joint from where it stands')

    def _holds(self, h: DriveHandle, steps: int) -> bool:
        """Sending `steps` again would change nothing: nothing was submitted for the drive
        since the last job that sent this very target, the drive did not reconnect since, and
        that job is still on its way (queued or running: it carries the target), or the drive
        confirmed it and its snapshot shows it moving or standing on it. A set point stream
        faster than a move's transactions (100 Hz on a serial line) thus sends a held target
        once, not once per message."""
        slot = h.slot
        now = (steps, slot, slot.submitted, slot.reconnects)
        pending = h.pending_target
        if pending is not None and pending[0] == now and not pending[1].done():
            return True
        if h.held_target != now:
            return False
        state = slot.state
        return state.moving or abs(state.position_steps - steps) <= 1

    def _position_done(self, h: DriveHandle, what: str, fut: concurrent.futures.Future,
                       target: tuple) -> None:
        """(Owner thread) a position job ended: a confirmed one is the held target (_holds);
        any other outcome forgets it."""
        ok = not fut.cancelled() and fut.exception() is None
        h.held_target = target if ok and target[2] is not None else None
        self._job_failed(h, what, fut)

    def command_velocity(self, h: DriveHandle, velocity: float,
                         age_s: float | None = None) -> None:
        """A velocity_command (or a joint_command velocity) published age_s ago. One older
        than command_timeout_s is refused: the watchdog would have stopped the drive by then,
        and taking it would start the drive again after that stop. A velocity 0 is taken at
        any age: it moves nothing."""
        what = f'velocity_command {velocity}'
        try:
            if velocity != 0.0:
                self._check_age(h, what, age_s, self.bus_params['command_timeout_s'],
                                'command_timeout_s')
            self._check_finite(h, 'velocity_command', velocity)
            vmax = h.param('max_velocity')
            if abs(velocity) > vmax:
                self.refuse(h, f'{what} exceeds max_velocity ({vmax:g})')
            self._check_ready(h, what)
        except CommandRefused:
            return
        if velocity != 0.0:
            # armed before anything is written: a write whose reply is lost still ran
            h.bus_owner.arm_watchdog(h.name)
        steps_s, motion = h.conv.to_steps(velocity), h.motion()
        fut = h.bus_owner.submit(h.name, Command.velocity_stream(
            lambda: h.drive.set_velocity(steps_s, motion), what, velocity), hand_over=True)
        fut.add_done_callback(lambda f: self._job_failed(h, what, f))

    def on_joint_command(self, msg: JointState, info: dict) -> None:
        """`info`: the sample's MessageInfo (rclpy passes it to a two-argument callback)."""
        age_s = sample_age_s(info)
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
                self._unknown_joint(joint)
                continue
            # NaN: no command for this joint (a ros2_control controller that has not written)
            if msg.position and not math.isnan(msg.position[i]):
                self.command_position(h, msg.position[i], age_s, stream=True)
            elif msg.velocity and not math.isnan(msg.velocity[i]):
                self.command_velocity(h, msg.velocity[i], age_s)

    def _unknown_joint(self, joint: str) -> None:
        """A joint_command name this node does not have. joint_command_shared (a ros2_control
        block for several nodes names all their joints): told once for each name; otherwise a
        mistake, warned every 5 s."""
        if not self.bus_params['joint_command_shared']:
            self.log.warning(f'joint_command: unknown joint {joint!r} (this node has '
                             f'{sorted(self.by_joint)})', throttle_duration_sec=5.0)
        elif joint not in self._foreign_joints:
            self._foreign_joints.add(joint)
            self.log.info(f"joint_command: joint {joint!r} is not one of this node's "
                          f'{sorted(self.by_joint)}: ignored (joint_command_shared)')

    # --------------------------------------------------------------- waiting without a thread
    async def await_future(self, fut: concurrent.futures.Future, *,
                           bus_owner: BusOwner | None = None, timeout_s: float | None = None):
        """Await an owner-thread future in an async callback. With timeout_s, `fut` is a job's
        of `bus_owner` (the bus of the job's drive, whose owner runs the time-out's timer): a job
        still queued when timeout_s passes is dropped, and this raises; one that started
        cannot be cancelled and is awaited to its end (its future gets its result). The timer
        is removed once the future ended."""
        ros_fut = RosFuture(executor=self.executor)
        ros_fut.add_done_callback(lambda _f: None)    # set_result then wakes the executor
        fut.add_done_callback(lambda _f: ros_fut.set_result(None))
        if timeout_s is not None:
            if bus_owner is None:
                raise ValueError('await_future: timeout_s without the bus owner of the job')
            remove_timer = bus_owner.after(timeout_s, fut.cancel)
            fut.add_done_callback(lambda _f: remove_timer())
        await ros_fut
        if fut.cancelled():
            raise DriveError(f'not started within {timeout_s:g} s: the drive is busy with '
                             'earlier commands')
        return fut.result()

    async def published(self, *handles: DriveHandle, timeout_s: float = 2.0,
                        after: int | None = None) -> bool:
        """Await the next snapshot of each drive that followed its writes, and its publication:
        /joint_states and the drive's status that carry it have gone out (False: no such
        snapshot within timeout_s, or the link is lost). `after`: the least write count of
        that snapshot (DriveState.after_write; a job's future has the count at its end); None:
        every write to the drive so far. The drive is polled at once, and its snapshot
        published at once. A service or action that changed a drive answers after this, so a
        client that reads /joint_states after the answer sees the change, never a snapshot
        whose read went out before it."""
        futs = []
        for h in handles:
            fut: concurrent.futures.Future = concurrent.futures.Future()

            def polled(fresh: bool, h=h, fut=fut) -> None:   # owner thread, after h's poll
                if fresh:
                    h.publish_waiters.append(fut)
                    # now, not at the end of the cycle
                    self.publishing.publish_states(h.bus_owner)
                else:
                    settle(fut, False)
            h.bus_owner.wait_poll(h.name, timeout_s, polled, after_write=after)
            h.bus_owner.poll_soon(h.name)
            # no cycle within twice timeout_s (the bus shuts down: at once): not published
            remove_timer = h.bus_owner.after(2 * timeout_s, lambda fut=fut: settle(fut, False))
            fut.add_done_callback(lambda _f, remove_timer=remove_timer: remove_timer())
            futs.append(fut)
        published = True
        for h, fut in zip(handles, futs):
            published = await self.await_future(fut) and published
            if not published and h.bus_owner.stopping:
                raise Cancelled('the node is shutting down')
        return published

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
            if p.name in ('publish_rate_hz', 'command_timeout_s', 'status_rate_hz',
                          'position_command_max_age_s', 'joint_command_shared'):
                self.bus_params[p.name] = p.value     # the bus_owners read it live
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

        def run(bus_owner: BusOwner) -> None:
            disable = [n for n in bus_owner.slots if self.handles[n].param('disable_on_shutdown')]
            bus_owner.shutdown(SHUTDOWN_STOP_TIMEOUT_S, disable)
        threads = [threading.Thread(target=run,
                                    args=(bus_owner,)) for bus_owner in self.bus_owners]
        for t in threads:                  # every bus stops at once
            t.start()
        for t in threads:
            t.join()


def _spin_commands(executor) -> None:
    from rclpy.executors import ExternalShutdownException, ShutdownException
    try:
        executor.spin()
    except (ExternalShutdownException, ShutdownException):
        pass                          # the process is ending: spin_node stops the drives
