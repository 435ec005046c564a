"""CiA 402 (DSP 402) power state machine and mode helpers as data tables; no transport, no rclpy.

Used by drives whose controlword/statusword follow CiA 402: the R.T.A. X-PLUS MT (Modbus
registers 1040/1001) and the AEC Vector Step (CANopen 0x6040/0x6041). Written like canopen's
`profiles/p402.py` (tables + short functions), but keyed by `drive.State` members and tuples, so
no lookup is a substring test.

Numbers cite the X-PLUS MT manual where it states them (T13 = "Bit of the Control Word", T14 =
"Bit of the Status Word", §12 transitions) and CiA 402 otherwise.
"""

from __future__ import annotations

import collections
import logging
import time
from typing import Callable

from ...contract.drive import DriveError, HomingState, Operation, State

logger = logging.getLogger(__name__)

# --- Controlword -----------------------------------------------------------------------------
# Bits (§13 "Register 1040"; CiA 402 0x6040).
CW_BIT_SWITCH_ON = 1 << 0
CW_BIT_ENABLE_VOLTAGE = 1 << 1
CW_BIT_QUICK_STOP = 1 << 2            # active low: 0 = quick stop
CW_BIT_ENABLE_OPERATION = 1 << 3
CW_BIT_NEW_SET_POINT = 1 << 4         # PP: new set point; homing: homing operation start
CW_BIT_CHANGE_SET_IMMEDIATELY = 1 << 5
CW_BIT_RELATIVE = 1 << 6              # PP: 0 = absolute, 1 = relative
CW_BIT_FAULT_RESET = 1 << 7           # acts on the 0 -> 1 edge (T13 "Trans. L/H")
CW_BIT_HALT = 1 << 8

CW_STATE_BITS = 0x008F                # bits T13 uses to encode the device-control commands
CW_MODE_BITS = (CW_BIT_NEW_SET_POINT | CW_BIT_CHANGE_SET_IMMEDIATELY | CW_BIT_RELATIVE
                | CW_BIT_HALT)

# Device-control commands, canonical values (T13; §12 "CW sequence").
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_DISABLE_OPERATION = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080

# Command recognition, controlword -> command: (mask, value) per T13 (X = not in the mask).
# Fault reset is an edge of bit 7, not a level, so it is not in this table.
CW_COMMANDS: dict[str, tuple[int, int]] = {
    'SHUTDOWN': (0x0087, 0x0006),           # 0 X 1 1 0
    'SWITCH ON': (0x0087, 0x0007),          # 0 X 1 1 1 (bit 3 = 1 goes on to OE, §12)
    'DISABLE VOLTAGE': (0x0082, 0x0000),    # 0 X X 0 X
    'QUICK STOP': (0x0086, 0x0002),         # 0 X 0 1 X
    'DISABLE OPERATION': (0x008F, 0x0007),  # 0 0 1 1 1
    'ENABLE OPERATION': (0x008F, 0x000F),   # 0 1 1 1 1
}

# --- Statusword ------------------------------------------------------------------------------
SW_BIT_READY_TO_SWITCH_ON = 1 << 0
SW_BIT_SWITCHED_ON = 1 << 1
SW_BIT_OPERATION_ENABLED = 1 << 2
SW_BIT_FAULT = 1 << 3
SW_BIT_VOLTAGE_ENABLED = 1 << 4       # X-PLUS MT: 0 = power supply out of range / no HV
SW_BIT_QUICK_STOP = 1 << 5            # active low: 0 = quick stop active
SW_BIT_SWITCH_ON_DISABLED = 1 << 6
SW_BIT_WARNING = 1 << 7
SW_BIT_REMOTE = 1 << 9
SW_BIT_TARGET_REACHED = 1 << 10       # PV: target velocity reached
SW_BIT_INTERNAL_LIMIT = 1 << 11
SW_BIT_SET_POINT_ACKNOWLEDGE = 1 << 12  # PP
SW_BIT_HOMING_ATTAINED = 1 << 12      # homing ("Homing Complete" in the X-PLUS MT manual)
SW_BIT_ZERO_SPEED = 1 << 12           # PV
SW_BIT_FOLLOWING_ERROR = 1 << 13      # PP/PV
SW_BIT_HOMING_ERROR = 1 << 13         # homing

# State decoding, first match wins: statusword & mask == value (CiA 402 masks over bits 0-3, 5,
# 6; T14 for the six states the manual lists).
SW_MASK: dict[State, tuple[int, int]] = {
    State.NOT_READY_TO_SWITCH_ON: (0x004F, 0x0000),
    State.SWITCH_ON_DISABLED: (0x004F, 0x0040),   # T14: bit 6 = 1 (T14 prints bit 5 = 1, CiA X)
    State.READY_TO_SWITCH_ON: (0x006F, 0x0021),
    State.SWITCHED_ON: (0x006F, 0x0023),
    State.OPERATION_ENABLED: (0x006F, 0x0027),
    State.QUICK_STOP_ACTIVE: (0x006F, 0x0007),
    State.FAULT_REACTION_ACTIVE: (0x004F, 0x000F),  # e.g. 0x201F (§13 "Register 1085")
    State.FAULT: (0x004F, 0x0008),                  # e.g. 0x1218
}

