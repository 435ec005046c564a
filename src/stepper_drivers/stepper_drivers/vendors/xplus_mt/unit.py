"""One R.T.A. X-PLUS MT as the driver reads it: the base of `drive.XplusMtDrive`. No rclpy.

Its registers (the helpers and read_register/write_register), the identity checks and settings
of connect() (§13 "Register 1162", T15, 1081..1097), the drive watchdog's disarm at close(), and
the polled state (status word .. velocity actual value, 1001..1021). The commands (power stage,
motion, homing, maintenance) are drive.py's.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Mapping

from ...contract.capabilities import SplitPoll
from ...contract.drive import (
    Bus,
    DriveError,
    DriveState,
    HomingState,
    IdentityError,
    State,
    register_type,
)
from ...profiles.cia402 import state_machine as cia402
from ...profiles.cia402.drive import Cia402Drive
from ...profiles.cia402.state_machine import (
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
from . import regmap as xm
from .settings import with_defaults

logger = logging.getLogger(__name__)

REG = xm.REGISTERS

# One FC03 covers status word .. velocity actual value (1001..1021, holes 1003, 1012-1013, 1019
# read as filler); if the drive refuses holes, SPLIT_READS (3 requests) is used instead.
STATE_BLOCK = (1001, 21)
SPLIT_READS = ((1001, 2), (1004, 8), (1020, 2))
# 1081..1097 have no hole: step revolution (identity), input config, brake delays, watchdog.
SETTINGS_BLOCK = (1081, 17)

SETTLE_MIN_S = 0.2             # §12 note after transition 16: ~50-200 ms settling, current on

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


class XplusMtUnit(Cia402Drive, SplitPoll):
    """What every XplusMtDrive command relies on: one Modbus client, the word order, the
    driver's own record (homed, current-on time, watchdog armed) and the state decoding.

    Split from XplusMtDrive for size only: the two work on one record, and only XplusMtDrive is
    made; the Cia402Drive class attributes are XplusMtDrive's.
    """

    def __init__(self, bus: Bus, name: str, params: Mapping[str, Any]):
        params = with_defaults(params)
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
        # register address -> the value this connection wrote there, confirmed (_write_once)
        self._written: dict[int, int] = {}

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

    def _write_once(self, name: str, value: int, what: str = '') -> None:
        """Write a profile register unless this connection already wrote `value` there and
        the drive confirmed it: a stream of set points with one profile costs one FC16 less
        each (1072 is not contiguous with 1042..1047). A write whose reply did not come
        leaves the register unknown, so the next one is sent; connect() and any raw
        write_register (1261 restores the defaults) forget every value."""
        address = REG[name].address
        if self._written.get(address) == value:
            return
        self._written.pop(address, None)
        self._write((name, value), what=what)
        self._written[address] = value

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
        self._written.clear()
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

    # ------------------------------------------------------------------ raw registers
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
        self._written.clear()
        if reg.words == 1:
            self.mb.write_register(self.unit_id, reg.address, words[0])
        else:
            self.mb.write_registers(self.unit_id, reg.address, words)
        if reg.address == 1040:
            self.cia.controlword = words[0]
            self._was_enabled = False       # a raw controlword is a command too
