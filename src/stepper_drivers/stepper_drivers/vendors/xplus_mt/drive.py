"""The R.T.A. X-PLUS MT drive class: power stage, motion, homing and maintenance on an
`XplusMtUnit`, filling the hooks of `profiles.cia402.drive.Cia402Drive`. No rclpy.

Operations that wait (enable, disable, fault_reset, move_to, set_velocity, start_homing) are
step-wise (`contract.drive.Operation`): they yield between transactions, so the bus owner serves
the other drives meanwhile. connect, read_state, stop and save_params are one short burst each.
"""

from __future__ import annotations

import time

from ...contract.capabilities import Retargeting
from ...contract.drive import DriveError, Homing, Motion, Operation, State
from ...profiles.cia402 import state_machine as cia402
from ...profiles.cia402.modes import HomingMode, Mode, ProfilePositionMode, ProfileVelocityMode
from ...profiles.cia402.state_machine import (
    CW_BIT_HALT,
    CW_BIT_NEW_SET_POINT,
    SW_BIT_VOLTAGE_ENABLED,
)
from ...protocol.modbus_tcp import ModbusExceptionError
from . import regmap as xm
from .unit import XplusMtUnit

_HALT = Mode()                     # a mode whose stop is Halt (bit 8): every X-PLUS MT mode
# A move_to on the connection (move_time_s), in round trips: the state read, the target, the
# set-point handshake's bit 4 up, acknowledge read and bit 4 down, and about one more for the
# work of its steps between them (against the simulator a move's steps take 6-7 round trips).
MOVE_TRANSACTIONS = 6