# States the drive leaves by itself; the host waits, it cannot command them.
AUTOMATIC_STATES = (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE)
COMMANDABLE_STATES = (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                      State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)
# The states of a fault: the drive goes on to FAULT by itself, and leaves it by a fault reset only.
FAULT_STATES = (State.FAULT, State.FAULT_REACTION_ACTIVE)

# Host-commanded transitions: (from, to) -> controlword. Numbers are CiA 402 / the manual's §12.
TRANSITIONS: dict[tuple[State, State], int] = {
    (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON): CW_SHUTDOWN,          # 2
    (State.READY_TO_SWITCH_ON, State.SWITCHED_ON): CW_SWITCH_ON,                # 3
    (State.SWITCHED_ON, State.OPERATION_ENABLED): CW_ENABLE_OPERATION,          # 4
    (State.OPERATION_ENABLED, State.SWITCHED_ON): CW_DISABLE_OPERATION,         # 5
    (State.SWITCHED_ON, State.READY_TO_SWITCH_ON): CW_SHUTDOWN,                 # 6
    (State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED): CW_DISABLE_VOLTAGE,   # 7
    (State.OPERATION_ENABLED, State.READY_TO_SWITCH_ON): CW_SHUTDOWN,           # 8
    (State.OPERATION_ENABLED, State.SWITCH_ON_DISABLED): CW_DISABLE_VOLTAGE,    # 9
    (State.SWITCHED_ON, State.SWITCH_ON_DISABLED): CW_DISABLE_VOLTAGE,          # 10
    (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE): CW_QUICK_STOP,          # 11
    (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED): CW_DISABLE_VOLTAGE,    # 12
    (State.FAULT, State.SWITCH_ON_DISABLED): CW_FAULT_RESET,                    # 15 (edge)
    (State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED): CW_ENABLE_OPERATION,    # 16 (QS code 5)
}

# Transitions the drive makes by itself (13/14 on an internal fault, 0/1 at power-on).
AUTOMATIC_TRANSITIONS: dict[State, State] = {
    State.NOT_READY_TO_SWITCH_ON: State.SWITCH_ON_DISABLED,   # 1
    State.FAULT_REACTION_ACTIVE: State.FAULT,                 # 14
}


def _routes() -> dict[tuple[State, State], State]:
    """NEXT_STATE from TRANSITIONS: shortest path, ties broken by TRANSITIONS order."""
    graph: dict[State, list[State]] = collections.defaultdict(list)
    for (a, b) in TRANSITIONS:
        graph[a].append(b)
    for a, b in AUTOMATIC_TRANSITIONS.items():
        graph[a].append(b)
    table: dict[tuple[State, State], State] = {}
    for start in list(COMMANDABLE_STATES) + [State.FAULT] + list(AUTOMATIC_STATES):
        first_hop: dict[State, State] = {}
        queue = collections.deque([start])
        seen = {start}
        while queue:
            node = queue.popleft()
            for nxt in graph[node]:
                if nxt not in seen:
                    seen.add(nxt)
                    first_hop[nxt] = nxt if node == start else first_hop[node]
                    queue.append(nxt)
        for target, hop in first_hop.items():
            if target in COMMANDABLE_STATES:
                table[(start, target)] = hop
    return table


# (current, target) -> the next state on the way, e.g. (FAULT, OPERATION ENABLED) ->
# SWITCH ON DISABLED. Derived from TRANSITIONS once, at import.
NEXT_STATE: dict[tuple[State, State], State] = _routes()

# --- Modes of operation (§12 "Mode of Operation"; CiA 402 0x6060) ------------------------------
MODE_NONE = 0
MODE_PROFILE_POSITION = 1
MODE_PROFILE_VELOCITY = 3
MODE_HOMING = 6

# Homing status from (bit 13 error, bit 12 attained, bit 10 target reached), CiA 402 table.
HOMING_STATUS: dict[tuple[bool, bool, bool], HomingState] = {
    (False, False, False): HomingState.RUNNING,    # in progress
    (False, False, True): HomingState.IDLE,        # interrupted (Halt) or not started
    (False, True, False): HomingState.RUNNING,     # attained, target not reached yet
    (False, True, True): HomingState.ATTAINED,     # completed successfully
    (True, False, False): HomingState.ERROR,       # error, velocity not 0
    (True, False, True): HomingState.ERROR,        # error, velocity 0
    (True, True, False): HomingState.ERROR,        # (reserved)
    (True, True, True): HomingState.ERROR,         # (reserved)
}


