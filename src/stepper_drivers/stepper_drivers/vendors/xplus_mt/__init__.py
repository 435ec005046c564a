"""R.T.A. X-PLUS MT (B4/S4) over Modbus TCP: the drive class and the vendor description.

Register numbers, bit meanings and timings come from the manual `rta_xplus_mt_modbus_tcp.txt`
(§12 drive sub-states and T13/T14, §13 registers, App.1); the map lives in `xplus_mt_map.py`, the
CiA 402 state machine in `cia402.py`, and enable, disable, the motion preconditions and the fault
reset in `cia402_drive.Cia402Drive`, whose hooks this class fills. No rclpy.

Operations that wait (enable, disable, fault_reset, move_to, set_velocity, start_homing,
save_params) are step-wise (`drive.Operation`): they yield between transactions, so the bus owner
serves the other drives meanwhile. connect, read_state and stop are one short burst each.

One class: every XplusMtDrive operation shares one Modbus client, the Cia402Walker handshake
and the driver's own record (homed, current-on time, watchdog armed).
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Mapping, Sequence

from ...contract import param_rules
from ...contract.drive import (
    Bus,
    DriveError,
    DriveState,
    Homing,
    HomingState,
    IdentityError,
    Motion,
    Operation,
    ParamSpec,
    State,
    Vendor,
    register_type,
)
from ...profiles.cia402 import state_machine as cia402
from ...profiles.cia402.drive import Cia402Drive
from ...profiles.cia402.modes import HomingMode, Mode, ProfilePositionMode, ProfileVelocityMode
from ...profiles.cia402.state_machine import (
    CW_BIT_HALT,
    CW_BIT_NEW_SET_POINT,
    SW_BIT_FOLLOWING_ERROR,
    SW_BIT_INTERNAL_LIMIT,
    SW_BIT_TARGET_REACHED,
    SW_BIT_VOLTAGE_ENABLED,
    SW_BIT_WARNING,
    SW_BIT_ZERO_SPEED,
)
from ...protocol.modbus import (
    FC_READ_HOLDING_REGISTERS,
    RawRegisterRules,
    Request,
    parse_raw_register,
    read_request,
)
from ...protocol.modbus_tcp import ModbusExceptionError, ModbusTcpBus
from ...protocol.modbus_tcp import make_bus as make_tcp_bus
from . import regmap as xm
from . import scan as xplus_mt_scan

logger = logging.getLogger(__name__)

REG = xm.REGISTERS

# One FC03 covers status word .. velocity actual value (1001..1021, holes 1003, 1012-1013, 1019
# read as filler); if the drive refuses holes, SPLIT_READS (3 requests) is used instead.
STATE_BLOCK = (1001, 21)
SPLIT_READS = ((1001, 2), (1004, 8), (1020, 2))
# 1081..1097 have no hole: step revolution (identity), input config, brake delays, watchdog.
SETTINGS_BLOCK = (1081, 17)

SETTLE_MIN_S = 0.2             # §12 note after transition 16: ~50-200 ms settling, current on

# Drive-side watchdog (§13 "Register 1097": no Modbus read or write within the timeout -> Fault,
# current off). 1 s: 50 polls at the default 50 Hz, and more than a lost reply (timeout_s 0.5 s)
# plus a quick reconnect or a scheduling stall of a loaded host, so only a master that is really
# gone trips it; a running axis still stops about 1 s after its master died.
WATCHDOG_MS_DEFAULT = 1000
WATCHDOG_MIN_MS = 100          # §13 "Register 1097": 100÷32000 ms (0 = off)
WATCHDOG_MIN_POLLS = 5         # the watchdog must span at least this many poll periods

_SIMPLE_INT_TYPES = ('u16', 'i16', 'u32', 'i32')
# read_register/write_register: the App.1 registers only, by their PDU address (§11).
_RAW_REGISTERS = RawRegisterRules(
    device='X-PLUS MT', registers=tuple(xm.REGISTERS.values()), dtypes=_SIMPLE_INT_TYPES,
    not_a_number='register address {address!r} is not a number (e.g. 1001 or 0x3E9)',
    outside='register {number} is not in the X-PLUS MT register map (manual App.1)',
    second_word='register {number} is the second word of {owner}; use address '
                '{owner.address} with data type {owner.dtype}',
    mismatch='{reg} is {reg.dtype}: data type {dtype} does not match its {bits} bits',
    read_only='{reg} is read-only (RO)')          # App.1's spelling of the access
_NO_SUCH_REGISTER = (0x01, 0x02)   # ILLEGAL FUNCTION / ILLEGAL DATA ADDRESS
_REFUSED = (0x01, 0x02, 0x03)      # ... and ILLEGAL DATA VALUE: the device says no
_HALT = Mode()                     # a mode whose stop is Halt (bit 8): every X-PLUS MT mode


class XplusMtDrive(Cia402Drive):
    """One X-PLUS MT on a Modbus TCP connection (unit id = parameter `unit_id`)."""

    start_stop_steps_s = float(xm.START_STOP_MAX_HZ)     # §13 "Motion Profiles"
    min_velocity_steps_s = 1.0        # PROFILE_VELOCITY (1044) in whole Hz, 0 refused
    # §13 "Multi-Set-Point Mode" (bit 5 set by every move): a monotonous new target is taken
    # "without intermediate stops"; a reversing one stops and restarts
    retargets_on_the_way = True
    CW_SW_DELAY_S = 0.012      # §13 "Register 1001" note: >= 12 ms before checking the SW
    ENABLE_TIMEOUT_S = 1.5     # the 3 steps + HV "at least 500 ms before" transition 3 (§12)
    STATUSWORD_READ_IS_TRANSACTION = True     # every statusword read is an FC03 of 1001
    # §12 "Mode of Operation", §13 "Register 1041": 1, 3, 6
    MODES = (ProfilePositionMode(), ProfileVelocityMode(), HomingMode())
    # The start edges (homing, PV) write 0x000F first in every case: it also clears bits 5/6 of
    # a profile position handshake before them.
    START_EDGE_LOW_ALWAYS = True

    def __init__(self, bus: Bus, name: str, params: Mapping[str, Any]):
        params = VENDOR.with_defaults(params)
        super().__init__(bus, name, params)
        if not isinstance(bus, ModbusTcpBus):
            raise TypeError(f'{name}: X-PLUS MT needs a ModbusTcpBus, got {type(bus).__name__}')
        self.mb: ModbusTcpBus = bus
        self.unit_id = int(params['unit_id'])
        self.address = self.unit_id
        self.word_order = str(params['word_order'])
        self.watchdog_ms = int(params['watchdog_ms'])
        self.input_config = int(params['input_config'])
        self._split_reads = False
        self._state_requests: tuple[bool | None, list[Request]] = (None, [])
        self._homed = False
        self._current_on_at: float | None = None
        self._settle_s = SETTLE_MIN_S
        self._last_position: int | None = None     # of the last poll (the velocity's sign)
        # (what read_state decoded, the DriveState): an idle drive's poll is one comparison
        self._snapshot: tuple[tuple, DriveState | None] = ((), None)
        self._was_enabled = False
        self._watchdog_armed = False
        # (statusword, mode display) of the last read of both before a motion command
        self._shown: tuple[int, int] = (0, 0)

    # ------------------------------------------------------------------ register helpers
    def _read_words(self, address: int, count: int) -> list[int]:
        return self.mb.read_holding_registers(self.unit_id, address, count)

    def _read(self, name: str) -> int:
        reg = REG[name]
        return xm.decode(reg, self._read_words(reg.address, reg.words), self.word_order)

    def _check(self, reg: xm.Register, value: int, what: str = '') -> None:
        if not reg.accepts(value):
            raise DriveError(f'{what}{value} is outside {reg} range {reg.range_text()}'
                             + (f' {reg.unit}' if reg.unit and not reg.allowed else ''))

    def _checked(self, name: str, value: float, what: str) -> int:
        """`value` rounded to the register's integer, refused (naming the register and its
        range) when it does not fit; nothing is sent."""
        reg = REG[name]
        if isinstance(value, float) and not math.isfinite(value):
            raise DriveError(f'{what}{value} is not a number for {reg} (range '
                             f'{reg.range_text()})')
        number = int(round(value))
        self._check(reg, number, what)
        return number

    def _write(self, *pairs: tuple[str, int], what: str = '') -> None:
        """Write registers; contiguous ones (in the order given) go in one FC16."""
        regs = [(REG[n], v) for n, v in pairs]
        for reg, value in regs:
            self._check(reg, value, what)
        start, words = None, []
        for reg, value in regs:
            if start is not None and reg.address != start + len(words):
                self.mb.write_registers(self.unit_id, start, words)
                start, words = None, []
            if start is None:
                start = reg.address
            words += xm.encode(reg, value, self.word_order)
        if words:
            self.mb.write_registers(self.unit_id, start, words)

    def _read_statusword(self) -> int:
        return self._read_words(1001, 1)[0]

    def _write_controlword(self, cw: int) -> None:
        self.mb.write_register(self.unit_id, 1040, cw)

    # ------------------------------------------------------------------ life cycle
    def _identity_read(self, address: int, count: int) -> list[int]:
        """A read at connect; a device without the register is not an X-PLUS MT."""
        try:
            return self._read_words(address, count)
        except ModbusExceptionError as exc:
            if exc.code not in _NO_SUCH_REGISTER:
                raise
            reg = xm.BY_ADDRESS[address]
            raise IdentityError(
                f'{reg}: the device at unit {self.unit_id} has no such register ({exc}); every '
                f'X-PLUS MT has it (App.1): not an X-PLUS MT') from exc

    def _identity_write(self, name: str, value: int, param: str) -> None:
        """A setting written at connect; a refusal means the drive is not what the parameter
        describes (e.g. input_config with the S4-only bit 7 on a B4)."""
        try:
            self._write((name, value), what=f'drives.{self.name}.{param}: ')
        except ModbusExceptionError as exc:
            if exc.code not in _REFUSED:
                raise                       # busy, device failure: the device's moment
            raise IdentityError(f'drives.{self.name}.{param}: the drive refuses {value} in '
                                f'{REG[name]} ({exc})') from exc

    def connect(self) -> dict[str, str]:
        """Identity checks (what the manual fixes), then the node's settings: input config
        (parameter input_config, RAM only) and the drive-side watchdog 1097 (watchdog_ms)."""
        order_value = self._identity_read(1162, 1)[0]
        drive_order = xm.WORD_ORDER_BY_1162.get(order_value)
        if drive_order is None:
            raise IdentityError(
                f'LITTLE_ENDIAN_BIG_ENDIAN (1162) reads {order_value}; an X-PLUS MT holds 1 '
                f'(little) or 0 (big) there (§13 "Register 1162"): not an X-PLUS MT')
        if drive_order != self.word_order:
            raise IdentityError(
                f'word order mismatch: register LITTLE_ENDIAN_BIG_ENDIAN (1162) reads '
                f'{order_value} ({drive_order}), but the word_order parameter is '
                f"'{self.word_order}' (1162 = {xm.REGISTER_1162_BY_WORD_ORDER[self.word_order]})"
                f'; set word_order to match the drive')
        words = self._identity_read(1152, 8)          # 1152..1159 identification (T15)
        sw_ver, product, hw_ver, serial = (
            xm.decode32(words[i:i + 2], self.word_order, signed=False) for i in (0, 2, 4, 6))
        start, count = SETTINGS_BLOCK
        settings = dict(zip(range(start, start + count), self._identity_read(start, count)))
        if settings[1081] != xm.STEPS_PER_REV:
            raise IdentityError(
                f'STEP_REVOLUTION (1081) reads {settings[1081]}; an X-PLUS MT has '
                f'{xm.STEPS_PER_REV} only (§13 "Register 1081"): not an X-PLUS MT')
        self._settle_s = max(SETTLE_MIN_S, settings[1096] / 1000.0)
        input_config = settings[1088]
        if 0 <= self.input_config != input_config:
            self._identity_write('INPUT_CONFIG', self.input_config, 'input_config')
            input_config = self.input_config
        if settings[1097] != self.watchdog_ms:
            self._identity_write('COUNTER_WATCHDOG', self.watchdog_ms, 'watchdog_ms')
        self._watchdog_armed = self.watchdog_ms > 0
        self.cia.controlword = None
        self._homed = False
        self._last_position = None
        self._snapshot = ((), None)
        self._current_on_at = None
        sw = self._read_statusword()
        if cia402.decode_state(sw) == State.OPERATION_ENABLED:
            self._current_on_at = time.monotonic() - self._settle_s
        return {
            'vendor': 'R.T.A.', 'product': 'X-PLUS MT',
            'product_code': f'0x{product:08X}', 'serial_number': str(serial),
            'software_version': str(sw_ver), 'hardware_version': str(hw_ver),
            'unit_id': str(self.unit_id),
            'word_order': f'{self.word_order} (1162 = {order_value})',
            'input_config': f'0x{input_config:04X} (1088)',
            'watchdog': (f'{self.watchdog_ms} ms (1097)' if self.watchdog_ms
                         else 'off (1097 = 0)'),
            'statusword': f'0x{sw:04X}', 'state': cia402.decode_state(sw).value,
        }

    def close(self) -> None:
        """The node is done with this drive (orderly shutdown): disarm the drive watchdog, so a
        drive left enabled on purpose (disable_on_shutdown false) keeps holding. A node that dies
        never gets here: then the watchdog faults the drive (current off)."""
        if not self._watchdog_armed or not self.mb.is_open:
            return
        try:
            self._write(('COUNTER_WATCHDOG', 0))
            self._watchdog_armed = False
        except DriveError as exc:
            logger.warning('%s: could not disarm the drive watchdog (1097 := 0): %s', self.name,
                           exc)

    def _read_state_words(self) -> list[int]:
        """Words 1001..1021 (holes as read, or 0 with split reads)."""
        start, count = STATE_BLOCK
        if not self._split_reads:
            try:
                return self._read_words(start, count)
            except ModbusExceptionError as exc:
                if exc.code != 0x02:        # ILLEGAL DATA ADDRESS: the holes
                    raise
                logger.info('%s: block read 1001..1021 refused (%s); using 3 reads', self.name,
                            exc)
                self._split_reads = True
        return self._joined([self._read_words(address, n) for address, n in SPLIT_READS])

    @staticmethod
    def _joined(parts: list[list[int]]) -> list[int]:
        """Words 1001..1021 from the replies of the SPLIT_READS, 0 in the holes."""
        start, count = STATE_BLOCK
        out = [0] * count
        for (address, n), words in zip(SPLIT_READS, parts):
            out[address - start:address - start + n] = words
        return out

    def read_state(self) -> DriveState:
        return self._state_from_words(self._read_state_words())

    def state_requests(self) -> list[Request]:
        """read_state()'s FC03 requests (§13): 1001..1021, or the three SPLIT_READS once the
        drive refused a read over the holes."""
        key = self._split_reads
        if self._state_requests[0] != key:
            reads = SPLIT_READS if key else (STATE_BLOCK,)
            self._state_requests = (key, [read_request(
                self.unit_id, FC_READ_HOLDING_REGISTERS, address, n) for address, n in reads])
        return self._state_requests[1]

    def state_from_replies(self, replies: list[list[int]]) -> DriveState:
        return self._state_from_words(replies[0] if len(replies) == 1 else
                                      self._joined(replies))

    def _state_from_words(self, w: list[int]) -> DriveState:
        """The state from words 1001..1021. The last snapshot again while nothing it is made of
        changed (the words, the position before them, the homed and enabled flags): an idle
        drive's poll is one transaction and one comparison, not a decode."""
        key = (w, self._last_position, self._homed, self._was_enabled)
        if key == self._snapshot[0]:
            return self._snapshot[1]
        order = self.word_order
        sw = w[0]                                                       # 1001
        mode = w[1] - 0x10000 if w[1] & 0x8000 else w[1]                # 1002 I16
        position = xm.decode32(w[3:5], order, signed=True)              # 1004-1005
        code = w[6]                                                     # 1007
        velocity = float(xm.decode32(w[19:21], order, signed=True))     # 1020-1021
        state = cia402.decode_state(sw)
        # A8: the tables give Velocity Actual Value min 0 although PV reverses; the register is
        # decoded as signed I32, and a non-negative value while the position falls is negated.
        if self._last_position is not None and velocity > 0 and position < self._last_position:
            velocity = -velocity
        self._last_position = position
        enabled = state == State.OPERATION_ENABLED
        torque = state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)
        reached = bool(sw & SW_BIT_TARGET_REACHED)
        homing = HomingState.IDLE
        if mode == xm.MODE_HOMING and torque:
            homing = cia402.homing_state(sw)
            if homing == HomingState.ATTAINED:
                self._homed = True
        if mode == xm.MODE_PROFILE_VELOCITY:
            moving = torque and (not sw & SW_BIT_ZERO_SPEED or velocity != 0)
        elif mode in (xm.MODE_PROFILE_POSITION, xm.MODE_HOMING) or state == \
                State.QUICK_STOP_ACTIVE:
            moving = torque and (not reached or velocity != 0)
        else:
            moving = velocity != 0
        fault = state in (State.FAULT, State.FAULT_REACTION_ACTIVE)
        fault_text = ''
        if fault:
            fault_text = self._error_text(code)
        alarms = []
        if sw & SW_BIT_FOLLOWING_ERROR and mode != xm.MODE_HOMING and not fault:
            alarms.append('Following error (status word bit 13)')
        if sw & SW_BIT_INTERNAL_LIMIT:
            alarms.append('Internal limit active (status word bit 11)')
        if sw & SW_BIT_WARNING:
            alarms.append('Warning (status word bit 7)')
        if not sw & SW_BIT_VOLTAGE_ENABLED and state != State.UNKNOWN:
            alarms.append('Voltage Enabled = 0: power supply out of range or absent '
                          '(status word bit 4)')
        if code and not fault:
            alarms.append(f'{self._error_text(code)} (error code 1007)')
        if self._was_enabled and state == State.SWITCH_ON_DISABLED and code == 0:
            # spec §9.2: STO (S4) has no error code; OE lost without a command or fault.
            alarms.append('torque disabled without a command or fault (possible STO)')
        snapshot = DriveState(
            state=state, enabled=enabled, moving=bool(moving), target_reached=reached,
            homed=self._homed, homing=homing, fault=fault, fault_code=code if fault else 0,
            fault_text=fault_text, alarms=tuple(alarms), mode=xm.MODES.get(mode, ''),
            status_word=sw, position_steps=position, velocity_steps_s=velocity)
        self._snapshot = (key, snapshot)
        return snapshot

    @staticmethod
    def _error_text(code: int) -> str:
        text = xm.ERROR_CODES.get(code)
        if text is None:
            return f'Error code 0x{code:04X} (not in the manual)'
        return f'{text} (0x{code:04X})' if code else 'Fault with error code 0x0000'

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
                    ('PROFILE_ACCELERATION', accel), ('PROFILE_DECELERATION', decel))
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
        self._write(('PROFILE_ACCELERATION', accel), ('TARGET_VELOCITY', velocity),
                    ('PROFILE_DECELERATION', decel))
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

    def read_register(self, address: str, data_type: str) -> int:
        reg = parse_raw_register(_RAW_REGISTERS, address, data_type, write=False)
        words = self._read_words(reg.address, reg.words)
        signed = data_type.lower().startswith('i')
        if reg.words == 2:
            return xm.decode32(words, self.word_order, signed)
        return words[0] - 0x10000 if signed and words[0] & 0x8000 else words[0]

    def write_register(self, address: str, data_type: str, value: int) -> None:
        reg = parse_raw_register(_RAW_REGISTERS, address, data_type, write=True)
        value = register_type(data_type).check(int(value))
        # data_type says how to read `value`; the range is the register's own (e.g. i16 -2 on
        # a u16 register is the word 0xFFFE = 65534).
        words = xm.encode(reg, value, self.word_order)
        self._check(reg, xm.decode(reg, words, self.word_order), 'write_register: value ')
        if reg.address == 1162 and xm.WORD_ORDER_BY_1162[words[0]] != self.word_order:
            raise DriveError(f'{reg}: {value} would change the 32-bit word order the driver '
                             f"uses (word_order parameter '{self.word_order}'); change the "
                             f'word_order parameter and the drive together')
        if reg.words == 1:
            self.mb.write_register(self.unit_id, reg.address, words[0])
        else:
            self.mb.write_registers(self.unit_id, reg.address, words)
        if reg.address == 1040:
            self.cia.controlword = words[0]
            self._was_enabled = False       # a raw controlword is a command too


