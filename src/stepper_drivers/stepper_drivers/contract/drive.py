"""The one small interface between the generic ROS node layer and a vendor drive.

No rclpy here and nothing below it: a vendor module implements `Bus` (one link: a TCP connection,
a serial line, a CAN bus) and `Drive` (one drive on that link) and raises the exceptions below.

Threading: one thread owns each bus (the bus owner, `owner.BusOwner`) and makes every call into its
Bus and Drive objects, so vendor code needs no locking of its own unless it runs background
threads (CANopen callbacks).

Step-wise operations: any Drive method may return a generator (an `Operation`) instead of a value.
Each `yield` gives the bus back to its owner between transactions; the number yielded is the least
time in seconds before the next step (0.0: as soon as the owner has served what is more urgent).
The generator's `return` value is the method's result. Between two steps the owner may poll other
drives, run their commands, run a stop of this very drive, or close the generator (GeneratorExit at
the yield, when a stop, a disable or a link loss cuts the operation short: write nothing to the
drive from a `finally` then). Keep one step to one or two transactions. `complete()` runs a
step-wise result to its end in the calling thread (tests, shutdown).

Drive-side units only: steps, steps/s (Hz), steps/s^2 (Hz/s). SI conversion lives in `units.py`.
"""

from __future__ import annotations

import abc
import dataclasses
import enum
import time
import types
from typing import Any, Callable, Generator, Mapping, Sequence, TypeVar

from .scanning import Scanner

T = TypeVar('T')
# A step-wise operation: yields delays [s], returns the result (see the module docstring).
Operation = Generator[float, None, T]


class DriveError(Exception):
    """A drive refused or could not carry out a command (the link itself is fine)."""


class LinkError(DriveError):
    """The link is down or a transaction got no (valid) answer: the node reconnects."""


class RefusedError(DriveError):
    """The drive cannot do this at all (for example X-MIND K fault reset). Message says why."""


class IdentityError(DriveError):
    """The device at this address is not the configured drive, or lacks what the driver needs
    (wrong model, a manufacturer object missing), as a well-formed answer says. Raised by
    `connect()`; the node does not drive it and checks again on a slow back-off (bus owner
    IDENTITY_RECHECK_S); the message names the register or object. An answer that breaks the
    protocol's format (garbled, wrong length or field count, bad CRC) is a LinkError."""


def is_operation(result: Any) -> bool:
    # types.GeneratorType, not typing.Generator: the ABC check costs microseconds per call,
    # and the bus owner asks this for every transaction.
    return isinstance(result, types.GeneratorType)


def complete(result: Any, sleep: Callable[[float], None] = time.sleep) -> Any:
    """Run a step-wise result to its end here, sleeping for every yielded delay; a plain value
    is returned as it is. For tests and for shutdown, where nothing else shares the bus."""
    if not is_operation(result):
        return result
    try:
        while True:
            delay = next(result)
            if delay:
                sleep(delay)
    except StopIteration as stop:
        return stop.value


class State(str, enum.Enum):
    """CiA 402 state names (as canopen's p402 spells them), plus DISCONNECTED.

    Vendors without CiA 402 map their own states onto these.
    """

    NOT_READY_TO_SWITCH_ON = 'NOT READY TO SWITCH ON'
    SWITCH_ON_DISABLED = 'SWITCH ON DISABLED'
    READY_TO_SWITCH_ON = 'READY TO SWITCH ON'
    SWITCHED_ON = 'SWITCHED ON'
    OPERATION_ENABLED = 'OPERATION ENABLED'
    QUICK_STOP_ACTIVE = 'QUICK STOP ACTIVE'
    FAULT_REACTION_ACTIVE = 'FAULT REACTION ACTIVE'
    FAULT = 'FAULT'
    UNKNOWN = 'UNKNOWN'
    DISCONNECTED = 'DISCONNECTED'


class HomingState(str, enum.Enum):
    IDLE = 'IDLE'            # no homing requested since start / since last result was read
    RUNNING = 'RUNNING'
    ATTAINED = 'ATTAINED'
    ERROR = 'ERROR'


