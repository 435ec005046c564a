"""R.T.A. X-PLUS MT (B4/S4) over Modbus TCP: the drive class and the vendor description.

Register numbers, bit meanings and timings come from the manual `rta_xplus_mt_modbus_tcp.txt`
(§12 drive sub-states and T13/T14, §13 registers, App.1); the map lives in `xplus_mt_map.py` and
the CiA 402 state machine in `cia402.py`. No rclpy.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Mapping, Sequence

from .. import cia402
from ..cia402 import (CW_BIT_CHANGE_SET_IMMEDIATELY, CW_BIT_HALT, CW_BIT_NEW_SET_POINT,
                      CW_ENABLE_OPERATION, SW_BIT_FOLLOWING_ERROR, SW_BIT_INTERNAL_LIMIT,
                      SW_BIT_TARGET_REACHED, SW_BIT_VOLTAGE_ENABLED, SW_BIT_WARNING,
                      SW_BIT_ZERO_SPEED)
from ..drive import (Bus, Drive, DriveError, DriveState, Homing, HomingState, LinkError, Motion,
                     ParamSpec, State, Vendor, register_type)
from ..protocol.modbus_tcp import ModbusTcpBus, make_bus as make_tcp_bus
from . import xplus_mt_map as xm

logger = logging.getLogger(__name__)

REG = xm.REGISTERS

# One FC03 covers status word .. velocity actual value (1001..1021, holes 1003, 1012-1013, 1019
# read as filler); if the drive refuses holes, SPLIT_READS (3 requests) is used instead.
STATE_BLOCK = (1001, 21)
SPLIT_READS = ((1001, 2), (1004, 8), (1020, 2))

CW_SW_DELAY_S = 0.012          # §13 "Register 1001" note: >= 12 ms before checking the SW
SETTLE_MIN_S = 0.2             # §12 note after transition 16: ~50-200 ms settling, current on
ENABLE_TIMEOUT_S = 1.5         # the 3 steps + HV "at least 500 ms before" transition 3 (§12)
DISABLE_TIMEOUT_S = 1.0
FAULT_RESET_TIMEOUT_S = 1.0
HANDSHAKE_TIMEOUT_S = 0.5
MODE_SWITCH_TIMEOUT_S = 0.5

_SIMPLE_INT_TYPES = ('u16', 'i16', 'u32', 'i32')


def _int(value: float) -> int:
    return int(round(value))


class XplusMtDrive(Drive):
    """One X-PLUS MT on a Modbus TCP connection (unit id = parameter `unit_id`)."""

    def __init__(self, bus: Bus, name: str, params: Mapping[str, Any]):
        super().__init__(bus, name, params)
        if not isinstance(bus, ModbusTcpBus):
            raise TypeError(f'{name}: X-PLUS MT needs a ModbusTcpBus, got {type(bus).__name__}')
        self.mb: ModbusTcpBus = bus
        self.unit_id = int(params.get('unit_id', 1))
        self.address = self.unit_id
        self.word_order = str(params.get('word_order', 'little'))
        self.cia = cia402.Cia402Device(self._read_statusword, self._write_controlword,
                                       min_delay_s=CW_SW_DELAY_S, name=name)
        self._split_reads = False
        self._homed = False
        self._current_on_at: float | None = None
        self._settle_s = SETTLE_MIN_S
        self._last_pos: tuple[int, float] | None = None
        self._last_velocity = 0.0
        self._was_enabled = False

    # ------------------------------------------------------------------ register helpers
    def _read_words(self, address: int, count: int) -> list[int]:
        return self.mb.read_registers(self.unit_id, address, count)

    def _read(self, name: str) -> int:
        reg = REG[name]
        return xm.decode(reg, self._read_words(reg.address, reg.words), self.word_order)

    def _check(self, reg: xm.Register, value: int, what: str = '') -> None:
        if not reg.accepts(value):
            raise DriveError(f'{what}{value} is outside {reg} range {reg.range_text()}'
                             + (f' {reg.unit}' if reg.unit and not reg.allowed else ''))

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
        self.mb.write_registers(self.unit_id, 1040, [cw], single=True)

    def _prefix(self) -> str:
        return f'{self.name}: '

    # ------------------------------------------------------------------ life cycle
    def connect(self) -> dict[str, str]:
        order_value = self._read_words(1162, 1)[0]
        drive_order = xm.WORD_ORDER_BY_1162.get(order_value)
        if drive_order != self.word_order:
            raise DriveError(
                f'word order mismatch: register LITTLE_ENDIAN_BIG_ENDIAN (1162) reads '
                f'{order_value} ({drive_order or "not 0/1"}), but the word_order parameter is '
                f"'{self.word_order}' (1162 = {xm.REGISTER_1162_BY_WORD_ORDER[self.word_order]})"
                f'; set word_order to match the drive')
        words = self._read_words(1152, 8)          # 1152..1159 identification (T15)
        sw_ver, product, hw_ver, serial = (
            xm.decode32(words[i:i + 2], self.word_order, signed=False) for i in (0, 2, 4, 6))
        settle_ms = self._read('BRAKE_DELAY_AZIO_READY')
        self._settle_s = max(SETTLE_MIN_S, settle_ms / 1000.0)
        self.cia.controlword = None
        self._homed = False
        self._last_pos = None
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
            'statusword': f'0x{sw:04X}', 'state': cia402.decode_state(sw).value,
        }

    def _read_state_words(self) -> list[int]:
        """Words 1001..1021 (holes as read, or 0 with split reads)."""
        start, count = STATE_BLOCK
        if not self._split_reads:
            try:
                return self._read_words(start, count)
            except LinkError:
                raise
            except DriveError as exc:
                if 'ILLEGAL DATA ADDRESS' not in str(exc):
                    raise
                logger.info('%s: block read 1001..1021 refused (%s); using 3 reads', self.name,
                            exc)
                self._split_reads = True
        out = [0] * count
        for address, n in SPLIT_READS:
            out[address - start:address - start + n] = self._read_words(address, n)
        return out

    def read_state(self) -> DriveState:
        w = self._read_state_words()
        now = time.monotonic()
        order = self.word_order
        sw = w[0]                                                       # 1001
        mode = w[1] - 0x10000 if w[1] & 0x8000 else w[1]                # 1002 I16
        position = xm.decode32(w[3:5], order, signed=True)              # 1004-1005
        code = w[6]                                                     # 1007
        velocity = float(xm.decode32(w[19:21], order, signed=True))     # 1020-1021
        state = cia402.decode_state(sw)
        # A8: the tables give Velocity Actual Value min 0 although PV reverses; the register is
        # decoded as signed I32, and a non-negative value while the position falls is negated.
        if self._last_pos is not None and velocity > 0 and position < self._last_pos[0]:
            velocity = -velocity
        self._last_pos = (position, now)
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
        return DriveState(
            state=state, enabled=enabled, moving=bool(moving), target_reached=reached,
            homed=self._homed, homing=homing, fault=fault, fault_code=code if fault else 0,
            fault_text=fault_text, alarms=tuple(alarms), mode=xm.MODES.get(mode, ''),
            status_word=sw, position_steps=position, velocity_steps_s=velocity)

    @staticmethod
    def _error_text(code: int) -> str:
        text = xm.ERROR_CODES.get(code)
        if text is None:
            return f'Error code 0x{code:04X} (not in the manual)'
        return f'{text} (0x{code:04X})' if code else 'Fault with error code 0x0000'

    # ------------------------------------------------------------------ power stage
    def enable(self) -> None:
        sw = self._read_statusword()
        state = cia402.decode_state(sw)
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            code = self._read('ERROR_CODE')
            raise DriveError(f'enable: drive is in {cia402.describe(sw)}, '
                             f'{self._error_text(code)}; call fault_reset first')
        if state == State.OPERATION_ENABLED:
            self._was_enabled = True
            return
        if state != State.QUICK_STOP_ACTIVE:
            # Nothing may move: Target Position := Position Actual Value, then Profile Position.
            actual = self._read('POSITION_ACTUAL_VALUE')
            self._write(('TARGET_POSITION', actual))
            self._set_mode(xm.MODE_PROFILE_POSITION)
        if state in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON):
            sw = self.cia.bring_to(State.READY_TO_SWITCH_ON, ENABLE_TIMEOUT_S)
            if not sw & SW_BIT_VOLTAGE_ENABLED:
                raise DriveError(
                    f'enable: the power stage has no high voltage: {cia402.describe(sw)} with '
                    f'Voltage Enabled (status word bit 4) = 0; Switch On needs HV present at '
                    f'least 500 ms before (§12 transition 3)')
        try:
            self.cia.bring_to(State.OPERATION_ENABLED, ENABLE_TIMEOUT_S)
        except DriveError as exc:
            sw = self._read_statusword()
            if cia402.decode_state(sw) == State.READY_TO_SWITCH_ON:
                hv = 'present' if sw & SW_BIT_VOLTAGE_ENABLED else 'absent (bit 4 = 0)'
                raise DriveError(f'{exc}; high voltage {hv}: Switch On needs HV at least '
                                 f'500 ms before the transition (§12 transition 3)') from exc
            raise
        self._current_on_at = time.monotonic()
        self._was_enabled = True

    def disable(self) -> None:
        sw = self._read_statusword()
        if cia402.decode_state(sw) in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return        # current is already off; leaving Fault needs fault_reset
        self.cia.bring_to(State.SWITCH_ON_DISABLED, DISABLE_TIMEOUT_S)
        self._current_on_at = None
        self._was_enabled = False

    # ------------------------------------------------------------------ motion
    def _require_enabled(self, what: str) -> int:
        sw = self._read_statusword()
        if cia402.decode_state(sw) != State.OPERATION_ENABLED:
            raise DriveError(f'{what}: drive is in {cia402.describe(sw)}, not OPERATION '
                             f'ENABLED; enable first')
        return sw

    def _wait_settled(self) -> None:
        """§12 note: New Set Points sent before the motor settled (~50-200 ms, and 1096 Brake
        Delay Azio Ready) after current on "can cause a loss of synchronism"."""
        if self._current_on_at is None:
            return
        rest = self._current_on_at + self._settle_s - time.monotonic()
        if rest > 0:
            time.sleep(rest)

    def _mode(self) -> int:
        return self._read('MODE_OF_OPERATION_DISPLAY')

    def _set_mode(self, mode: int) -> None:
        self._write(('MODE_OF_OPERATION', mode))
        deadline = time.monotonic() + MODE_SWITCH_TIMEOUT_S
        while self._mode() != mode:
            if time.monotonic() > deadline:
                raise DriveError(f'MODE_OF_OPERATION (1041) := {mode} not taken: '
                                 f'MODE_OF_OPERATION_DISPLAY (1002) reads {self._mode()}')
            time.sleep(cia402.Cia402Device.POLL_S)

    def _ensure_mode(self, mode: int, what: str) -> None:
        current = self._mode()
        if current == mode:
            return
        state = self.read_state()
        if state.moving:
            raise DriveError(f'{what}: the drive is moving in {state.mode or f"mode {current}"};'
                             f' stop first (modes change at standstill only)')
        self._set_mode(mode)
        self.cia.controlword = None

    def _base_cw(self) -> int:
        """Enable Operation plus Change Set Immediately, Halt released in two steps."""
        cw = self.cia.controlword
        base = CW_ENABLE_OPERATION | CW_BIT_CHANGE_SET_IMMEDIATELY
        if cw is not None and cw & CW_BIT_HALT:
            # Release Halt on its own first: a halt release and a new set point in one write
            # is not described by the manual (§13 "Register 1040" bit 8).
            self.cia.write(cw & ~(CW_BIT_HALT | CW_BIT_NEW_SET_POINT))
        return base

    def _motion_values(self, motion: Motion, what: str) -> tuple[int, int, int]:
        velocity = _int(abs(motion.velocity_steps_s))
        accel = _int(motion.acceleration_steps_s2)
        decel = _int(motion.deceleration_steps_s2)
        self._check(REG['PROFILE_ACCELERATION'], accel, f'{what}: acceleration ')
        self._check(REG['PROFILE_DECELERATION'], decel, f'{what}: deceleration ')
        return velocity, accel, decel

    def move_to(self, target_steps: int, motion: Motion) -> None:
        self._require_enabled('move_to')
        velocity, accel, decel = self._motion_values(motion, 'move_to')
        if velocity == 0:
            raise DriveError('move_to: velocity 0 is not accepted by PROFILE_VELOCITY (1044) '
                             'for a move (§13 "Multi-Set-Point Mode" limit 3)')
        self._check(REG['PROFILE_VELOCITY'], velocity, 'move_to: velocity ')
        self._check(REG['TARGET_POSITION'], int(target_steps), 'move_to: target ')
        self._ensure_mode(xm.MODE_PROFILE_POSITION, 'move_to')
        # 1042..1047 contiguous: one FC16 for target, velocity and acceleration (§11: a 32-bit
        # value is committed when its second word is written; all pairs complete in one request).
        self._write(('TARGET_POSITION', int(target_steps)), ('PROFILE_VELOCITY', velocity),
                    ('PROFILE_ACCELERATION', accel), ('PROFILE_DECELERATION', decel))
        self._wait_settled()
        base = self._base_cw()
        self.cia.start_set_point(base, relative=False, immediate=True,
                                 timeout_s=HANDSHAKE_TIMEOUT_S)

    def set_velocity(self, velocity_steps_s: float, motion: Motion) -> None:
        self._require_enabled('set_velocity')
        _, accel, decel = self._motion_values(motion, 'set_velocity')
        velocity = _int(velocity_steps_s)     # A8: signed, negative = reverse
        self._check(REG['TARGET_VELOCITY'], velocity, 'set_velocity: ')
        self._ensure_mode(xm.MODE_PROFILE_VELOCITY, 'set_velocity')
        self._write(('PROFILE_ACCELERATION', accel), ('TARGET_VELOCITY', velocity),
                    ('PROFILE_DECELERATION', decel))
        cw = self.cia.controlword
        running = cw is not None and cw & CW_BIT_NEW_SET_POINT and not cw & CW_BIT_HALT
        if not running:
            # A10: PV follows Target Velocity in OE after a bit-4 rising edge (bit 4 held).
            self._wait_settled()
            self.cia.write(CW_ENABLE_OPERATION)
            time.sleep(CW_SW_DELAY_S)
            self.cia.write(CW_ENABLE_OPERATION | CW_BIT_NEW_SET_POINT)

    def stop(self, quick: bool = False) -> None:
        sw = self._read_statusword()
        state = cia402.decode_state(sw)
        if quick:
            if state == State.OPERATION_ENABLED:
                self.cia.write(cia402.CW_QUICK_STOP)     # transition 11, QS option code 5
            return
        if state != State.OPERATION_ENABLED:
            return
        cw = self.cia.controlword
        if cw is None or cw & 0x000F != CW_ENABLE_OPERATION:
            cw = CW_ENABLE_OPERATION
        self.cia.write(cw | CW_BIT_HALT)     # decelerates with the mode's deceleration

    def start_homing(self, homing: Homing) -> str:
        method = int(homing.method)
        if method not in xm.HOMING_METHODS:
            raise DriveError(f'homing.method: {method} is not a homing method of the X-PLUS MT '
                             f'(allowed: {", ".join(map(str, xm.HOMING_METHODS))})')
        self._require_enabled('home')
        if method in xm.HOMING_METHODS_HOME_SWITCH:
            input_config = self._read('INPUT_CONFIG')
            if input_config & 0x01:
                raise DriveError(
                    f'home: method {method} needs the home switch on I0, but INPUT_CONFIG '
                    f'(1088) = {input_config} has bit 0 (IC0) = 1, i.e. I0 is a general-purpose '
                    f'input; write 1088 with bit 0 = 0 (proximity input) and save_params')
        if method in xm.HOMING_METHODS_NEED_INDEX and \
                self._read('FOLLOWING_ERROR_REACTION_CODE') == 17:
            raise DriveError(f'home: method {method} uses the encoder index, but '
                             f'FOLLOWING_ERROR_REACTION_CODE (1085) = 17 (motor without encoder)')
        writes: list[tuple[str, int]] = [('HOMING_METHOD', method)]
        labels = {'HOMING_OFFSET': 'homing.offset'}
        if method not in xm.HOMING_METHODS_CURRENT_POSITION:   # 35/37 do not move
            writes += [('HOMING_SPEED_SEARCH_SWITCH', _int(homing.speed_search_steps_s)),
                       ('HOMING_SPEED_SEARCH_ZERO', _int(homing.speed_zero_steps_s)),
                       ('HOMING_ACCELERATION', _int(homing.acceleration_steps_s2))]
            labels.update(HOMING_SPEED_SEARCH_SWITCH='homing.speed_search',
                          HOMING_SPEED_SEARCH_ZERO='homing.speed_zero',
                          HOMING_ACCELERATION='homing.acceleration')
        writes.append(('HOMING_OFFSET', int(homing.offset_steps)))
        for reg_name, value in writes:      # all checked before anything is written
            self._check(REG[reg_name], value, f'home: {labels.get(reg_name, "method")} ')
        self._ensure_mode(xm.MODE_HOMING, 'home')
        self._write(*writes)
        self._homed = False
        self._wait_settled()
        base = self._base_cw() & ~CW_BIT_CHANGE_SET_IMMEDIATELY
        self.cia.write(base)                         # bit 4 low, so the next write is an edge
        time.sleep(CW_SW_DELAY_S)
        self.cia.write(base | CW_BIT_NEW_SET_POINT)  # homing start, held high while homing
        met, sw = self.cia.wait_for(
            lambda s: cia402.homing_state(s) != HomingState.IDLE, HANDSHAKE_TIMEOUT_S)
        if not met:
            raise DriveError(f'home: homing did not start (status word bits 13/12/10 still '
                             f'"not started"): {cia402.describe(sw)}')
        return ''

    # ------------------------------------------------------------------ maintenance
    def fault_reset(self) -> str:
        sw = self.cia.fault_reset(FAULT_RESET_TIMEOUT_S)
        state = cia402.decode_state(sw)
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return (f'{self._error_text(self._read("ERROR_CODE"))}; still in '
                    f'{cia402.describe(sw)}: the cause is still present')
        self._was_enabled = False
        return ''

    def save_params(self) -> str:
        self.mb.write_registers(self.unit_id, xm.SAVE_PARAMS_REGISTER,
                                [xm.SAVE_PARAMS_SIGNATURE], single=True)
        echo = self._read_words(xm.SAVE_PARAMS_REGISTER, 1)[0]
        return (f'signature 0x{xm.SAVE_PARAMS_SIGNATURE:04X} written to SAVE_ALL_PARAMETERS '
                f'(1260) and acknowledged by the drive (1260 now reads 0x{echo:04X}); the '
                f'manual gives no completion flag, so the save itself cannot be verified over '
                f'Modbus; keep the 24 V logic supply on for more than '
                f'{xm.SAVE_HOLD_24V_S:g} s (§13 "Register 1260" Note1)')

    def _raw_register(self, address: str, data_type: str, write: bool) -> xm.Register:
        try:
            number = int(str(address).strip(), 0)
        except ValueError:
            raise DriveError(f'register address {address!r} is not a number (e.g. 1001 or '
                             f'0x3E9)') from None
        dtype = register_type(data_type).name
        if dtype not in _SIMPLE_INT_TYPES:
            raise DriveError(f'data type {dtype} not supported by the X-PLUS MT (allowed: '
                             f'{", ".join(_SIMPLE_INT_TYPES)})')
        reg = xm.BY_ADDRESS.get(number)
        if reg is None:
            owner = xm.WORD_OWNER.get(number)
            if owner is not None:
                raise DriveError(f'register {number} is the second word of {owner}; use '
                                 f'address {owner.address} with data type {owner.dtype}')
            raise DriveError(f'register {number} is not in the X-PLUS MT register map '
                             f'(manual App.1)')
        if int(dtype[1:]) != 16 * reg.words:
            raise DriveError(f'{reg} is {reg.dtype}: data type {dtype} does not match its '
                             f'{16 * reg.words} bits')
        if write and not reg.writable:
            raise DriveError(f'{reg} is read-only ({reg.access})')
        return reg

    def read_register(self, address: str, data_type: str) -> int:
        reg = self._raw_register(address, data_type, write=False)
        words = self._read_words(reg.address, reg.words)
        signed = data_type.lower().startswith('i')
        if reg.words == 2:
            return xm.decode32(words, self.word_order, signed)
        return words[0] - 0x10000 if signed and words[0] & 0x8000 else words[0]

    def write_register(self, address: str, data_type: str, value: int) -> None:
        reg = self._raw_register(address, data_type, write=True)
        value = register_type(data_type).check(int(value))
        # data_type says how to read `value`; the range is the register's own (e.g. i16 -2 on
        # a u16 register is the word 0xFFFE = 65534).
        words = xm.encode(reg, value, self.word_order)
        self._check(reg, xm.decode(reg, words, self.word_order), 'write_register: value ')
        if reg.address == 1162 and xm.WORD_ORDER_BY_1162[words[0]] != self.word_order:
            raise DriveError(f'{reg}: {value} would change the 32-bit word order the driver '
                             f"uses (word_order parameter '{self.word_order}'); change the "
                             f'word_order parameter and the drive together')
        self.mb.write_registers(self.unit_id, reg.address, words, single=reg.words == 1)
        if reg.address == 1040:
            self.cia.controlword = words[0]
            self._was_enabled = False       # a raw controlword is a command too


# ---------------------------------------------------------------------- vendor description
PARAMS = (
    ParamSpec('host', '127.0.0.1', 'IP address of the drive (Modbus TCP server)', scope='bus'),
    ParamSpec('port', 502, 'TCP port of the drive (§11 "TCP Port": 502)', scope='bus',
              min_value=1, max_value=65535),
    ParamSpec('word_order', 'little', "32-bit word order, must match register 1162: 'little' "
              "(1162 = 1, default, low word at the lower address) or 'big' (1162 = 0)",
              scope='bus', choices=xm.WORD_ORDERS),
    ParamSpec('unit_id', 1, 'Modbus unit identifier of the drive (the manual does not fix it)',
              scope='drive', min_value=0, max_value=255),
)


def make_bus(params: Mapping[str, Any]) -> ModbusTcpBus:
    """Bus params 'host', 'port' and the common 'timeout_s'."""
    return make_tcp_bus(params)


def _check_choice(key: str, value: Any, allowed: Sequence[Any], what: str) -> None:
    if value not in allowed:
        raise ValueError(f'{key}: {value!r} is not {what} (allowed: '
                         f'{", ".join(map(str, allowed))})')


def make_drive(bus: Bus, name: str, params: Mapping[str, Any]) -> XplusMtDrive:
    prefix = f'drives.{name}.'
    method = params.get('homing.method', 35)
    if method not in xm.HOMING_METHODS:
        raise ValueError(f'{prefix}homing.method: {method} is not a homing method of the '
                         f'X-PLUS MT (allowed: {", ".join(map(str, xm.HOMING_METHODS))})')
    unit_id = params.get('unit_id', 1)
    if not isinstance(unit_id, int) or not 0 <= unit_id <= 255:
        raise ValueError(f'{prefix}unit_id: {unit_id!r} is not a Modbus unit id '
                         f'(allowed: 0..255)')
    _check_choice('word_order', params.get('word_order', 'little'), xm.WORD_ORDERS,
                  'a word order')
    steps = params.get('steps_per_rev', xm.STEPS_PER_REV)
    if float(steps) != xm.STEPS_PER_REV:
        raise ValueError(f'{prefix}steps_per_rev: {steps:g} is not the X-PLUS MT resolution '
                         f'(allowed: {xm.STEPS_PER_REV}, fixed by STEP_REVOLUTION (1081))')
    return XplusMtDrive(bus, name, params)


VENDOR = Vendor(
    name='X-PLUS MT',
    params=PARAMS,
    make_bus=make_bus,
    make_drive=make_drive,
    # float: the common parameter steps_per_rev is a double (params.py)
    drive_defaults={'steps_per_rev': float(xm.STEPS_PER_REV), 'homing.method': 35},
)