# ---------------------------------------------------------------------- vendor description
PARAMS = (
    ParamSpec('host', '127.0.0.1', 'IP address of the drive (Modbus TCP server); the drives '
              'that set no drives.<name>.host of their own', scope='bus'),
    ParamSpec('port', 502, 'TCP port of the drive (§11 "TCP Port": 502); the drives that set '
              'no drives.<name>.port of their own', scope='bus', min_value=1, max_value=65535),
    ParamSpec('word_order', 'little', "32-bit word order, must match register 1162: 'little' "
              "(1162 = 1, default, low word at the lower address) or 'big' (1162 = 0)",
              scope='bus', choices=xm.WORD_ORDERS),
    ParamSpec('unit_id', 1, 'Modbus unit identifier of the drive (the manual does not fix it)',
              scope='drive', min_value=0, max_value=255),
    # Every X-PLUS MT is its own Modbus TCP server: drives on other hosts get a link of their own
    # (Vendor.drive_bus_params); drives with equal host and port share one.
    ParamSpec('host', '', "IP address of this drive when it is not the bus-level host ('' = "
              'the bus-level host)', scope='drive'),
    ParamSpec('port', 0, 'TCP port of this drive when it is not the bus-level port (0 = the '
              'bus-level port)', scope='drive', min_value=0, max_value=65535),
    ParamSpec('watchdog_ms', WATCHDOG_MS_DEFAULT, 'drive-side watchdog, register 1097, written at '
              'connect: with no Modbus request (from any client) for this long the drive goes to '
              'Fault, current off (§13 "Register 1097"); 0 = off, else 100..32000 ms [ms]',
              scope='drive', min_value=0, max_value=32000),
    ParamSpec('input_config', -1, 'Input Config 1088 written at connect (RAM; save_params stores '
              'it): bit 0 = 0 makes I0 the home proximity input, bits 1/2 = 0 make I1/I2 limit '
              'switches, bit 3 = 0 I3 the touch probe (§13 "Register 1088"; factory 15: all '
              'general purpose); -1 = leave the drive as it is', scope='drive', min_value=-1,
              max_value=xm.REGISTERS['INPUT_CONFIG'].max),
)