# --- Pure functions ----------------------------------------------------------------------------
def decode_state(statusword: int) -> State:
    for state, (mask, value) in SW_MASK.items():
        if statusword & mask == value:
            return state
    return State.UNKNOWN


def describe(statusword: int) -> str:
    """'SWITCH ON DISABLED (statusword 0x0270)' for messages."""
    return f'{decode_state(statusword).value} (statusword 0x{statusword:04X})'


def decode_commands(controlword: int) -> tuple[str, ...]:
    """T13 command names the controlword matches (several where bits are X)."""
    return tuple(name for name, (mask, value) in CW_COMMANDS.items()
                 if controlword & mask == value)


def check_target(target: State) -> None:
    if target not in COMMANDABLE_STATES:
        raise ValueError(f'{target.value} cannot be commanded (allowed targets: '
                         f'{", ".join(s.value for s in COMMANDABLE_STATES)})')


def next_state(current: State, target: State) -> State | None:
    """The next state on the way from current to target; None when there already."""
    check_target(target)
    if current == target:
        return None
    try:
        return NEXT_STATE[(current, target)]
    except KeyError:
        raise ValueError(f'Illegal state transition from {current.value} to {target.value}'
                         ) from None


def next_controlword(current: State, target: State) -> int | None:
    """Controlword for the next step from current towards target.

    None when current == target or when the drive leaves `current` by itself (NOT READY TO
    SWITCH ON, FAULT REACTION ACTIVE): the host waits. For FAULT the value is CW_FAULT_RESET,
    which only acts as a 0 -> 1 edge (see FAULT_RESET_EDGE).
    """
    if current in AUTOMATIC_STATES:
        check_target(target)
        return None
    hop = next_state(current, target)
    if hop is None:
        return None
    return TRANSITIONS[(current, hop)]


# Fault reset: bit 7 must go 0 -> 1 (T13 "Trans. L/H"), then back to 0 ("After this bit 7 has to
# be set to 0", §13 "Register 1040").
FAULT_RESET_EDGE = (CW_DISABLE_VOLTAGE, CW_FAULT_RESET)
FAULT_RESET_RELEASE = CW_DISABLE_VOLTAGE


def set_point_controlword(base_cw: int, relative: bool = False, immediate: bool = False,
                          halt: bool = False) -> int:
    """Controlword with New Set Point (bit 4) set, for a PP start (e.g. 0x000F -> 0x001F)."""
    cw = (base_cw & ~CW_MODE_BITS) | CW_BIT_NEW_SET_POINT
    if relative:
        cw |= CW_BIT_RELATIVE
    if immediate:
        cw |= CW_BIT_CHANGE_SET_IMMEDIATELY
    if halt:
        cw |= CW_BIT_HALT
    return cw


def set_point_acknowledged(statusword: int) -> bool:
    return bool(statusword & SW_BIT_SET_POINT_ACKNOWLEDGE)


def target_reached(statusword: int) -> bool:
    return bool(statusword & SW_BIT_TARGET_REACHED)


def homing_state(statusword: int) -> HomingState:
    """Meaning of bits 13/12/10 while in homing mode."""
    key = (bool(statusword & SW_BIT_HOMING_ERROR), bool(statusword & SW_BIT_HOMING_ATTAINED),
           bool(statusword & SW_BIT_TARGET_REACHED))
    return HOMING_STATUS[key]


