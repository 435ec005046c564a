"""Device-side CiA 402 (DSP 402) for the simulators, as tables: the drive's half of the protocol.

One module for both CiA 402 simulators (R.T.A. X-PLUS MT on Modbus registers 1040/1001, AEC Vector
Step on CANopen 0x6040/0x6041), written like canopen's `profiles/p402.py`: tables, and a short
engine that walks them. It plays the drive, so it is independent of the driver's
`stepper_drivers/profiles/cia402/state_machine.py` (which plays the master); the simulators
must not share its logic.

Sources, cited below as:
- X-PLUS: `shared/manuals/rta_xplus_mt_modbus_tcp.txt` §12 "Drive Sub-States" (transitions), T13
  "Bit of the Control Word", T14 "Bit of the Status Word", §13 "Register 1001"/"Register 1040"/
  "Register 1085", §13 "Multi-Set-Point Mode";
- AEC: `shared/manuals/aec_vector_step_canopen_it.txt` [CONTROLWORD] (command table), [STATUSWORD]
  (state table), [MACCHINA A STATI DSP-402 V1.1] "Definizioni transizioni", [QUICK STOP OPTION
  CODE], [SHUTDOWN OPTION CODE], [DISABLE OPERATION OPTION CODE], [FAULT REACTION OPTION CODE].
Where the two manuals differ, `Profile` says how (`XPLUS_MT`, `VECTOR_STEP`); the tables are one.

What stays in each drive: its modes' motion, what a transition does to its own flags (homing
abort, JOG, encoder reset), the conditions a transition needs on that drive (HV, STO), and the
statusword bits of its modes (zero speed, motor moving, following error).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Protocol

logger = logging.getLogger(__name__)

# --- States (T14; AEC [STATUSWORD] state table) -----------------------------------------------
NOT_READY_TO_SWITCH_ON = 'NOT READY TO SWITCH ON'
SWITCH_ON_DISABLED = 'SWITCH ON DISABLED'
READY_TO_SWITCH_ON = 'READY TO SWITCH ON'
SWITCHED_ON = 'SWITCHED ON'
OPERATION_ENABLED = 'OPERATION ENABLED'
QUICK_STOP_ACTIVE = 'QUICK STOP ACTIVE'
FAULT_REACTION_ACTIVE = 'FAULT REACTION ACTIVE'
FAULT = 'FAULT'
NRTSO, SOD, RTSO, SO = (NOT_READY_TO_SWITCH_ON, SWITCH_ON_DISABLED, READY_TO_SWITCH_ON,
                        SWITCHED_ON)
OE, QSA, FRA = OPERATION_ENABLED, QUICK_STOP_ACTIVE, FAULT_REACTION_ACTIVE
CURRENT_ON_STATES = (OE, QSA)      # X-PLUS §12: current in the windings in OE and QSA only

# --- Controlword bits (X-PLUS §13 "Register 1040"; AEC [CONTROLWORD] "Dettagli") --------------
CW_SWITCH_ON = 1 << 0
CW_ENABLE_VOLTAGE = 1 << 1
CW_QUICK_STOP = 1 << 2             # active low
CW_ENABLE_OPERATION = 1 << 3
CW_NEW_SET_POINT = 1 << 4          # PP: new set-point; homing: start (both on the rising edge)
CW_CHANGE_SET_IMMEDIATELY = 1 << 5
CW_RELATIVE = 1 << 6               # PP: 0 = absolute, 1 = relative
CW_FAULT_RESET = 1 << 7            # rising edge (T13 "Trans. L/H", AEC "↗")
CW_HALT = 1 << 8                   # X-PLUS only (AEC: bit 8 "Riservato")

# --- Device control commands: name -> (mask, value) over bits 7, 3, 2, 1, 0 --------------------
# T13 and AEC [CONTROLWORD] "Command / Bit of Controlword" (X = not in the mask). Fault reset is
# an edge of bit 7, not a level, so it is not here.
SHUTDOWN = 'shutdown'
SWITCH_ON = 'switch on'
DISABLE_VOLTAGE = 'disable voltage'
QUICK_STOP = 'quick stop'
DISABLE_OPERATION = 'disable operation'
ENABLE_OPERATION = 'enable operation'
COMMANDS: dict[str, tuple[int, int]] = {
    SHUTDOWN: (0x0087, 0x0006),            # 0 X 1 1 0  -> 2, 6, 8
    SWITCH_ON: (0x0087, 0x0007),           # 0 X 1 1 1  -> 3 (bit 3 X: 0x0F goes on to OE)
    DISABLE_VOLTAGE: (0x0082, 0x0000),     # 0 X X 0 X  -> 7, 9, 10, 12
    QUICK_STOP: (0x0086, 0x0002),          # 0 X 0 1 X  -> 7, 10, 11
    DISABLE_OPERATION: (0x008F, 0x0007),   # 0 0 1 1 1  -> 5
    ENABLE_OPERATION: (0x008F, 0x000F),    # 0 1 1 1 1  -> 4, 16
}

# --- Transitions: (state, command) -> (next state, transition number) --------------------------
# X-PLUS §12 / T13 "Transitions" column; AEC "Definizioni transizioni" (same DSP-402 numbering).
# Quick stop in RTSO/SO (7, 10): T13 and X-PLUS §12 transition 10 list it, the AEC table lists
# quick stop for 11 only; CiA 402 has it, and so do both simulators.
TRANSITIONS: dict[tuple[str, str], tuple[str, int]] = {
    (SOD, SHUTDOWN): (RTSO, 2),
    (RTSO, SWITCH_ON): (SO, 3),
    (SO, ENABLE_OPERATION): (OE, 4),
    (OE, DISABLE_OPERATION): (SO, 5),
    (SO, SHUTDOWN): (RTSO, 6),
    (RTSO, DISABLE_VOLTAGE): (SOD, 7),
    (RTSO, QUICK_STOP): (SOD, 7),
    (OE, SHUTDOWN): (RTSO, 8),
    (OE, DISABLE_VOLTAGE): (SOD, 9),
    (SO, DISABLE_VOLTAGE): (SOD, 10),
    (SO, QUICK_STOP): (SOD, 10),
    (OE, QUICK_STOP): (QSA, 11),
    (QSA, DISABLE_VOLTAGE): (SOD, 12),
    (QSA, ENABLE_OPERATION): (OE, 16),     # only with quick stop option 5 or 6 (below)
}
FAULT_TRANSITION = 13                  # any -> FRA on an internal fault
FAULT_RESET_TRANSITION = 15            # FAULT -> SOD on the bit 7 edge, once the cause is gone
DIRECT_SEQUENCE = 3                    # X-PLUS §12: 0x0006 -> 0x000F passes RTSO, SO, OE at once

# --- Statusword ------------------------------------------------------------------------------
SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4        # X-PLUS "Voltage Enabled"; AEC "Voltage disabled" (A16: = 1)
SW_QUICK_STOP = 1 << 5             # active low
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_MANUFACTURER_8 = 1 << 8         # AEC: "Motor moving"
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_BIT12 = 1 << 12                 # PP set-point ack / homing attained / PV, JOG zero speed
SW_BIT13 = 1 << 13                 # following error / homing error
SW_PROFILE_RAMP = 1 << 15          # X-PLUS (1107 = 1)
SW_SET_POINT_ACKNOWLEDGE = SW_HOMING_ATTAINED = SW_BIT12
SW_FOLLOWING_ERROR = SW_HOMING_ERROR = SW_BIT13

# State -> (bits 0-3, 5, 6 as the tables give them, the bits the tables leave X). T14 and AEC
# [STATUSWORD]; FRA: AEC table (X-PLUS quotes it only as 0x201F, §13 "Register 1085").
STATE_WORD: dict[str, tuple[int, int]] = {
    NRTSO: (0x0000, SW_QUICK_STOP),
    SOD: (0x0040, SW_QUICK_STOP),      # T14 prints bit 5 = 1 here, AEC and CiA 402 print X
    RTSO: (0x0021, 0),
    SO: (0x0023, 0),
    OE: (0x0027, 0),
    QSA: (0x0007, 0),
    FRA: (0x000F, SW_QUICK_STOP),
    FAULT: (0x0008, SW_QUICK_STOP),
}

# --- Option codes: how a transition stops the motor ---------------------------------------------
CURRENT_OFF = 'current off'          # "Disable drive function": no ramp, the shaft is not driven
SLOW_DOWN_RAMP = 'slow down ramp'    # the profile (mode) deceleration
QUICK_STOP_RAMP = 'quick stop ramp'  # the quick stop deceleration
# 0x605A (AEC [QUICK STOP OPTION CODE]; X-PLUS: fixed at 5, §12 transition 16): transition 11 ->
# (ramp, state once stopped).
QUICK_STOP_OPTIONS: dict[int, tuple[str, str]] = {
    0: (CURRENT_OFF, SOD), 1: (SLOW_DOWN_RAMP, SOD), 2: (QUICK_STOP_RAMP, SOD),
    5: (SLOW_DOWN_RAMP, QSA), 6: (QUICK_STOP_RAMP, QSA),
}
QUICK_STOP_RESERVED = (SLOW_DOWN_RAMP, QSA)       # reserved codes: ramp, stay (as the sims did)
STAY_IN_QUICK_STOP = tuple(k for k, (_, final) in QUICK_STOP_OPTIONS.items() if final == QSA)
# 0x605B (transition 8) and 0x605C (transition 5): 0 disable drive function, 1 slow down ramp.
SHUTDOWN_OPTIONS = DISABLE_OPERATION_OPTIONS = {0: CURRENT_OFF, 1: SLOW_DOWN_RAMP}
# 0x605E fault reaction (AEC [FAULT REACTION OPTION CODE]); 0x605D stop option has the same codes.
FAULT_REACTION_OPTIONS = {0: CURRENT_OFF, 1: SLOW_DOWN_RAMP, 2: QUICK_STOP_RAMP}
STOP_OPTIONS = FAULT_REACTION_OPTIONS
OPTION_TABLES = {5: DISABLE_OPERATION_OPTIONS, 8: SHUTDOWN_OPTIONS}


@dataclasses.dataclass(frozen=True)
class Profile:
    """What the two manuals make differ in the same standard behaviour."""

    name: str
    # states whose "X" bit 5 (quick stop) reads 1: T14 prints 1 for SOD; the X-PLUS quotes
    # 0x1218 (Fault) and 0x201F (FRA) with bit 5 = 0. The AEC table leaves it X: shown 1.
    quick_stop_bit_in: frozenset[str]
    # X-PLUS §13 "Register 1085": FRA reads 0x201F, "bit Remote and Quick Stop are set = 0"
    remote_in_fault_reaction: bool
    # option codes the manual fixes (X-PLUS: quick stop 5, §12 transition 16; transitions 5/8
    # "current disabled", §12); None: the drive's object (AEC 0x605A/0x605B/0x605C)
    fixed_options: dict[int, int] | None
    # set-points accepted behind a running one with bit 5 = 0: X-PLUS none ("parameters cannot
    # be modified when motor is running", Multi-Set-Point bit 5 = 0), AEC one (CiA 402 PP)
    set_point_buffer: int
    # states in which bit 10 (target reached) is shown: X-PLUS only with current on (0x0233,
    # 0x0231 quoted without it), AEC in every state
    target_reached_states: frozenset[str] | None


XPLUS_MT = Profile('X-PLUS MT', quick_stop_bit_in=frozenset({SOD}),
                   remote_in_fault_reaction=False, fixed_options={11: 5, 8: 0, 5: 0},
                   set_point_buffer=0, target_reached_states=frozenset(CURRENT_ON_STATES))
VECTOR_STEP = Profile('Vector Step', quick_stop_bit_in=frozenset({NRTSO, SOD, FRA, FAULT}),
                      remote_in_fault_reaction=True, fixed_options=None, set_point_buffer=1,
                      target_reached_states=None)


def commands(controlword: int) -> tuple[str, ...]:
    """The device control commands a controlword level matches (several where bits are X)."""
    return tuple(name for name, (mask, value) in COMMANDS.items() if controlword & mask == value)


def next_transition(state: str, controlword: int) -> tuple[str, int] | None:
    """(next state, number) the controlword level asks for in `state`, or None."""
    for command in commands(controlword):
        found = TRANSITIONS.get((state, command))
        if found is not None:
            return found
    return None


def state_word(profile: Profile, state: str, *, voltage_enabled: bool) -> int:
    """Statusword bits 0-6 and 9 of a state (T14 / AEC [STATUSWORD]), no mode bits."""
    value, x_bits = STATE_WORD[state]
    if state in profile.quick_stop_bit_in:
        value |= x_bits & SW_QUICK_STOP
    if voltage_enabled:
        value |= SW_VOLTAGE_ENABLED
    if state != FRA or profile.remote_in_fault_reaction:
        value |= SW_REMOTE
    return value


def homing_bits(*, attained: bool, error: bool, running: bool, moving: bool) -> int:
    """Homing mode bits 13/12/10 (X-PLUS §13 "Register 1001" Homing table; AEC [STATUSWORD]
    "Home eseguito"/"Errore in azzeramento"; CiA 402: bit 10 once the procedure has ended and the
    motor stands)."""
    bits = SW_HOMING_ATTAINED if attained else 0
    if error:
        bits |= SW_HOMING_ERROR
    if not running and not moving:
        bits |= SW_TARGET_REACHED
    return bits


class DriveHooks(Protocol):
    """What the engine needs from the drive it runs in (methods `cia_*` of the drive)."""

    def cia_allows(self, number: int) -> bool:
        """The drive's own conditions for a transition (X-PLUS HV for 3/4, AEC STO for 2)."""

    def cia_moving(self) -> bool: ...

    def cia_option_code(self, transition: int) -> int:
        """The option code object for transition 5 (0x605C), 8 (0x605B), 11 (0x605A)."""

    def cia_stop(self, ramp: str, transition: int) -> None:
        """Stop the motor for `transition` (13 = fault reaction): CURRENT_OFF at once, or on
        SLOW_DOWN_RAMP / QUICK_STOP_RAMP."""

    def cia_leaving(self, number: int, source: str, target: str) -> None:
        """The drive's own effects of a transition, before the engine stops the motor."""

    def cia_left(self, number: int, source: str, target: str) -> None:
        """... and after it (the state may still wait for standstill: `pending`)."""