# Per-drive parameters that give a drive a link of its own (Vendor.drive_bus_params).
DRIVE_BUS_PARAMS = ('host', 'port')


def make_bus(params: Mapping[str, Any]) -> ModbusTcpBus:
    """Bus params 'host', 'port' and the common 'timeout_s'. For a drive with its own host or
    port the node passes the bus params with the drive's non-empty values in their place."""
    return make_tcp_bus(VENDOR.with_defaults(params))


def _check_choice(key: str, value: Any, allowed: Sequence[Any], what: str) -> None:
    if value not in allowed:
        raise ValueError(f'{key}: {value!r} is not {what} (allowed: '
                         f'{", ".join(map(str, allowed))})')


def _check_link(params: Mapping[str, Any]) -> None:
    """What protocol.modbus_tcp.make_bus refuses, without making the bus (same messages)."""
    params = VENDOR.with_defaults(params)
    if not str(params['host']).strip():
        raise ValueError("host: '' (allowed: an IP address or host name of the Modbus server)")
    port = params['port']
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ValueError(f'port: {port!r} (allowed: a TCP port 1..65535)')


def _check_drive(name: str, params: Mapping[str, Any]) -> None:
    """The rules of one drive's parameters (with the bus-level ones), or ValueError."""
    prefix = f'drives.{name}.'
    params = VENDOR.with_defaults(params)
    method = params['homing.method']
    if method not in xm.HOMING_METHODS:
        raise ValueError(f'{prefix}homing.method: {method} is not a homing method of the '
                         f'X-PLUS MT (allowed: {", ".join(map(str, xm.HOMING_METHODS))})')
    unit_id = params['unit_id']
    if not isinstance(unit_id, int) or not 0 <= unit_id <= 255:
        raise ValueError(f'{prefix}unit_id: {unit_id!r} is not a Modbus unit id '
                         f'(allowed: 0..255)')
    _check_choice('word_order', params['word_order'], xm.WORD_ORDERS,
                  'a word order')
    steps = params['steps_per_rev']
    if float(steps) != xm.STEPS_PER_REV:
        raise ValueError(f'{prefix}steps_per_rev: {steps:g} is not the X-PLUS MT resolution '
                         f'(allowed: {xm.STEPS_PER_REV}, fixed by STEP_REVOLUTION (1081))')
    watchdog_ms = params['watchdog_ms']
    if not isinstance(watchdog_ms, int) or not (
            watchdog_ms == 0 or WATCHDOG_MIN_MS <= watchdog_ms <= REG['COUNTER_WATCHDOG'].max):
        raise ValueError(f'{prefix}watchdog_ms: {watchdog_ms!r} (allowed: 0 = off, or '
                         f'{WATCHDOG_MIN_MS}..{REG["COUNTER_WATCHDOG"].max} ms, §13 "Register '
                         f'1097")')
    rate = float(params.get('publish_rate_hz', 50.0))
    if watchdog_ms and watchdog_ms / 1000.0 < WATCHDOG_MIN_POLLS / rate:
        raise ValueError(f'{prefix}watchdog_ms: {watchdog_ms} ms is less than '
                         f'{WATCHDOG_MIN_POLLS} poll periods at publish_rate_hz {rate:g} (the '
                         f'polls feed the drive watchdog); allowed: >= '
                         f'{math.ceil(WATCHDOG_MIN_POLLS * 1000.0 / rate)} ms, or 0 = off')
    input_config = params['input_config']
    if not isinstance(input_config, int) or not (
            input_config == -1 or REG['INPUT_CONFIG'].accepts(input_config)):
        raise ValueError(f'{prefix}input_config: {input_config!r} (allowed: -1 = leave the drive '
                         f'as it is, or INPUT_CONFIG (1088) {REG["INPUT_CONFIG"].range_text()})')
    if method in xm.HOMING_METHODS_HOME_SWITCH and input_config >= 0 and input_config & 0x01:
        raise ValueError(f'{prefix}homing.method: {method} needs the home switch on I0, but '
                         f'{prefix}input_config {input_config} has bit 0 = 1 (I0 general '
                         f'purpose, §13 "Register 1088"); clear bit 0 (e.g. 14)')


def make_drive(bus: Bus, name: str, params: Mapping[str, Any]) -> XplusMtDrive:
    _check_drive(name, params)
    return XplusMtDrive(bus, name, params)


def validate(params: Mapping[str, Any]) -> list[str]:
    """The X-PLUS MT's parameter rules on the node's parameters (param_rules), at start-up and
    for every run-time change: each drive's link, and per drive homing method, unit id, word
    order, resolution, watchdog against the poll rate, input config."""
    return param_rules.check_each(params, _check_link, _check_drive, DRIVE_BUS_PARAMS)


VENDOR = Vendor(
    name='X-PLUS MT',
    params=PARAMS,
    make_bus=make_bus,
    make_drive=make_drive,
    # float: the common parameter steps_per_rev is a double (params.py)
    drive_defaults={'steps_per_rev': float(xm.STEPS_PER_REV), 'homing.method': 35},
    drive_bus_params=DRIVE_BUS_PARAMS,
    validate=validate,
    scanner=xplus_mt_scan.SCANNER,
)
