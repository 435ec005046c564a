"""DriveNode: the one ROS layer every vendor node shares (docs/interface.md): a thin adapter.

Each bus has one owner thread (`owner.BusOwner`, no rclpy) that makes every call into
the vendor code: polls, commands, reconnects, the velocity watchdog and shutdown; a node with
several links that poll without blocking (X-PLUS MT hosts) lends their idle periodic polls to one
thread (`owner.poll_group.PollGroup`). This module only turns ROS into jobs and snapshots into ROS:
- Command subscriptions check a command against the limits and the latest snapshot and enqueue
  it; they never wait. They belong to a hidden companion node (`_<node>_commands`, the pattern of
  tf2_ros's TransformListener) served by an executor thread of its own, whose wait set holds
  nothing else: a command is not delayed by rclpy scanning the node's ~80 services, actions and
  event handlers, nor by a service callback (the command-to-wire goal). One thread serves
  them, so the messages of one topic are handled in the order they arrived
  (command_topics.CommandTopics, with the rules of a streamed command).
- Services and actions are async callbacks: they enqueue a job and `await` its result (and then
  the polls they need) without holding an executor thread, so one SingleThreadedExecutor serves
  the node and a stop is never queued behind a homing (services.DriveServices).
- The owner threads (or the poll group) publish joint_states and status after each poll cycle
  of their bus, and /diagnostics when it is due: the executor has no timer and sleeps until a
  command comes (publishing.StatePublisher).
- process.py runs the node: signals, the executor thread, the order of shutdown.

DriveNode is one rclpy Node. This module holds its construction, parameters, buses, the checks
that commands and services share (`refuse`, `check_link`, `check_ready`, `check_position`), the
bus_owners' callbacks, the awaiting of owner-thread futures and the shutdown. The command topics,
the services and actions, the publishing and the trajectory interface are objects of their own
(command_topics.py, services.py, publishing.py, trajectory_interface.py), each created by the
node and given it; each names what it uses of the node in a Protocol of its own (CommandHost,
ServiceHost, PublishingHost, TrajectoryHost) and imports nothing of this module, so every import
points one way. The drive handles they share are handle.py's.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import math
import threading
from typing import Any, Callable

from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.task import Future as RosFuture

from ..contract.capabilities import GroupStarting, NonblockingPolls
from ..contract.drive import DriveError, Vendor
from ..owner import BusOwner, Cancelled, Slot
from ..owner.commands import Command, CommandRefused
from ..owner.poll_group import PollGroup
from .command_topics import COMMAND_QOS, CommandTopics, message_kind
from .handle import DriveHandle
from .params import BusConfig, DriveConfig, ParameterError, current_values
from .publishing import StatePublisher, settle
from .services import DriveServices
from .trajectory_interface import TrajectoryInterface

# On shutdown, how long a controlled stop may take before the power stage is disabled anyway.
SHUTDOWN_STOP_TIMEOUT_S = 5.0


class DriveNode(Node):
    """The plain node: built, connected and publishing from the start. With `managed` (the
    lifecycle variant, lifecycle_node.py) the buses and interfaces wait for on_configure.

    What its parts use of it: command_topics.CommandHost, services.ServiceHost,
    publishing.PublishingHost, trajectory_interface.TrajectoryHost."""

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
        self.refusals = 0                      # of every drive (under _refusal_lock)
        self._handlers = 0                     # service and action callbacks running (handling)
        self._handlers_cv = threading.Condition()
        # the command topics and their companion node (subscribed with the interfaces); the
        # companion stays reachable as the node's cmd_node
        self.command_topics = CommandTopics(self)
        self.cmd_node = self.command_topics.cmd_node
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
        self.command_topics.create_subscriptions()
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
        # the idle ones (owner/poll_group.py)
        self.poll_group = None
        if len(self.bus_owners) > 1 and all(isinstance(s.bus, NonblockingPolls)
                                            for s in self.bus_owners):
            self.poll_group = PollGroup(self.bus_owners, on_event=self._on_event)

    def start_command_executor(self) -> None:
        """Serve the command subscriptions from a thread of their own (process.spin_node)."""
        self.command_topics.start_executor()

    def stop_command_executor(self) -> None:
        """No more commands: the command executor ends (process.spin_node, at shutdown)."""
        self.command_topics.stop_executor()

    def destroy_node(self) -> None:
        self.command_topics.destroy()
        super().destroy_node()

    def _make_drive_interfaces(self, h: DriveHandle) -> None:
        ns = f'~/{h.name}/'
        self.publishing.add_drive(h, ns)
        self.command_topics.add_drive(h, ns)
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
        before it starts drives together (GroupStarting.group_start_check: the X-MIND K line
        probe of broadcast_start), queued once as a MAINTENANCE job of this drive; its result is
        logged. Until it ran, group starts fall back to per-drive starts."""
        why = self._check_identity(bus_owner, slot)
        bus = bus_owner.bus
        check = bus.group_start_check() if not why and isinstance(bus, GroupStarting) else None
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

    # --------------------------------------------------------- checks (commands and services)
    def refuse(self, h: DriveHandle, why: str) -> None:
        """Count every refusal and keep its reason for the status; log the first of a run of
        refusals of one kind (the reason with its numbers masked: a controller streaming set
        points to a drive that is not enabled sends a new value each time, for one reason: a
        warning each flooded the log and /rosout, and the command thread took 2100 refused
        commands/s instead of 6700). A command that passes its checks (`check_ready`) ends
        the run."""
        kind = message_kind(why)
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

    def check_ready(self, h: DriveHandle, what: str, taken: bool = True) -> None:
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

    def check_finite(self, h: DriveHandle, what: str, value: float) -> None:
        if not math.isfinite(value):
            self.refuse(h, f'{what} {value} is not a finite number')

    def check_position(self, h: DriveHandle, what: str, position: float,
                       taken: bool = True) -> int:
        self.check_finite(h, what, position)
        lo, hi = h.param('min_position'), h.param('max_position')
        if not lo <= position <= hi:
            self.refuse(h, f'{what} {position} is outside min_position..max_position '
                           f'({lo:g}..{hi:g})')
        steps = h.conv.to_steps(position)
        if not math.isfinite(steps) or abs(steps) >= 2 ** 63:
            self.refuse(h, f'{what} {position} is {steps:g} steps: beyond any drive position')
        self.check_ready(h, f'{what} {position}', taken)
        return h.conv.to_steps_int(position)

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