class SetPointHandshake:
    """PP new-set-point / set-point-acknowledge (X-PLUS §13 "Register 1040" bit 4-5 and
    "Multi-Set-Point Mode"; AEC [CONTROLWORD] bits 4-6, [STATUSWORD] bit 12 "Setpoint
    acquisito"; CiA 402 PP handshake)."""

    START, QUEUED, IGNORED = 'start', 'queued', 'ignored'

    def __init__(self, buffer: int):
        self.buffer = buffer
        self.acknowledged = False
        self.queued: float | None = None

    def reset(self) -> None:
        self.acknowledged = False
        self.queued = None

    def new_set_point(self, target: float | None, *, busy: bool, immediate: bool) -> str:
        """Bit 4 rising edge. busy: a set-point is running; immediate: bit 5."""
        if busy and not immediate:
            if not self.buffer:
                return self.IGNORED         # X-PLUS: not acknowledged, the move goes on
            self.queued = target            # CiA 402: run after the current one
            self.acknowledged = True
            return self.QUEUED
        self.queued = None
        self.acknowledged = True
        return self.START

    def released(self) -> None:
        """Bit 4 falling edge: the master saw the acknowledge."""
        self.acknowledged = False

    def take_queued(self) -> float | None:
        """At standstill: the buffered set-point, now to run."""
        target, self.queued = self.queued, None
        return target

    def target_reached(self, moving: bool) -> bool:
        return not moving and self.queued is None


