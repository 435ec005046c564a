"""One simulated R.T.A. X-PLUS MT drive: configuration, register image, CiA 402 glue.

The drive behind the Modbus TCP front of `xplus_mt.sim` (behaviour and manual references are
listed there). The CiA 402 power state machine, the statusword state bits and the PP set-point
handshake are the shared device-side tables of `cia402.slave` (profile `XPLUS_MT`). This
module holds the device's state and lock, the register image and its Modbus reads and writes
(§11, §13 register by register), the digital I/O registers, HV for Switch On (§12 transition 3),
the cia402.slave hooks and the 1097 watchdog. Along the drive's own seams, three mixins hold the
rest: `xplus_mt.modes` (profile position with multi-set-point and halt, profile velocity, homing
on a SimAxis, limit switches, the statusword bits of each mode), `xplus_mt.faults` (faults, the
alarm log, the 1085 following-error reaction, injections) and `xplus_mt.storage` (1260/1261
storage).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from typing import Callable, Sequence

from pymodbus.constants import ExcCodes
from stepper_drivers.vendors.xplus_mt import regmap as xm

from ..cia402 import slave as cia
from ..cia402.slave import FAULT, FRA, OE, QSA, RTSO, SO, SOD
from ..core.axis import HOME, LIMIT_NEG, LIMIT_POS, SimAxis
from ..core.homing import HomingRun
from ..core.motion import INF
from .faults import HV_STABLE_S, LOST_REPLY_HOLD_S, XplusMtFaults
from .modes import XplusMtModes
from .storage import XplusMtStorage

# LOST_REPLY_HOLD_S: xplus_mt_sim holds a lost reply this long
__all__ = ['LOST_REPLY_HOLD_S', 'XplusMtDriveConfig', 'XplusMtDriveSim']

logger = logging.getLogger(__name__)


# Output Config (1089) -> functions of O0, O1, O2 (T23 S4, T25 B4); 'gp' = general purpose.
OUTPUT_FUNCTIONS = {
    'S4': {1: ('gp', 'edm', 'fault'), 5: ('gp', 'edm', 'gp'), 7: ('gp', 'gp', 'gp'),
           17: ('busy', 'edm', 'fault'), 21: ('busy', 'edm', 'gp'), 23: ('busy', 'gp', 'gp'),
           33: ('gp', 'edm', 'brake'), 38: ('busy', 'edm', 'brake')},
    'B4': {3: ('gp', 'gp', 'fault'), 7: ('gp', 'gp', 'gp'), 13: ('busy', 'gp', 'fault'),
           17: ('busy', 'gp', 'gp'), 35: ('gp', 'brake', 'fault'), 36: ('busy', 'brake', 'fault'),
           39: ('gp', 'brake', 'gp')},
}


class _Refused(Exception):
    """A write the drive refuses; carries the Modbus exception code."""

    def __init__(self, code: ExcCodes, message: str):
        super().__init__(message)
        self.code = code


@dataclasses.dataclass
class XplusMtDriveConfig:
    """One simulated drive. Positions are raw axis positions in steps (NaN/None = no switch).

    The home switch (proximity input I0) is active between home_switch_steps and
    home_switch_steps + home_switch_width_steps; limit_neg is active below limit_neg_steps,
    limit_pos at and above limit_pos_steps. An index pulse comes every 12800 steps (T20 1081)
    at index_phase_steps.
    """

    name: str
    unit_id: int = 1
    home_switch_steps: float | None = 50_000.0
    limit_neg_steps: float | None = -1_000_000.0
    limit_pos_steps: float | None = 1_000_000.0
    home_switch_width_steps: float = 6_400.0
    index_phase_steps: float = 0.0
    hv_present: bool = True
    model: str = 'S4'                 # 'S4' (STO version) or 'B4' (§6 "Nomenclature")
    software_version: int = 51        # T15 default
    product_code: int = 0
    hardware_version: int = 0
    serial_number: int | None = None  # default 100000 + unit_id
    homing_max_travel_steps: float = 50 * xm.STEPS_PER_REV
    input_config: int | None = None   # initial 1088 (a commissioned drive); None: default/stored
    # power-on register values by address, not checked against the map (a device that is not an
    # X-PLUS MT, e.g. {1081: 200}; tests of the driver's identity checks)
    registers: dict[int, int] = dataclasses.field(default_factory=dict)
    watchdog_error_code: int = 0x8400  # A15: the manual gives no code for the 1097 timeout
    pv_bit10: str = 'threshold'       # A9: 'threshold' (literal manual) or 'cia' (|vt - v| band)

    def __post_init__(self):
        if not 1 <= int(self.unit_id) <= 255:
            raise ValueError(f'drive {self.name}: unit_id {self.unit_id} not in 1..255')
        if self.model not in OUTPUT_FUNCTIONS:
            raise ValueError(f'drive {self.name}: model {self.model!r}; allowed: S4, B4')
        if self.pv_bit10 not in ('threshold', 'cia'):
            raise ValueError(f'drive {self.name}: pv_bit10 {self.pv_bit10!r}; allowed: '
                             'threshold, cia')
        for key in ('home_switch_steps', 'limit_neg_steps', 'limit_pos_steps'):
            value = getattr(self, key)
            if value is not None and math.isnan(value):
                setattr(self, key, None)


def _none_if_nan(value: float | None) -> float | None:
    return None if value is None or math.isnan(value) else float(value)


class XplusMtDriveSim(XplusMtModes, XplusMtFaults, XplusMtStorage):
    """One X-PLUS MT: register image, state machine, modes, faults, over a SimAxis.

    Thread-safe (one lock): the Modbus server thread and the ROS thread both call it.
    """

    def __init__(self, config: XplusMtDriveConfig, *, word_order: str = 'little',
                 storage_dir: str | None = None, strict: bool = True,
                 clock: Callable[[], float] = time.monotonic):
        self.config = config
        self.name = config.name
        self.unit_id = int(config.unit_id)
        self.strict = strict
        self.storage_dir = storage_dir or None
        self._clock = clock
        self._lock = threading.RLock()
        self.lose_write_reply: tuple[int, int] | None = None   # (register, bits)
        now = clock()
        self.power_on_s = now
        self.axis = SimAxis(home_switch_steps=_none_if_nan(config.home_switch_steps),
                            home_switch_width_steps=config.home_switch_width_steps,
                            limit_neg_steps=_none_if_nan(config.limit_neg_steps),
                            limit_pos_steps=_none_if_nan(config.limit_pos_steps),
                            steps_per_rev=xm.STEPS_PER_REV,
                            index_phase_steps=config.index_phase_steps, clock=clock)
        self.axis.add_listener(self._on_axis_event)
        self._regs: dict[int, int] = {reg.address: reg.default for reg in xm.REGISTERS.values()}
        self._regs[1162] = xm.REGISTER_1162_BY_WORD_ORDER[word_order]
        self._regs[1152] = config.software_version
        self._regs[1154] = config.product_code
        self._regs[1156] = config.hardware_version
        self._regs[1158] = (config.serial_number if config.serial_number is not None
                            else 100_000 + self.unit_id)
        self._regs[1250], self._regs[1251], self._regs[1252] = (
            0x0000 + self.unit_id, 0x5A00, 0x0050)   # a made-up MAC per unit
        self._load_storage()
        if config.input_config is not None:
            if not xm.REGISTERS['INPUT_CONFIG'].accepts(config.input_config):
                raise ValueError(f'drive {self.name}: input_config {config.input_config} not '
                                 f'in {xm.REGISTERS["INPUT_CONFIG"].range_text()}')
            self._regs[1088] = config.input_config
        for address, value in config.registers.items():
            if address not in self._regs:
                raise ValueError(f'drive {self.name}: registers: {address} is not a register')
            self._regs[address] = int(value)
        self._pending: dict[int, int] = {}      # first words of 32-bit pairs written alone
        # §12 note: 24 V on -> SWITCH ON DISABLED
        self.cia = cia.PowerStateMachine(cia.XPLUS_MT, self, self.name, SOD)
        self.controlword = 0
        self._now = now
        # HV: "present since" (at start: present before the logic supply came up).
        self.hv_present = bool(config.hv_present)
        self._hv_since = -INF if self.hv_present else INF
        self.error_register = 0
        self.error_code = 0
        self._fault_causes: set[int] = set()
        self.alarm_log: list[tuple[int, int]] = []    # newest first (A23)
        self._following_error = False
        self._first_enable_done = False
        self._encoder_reset_pending = False
        # Profile position.
        self._set_point = cia.SetPointHandshake(cia.XPLUS_MT.set_point_buffer)
        self._halted = False
        self._halt_released = False
        self._move_origin = 0.0
        self._move_relative = False
        self._move_immediate = False
        self._move_accel = float(self._regs[1046])
        self._pp_moving = False
        self._pp_target = 0.0
        # Profile velocity.
        self._pv_started = False
        self._v_above_since: float | None = None
        self._v_below_since: float | None = now
        # Homing.
        self._homing: HomingRun | None = None
        self._homing_attained = False
        self._homing_error = False
        self._homing_message = ''
        # Limits, I/O, watchdog.
        self._limit_stop = False
        self._last_moving_s = -INF
        self._last_request_s = now

    # ------------------------------------------------------------------ public helpers
    @property
    def state(self) -> str:
        return self.cia.state

    @property
    def word_order(self) -> str:
        # a foreign 1162 value (config.registers) reads as the X-PLUS MT default order
        return xm.WORD_ORDER_BY_1162.get(self._regs[1162], 'little')

    @property
    def mode(self) -> int:
        return self._regs[1041]

    @property
    def true_position_steps(self) -> float:
        """The exact position counter of the drive (what 1004-1005 report, unrounded)."""
        with self._lock:
            self.update()
            return self.axis.position_steps

    @property
    def statusword(self) -> int:
        with self._lock:
            self.update()
            return self._statusword()

    def register(self, name: str) -> int:
        """Current value of a register by name (for tests)."""
        with self._lock:
            self.update()
            return self._value(xm.REGISTERS[name])

    # ------------------------------------------------------------------ time
    def update(self, now: float | None = None) -> None:
        with self._lock:
            now = self._clock() if now is None else now
            self.axis.update(now)
            m = self.axis.motion
            if m.moving:
                self._last_moving_s = now
            if self._pp_moving and not m.moving:
                self._pp_moving = False
            if self.state == FRA:
                self.cia.settle()           # §13 "Register 1085" 0x02, C: the motor stopped
            if self.state == RTSO and self._hv_stable(now):
                self._apply_levels(now)     # A4: a held Switch On completes once HV is stable
            self._update_pv_timers(now)
            timeout_ms = self._regs[1097]
            if timeout_ms and self.state not in (FAULT, FRA) and \
                    now - self._last_request_s > timeout_ms / 1000.0:
                logger.info('%s: watchdog (1097 = %d ms) expired', self.name, timeout_ms)
                self._fault(self.config.watchdog_error_code, now, persistent=False)

    def excuse(self, stall_s: float) -> None:
        """The simulator did not run for stall_s (a starved host): requests may have waited in
        the socket meanwhile, so that time does not count against the master (1097)."""
        with self._lock:
            self._last_request_s += stall_s

    def _hv_stable(self, now: float) -> bool:
        return self.hv_present and now - self._hv_since >= HV_STABLE_S

    # ------------------------------------------------------------------ Modbus access
    def read(self, address: int, count: int) -> list[int] | ExcCodes:
        with self._lock:
            now = self._clock()
            self._last_request_s = now
            self.update(now)
            words: list[int] = []
            cache: dict[int, list[int]] = {}
            for addr in range(address, address + count):
                reg = xm.WORD_OWNER.get(addr)
                if reg is None:
                    if self.strict:
                        logger.info('%s: read of unmapped address %d', self.name, addr)
                        return ExcCodes.ILLEGAL_ADDRESS
                    words.append(0)
                    continue
                if reg.address not in cache:
                    cache[reg.address] = xm.encode(reg, self._value(reg), self.word_order)
                words.append(cache[reg.address][addr - reg.address])
            return words

    def write(self, address: int, values: Sequence[int]) -> ExcCodes | None:
        with self._lock:
            now = self._clock()
            self._last_request_s = now
            self.update(now)
            try:
                commits, pending = self._plan_write(address, list(values))
            except _Refused as exc:
                logger.info('%s: write %d..%d refused (exception 0x%02X): %s', self.name,
                            address, address + len(values) - 1, exc.code, exc)
                return exc.code
            self._pending = pending
            for reg, value in commits:
                self._apply(reg, value, now)
            return None

    def _plan_write(self, address: int, values: list[int]):
        """Check a whole request first (nothing is applied when any part is refused)."""
        pending = dict(self._pending)
        commits: list[tuple[xm.Register, int]] = []
        order = self.word_order
        for offset, word in enumerate(values):
            addr = address + offset
            reg = xm.WORD_OWNER.get(addr)
            if reg is None:
                raise _Refused(ExcCodes.ILLEGAL_ADDRESS, f'address {addr} is not a register')
            if not reg.writable:
                raise _Refused(ExcCodes.ILLEGAL_ADDRESS, f'{reg} is read-only')
            if reg.words == 1:
                value = xm.decode(reg, [word], order)
            elif addr == reg.address:
                pending[reg.address] = word     # §11: committed with the second word
                continue
            else:
                first = pending.pop(reg.address, None)
                if first is None:   # second word alone: combine with the committed first word
                    first = xm.encode(reg, self._regs[reg.address], order)[0]
                value = xm.decode(reg, [first, word], order)
            self._check_write(reg, value)
            commits.append((reg, value))
        return commits, pending

    def _check_write(self, reg: xm.Register, value: int) -> None:
        if not reg.accepts(value):
            raise _Refused(ExcCodes.ILLEGAL_VALUE,
                           f'{value} outside {reg} range {reg.range_text()}')
        a = reg.address
        if a == 1041 and self.state not in (SOD, RTSO, SO, OE):
            raise _Refused(ExcCodes.ILLEGAL_VALUE,   # §13 PP/PV/Homing: modes change in these
                           f'mode of operation cannot change in {self.state}')
        if a == 1097 and 0 < value < 100:
            raise _Refused(ExcCodes.ILLEGAL_VALUE, '1097 watchdog: 0 or 100..32000 ms (§13)')
        if a == 1085 and value == 17 and self.state in (OE, QSA):
            raise _Refused(ExcCodes.ILLEGAL_VALUE,
                           '1085 = 17 only in a state lower than Operation Enabled (§13)')
        if a == 1089:
            if self.state in (OE, QSA):
                raise _Refused(ExcCodes.ILLEGAL_VALUE, '1089 cannot be changed in OE (§13)')
            if value not in OUTPUT_FUNCTIONS[self.config.model]:
                raise _Refused(ExcCodes.ILLEGAL_VALUE, f'1089 = {value} is not a '
                               f'{self.config.model} output configuration (T23/T25)')
        if a == 1088 and value & 0x80 and self.config.model != 'S4':
            raise _Refused(ExcCodes.ILLEGAL_VALUE, '1088 bit 7 (IC7) exists on S4 only')

    def _apply(self, reg: xm.Register, value: int, now: float) -> None:
        a = reg.address
        if a == 1040:
            self._on_controlword(value, now)
            return
        if a in (xm.SAVE_PARAMS_REGISTER, xm.RESTORE_DEFAULTS_REGISTER):
            self._signature(a, value)
            return
        if a == xm.ALARM_LOG_RESET:
            if value == 1:
                self.alarm_log.clear()      # §13 "Register 1240"
            return
        if a == 1086:
            self._regs[a] = value
            if value in (1, 2) and self.state == OE and self._regs[1085] != 17:
                self._following_error = False       # §13 "Register 1086"
            return
        if a == 1044 and value == 0 and self._pp_moving:
            logger.info('%s: Profile Velocity 0 ignored while running (§13 Multi-Set-Point)',
                        self.name)
            return
        self._regs[a] = value
        if a == 1041:
            self._on_mode_change(now)
        elif a == 1044 and self._pp_moving and self._move_immediate and not self._halted:
            self._replan_pp()               # §13 Multi-Set-Point: new PV at once
        elif a == 1048 and self._pv_following():
            self._pv_follow()
        elif a == 1121:
            if self.state in (OE, QSA):
                self._encoder_reset_pending = True  # §13 "Register 1121": at next current off
            else:
                self.axis.set_position(0.0)
        elif a in (1081, 1092) and self._regs[1114] == 1:
            self.axis.set_position(0.0)             # §13 "Register 1114" (A20)
        elif a == 1088:
            self._limit_stop = self._limit_stop and self._limit_active_now()

    # ------------------------------------------------------------------ register values
    def _value(self, reg: xm.Register) -> int:
        a = reg.address
        if a == 1001:
            return self._statusword()
        if a == 1002:
            return self._regs[1041]
        if a == 1004:
            return _clamp_i32(round(self.axis.position_steps))
        if a == 1006:
            return self.error_register
        if a == 1007:
            return self.error_code
        if a == 1008:
            return self._digital_inputs()
        if a == 1010:
            return self._digital_outputs()
        if a == 1020:
            return max(-800_000, min(800_000, round(self.axis.velocity_hz)))
        if a == 1040:
            return self.controlword
        if xm.ALARM_LOG_FIRST <= a <= xm.ALARM_LOG_LAST:
            k, is_code = divmod(a - xm.ALARM_LOG_FIRST, 2)
            if k < len(self.alarm_log):
                return self.alarm_log[k][is_code]
            return 0
        if a in (xm.SAVE_PARAMS_REGISTER, xm.RESTORE_DEFAULTS_REGISTER):
            return 0                        # [R] signature registers read 0 (spec §7)
        if a == 1262:
            return self._regs[1152]         # A18: copy of Software Version
        if a == 1268:
            return self._regs[1156]
        return self._regs[a]

    def _digital_inputs(self) -> int:
        ax = self.axis
        neg, pos, home = ax.input(LIMIT_NEG), ax.input(LIMIT_POS), ax.input(HOME)
        i3 = ax.inputs.get('I3', False)
        # §13 "Registers 1008-1009": bits 0-2 functions (1 = active), 16-19 input levels; the
        # limit inputs are normally closed ("ON = free to move", §13 1008).
        return (neg << 0 | pos << 1 | home << 2 | home << 16 | (not neg) << 17
                | (not pos) << 18 | i3 << 19)

    def _digital_outputs(self) -> int:
        functions = OUTPUT_FUNCTIONS[self.config.model].get(self._regs[1089], ('gp',) * 3)
        now = self.axis.motion.time_s
        value = 0
        for k, function in enumerate(functions):
            if function == 'gp':
                on = bool(self._regs[1087] & (1 << k))
            elif function == 'busy':   # §13 "Register 1104": off 1104 ms after the motion
                on = now - self._last_moving_s <= self._regs[1104] / 1000.0
            elif function == 'fault':  # T6 note: ON when the drive is not inhibited
                on = self.state not in (FAULT, FRA)
            elif function == 'brake':
                on = self.state in (OE, QSA)
            else:                      # EDM: ON only with both STO inputs OFF (no STO here)
                on = False
            value |= on << (16 + k)
        if 'brake' in functions and self.state in (OE, QSA):
            value |= 1                 # bit 0 Brake Out
        return value

    # ------------------------------------------------------------------ state machine
    def _on_controlword(self, cw: int, now: float) -> None:
        old, self.controlword = self.controlword, cw
        rising, falling = cw & ~old, old & ~cw
        if self.state == FAULT:
            if self.cia.fault_reset_edge(cw, old):
                self._fault_reset()
            return
        if self.state == FRA:
            return      # §13 "Register 1085": new commands ignored until the motor stopped
        self._apply_levels(now)
        if self.state == OE:
            self._mode_bits(cw, rising, falling)

    def _apply_levels(self, now: float) -> None:
        self._now = now
        self.cia.apply(self.controlword)

    # cia402_device hooks: what the X-PLUS MT adds to the shared transitions (§12).
    def cia_allows(self, number: int) -> bool:
        if number == 3:
            return self._hv_stable(self._now)   # §12 transition 3: HV present >= 500 ms
        if number == 4:
            return self.hv_present
        return True

    def cia_moving(self) -> bool:
        return self.axis.moving

    def cia_option_code(self, transition: int) -> int:
        raise AssertionError('the X-PLUS MT option codes are fixed (cia402_device.XPLUS_MT)')

    def cia_stop(self, ramp: str, transition: int) -> None:
        if ramp == cia.CURRENT_OFF:
            self.axis.motion.stop_immediately()     # CURRENT OFF: the shaft is not driven
        elif transition == cia.FAULT_TRANSITION:
            self.axis.motion.stop(float(self._regs[1072]))   # §13 1085 0x02 in PV
        else:
            self.axis.motion.quick_stop(self._mode_decel())  # spec §3.7 [R]: the mode's ramp

    def cia_leaving(self, number: int, source: str, target: str) -> None:
        if number == 4:
            if not self._first_enable_done:
                self._first_enable_done = True
                if self._regs[1114] == 1:
                    self.axis.set_position(0.0)     # §12 transition 4 with 1114 = 1
        elif number in (5, 8, 9, 11, 12):
            self._abort_homing()

    def cia_left(self, number: int, source: str, target: str) -> None:
        if number in (4, 16):
            self._halted = False
        if number == 4:
            self._set_point.reset()
            self._halt_released = False
            self._pv_started = False
        elif number in (5, 8, 9, 11, 12):      # 11: quick stop; the others: CURRENT OFF
            self._pp_moving = False
            self._pv_started = False
            self._set_point.reset()
            if number != 11:
                self._following_error = False       # §13 "Register 1086": cleared on current off
                if self._encoder_reset_pending:
                    self._encoder_reset_pending = False
                    self.axis.set_position(0.0)

def _clamp_i32(value: int) -> int:
    return max(xm.I32_MIN, min(xm.I32_MAX, int(value)))
