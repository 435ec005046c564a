"""DriveNode: the one ROS layer every vendor node shares (ros_interface.md).

One node per bus, one or more drives per bus. The vendor code below it (drive.py's Bus/Drive) is
blocking and not re-entrant, so every call into it holds `bus_lock`. The poll thread reads every
drive at publish_rate_hz and publishes joint_states and status; services may block (home waits for
the result) but hold the lock only per bus transaction, so joint_states flow during a homing.
"""

from __future__ import annotations

import math
import sys
import threading
import time
import traceback
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import rclpy
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rcl_interfaces.msg import SetParametersResult
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64
from std_srvs.srv import SetBool, Trigger
from stepper_drivers_msgs.action import Home, MoveTo
from stepper_drivers_msgs.msg import DriveStatus
from stepper_drivers_msgs.srv import ReadRegister, WriteRegister

from .drive import (Bus, Drive, DriveError, DriveState, Homing, HomingState, LinkError, Motion,
                    RefusedError, State, Vendor, complete)
from .params import RUNTIME_DRIVE_PARAMS, BusConfig, DriveConfig, ParameterError, check_drive

# Position tolerance for "target reached" in a MoveTo action, in steps.
TARGET_TOLERANCE_STEPS = 2
# On shutdown, how long a controlled stop may take before the power stage is disabled anyway.
SHUTDOWN_STOP_TIMEOUT_S = 5.0
STANDSTILL_POLL_S = 0.02
# When polling cannot keep up with publish_rate_hz, this pause gives waiting commands the bus lock.
OVERRUN_YIELD_S = 0.0005
GIL_SWITCH_INTERVAL_S = 0.0005


class CommandRefused(Exception):
    """A command the node does not send to the drive; str() is the reason."""