class PowerStateMachine:
    """The drive's CiA 402 power state machine, evaluated on controlword levels (X-PLUS A4).

    `pending` is a transition that completes at standstill (a ramp option of 0x605A/B/C).
    """

    def __init__(self, profile: Profile, hooks: DriveHooks, name: str,
                 state: str = SOD):
        self.profile = profile
        self.hooks = hooks
        self.name = name
        self.state = state
        self.pending: tuple[str, int] | None = None

    # ---------------------------------------------------------------- controlword
    def option(self, transition: int) -> int:
        fixed = self.profile.fixed_options
        return fixed[transition] if fixed is not None else self.hooks.cia_option_code(transition)

    def apply(self, controlword: int) -> bool:
        """Follow the controlword level (the direct sequence of X-PLUS §12 included)."""
        changed = False
        for _ in range(DIRECT_SEQUENCE):
            if self.pending is not None or self.state in (FAULT, FRA):
                break
            found = self._allowed(next_transition(self.state, controlword))
            if found is None:
                break
            self._fire(*found)
            changed = True
        return changed

    def _allowed(self, found: tuple[str, int] | None) -> tuple[str, int] | None:
        if found is None:
            return None
        if found[1] == 16 and self.option(11) not in STAY_IN_QUICK_STOP:
            return None                 # QSA -> OE only with option 5/6 (X-PLUS §12 tr. 16)
        return found if self.hooks.cia_allows(found[1]) else None

    def _fire(self, target: str, number: int) -> None:
        source = self.state
        logger.info('%s: transition %d %s -> %s', self.name, number, source, target)
        self.hooks.cia_leaving(number, source, target)
        if number == 11:
            ramp, final = QUICK_STOP_OPTIONS.get(self.option(11), QUICK_STOP_RESERVED)
            self.state = QSA
            if ramp == CURRENT_OFF or not self.hooks.cia_moving():
                self.hooks.cia_stop(CURRENT_OFF, number)
                self.state = final
            else:
                self.hooks.cia_stop(ramp, number)
                if final != QSA:
                    self.pending = (final, 12)       # CiA 402: transition 12 at standstill
        elif source in CURRENT_ON_STATES and target not in CURRENT_ON_STATES:
            table = OPTION_TABLES.get(number)
            ramp = table.get(self.option(number), CURRENT_OFF) if table else CURRENT_OFF
            if ramp != CURRENT_OFF and self.hooks.cia_moving():
                self.hooks.cia_stop(ramp, number)
                self.pending = (target, number)      # current off once stopped
            else:
                self.hooks.cia_stop(CURRENT_OFF, number)
                self.state = target
        else:
            self.state = target
        self.hooks.cia_left(number, source, target)

    def settle(self) -> None:
        """At standstill: a pending transition completes; FRA -> FAULT (transition 14)."""
        if self.hooks.cia_moving():
            return
        if self.pending is not None:
            target, number = self.pending
            self.pending = None
            logger.info('%s: transition %d completed at standstill', self.name, number)
            self.state = target
        if self.state == FRA:
            self.state = FAULT

    # ---------------------------------------------------------------- faults
    def fault(self, ramp: str) -> bool:
        """Transition 13: FAULT REACTION ACTIVE, the motor stopped per the fault reaction;
        `settle` completes transition 14. False when already in FRA/FAULT."""
        if self.state in (FAULT, FRA):
            return False
        was_on = self.state in CURRENT_ON_STATES
        self.pending = None
        self.state = FRA
        if not was_on or ramp == CURRENT_OFF or not self.hooks.cia_moving():
            self.hooks.cia_stop(CURRENT_OFF, FAULT_TRANSITION)
        else:
            self.hooks.cia_stop(ramp, FAULT_TRANSITION)
        return True

    def fault_reset_edge(self, controlword: int, previous: int) -> bool:
        """Bit 7 rising edge in FAULT: a fault reset request (transition 15 if it may)."""
        return (self.state == FAULT and bool(controlword & CW_FAULT_RESET)
                and not previous & CW_FAULT_RESET)

    def fault_reset(self) -> None:
        """Transition 15, the drive having checked that the cause is gone."""
        logger.info('%s: transition %d %s -> %s', self.name, FAULT_RESET_TRANSITION, self.state,
                    SOD)
        self.state = SOD

    def force(self, state: str) -> None:
        """A change outside the controlword (power-on, STO, a vendor disable command)."""
        self.pending = None
        if state != self.state:
            logger.info('%s: %s -> %s', self.name, self.state, state)
            self.state = state

    # ---------------------------------------------------------------- statusword
    def state_word(self, *, voltage_enabled: bool) -> int:
        return state_word(self.profile, self.state, voltage_enabled=voltage_enabled)

    def shows_target_reached(self) -> bool:
        states = self.profile.target_reached_states
        return states is None or self.state in states