class XplusMtDrive(XplusMtUnit, Retargeting):
    """One X-PLUS MT on a Modbus TCP connection (unit id = parameter `unit_id`).

    Retargeting: §13 "Multi-Set-Point Mode" (bit 5 set by every move): a monotonous new target
    is taken "without intermediate stops"; a reversing one stops and restarts."""

    start_stop_steps_s = float(xm.START_STOP_MAX_HZ)     # §13 "Motion Profiles"
    min_velocity_steps_s = 1.0        # PROFILE_VELOCITY (1044) in whole Hz, 0 refused
    CW_SW_DELAY_S = 0.012      # §13 "Register 1001" note: >= 12 ms before checking the SW
    ENABLE_TIMEOUT_S = 1.5     # the 3 steps + HV "at least 500 ms before" transition 3 (§12)
    STATUSWORD_READ_IS_TRANSACTION = True     # every statusword read is an FC03 of 1001
    # §12 "Mode of Operation", §13 "Register 1041": 1, 3, 6
    MODES = (ProfilePositionMode(), ProfileVelocityMode(), HomingMode())
    # The start edges (homing, PV) write 0x000F first in every case: it also clears bits 5/6 of
    # a profile position handshake before them.
    START_EDGE_LOW_ALWAYS = True

    def move_time_s(self) -> float:
        """A move_to's time on the connection: MOVE_TRANSACTIONS of its measured round trip
        (the 12 ms wait in the set-point handshake is not the connection's)."""
        return MOVE_TRANSACTIONS * self.mb.transaction_s

    # ------------------------------------------------------------------ power stage
    # enable() and disable() are Cia402Drive's; the X-PLUS MT's parts of them:
    def _enable_refusal(self, sw: int) -> str:
        code = self._read('ERROR_CODE')
        return f'enable: drive is in {cia402.describe(sw)}, {self._error_text(code)}'

    def _hold_position(self, state: State) -> Operation[None]:
        if state != State.QUICK_STOP_ACTIVE:
            # Nothing may move: Target Position := Position Actual Value, then Profile Position.
            actual = self._read('POSITION_ACTUAL_VALUE')
            self._write(('TARGET_POSITION', actual))
            yield 0.0
            yield from self._set_mode(xm.MODE_PROFILE_POSITION)

    def _before_switch_on(self, state: State) -> Operation[None]:
        """Switch On (transition 3) needs the high voltage: checked in READY TO SWITCH ON."""
        if state in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON):
            sw = yield from self.cia.bring_to(State.READY_TO_SWITCH_ON, self.ENABLE_TIMEOUT_S)
            if not sw & SW_BIT_VOLTAGE_ENABLED:
                raise DriveError(
                    f'enable: the power stage has no high voltage: {cia402.describe(sw)} with '
                    f'Voltage Enabled (status word bit 4) = 0; Switch On needs HV present at '
                    f'least 500 ms before (§12 transition 3)')
            yield 0.0

    def _enable_failed(self, exc: DriveError) -> None:
        sw = self._read_statusword()
        if cia402.decode_state(sw) == State.READY_TO_SWITCH_ON:
            hv = 'present' if sw & SW_BIT_VOLTAGE_ENABLED else 'absent (bit 4 = 0)'
            raise DriveError(f'{exc}; high voltage {hv}: Switch On needs HV at least '
                             f'500 ms before the transition (§12 transition 3)') from exc

    def _enabled(self, switched_on: bool) -> None:
        if switched_on:
            self._current_on_at = time.monotonic()
        self._was_enabled = True

    def _disabled(self) -> None:
        # (disable leaves a drive in FAULT alone: current is already off; leaving Fault needs
        # fault_reset)
        self._current_on_at = None
        self._was_enabled = False

    # ------------------------------------------------------------------ motion
    def _statusword_for_motion(self) -> tuple[int, int]:
        """One FC03 of 1001..1002: the state checked on the wire, and Modes of Operation Display
        (1002), so no second read is needed for the mode."""
        sw, mode = self._read_words(1001, 2)
        mode = mode - 0x10000 if mode & 0x8000 else mode
        self._shown = (sw, mode)
        return sw, mode

    def _wait_settled(self) -> Operation[None]:
        """§12 note: New Set Points sent before the motor settled (~50-200 ms, and 1096 Brake
        Delay Azio Ready) after current on "can cause a loss of synchronism"."""
        if self._current_on_at is None:
            return
        rest = self._current_on_at + self._settle_s - time.monotonic()
        if rest > 0:
            yield rest

    def _set_mode(self, mode: int) -> Operation[None]:
        self._write(('MODE_OF_OPERATION', mode))
        deadline = time.monotonic() + self.MODE_SWITCH_TIMEOUT_S
        while True:
            yield cia402.Cia402Walker.POLL_S
            # the display (1002) with the statusword (1001) in one FC03: its bits in the new
            # mode (a homing's previous result) come with it
            sw, shown = self._read_words(1001, 2)
            shown = shown - 0x10000 if shown & 0x8000 else shown
            self._shown = (sw, shown)
            if shown == mode:
                yield 0.0       # the caller's next transaction in a step of its own
                return
            if time.monotonic() > deadline:
                raise DriveError(f'MODE_OF_OPERATION (1041) := {mode} not taken: '
                                 f'MODE_OF_OPERATION_DISPLAY (1002) reads {shown}')

    def _in_mode(self, mode: int, current: int | None = None) -> bool:
        """`current`: 1002 as read by _require_enabled just before (the step that read it)."""
        return current == mode

    def _switch_mode(self, mode: Mode, what: str, current: int | None) -> Operation[None]:
        state = self.read_state()
        if state.moving:
            raise DriveError(f'{what}: the drive is moving in {state.mode or f"mode {current}"};'
                             f' stop first (modes change at standstill only)')
        yield 0.0
        yield from self._set_mode(mode.code)
        self.cia.controlword = None

    def _release_halt(self) -> Operation[None]:
        """A Halt we commanded is released on its own first: a halt release and a new set point
        in one write is not described by the manual (§13 "Register 1040" bit 8)."""
        cw = self.cia.controlword
        if cw is not None and cw & CW_BIT_HALT:
            self.cia.write(cw & ~(CW_BIT_HALT | CW_BIT_NEW_SET_POINT))
            yield 0.0

    def _motion_values(self, motion: Motion, what: str) -> tuple[float, int, int]:
        accel = self._checked('PROFILE_ACCELERATION', motion.acceleration_steps_s2,
                              f'{what}: acceleration ')
        decel = self._checked('PROFILE_DECELERATION', motion.deceleration_steps_s2,
                              f'{what}: deceleration ')
        return motion.velocity_steps_s, accel, decel

    def move_to(self, target_steps: int, motion: Motion) -> Operation[None]:
        # Every value is checked against its register before anything is read or written.
        velocity, accel, decel = self._motion_values(motion, 'move_to')
        velocity = self._checked('PROFILE_VELOCITY', abs(velocity), 'move_to: velocity ')
        if velocity == 0:
            raise DriveError('move_to: velocity 0 is not accepted by PROFILE_VELOCITY (1044) '
                             'for a move (§13 "Multi-Set-Point Mode" limit 3)')
        target = self._checked('TARGET_POSITION', target_steps, 'move_to: target ')
        mode = self._require_enabled('move_to')    # one FC03 for the state and the mode
        pp = yield from self._ensure_mode(xm.MODE_PROFILE_POSITION, 'move_to', mode)
        # 1042..1047 contiguous: one FC16 for target, velocity and acceleration (§11: a 32-bit
        # value is committed when its second word is written; all pairs complete in one request).
        self._write(('TARGET_POSITION', target), ('PROFILE_VELOCITY', velocity),
                    ('PROFILE_ACCELERATION', accel))
        self._write_once('PROFILE_DECELERATION', decel)
        yield 0.0
        yield from self._wait_settled()
        yield from self._release_halt()
        yield from pp.start(self)

    def set_velocity(self, velocity_steps_s: float, motion: Motion) -> Operation[None]:
        _, accel, decel = self._motion_values(motion, 'set_velocity')
        # A8: signed, negative = reverse
        velocity = self._checked('TARGET_VELOCITY', velocity_steps_s, 'set_velocity: ')
        mode = self._require_enabled('set_velocity')
        pv = yield from self._ensure_mode(xm.MODE_PROFILE_VELOCITY, 'set_velocity', mode)
        self._write(('PROFILE_ACCELERATION', accel), ('TARGET_VELOCITY', velocity))
        self._write_once('PROFILE_DECELERATION', decel)
        cw = self.cia.controlword
        running = cw is not None and cw & CW_BIT_NEW_SET_POINT and not cw & CW_BIT_HALT
        if not running:
            # A10: PV follows Target Velocity in OE after a bit-4 rising edge (bit 4 held).
            yield 0.0
            yield from self._wait_settled()
            yield from pv.start_edge(self)

    def stop(self, quick: bool = False) -> None:
        """One FC03 and at most one FC06: the urgent path waits for nothing."""
        sw = self._read_statusword()
        state = cia402.decode_state(sw)
        if quick:
            if state == State.OPERATION_ENABLED:
                self.cia.write(cia402.CW_QUICK_STOP)     # transition 11, QS option code 5
            return
        if state != State.OPERATION_ENABLED:
            return
        # Halt (bit 8) stops a run in each of the modes (§13 "Register 1040" bit 8), with the
        # mode's deceleration: which one the drive is in needs no read.
        self.cia.write(_HALT.stop_controlword(self.cia.controlword))

    def start_homing(self, homing: Homing) -> Operation[str]:
        method = int(homing.method)
        if method not in xm.HOMING_METHODS:
            raise DriveError(f'homing.method: {method} is not a homing method of the X-PLUS MT '
                             f'(allowed: {", ".join(map(str, xm.HOMING_METHODS))})')
        # all values checked against their registers before anything is read or written
        writes: list[tuple[str, int]] = [('HOMING_METHOD', method)]
        if method not in xm.HOMING_METHODS_CURRENT_POSITION:   # 35/37 do not move
            writes += [
                ('HOMING_SPEED_SEARCH_SWITCH', self._checked(
                    'HOMING_SPEED_SEARCH_SWITCH', homing.speed_search_steps_s,
                    'home: homing.speed_search ')),
                ('HOMING_SPEED_SEARCH_ZERO', self._checked(
                    'HOMING_SPEED_SEARCH_ZERO', homing.speed_zero_steps_s,
                    'home: homing.speed_zero ')),
                ('HOMING_ACCELERATION', self._checked(
                    'HOMING_ACCELERATION', homing.acceleration_steps_s2,
                    'home: homing.acceleration '))]
        writes.append(('HOMING_OFFSET', self._checked('HOMING_OFFSET', homing.offset_steps,
                                                      'home: homing.offset ')))
        mode = self._require_enabled('home')
        if method in xm.HOMING_METHODS_HOME_SWITCH:
            # 1085..1088 in one FC03: following error reaction and input config
            reaction, _, _, input_config = self._read_words(1085, 4)
            if input_config & 0x01:
                raise DriveError(
                    f'home: method {method} needs the home switch on I0, but INPUT_CONFIG '
                    f'(1088) = {input_config} has bit 0 (IC0) = 1, i.e. I0 is a general-purpose '
                    f'input; set drives.{self.name}.input_config with bit 0 = 0 (e.g. 14: I0 '
                    f'proximity input), or write 1088 and save_params')
            if method in xm.HOMING_METHODS_NEED_INDEX and reaction == 17:
                raise DriveError(f'home: method {method} uses the encoder index, but '
                                 f'FOLLOWING_ERROR_REACTION_CODE (1085) = 17 (motor without '
                                 f'encoder)')
        homing_mode = yield from self._ensure_mode(xm.MODE_HOMING, 'home', mode)
        # what the drive showed in homing mode before the start edge (the read above, or the
        # mode switch's): its previous homing's ATTAINED is no start of this one
        sw, shown = self._shown
        self._homing_shown_before = cia402.homing_state(sw) if shown == xm.MODE_HOMING else None
        self._write(*writes)
        self._homed = False
        yield 0.0
        yield from self._wait_settled()
        yield from self._release_halt()
        # homing start: bit 4 rising edge held high while homing, then "homing started"
        yield from homing_mode.start(self)
        return ''

    # ------------------------------------------------------------------ maintenance
    # fault_reset() is Cia402Drive's (one bit-7 edge); the X-PLUS MT's parts of it:
    def _fault_remains(self, sw: int) -> Operation[str]:
        yield 0.0
        return (f'{self._error_text(self._read("ERROR_CODE"))}; still in '
                f'{cia402.describe(sw)}: the cause is still present')

    def _fault_cleared(self, sw: int) -> None:
        self._was_enabled = False

    def save_params(self) -> str:
        """One burst, not step-wise: the watchdog is off in between (see below), and a step
        boundary there could leave it off if the operation were cut short."""
        # 1097 is storable (App.1 '**'), but the node arms it at every connect: stored, it would
        # fault every drive powered up without a master. So the flash gets 1097 = 0 and RAM gets
        # the node's value back right after the signature.
        if self._watchdog_armed:
            self._write(('COUNTER_WATCHDOG', 0))
        try:
            self.mb.write_register(self.unit_id, xm.SAVE_PARAMS_REGISTER,
                                   xm.SAVE_PARAMS_SIGNATURE)
            echo = self._read_words(xm.SAVE_PARAMS_REGISTER, 1)[0]
        except ModbusExceptionError:
            if self._watchdog_armed:     # refused: the link is fine, re-arm before reporting
                self._write(('COUNTER_WATCHDOG', self.watchdog_ms))
            raise
        # (after a LinkError the node reconnects, and connect() arms the watchdog again)
        watchdog = ''
        if self._watchdog_armed:
            self._write(('COUNTER_WATCHDOG', self.watchdog_ms))
            watchdog = (f'; COUNTER_WATCHDOG (1097) was stored as 0 (off) and is armed again '
                        f'({self.watchdog_ms} ms) in RAM')
        return (f'signature 0x{xm.SAVE_PARAMS_SIGNATURE:04X} written to SAVE_ALL_PARAMETERS '
                f'(1260) and acknowledged by the drive (1260 now reads 0x{echo:04X}); the '
                f'manual gives no completion flag, so the save itself cannot be verified over '
                f'Modbus; keep the 24 V logic supply on for more than '
                f'{xm.SAVE_HOLD_24V_S:g} s (§13 "Register 1260" Note1){watchdog}')
