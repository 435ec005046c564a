"""The command topics of a DriveNode: `~/<drive>/position_command`, `~/<drive>/velocity_command`
and `~/joint_command` (docs/interface.md), with the rules of a streamed command.

A command is checked against the limits and the drive's latest snapshot (the node's checks) and
enqueued for the bus owner; nothing here waits. The subscriptions belong to a hidden companion
node (`_<node>_commands`) served by one executor thread of its own, the command thread (why: see
node.py's docstring). The stream rules: a command's age (its sample's DDS source timestamp), the
start guard of a joint_command stream, a held target not sent again, and the joints of other
nodes on a shared joint_command.
"""

from __future__ import annotations

import concurrent.futures
import math
import re
import threading
import time
from typing import Any, Mapping, Protocol

import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

from ..owner import Cancelled, Superseded
from ..owner.commands import Command, CommandRefused
from .handle import DriveHandle

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


def message_kind(text: str) -> str:
    """The kind of a refusal or a failure: its text with the numbers masked. The log tells the
    first of a run of one kind (the node's `refuse`, `CommandTopics._job_failed`)."""
    return _NUMBER.sub('#', text)


class CommandHost(Protocol):
    """What the command topics need of their node (node.DriveNode): its joints, its bus
    parameters (read at each command: a run-time change applies to the next one), its checks
    and refusals, and the rclpy Node calls below."""

    by_joint: Mapping[str, DriveHandle]
    bus_params: Mapping[str, Any]
    log: Any                 # the node's logger
    context: Any             # the rclpy Context

    def refuse(self, h: DriveHandle, why: str) -> None: ...

    def check_ready(self, h: DriveHandle, what: str, taken: bool = True) -> None: ...

    def check_finite(self, h: DriveHandle, what: str, value: float) -> None: ...

    def check_position(self, h: DriveHandle, what: str, position: float,
                       taken: bool = True) -> int: ...

    def get_name(self) -> str: ...

    def get_namespace(self) -> str: ...

    def resolve_topic_name(self, topic: str, *, only_expand: bool = False) -> str: ...