@dataclasses.dataclass
class DriveState:
    """One snapshot of a drive, read by `Drive.read_state()`; drive units."""

    state: State = State.UNKNOWN
    enabled: bool = False             # power stage on, holding torque
    moving: bool = False
    target_reached: bool = False
    homed: bool = False               # position is referenced
    homing: HomingState = HomingState.IDLE
    fault: bool = False
    fault_code: int = 0
    fault_text: str = ''
    alarms: tuple[str, ...] = ()      # active alarms/warnings in the manual's words
    mode: str = ''                    # e.g. 'PROFILE POSITION', 'PROFILE VELOCITY', 'HOMING'
    status_word: int = 0              # raw status word (0 where the drive has none)
    position_steps: int = 0
    velocity_steps_s: float = 0.0
    velocity_valid: bool = True       # False where the drive cannot report velocity
    position_estimated: bool = False  # True where position is estimated (X-MIND K while busy)
    effort: float | None = None       # motor current in A where the drive reports it
    # time.monotonic() at which position_steps was true, where the driver knows it to be
    # earlier than the end of the poll (a TxPDO held back by its inhibit time); None: the poll.
    # Not part of equality: a snapshot with the same values is no change (status on change).
    measured_at_s: float | None = dataclasses.field(default=None, compare=False)
    # Set by the bus owner, not by drives: its count of the writes to this drive (jobs started
    # and ended, owner.Slot.write_seq) when the read that gave this snapshot began; the
    # snapshot follows every write up to that count. A later read that returns this same object
    # (its values unchanged) sets it again. Not part of equality.
    after_write: int = dataclasses.field(default=0, compare=False)


@dataclasses.dataclass(frozen=True)
class Motion:
    """Profile for a move, in drive units."""

    velocity_steps_s: float
    acceleration_steps_s2: float
    deceleration_steps_s2: float


@dataclasses.dataclass(frozen=True)
class Homing:
    """Homing configuration, in drive units (the method number is the drive's own)."""

    method: int
    offset_steps: int
    speed_search_steps_s: float
    speed_zero_steps_s: float
    acceleration_steps_s2: float


@dataclasses.dataclass(frozen=True)
class RegisterType:
    name: str
    bits: int
    signed: bool

    def check(self, value: int) -> int:
        lo, hi = (-(1 << (self.bits - 1)), (1 << (self.bits - 1)) - 1) if self.signed \
            else (0, (1 << self.bits) - 1)
        if not lo <= value <= hi:
            raise DriveError(f'value {value} out of range for {self.name} ({lo}..{hi})')
        return value


REGISTER_TYPES: Mapping[str, RegisterType] = {
    t.name: t for t in (
        RegisterType('u8', 8, False), RegisterType('i8', 8, True),
        RegisterType('u16', 16, False), RegisterType('i16', 16, True),
        RegisterType('u32', 32, False), RegisterType('i32', 32, True),
        RegisterType('u64', 64, False), RegisterType('i64', 64, True),
    )
}


def register_type(name: str) -> RegisterType:
    try:
        return REGISTER_TYPES[name.lower()]
    except KeyError:
        raise DriveError(
            f'unknown data type {name!r}; allowed: {", ".join(REGISTER_TYPES)}') from None