class DriveHandle:
    """Runtime state of one drive: its vendor object, conversion, last snapshot, watchdog."""

    def __init__(self, node: 'DriveNode', cfg: DriveConfig, drive: Drive):
        self.node = node
        self.cfg = cfg
        self.name = cfg.name
        self.drive = drive
        self.conv = cfg.conversion
        self.state = DriveState(state=State.DISCONNECTED)
        self.connected = False      # this drive answers (see DriveNode.connected for the bus)
        self.identity: dict[str, str] = {}
        self.velocity_deadline: float | None = None  # watchdog, time.monotonic()
        self.commands_refused = 0
        self.last_refusal = ''
        self.last_error = ''
        self.polls = 0              # read_state() calls that succeeded; services wait on it
        self.reconnects = 0         # successful connects (the first one included)
        self.next_connect = 0.0     # time.monotonic() of the next attempt while disconnected
        self.backoff_s = node.bus_params['reconnect_period_s']

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
    def __init__(self, vendor: Vendor, node_name: str, config_loader: Callable[[Node], BusConfig]):
        super().__init__(node_name)
        self.vendor = vendor
        self.log = self.get_logger()
        self.cfg = config_loader(self)                       # raises ParameterError
        self.bus_params = self.cfg.params
        self.bus: Bus = vendor.make_bus(dict(self.bus_params))
        self.bus_lock = threading.RLock()
        self.changed = threading.Condition()                 # notified after every poll
        self.handles: dict[str, DriveHandle] = {}
        for dcfg in self.cfg.drives:
            try:
                drive = vendor.make_drive(self.bus, dcfg.name, {**self.bus_params, **dcfg.params})
            except ValueError as e:
                raise ParameterError(str(e)) from None
            self.handles[dcfg.name] = DriveHandle(self, dcfg, drive)
        self.by_joint = {h.cfg.joint_name: h for h in self.handles.values()}
        self.shutting_down = False

        self.poll_group = MutuallyExclusiveCallbackGroup()
        self.cmd_group = ReentrantCallbackGroup()
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.joint_pub = self.create_publisher(JointState, 'joint_states', reliable)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_subscription(JointState, 'joint_command', self.on_joint_command, 10,
                                 callback_group=self.cmd_group)
        self.status_pubs = {}
        for h in self.handles.values():
            self._make_drive_interfaces(h)
        # The poll loop is a thread of its own, not an executor timer: rclpy's executor costs
        # more per callback than a Modbus TCP transaction, and commands must not queue behind it.
        self.poll_period_s = 1.0 / self.bus_params['publish_rate_hz']
        self.poll_stop = threading.Event()
        self.poll_thread = threading.Thread(target=self._poll_loop, name='poll', daemon=True)
        self.create_timer(1.0 / self.bus_params['diagnostics_rate_hz'], self.publish_diagnostics,
                          callback_group=self.poll_group)
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.add_post_set_parameters_callback(self.after_set_parameters)
        self.log.info(f'{vendor.name} node on {self.bus.description}: drives '
                      + ', '.join(f'{h.name} ({h.cfg.joint_name})' for h in self.handles.values()))

    # ----------------------------------------------------------------------------------- set-up
    def _make_drive_interfaces(self, h: DriveHandle) -> None:
        ns = f'~/{h.name}/'
        g = self.cmd_group
        self.status_pubs[h.name] = self.create_publisher(DriveStatus, ns + 'status', 10)
        self.create_subscription(Float64, ns + 'position_command',
                                 lambda m, h=h: self.command_position(h, m.data), 10,
                                 callback_group=g)
        self.create_subscription(Float64, ns + 'velocity_command',
                                 lambda m, h=h: self.command_velocity(h, m.data), 10,
                                 callback_group=g)
        srv = [(SetBool, 'enable', self.srv_enable), (Trigger, 'stop', self.srv_stop),
               (Trigger, 'home', self.srv_home), (Trigger, 'fault_reset', self.srv_fault_reset),
               (Trigger, 'save_params', self.srv_save_params),
               (ReadRegister, 'read_register', self.srv_read_register),
               (WriteRegister, 'write_register', self.srv_write_register)]
        for srv_type, name, fn in srv:
            self.create_service(srv_type, ns + name,
                                lambda req, resp, h=h, fn=fn: fn(h, req, resp), callback_group=g)
        ActionServer(self, MoveTo, ns + 'move_to',
                     execute_callback=lambda goal, h=h: self.act_move_to(h, goal),
                     goal_callback=lambda _req: GoalResponse.ACCEPT,
                     cancel_callback=lambda _goal: CancelResponse.ACCEPT, callback_group=g)
        ActionServer(self, Home, ns + 'homing',
                     execute_callback=lambda goal, h=h: self.act_home(h, goal),
                     goal_callback=lambda _req: GoalResponse.ACCEPT,
                     cancel_callback=lambda _goal: CancelResponse.ACCEPT, callback_group=g)

    # ----------------------------------------------------------------------------- bus access
    # Link state is kept per drive: a CANopen node whose heartbeat stops, or an RS-485 unit that
    # no longer answers, is DISCONNECTED while the others on the bus go on. When no drive is left
    # the bus itself is closed and reopened on the next attempt.
    @property
    def connected(self) -> bool:
        return any(h.connected for h in self.handles.values())

    def call(self, h: DriveHandle, fn: Callable, *args):
        """Run one vendor call under the bus lock; a LinkError disconnects the drive."""
        if not h.connected:
            raise CommandRefused(f'drive {h.name} is DISCONNECTED ({self.bus.description}); '
                                 'the node is reconnecting')
        with self.bus_lock:
            try:
                return complete(fn(*args))
            except LinkError as e:
                self._drive_lost(h, str(e))
                raise
            except DriveError:
                raise
            except Exception as e:  # noqa: BLE001 - a vendor bug must not kill the node
                self.log.error(f'{h.name}: internal error in {fn.__name__}: {e!r}\n'
                               + traceback.format_exc())
                raise DriveError(f'internal error in {fn.__name__}: {e!r}') from e

    def _drive_lost(self, h: DriveHandle, why: str) -> None:
        with self.bus_lock:
            if not h.connected:
                return
            # velocity_deadline stays: a velocity run the drive may still be doing is stopped by
            # the watchdog at the first poll after reconnecting.
            h.connected = False
            h.state = DriveState(state=State.DISCONNECTED, position_steps=h.state.position_steps,
                                 homed=h.state.homed)
            h.backoff_s = self.bus_params['reconnect_period_s']
            h.next_connect = time.monotonic() + h.backoff_s
            self.log.error(f'{h.name}: link lost ({why}); reconnecting every '
                           f"{self.bus_params['reconnect_period_s']:g} s and more (back-off)")
            if not self.connected:
                self._close_bus()

    def _close_bus(self) -> None:
        try:
            self.bus.close()
        except Exception as e:  # noqa: BLE001 - closing a dead link may fail any way
            self.log.debug(f'close after link loss: {e}')

    def try_connect(self, h: DriveHandle) -> bool:
        """One connection attempt for one drive (opening the bus first if it is closed)."""
        with self.bus_lock:
            try:
                if not self.bus.is_open:
                    self.bus.open()
                h.identity = complete(h.drive.connect())
                h.state = complete(h.drive.read_state())
            except Exception as e:  # noqa: BLE001 - DriveError, or a vendor/library bug
                if not isinstance(e, DriveError):
                    self.log.error(f'{h.name}: connect: {e!r}\n' + traceback.format_exc())
                if not self.connected:
                    self._close_bus()
                if h.backoff_s == self.bus_params['reconnect_period_s'] or h.reconnects == 0:
                    self.log.warning(f'{h.name}: cannot connect on {self.bus.description}: {e}; '
                                     'retrying')
                h.next_connect = time.monotonic() + h.backoff_s
                h.backoff_s = min(h.backoff_s * 2, 8 * self.bus_params['reconnect_period_s'])
                return False
            h.connected = True
            h.reconnects += 1
            h.backoff_s = self.bus_params['reconnect_period_s']
        # After a (re)connect, report what the drive does; never resume a motion by itself.
        identity = ', '.join(f'{k}={v}' for k, v in h.identity.items())
        self.log.info(f'{h.name}: connected ({identity}); state {h.state.state.value}, '
                      f'position {h.position:.6g}')
        return True

    # ------------------------------------------------------------------------------ poll loop
    def start(self) -> None:
        self.poll_thread.start()

    def _poll_loop(self) -> None:
        next_t = time.monotonic()
        while not self.poll_stop.is_set():
            try:
                self.poll()
            except Exception as e:  # noqa: BLE001 - the loop must survive anything
                if not self.context.ok():   # SIGINT/SIGTERM shut the context down: we are done
                    return
                self.log.error(f'poll: {e!r}\n' + traceback.format_exc())
            next_t += self.poll_period_s
            delay = next_t - time.monotonic()
            if delay < OVERRUN_YIELD_S:  # overrun: no catch-up burst, and let commands in
                next_t = time.monotonic()
                delay = OVERRUN_YIELD_S
            self.poll_stop.wait(delay)

    def poll(self) -> None:
        if self.shutting_down:
            return
        for h in self.handles.values():
            now = time.monotonic()
            if not h.connected:
                if now >= h.next_connect and self.try_connect(h):
                    if h.param('auto_enable') and h.reconnects == 1:
                        self._auto_enable(h)
                continue
            try:
                with self.bus_lock:
                    if not h.connected:
                        continue
                    h.state = complete(h.drive.read_state())
                    h.polls += 1
            except LinkError as e:
                self._drive_lost(h, str(e))
                continue
            except DriveError as e:
                self._note_error(h, f'read state: {e}')
                continue
            except Exception as e:  # noqa: BLE001 - unknown trouble: treat as a link loss
                self.log.error(f'{h.name}: read_state: {e!r}\n' + traceback.format_exc())
                self._drive_lost(h, f'unexpected error {e!r}')
                continue
            if h.velocity_deadline is not None and now > h.velocity_deadline:
                h.velocity_deadline = None
                self.log.warning(
                    f'{h.name}: velocity watchdog: no velocity_command for '
                    f"{self.bus_params['command_timeout_s']:g} s (command_timeout_s), stopping")
                self._safe(h, h.drive.stop)
        with self.changed:
            self.changed.notify_all()
        if self.context.ok():
            self.publish_states()

    def _auto_enable(self, h: DriveHandle) -> None:
        try:
            self.call(h, h.drive.enable)
            self.log.info(f'{h.name}: enabled at start-up (auto_enable)')
        except (DriveError, CommandRefused) as e:
            self.log.error(f'{h.name}: auto_enable failed: {e}')

    def _safe(self, h: DriveHandle, fn: Callable, *args) -> bool:
        try:
            self.call(h, fn, *args)
            return True
        except (DriveError, CommandRefused) as e:
            self._note_error(h, str(e))
            return False

    def _note_error(self, h: DriveHandle, msg: str) -> None:
        if msg != h.last_error:
            self.log.error(f'{h.name}: {msg}')
        h.last_error = msg

    def publish_states(self) -> None:
        stamp = self.get_clock().now().to_msg()
        js = JointState()
        js.header.stamp = stamp
        for h in self.handles.values():
            js.name.append(h.cfg.joint_name)
            js.position.append(h.position)
            js.velocity.append(h.velocity if h.state.velocity_valid else math.nan)
        if all(h.state.effort is not None for h in self.handles.values()):
            js.effort = [float(h.state.effort) for h in self.handles.values()]
        self.joint_pub.publish(js)
        counters = self.bus.counters()
        for h in self.handles.values():
            self.status_pubs[h.name].publish(self._status_msg(h, stamp, counters))

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
        m.status_word = s.status_word & 0xFFFFFFFF
        m.position_steps = int(s.position_steps)
        m.velocity_steps_s = float(s.velocity_steps_s)
        m.velocity_valid, m.position_estimated = s.velocity_valid, s.position_estimated
        m.position, m.velocity = h.position, h.velocity
        m.link_transactions = counters.get('transactions', 0) & 0xFFFFFFFF
        m.link_errors = counters.get('errors', 0) & 0xFFFFFFFF
        m.link_reconnects = max(h.reconnects - 1, 0)
        m.commands_refused, m.last_refusal = h.commands_refused, h.last_refusal
        return m

    def publish_diagnostics(self) -> None:
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        link = DiagnosticStatus(name=f'{self.get_name()}: link', hardware_id=self.bus.description)
        lost = [h.name for h in self.handles.values() if not h.connected]
        if not lost:
            link.level, link.message = DiagnosticStatus.OK, 'connected'
        elif len(lost) < len(self.handles):
            link.level = DiagnosticStatus.WARN
            link.message = f'{", ".join(lost)} DISCONNECTED, reconnecting'
        else:
            link.level, link.message = DiagnosticStatus.ERROR, 'DISCONNECTED, reconnecting'
        link.values = [KeyValue(key=k, value=str(v)) for k, v in self.bus.counters().items()]
        link.values.append(KeyValue(key='reconnects', value=str(
            sum(max(h.reconnects - 1, 0) for h in self.handles.values()))))
        arr.status.append(link)
        for h in self.handles.values():
            s = h.state
            d = DiagnosticStatus(name=f'{self.get_name()}: {h.name}',
                                 hardware_id=f'{self.vendor.name} {h.drive.address}')
            if not h.connected:
                d.level, d.message = DiagnosticStatus.ERROR, 'DISCONNECTED'
            elif s.fault:
                d.level = DiagnosticStatus.ERROR
                d.message = f'FAULT 0x{s.fault_code:04X}: {s.fault_text}'
            elif s.alarms or h.last_error:
                d.level = DiagnosticStatus.WARN
                d.message = '; '.join(s.alarms) or h.last_error
            else:
                d.level, d.message = DiagnosticStatus.OK, s.state.value
            kv = {'state': s.state.value, 'joint': h.cfg.joint_name, 'enabled': s.enabled,
                  'moving': s.moving, 'homed': s.homed, 'mode': s.mode,
                  'position': f'{h.position:.6g}', 'position_steps': s.position_steps,
                  'status_word': f'0x{s.status_word:04X}', 'fault_code': f'0x{s.fault_code:04X}',
                  'fault_text': s.fault_text, 'commands_refused': h.commands_refused,
                  'last_refusal': h.last_refusal, **h.identity}
            d.values = [KeyValue(key=k, value=str(v)) for k, v in kv.items()]
            arr.status.append(d)
        self.diag_pub.publish(arr)

    # ------------------------------------------------------------------------------- commands
    def refuse(self, h: DriveHandle, why: str) -> None:
        if why != h.last_refusal:     # log once per distinct reason, count every time
            self.log.warning(f'{h.name}: command refused: {why}')
        h.last_refusal = why          # before the count: a status published in between is whole
        h.commands_refused += 1
        raise CommandRefused(why)

    def _check_ready(self, h: DriveHandle, what: str) -> None:
        if not h.connected:
            self.refuse(h, f'{what}: drive is DISCONNECTED')
        if h.state.fault:
            self.refuse(h, f'{what}: drive is in FAULT 0x{h.state.fault_code:04X} '
                           f'({h.state.fault_text}); call fault_reset first')
        if not h.state.enabled:
            self.refuse(h, f'{what}: drive is not enabled (state {h.state.state.value}); '
                           'call enable first')

    def _check_finite(self, h: DriveHandle, what: str, value: float) -> None:
        if not math.isfinite(value):
            self.refuse(h, f'{what} {value} is not a finite number')

    def command_position(self, h: DriveHandle, position: float) -> None:
        try:
            self.start_move(h, position)
        except (CommandRefused, DriveError):
            pass

    def start_move(self, h: DriveHandle, position: float) -> None:
        what = f'position_command {position}'
        self._check_finite(h, 'position_command', position)
        lo, hi = h.param('min_position'), h.param('max_position')
        if not lo <= position <= hi:
            self.refuse(h, f'{what} is outside min_position..max_position ({lo:g}..{hi:g})')
        self._check_ready(h, what)
        h.velocity_deadline = None
        try:
            self.call(h, h.drive.move_to, h.conv.to_steps_int(position), h.motion())
        except DriveError as e:
            self._note_error(h, f'{what}: {e}')
            raise

    def command_velocity(self, h: DriveHandle, velocity: float) -> None:
        try:
            what = f'velocity_command {velocity}'
            self._check_finite(h, 'velocity_command', velocity)
            vmax = h.param('max_velocity')
            if abs(velocity) > vmax:
                self.refuse(h, f'{what} exceeds max_velocity ({vmax:g})')
            self._check_ready(h, what)
            self.call(h, h.drive.set_velocity, h.conv.to_steps(velocity), h.motion())
            h.velocity_deadline = (time.monotonic() + self.bus_params['command_timeout_s']
                                   if velocity != 0.0 else None)
        except CommandRefused:
            pass
        except DriveError as e:
            self._note_error(h, f'velocity_command {velocity}: {e}')

    def on_joint_command(self, msg: JointState) -> None:
        for i, joint in enumerate(msg.name):
            h = self.by_joint.get(joint)
            if h is None:
                self.log.warning(f'joint_command: unknown joint {joint!r} (this node has '
                                 f'{sorted(self.by_joint)})', throttle_duration_sec=5.0)
                continue
            if i < len(msg.position) and not math.isnan(msg.position[i]):
                self.command_position(h, msg.position[i])
            elif i < len(msg.velocity) and not math.isnan(msg.velocity[i]):
                self.command_velocity(h, msg.velocity[i])

    # ------------------------------------------------------------------------------- services
    def _run(self, h: DriveHandle, resp, fn: Callable, ok_message: Callable[[Any], str]):
        """Call fn, fill a success/message response; errors become success=false + reason."""
        try:
            result = fn()
            resp.success, resp.message = True, ok_message(result)
        except (CommandRefused, RefusedError, DriveError) as e:
            resp.success, resp.message = False, f'{h.name}: {e}'
            if not isinstance(e, CommandRefused):
                self.log.warning(resp.message)
        return resp

    def wait_polls(self, h: DriveHandle, n: int, timeout_s: float) -> bool:
        """Wait until n fresh snapshots of h were read (so a state after a command is current)."""
        target = h.polls + n
        deadline = time.monotonic() + timeout_s
        with self.changed:
            while h.polls < target:
                left = deadline - time.monotonic()
                if left <= 0 or not h.connected:
                    return False
                self.changed.wait(left)
        return True

    def srv_enable(self, h: DriveHandle, req, resp):
        def do():
            if not h.connected:
                self.refuse(h, 'enable: drive is DISCONNECTED')
            h.velocity_deadline = None
            self.call(h, h.drive.enable if req.data else h.drive.disable)
            self.wait_polls(h, 1, 2.0)
            return h.state.state.value
        return self._run(h, resp, do, lambda st: f'{h.name}: {st}')

    def srv_stop(self, h: DriveHandle, req, resp):
        def do():
            h.velocity_deadline = None
            self.call(h, h.drive.stop)
        return self._run(h, resp, do,
                         lambda _: f'{h.name}: stopping with the profile deceleration')

    def run_homing(self, h: DriveHandle, feedback: Callable[[], None] | None = None,
                   cancelled: Callable[[], bool] = lambda: False) -> str:
        if h.state.fault:
            self.refuse(h, f'home: drive is in FAULT 0x{h.state.fault_code:04X} '
                           f'({h.state.fault_text}); call fault_reset first')
        if not h.connected:
            self.refuse(h, 'home: drive is DISCONNECTED')
        h.velocity_deadline = None
        note = self.call(h, h.drive.start_homing, h.homing())
        timeout_s = h.param('homing.timeout_s')
        deadline = time.monotonic() + timeout_s
        self.wait_polls(h, 1, 2.0)
        while True:
            st = h.state.homing
            if st == HomingState.ATTAINED:
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
                self._safe(h, h.drive.stop)
                raise DriveError('homing cancelled; drive stopped')
            if time.monotonic() > deadline:
                self._safe(h, h.drive.stop)
                raise DriveError(f'homing timed out after {timeout_s:g} s (homing.timeout_s); '
                                 'drive stopped')
            if feedback:
                feedback()
            self.wait_polls(h, 1, 1.0)

    def srv_home(self, h: DriveHandle, req, resp):
        return self._run(h, resp, lambda: self.run_homing(h), lambda msg: msg)

    def srv_fault_reset(self, h: DriveHandle, req, resp):
        def do():
            remaining = self.call(h, h.drive.fault_reset)
            self.wait_polls(h, 1, 2.0)
            if remaining:
                raise DriveError(f'fault remains: {remaining}')
            return h.state.state.value
        return self._run(h, resp, do, lambda st: f'{h.name}: fault cleared, state {st}')

    def srv_save_params(self, h: DriveHandle, req, resp):
        return self._run(h, resp, lambda: self.call(h, h.drive.save_params),
                         lambda note: f'{h.name}: parameters saved'
                         + (f'; {note}' if note else ''))

    def srv_read_register(self, h: DriveHandle, req, resp):
        resp.value, resp.text = 0, ''

        def do():
            value = self.call(h, h.drive.read_register, req.address, req.data_type)
            if isinstance(value, str):
                resp.text = value
            else:
                resp.value = int(value)
            return value
        return self._run(h, resp, do, lambda v: f'{req.address} ({req.data_type}) = {v}')

    def srv_write_register(self, h: DriveHandle, req, resp):
        def do():
            if not h.param('allow_raw_write'):
                self.refuse(h, f'write_register {req.address}: raw writes are disabled '
                               f'(set drives.{h.name}.allow_raw_write: true)')
            value = req.text if req.data_type.lower() == 'string' else req.value
            self.call(h, h.drive.write_register, req.address, req.data_type, value)
        shown = req.text if req.data_type.lower() == 'string' else req.value
        return self._run(h, resp, do, lambda _: f'{req.address} ({req.data_type}) := {shown}')

    # -------------------------------------------------------------------------------- actions
    def act_move_to(self, h: DriveHandle, goal_handle):
        result = MoveTo.Result()
        target = goal_handle.request.position
        try:
            self.start_move(h, target)
            self.wait_polls(h, 1, 2.0)
            target_steps = h.conv.to_steps_int(target)
            fb = MoveTo.Feedback()
            while True:
                s = h.state
                if s.fault or not h.connected:
                    raise DriveError(f'move aborted: state {s.state.value} {s.fault_text}'.strip())
                if goal_handle.is_cancel_requested:
                    self._safe(h, h.drive.stop)
                    goal_handle.canceled()
                    result.message, result.final_position = 'cancelled; drive stopped', h.position
                    return result
                at_target = abs(s.position_steps - target_steps) <= TARGET_TOLERANCE_STEPS
                if not s.moving and at_target:
                    break
                if not s.moving and s.target_reached and h.polls > 0 and \
                        abs(s.position_steps - target_steps) > TARGET_TOLERANCE_STEPS:
                    raise DriveError(f'drive stopped at {h.position:.6g}, not at {target:.6g}')
                fb.position, fb.state = h.position, s.state.value
                fb.distance_remaining = target - h.position
                goal_handle.publish_feedback(fb)
                self.wait_polls(h, 1, 1.0)
            goal_handle.succeed()
            result.success, result.message = True, f'{h.name}: at {h.position:.6g}'
        except (CommandRefused, DriveError) as e:
            goal_handle.abort()
            result.success, result.message = False, f'{h.name}: {e}'
        result.final_position = h.position
        return result

    def act_home(self, h: DriveHandle, goal_handle):
        result = Home.Result()
        fb = Home.Feedback()

        def feedback():
            fb.homing_state, fb.position = h.state.homing.value, h.position
            goal_handle.publish_feedback(fb)
        try:
            result.message = self.run_homing(h, feedback, lambda: goal_handle.is_cancel_requested)
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
        """Validate runtime changes (ranges are checked by rclpy); cross-field rules here."""
        bus_changes = {p.name: p.value for p in params if p.name in self.bus_params}
        for h in self.handles.values():
            prefix = f'drives.{h.name}.'
            mine = {p.name[len(prefix):]: p.value for p in params if p.name.startswith(prefix)}
            if mine:
                values = {n: h.param(n) for n in RUNTIME_DRIVE_PARAMS}
                values.update(mine)
                try:
                    check_drive(prefix, values)
                except ParameterError as e:
                    return SetParametersResult(successful=False, reason=str(e))
            # the vendor's own rules: homing methods, and rules that tie a drive to the poll
            # rate (RD4: the 1 s watchdog must be fed)
            if bus_changes or 'homing.method' in mine:
                try:
                    self.vendor.make_drive(self.bus, h.name, {**self.bus_params, **bus_changes,
                                                              **h.cfg.params, **mine})
                except ValueError as e:
                    return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    def after_set_parameters(self, params: list[Parameter]) -> None:
        for p in params:
            if p.name in ('publish_rate_hz', 'command_timeout_s'):
                self.bus_params[p.name] = p.value
            if p.name == 'publish_rate_hz':
                self.poll_period_s = 1.0 / p.value
            self.log.info(f'parameter {p.name} := {p.value}')

    # ------------------------------------------------------------------------------- shutdown
    def shutdown_drives(self) -> None:
        """Stop motion, disable where disable_on_shutdown, close the link. No ROS needed."""
        self.shutting_down = True
        self.poll_stop.set()
        if self.poll_thread.is_alive():
            self.poll_thread.join(timeout=5.0)
        with self.bus_lock:
            live = [h for h in self.handles.values() if h.connected]
            for h in live:              # every drive decelerates at once ...
                self._shutdown_step(h, h.drive.stop)
            for h in live:              # ... then each is disabled once it stands still
                if h.param('disable_on_shutdown'):
                    self._shutdown_step(h, self._wait_standstill, h, SHUTDOWN_STOP_TIMEOUT_S)
                    self._shutdown_step(h, h.drive.disable)
            for h in self.handles.values():
                try:
                    h.drive.close()
                except Exception:  # noqa: BLE001
                    pass
            try:
                self.bus.close()
            except Exception:  # noqa: BLE001
                pass

    def _shutdown_step(self, h: DriveHandle, fn: Callable, *args) -> None:
        try:
            complete(fn(*args))
        except Exception as e:  # noqa: BLE001 - go on with the other steps and drives
            # the ROS context is gone by now: print, do not log through rclpy
            print(f'[{self.get_name()}] {h.name}: shutdown: {fn.__name__}: {e}', flush=True)

    def _wait_standstill(self, h: DriveHandle, timeout_s: float) -> None:
        """Let the controlled stop finish before the power stage goes off (bounded)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            h.state = complete(h.drive.read_state())
            if not h.state.moving:
                return
            time.sleep(STANDSTILL_POLL_S)  # rate limit of the poll; nothing to wait on without ROS


def spin_node(node: DriveNode) -> None:
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    # The poll thread waits on the bus and then needs the GIL back from the executor threads:
    # a short switch interval keeps that hand-over well below a transaction time.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    node.start()
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.shutdown_drives()
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown()