class CommandTopics:
    """The command subscriptions of `node` and their companion node. Built with the node (the
    companion node, no subscription); `create_subscriptions` and `add_drive` subscribe with the
    node's interfaces, `start_executor` serves them."""

    def __init__(self, node: CommandHost):
        self.node = node
        # The subscriptions' own node: no global arguments (a launch file's `__node:=` would
        # give it this node's name), topics resolved by this node's rules.
        self.cmd_node = rclpy.create_node(
            f'_{node.get_name()}_commands', namespace=node.get_namespace(),
            context=node.context, use_global_arguments=False, start_parameter_services=False,
            enable_rosout=False, parameter_overrides=[
                Parameter('start_type_description_service', value=False)])   # no service
        self._executor = None
        self._foreign_joints: set[str] = set()   # joint_command names told (command thread)

    def _subscribe(self, msg_type, topic: str, callback) -> None:
        """A command topic of the node (its name resolved and remapped as the node's own),
        subscribed by the companion node."""
        self.cmd_node.create_subscription(msg_type, self.node.resolve_topic_name(topic),
                                          callback, COMMAND_QOS)

    def create_subscriptions(self) -> None:
        """The node's `~/joint_command` (with the node's interfaces)."""
        self._subscribe(JointState, 'joint_command', self.on_joint_command)

    def add_drive(self, h: DriveHandle, ns: str) -> None:
        """The position_command and velocity_command of drive h, under the namespace ns."""
        # two arguments: rclpy passes the sample's MessageInfo (its source timestamp)
        self._subscribe(Float64, ns + 'position_command',
                        lambda m, info, h=h: self.command_position(h, m.data, sample_age_s(info)))
        self._subscribe(Float64, ns + 'velocity_command',
                        lambda m, info, h=h: self.command_velocity(h, m.data, sample_age_s(info)))

    # ----------------------------------------------------------------------- the command thread
    def start_executor(self) -> None:
        """Serve the command subscriptions from a thread of their own (see the module doc)."""
        from rclpy.executors import SingleThreadedExecutor
        self._executor = SingleThreadedExecutor(context=self.node.context)
        self._executor.add_node(self.cmd_node)
        threading.Thread(target=_spin_commands, args=(self._executor,),
                         name='command executor', daemon=True).start()

    def stop_executor(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(timeout_sec=1.0)
            self._executor = None

    def destroy(self) -> None:
        """The executor stopped, the companion node destroyed (the node's destroy_node)."""
        self.stop_executor()
        self.cmd_node.destroy_node()

    # --------------------------------------------------------------------------------- checks
    def _check_age(self, h: DriveHandle, what: str, age_s: float | None, bound_s: float,
                   parameter: str) -> None:
        """Refuse a streamed command published more than bound_s before it arrived, or
        stamped more than bound_s ahead of this host's clock (the two clocks disagree, so its
        age cannot be told). No age (no source timestamp): taken."""
        if age_s is None or bound_s <= 0.0:
            return
        if age_s > bound_s:
            self.node.refuse(h, f'{what} was published {age_s:.3f} s before it arrived, more '
                                f'than {parameter} ({bound_s:g} s): a stale command, not sent')
        if age_s < -bound_s:
            self.node.refuse(h, f'{what} is stamped {-age_s:.3f} s ahead of the clock of this '
                                f'host, more than {parameter} ({bound_s:g} s): its age cannot '
                                'be told; synchronise the clocks of the hosts (chrony, PTP)')

    def _check_start(self, h: DriveHandle, what: str, position: float) -> None:
        """A joint_command position that starts a stream (none for command_timeout_s) must be
        within joint_command_max_start_offset of where the joint stands: ros2_control's older
        topic plugin sends 0.0 (or the URDF's initial_value) before a controller writes."""
        if time.monotonic() - h.stream_t <= self.node.bus_params['command_timeout_s']:
            return
        bound = h.param('joint_command_max_start_offset')
        actual = h.position
        if abs(position - actual) > bound:
            self.node.refuse(
                h, f'{what} {position:g} for joint {h.cfg.joint_name!r} starts a stream '
                   f'{abs(position - actual):g} from where the joint stands ({actual:g}), '
                   f'more than drives.{h.name}.joint_command_max_start_offset '
                   f'({bound:g}): not sent; command the joint from where it stands')

    def _holds(self, h: DriveHandle, steps: int) -> bool:
        """(Command thread) Sending `steps` again would change nothing: nothing was submitted
        for the drive since the last job that sent this very target, the drive did not
        reconnect since, and that job is still on its way (queued or running: it carries the
        target), or the drive confirmed it and its snapshot shows it moving or standing on it.
        A set point stream faster than a move's transactions (100 Hz on a serial line) thus
        sends a held target once, not once per message."""
        slot = h.slot
        now = (steps, slot, slot.submitted, slot.reconnects)
        pending = h.pending_target
        if pending is not None and pending[0] == now and not pending[1].done():
            return True
        if h.held_target != now:
            return False
        state = slot.state
        return state.moving or abs(state.position_steps - steps) <= 1

    # ------------------------------------------------------------------------------- commands
    def command_position(self, h: DriveHandle, position: float,
                         age_s: float | None = None, stream: bool = False) -> None:
        """(Command thread) A position_command, or with `stream` a joint_command position,
        published age_s ago. A target the drive already took, with no job for the drive since
        and its snapshot moving or standing there, is not sent again: a ros2_control hold
        streams one target 100 times a second. A stream's first position must be near the
        joint (`_check_start`)."""
        node = self.node
        what = 'joint_command position' if stream else 'position_command'
        try:
            self._check_age(h, f'{what} {position}', age_s,
                            node.bus_params['position_command_max_age_s'],
                            'position_command_max_age_s')
            steps = node.check_position(h, what, position, taken=not stream)
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

    def command_velocity(self, h: DriveHandle, velocity: float,
                         age_s: float | None = None) -> None:
        """(Command thread) A velocity_command (or a joint_command velocity) published age_s
        ago. One older than command_timeout_s is refused: the watchdog would have stopped the
        drive by then, and taking it would start the drive again after that stop. A velocity 0
        is taken at any age: it moves nothing."""
        node = self.node
        what = f'velocity_command {velocity}'
        try:
            if velocity != 0.0:
                self._check_age(h, what, age_s, node.bus_params['command_timeout_s'],
                                'command_timeout_s')
            node.check_finite(h, 'velocity_command', velocity)
            vmax = h.param('max_velocity')
            if abs(velocity) > vmax:
                node.refuse(h, f'{what} exceeds max_velocity ({vmax:g})')
            node.check_ready(h, what)
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
        """(Command thread) `info`: the sample's MessageInfo (rclpy passes it to a two-argument
        callback)."""
        node = self.node
        age_s = sample_age_s(info)
        n = len(msg.name)
        for field in ('position', 'velocity'):
            values = getattr(msg, field)
            if values and len(values) != n:
                # executed index by index it would send one joint's value to another
                why = (f'joint_command: {len(values)} {field} values for {n} names '
                       f'{list(msg.name)} (a non-empty array needs one value per name); '
                       'the whole message is refused')
                mine = [node.by_joint[j] for j in msg.name if j in node.by_joint]
                for h in mine:
                    try:
                        node.refuse(h, why)
                    except CommandRefused:
                        pass
                if not mine:
                    node.log.warning(why, throttle_duration_sec=5.0)
                return
        for i, joint in enumerate(msg.name):
            h = node.by_joint.get(joint)
            if h is None:
                self._unknown_joint(joint)
                continue
            # NaN: no command for this joint (a ros2_control controller that has not written)
            if msg.position and not math.isnan(msg.position[i]):
                self.command_position(h, msg.position[i], age_s, stream=True)
            elif msg.velocity and not math.isnan(msg.velocity[i]):
                self.command_velocity(h, msg.velocity[i], age_s)

    def _unknown_joint(self, joint: str) -> None:
        """(Command thread) A joint_command name the node does not have. joint_command_shared (a
        ros2_control block for several nodes names all their joints): told once for each name;
        otherwise a mistake, warned every 5 s."""
        node = self.node
        if not node.bus_params['joint_command_shared']:
            node.log.warning(f'joint_command: unknown joint {joint!r} (this node has '
                             f'{sorted(node.by_joint)})', throttle_duration_sec=5.0)
        elif joint not in self._foreign_joints:
            self._foreign_joints.add(joint)
            node.log.info(f"joint_command: joint {joint!r} is not one of this node's "
                          f'{sorted(node.by_joint)}: ignored (joint_command_shared)')

    # -------------------------------------------------------------------------- owner threads
    def _position_done(self, h: DriveHandle, what: str, fut: concurrent.futures.Future,
                       target: tuple) -> None:
        """(Owner thread) a position job ended: a confirmed one is the held target (_holds);
        any other outcome forgets it."""
        ok = not fut.cancelled() and fut.exception() is None
        h.held_target = target if ok and target[2] is not None else None
        self._job_failed(h, what, fut)

    def _job_failed(self, h: DriveHandle, what: str, fut: concurrent.futures.Future) -> None:
        """When a queued command ended (the owner thread; the submitting one when it ended
        before its callback was added, or was refused at once): a failure goes to the status and
        /diagnostics each time, to the log at the first of a run of one kind (as the node's
        `refuse`: a stream of set points the drive cannot take is one error, not one per set
        point); one the drive took ends the run. Superseded and dropped ones are normal."""
        if fut.cancelled():
            return
        exc = fut.exception()
        if exc is None:
            h.job_error_logged = ''
            return
        if isinstance(exc, (Superseded, Cancelled)):
            return
        msg = f'{what}: {exc}'
        kind = message_kind(msg)
        if kind != h.job_error_logged:
            self.node.log.error(f'{h.name}: {msg}')
            h.job_error_logged = kind
        h.bus_owner.report_error(h.name, msg)


def _spin_commands(executor) -> None:
    from rclpy.executors import ExternalShutdownException, ShutdownException
    try:
        executor.spin()
    except (ExternalShutdownException, ShutdownException):
        pass                          # the process is ending: spin_node stops the drives