class Bus(abc.ABC):
    """One link. `open()` raises LinkError with a message naming the port/host on failure."""

    description: str = ''       # e.g. 'modbus tcp 127.0.0.1:1502', used in logs and diagnostics
    errors: int = 0             # transactions that failed (timeout, CRC, exception reply)
    transactions: int = 0

    @abc.abstractmethod
    def open(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    @property
    @abc.abstractmethod
    def is_open(self) -> bool: ...

    def counters(self) -> dict[str, int]:
        """Link counters shown in status and diagnostics; vendors may add their own keys."""
        return {'transactions': self.transactions, 'errors': self.errors}

    def health(self) -> tuple[str, str] | None:
        """Trouble of the link itself that its drives' states do not show (a CAN controller's
        error frames, bus-off): ('warn' or 'error', text), or None. The node raises the
        link's /diagnostics level by it and adds the text to each drive's status alarms."""
        return None


class Drive(abc.ABC):
    """One drive on a bus. Construct with the bus, the drive's name and its vendor parameters.

    Contract for every implementation:
    - `connect()` reads identity and state, never enables or moves anything.
    - `enable()` first sets the target to the actual position, so nothing moves.
    - Commands are checked by the node layer (limits, NaN); the drive checks its own ranges.
    - Anything the drive cannot do raises RefusedError with the reason for the user.

    What a drive can do beyond this interface is a capability it also derives from
    (capabilities.py); the attributes below only tell the trajectory planner its limits.
    """

    address: Any = ''   # bus address as the user configured it (unit id, node id, ASCII address)
    # Velocities up to this are run start-stop, without the profile's ramps (X-PLUS MT); the
    # trajectory planner needs it to time a move. 0: every move ramps.
    start_stop_steps_s: float = 0.0
    # The least speed the drive runs a move at (its velocity resolution or range); a slower
    # trajectory segment runs at this speed and arrives early. 0: any speed.
    min_velocity_steps_s: float = 0.0
    # time.monotonic() at which the last move_to's motion frame went out, where move_to goes on
    # after it (a CiA 402 set-point handshake waits for the acknowledge); None: at its end.
    motion_sent_t: float | None = None

    def __init__(self, bus: Bus, name: str, params: Mapping[str, Any]):
        self.bus = bus
        self.name = name
        self.params = params

    # Life cycle -----------------------------------------------------------------------------
    @abc.abstractmethod
    def connect(self) -> dict[str, str]:
        """Check the drive answers; return identity key/values for diagnostics."""

    @abc.abstractmethod
    def read_state(self) -> DriveState: ...

    # Power stage ----------------------------------------------------------------------------
    @abc.abstractmethod
    def enable(self) -> None:
        """Bring the drive to OPERATION ENABLED (or its equivalent) without moving."""

    @abc.abstractmethod
    def disable(self) -> None: ...

    # Motion -----------------------------------------------------------------------------------
    def until_ready_for_move(self) -> Operation[bool] | None:
        """Step-wise, until the drive can take a new move at once (a drive that takes no command
        while it runs waits for the run that is about to end); None: ready now. The trajectory
        follower times a move from then."""
        return None

    def move_time_s(self) -> float:
        """What one `move_to` costs on the bus before the drive runs (its transactions),
        estimated from the line settings: the trajectory follower makes its segments long
        enough for the moves of every axis of a bus until it has timed real ones. 0: a fast
        link, where it does not matter."""
        return 0.0

    @abc.abstractmethod
    def move_to(self, target_steps: int, motion: Motion) -> None:
        """Start an absolute move; returns once the drive has accepted it."""

    @abc.abstractmethod
    def set_velocity(self, velocity_steps_s: float, motion: Motion) -> None:
        """Run at a velocity (0 = ramp to standstill); the node layer runs the watchdog."""

    @abc.abstractmethod
    def stop(self, quick: bool = False) -> None:
        """Controlled stop with the profile deceleration (quick: the drive's fastest stop)."""

    @abc.abstractmethod
    def start_homing(self, homing: Homing) -> str:
        """Start the homing (or re-reference); progress via read_state().homing.

        Returns a note for the service message (e.g. 'RD4 has no homing run: preset used').
        """

    # Maintenance ----------------------------------------------------------------------------
    @abc.abstractmethod
    def fault_reset(self) -> str:
        """Clear faults the drive allows to clear; return what remains ('' when none)."""

    @abc.abstractmethod
    def save_params(self) -> str:
        """Store parameters in non-volatile memory; verify where possible; return a note."""

    @abc.abstractmethod
    def read_register(self, address: str, data_type: str) -> int: ...

    @abc.abstractmethod
    def write_register(self, address: str, data_type: str, value: int) -> None: ...

    def close(self) -> None:  # noqa: B027 - an optional hook: most drives hold nothing
        """Release per-drive resources (the bus is closed by the node)."""


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """A vendor-specific parameter: the node layer declares and validates it.

    `scope` is 'bus' (name as given) or 'drive' (declared as drives.<name>.<param>).
    `choices` restricts strings; `min_value`/`max_value` restrict numbers.
    """

    name: str
    default: Any
    description: str
    scope: str = 'drive'
    min_value: float | None = None
    max_value: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = True


@dataclasses.dataclass(frozen=True)
class Vendor:
    """Everything a vendor module gives the node layer and stepperctl, in one object: its
    parameters, the two factories, the check of a whole configuration, the files of the
    installed package its parameters may name, and its bus scanner. What its drives and buses
    can do beyond the Drive and Bus interfaces are the capabilities they implement
    (capabilities.py)."""

    name: str                      # e.g. 'X-PLUS MT'
    params: tuple[ParamSpec, ...]  # vendor bus and per-drive parameters
    make_bus: Callable[[Mapping[str, Any]], Bus]
    make_drive: Callable[[Bus, str, Mapping[str, Any]], Drive]
    # defaults for the common per-drive parameters that differ by vendor (steps_per_rev ...)
    drive_defaults: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    # defaults for the joint parameters constraints.<joint>.* that differ by vendor, for a joint
    # in rad (X-MIND K: path_bound, what its line can carry of a MoveIt plan)
    joint_defaults: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    # Per-drive parameters that choose the drive's link (X-PLUS MT: 'host', 'port'): a drive
    # that sets one ('' and 0 mean "as the bus-level parameter of the same name") gets a bus of
    # its own, with its own owner thread (and polls lent to one poll group where the bus is
    # capabilities.NonblockingPolls); drives with equal values share one bus.
    drive_bus_params: tuple[str, ...] = ()
    # The check of a whole configuration (bus and every drive's params): one line per problem,
    # naming the parameter. Run by the node at start-up, after the per-parameter checks.
    validate: Callable[[Mapping[str, Any]], list[str]] = lambda params: []
    # Parameters whose '' means a file of the installed stepper_drivers package (the node
    # finds it through ROS's package index; without a node, the source tree's): {param: path}
    share_files: Mapping[str, str] = dataclasses.field(default_factory=dict)
    # `stepperctl scan <key>` (vendors/<key>_scan.py); None: the vendor has no scanner
    scanner: Scanner | None = None

    def with_defaults(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """One drive's `params` over this vendor's defaults (`param_defaults` of its params,
        drive_defaults and drive_bus_params)."""
        return param_defaults(self.params, self.drive_defaults, self.drive_bus_params, params)


def param_defaults(param_specs: Sequence[ParamSpec], drive_defaults: Mapping[str, Any],
                   drive_bus_params: Sequence[str], params: Mapping[str, Any]
                   ) -> dict[str, Any]:
    """One drive's `params` over a vendor's defaults: its bus-scope and drive-scope ParamSpecs
    (not the drive_bus_params, whose drive-level '' / 0 means "as the bus"), then
    drive_defaults. The node declares every parameter with these same defaults; a drive made
    without it (scripts, benchmarks) gets them from here, the one place, and not from literals
    in a drive class that can disagree with the docs (the Vector Step's sync_timeout_s fell
    back to 0, its SYNC watchdog off, against a documented 0.5 s). Both `Vendor.with_defaults`
    and a vendor's `settings.with_defaults` (what its drive class calls: the drive does not
    import the vendor entry that builds the Vendor) come here."""
    defaults = {p.name: p.default for p in param_specs if p.scope == 'bus'}
    defaults.update((p.name, p.default) for p in param_specs
                    if p.scope == 'drive' and p.name not in drive_bus_params)
    return {**defaults, **drive_defaults, **params}