# --- A small step-wise driver -------------------------------------------------------------------
class Cia402Walker:
    """Steps a drive through the tables over two callables (no transport of its own).

    The waits are step-wise (`drive.Operation`): every method that waits is a generator that yields
    the delay before its next transaction, so the bus owner serves other drives meanwhile; run one
    to its end with `drive.complete()`. One step is one or two transactions. Closing a generator
    at a yield writes nothing (no `finally` here talks to the drive).

    `min_delay_s` is the wait between a controlword write and the first statusword read that
    checks its effect (X-PLUS MT: "at least 12 ms", §13 "Register 1001" note).
    """

    POLL_S = 0.004   # statusword poll interval while waiting (rate limit, not synchronisation)
    RESEND_S = 0.25  # a command not answered by a state change is written again after this

    def __init__(self, read_statusword: Callable[[], int],
                 write_controlword: Callable[[int], None], min_delay_s: float = 0.012,
                 name: str = ''):
        self._read = read_statusword
        self._write = write_controlword
        self.min_delay_s = min_delay_s
        self.name = name
        self.controlword: int | None = None   # last value commanded, None before the first
        self._written_at = 0.0
        self.set_point_sent_t: float | None = None   # the last new set point's write (bit 4 up)

    # Low level ---------------------------------------------------------------------------------
    def write(self, controlword: int) -> None:
        """One transaction. The value counts as commanded even when the reply is lost (a lost
        reply is assumed to have reached the drive), so later words build on it."""
        self.controlword = controlword
        self._write(controlword)
        self._written_at = time.monotonic()

    def read(self) -> int:
        return self._read()

    def state(self) -> State:
        return decode_state(self._read())

    def settle(self) -> Operation[None]:
        """The rest of the controlword -> statusword delay after the last write."""
        rest = self._written_at + self.min_delay_s - time.monotonic()
        if rest > 0:
            yield rest

    def wait_for(self, condition: Callable[[int], bool], timeout_s: float
                 ) -> Operation[tuple[bool, int]]:
        """Poll the statusword (after the CW->SW delay) until condition(sw); (met, last sw)."""
        deadline = time.monotonic() + timeout_s
        yield from self.settle()
        while True:
            sw = self._read()
            if condition(sw):
                return True, sw
            if time.monotonic() >= deadline:
                return False, sw
            yield self.POLL_S

    def _prefix(self) -> str:
        return f'{self.name}: ' if self.name else ''

    # State machine -----------------------------------------------------------------------------
    def bring_to(self, target: State, timeout_s: float, reset_faults: bool = False
                 ) -> Operation[int]:
        """Walk the table to `target`; return the final statusword.

        Each step writes one controlword and waits (up to the overall deadline) for the state to
        change. Raises DriveError naming the state it stuck in and the statusword; a FAULT on the
        way raises too, unless reset_faults (then one fault-reset edge is tried).
        """
        check_target(target)   # before anything is written
        deadline = time.monotonic() + timeout_s
        sw = self._read()
        while True:
            state = decode_state(sw)
            if state == target:
                return sw
            if state == State.FAULT and not reset_faults:
                raise DriveError(f'{self._prefix()}in {describe(sw)} on the way to '
                                 f'{target.value}: fault reset first')
            if state == State.FAULT:
                reset_faults = False   # one attempt
                sw = yield from self.fault_reset(
                    max(deadline - time.monotonic(), self.min_delay_s))
                continue
            cw = next_controlword(state, target) if state != State.UNKNOWN else None
            while True:
                if cw is not None:
                    self.write(cw)   # again after RESEND_S: harmless for level commands
                left = max(deadline - time.monotonic(), 0.0)
                met, sw = yield from self.wait_for(lambda s, st=state: decode_state(s) != st,
                                                   min(left, self.RESEND_S))
                if met or left <= self.RESEND_S:
                    break
            if not met:
                after = f' after controlword 0x{cw:04X}' if cw is not None else ''
                raise DriveError(f'{self._prefix()}stuck in {describe(sw)}{after} on the way '
                                 f'to {target.value} ({timeout_s:g} s)')

    def fault_reset(self, timeout_s: float) -> Operation[int]:
        """Fault reset as a bit-7 rising edge; returns the statusword afterwards.

        Waits out FAULT REACTION ACTIVE first. Leaves bit 7 at 0. Does not raise when the fault
        persists (cause still present): the caller reads why.
        """
        deadline = time.monotonic() + timeout_s
        met, sw = yield from self.wait_for(
            lambda s: decode_state(s) != State.FAULT_REACTION_ACTIVE, timeout_s)
        if decode_state(sw) != State.FAULT:
            return sw
        for cw in FAULT_RESET_EDGE:
            self.write(cw)
            yield from self.settle()
        met, sw = yield from self.wait_for(lambda s: decode_state(s) != State.FAULT,
                                           max(deadline - time.monotonic(), 0.0))
        self.write(FAULT_RESET_RELEASE)
        if not met:
            logger.info('%sfault reset did not clear the fault: %s', self._prefix(), describe(sw))
        return sw

    # Profile position --------------------------------------------------------------------------
    def start_set_point(self, base_cw: int, relative: bool = False, immediate: bool = False,
                        timeout_s: float = 0.5) -> Operation[int]:
        """New-set-point handshake: bit 4 up, wait for SW bit 12, bit 4 down; returns the sw.

        A previous bit 4 still set is first cleared, so the drive sees a rising edge.
        """
        cw = set_point_controlword(base_cw, relative, immediate)
        idle = cw & ~CW_BIT_NEW_SET_POINT
        if self.controlword is None or self.controlword & CW_BIT_NEW_SET_POINT:
            self.write(idle)
            yield from self.wait_for(lambda s: not set_point_acknowledged(s), timeout_s)
        self.write(cw)
        self.set_point_sent_t = self._written_at
        met, sw = yield from self.wait_for(set_point_acknowledged, timeout_s)
        self.write(idle)
        if not met:
            raise DriveError(f'{self._prefix()}set point not acknowledged (statusword bit 12) '
                             f'within {timeout_s:g} s after controlword 0x{cw:04X}: '
                             f'{describe(sw)}')
        return sw
