"""One simulated Lika RD4 ROTADRIVE unit: the device behind the Modbus RTU line of `rd4.sim`.

`Rd4DriveSim`: one RD4 by node id: the register map of the manual §8.1 with the §10 defaults,
positioning and jog on a `MotionModel`, software limits, alarms and alarm reset, watchdog,
save/load defaults/preset, and the Modbus requests (reads of holding and input registers,
writes) on its register image. The Control Word [0x2A] logic of §8.1.1 (edges and levels) is the
mixin `rd4.control.Rd4ControlWord`.

Behaviour the manual leaves open is decided as in the spec's best readings (spec/lika_rd4.md §10),
most of them switchable (see `Rd4Options`); docs/rd4.md lists them. Not here: framing, CRC,
line timing and the pty (`rd4.sim.RtuLine`), the ROS backend.

Rd4DriveSim's parts (map, Control Word, motion, alarms, flash) share its register image.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import pathlib
import random
import time
from typing import Callable, Sequence

from stepper_drivers.protocol import modbus_rtu as rtu
from stepper_drivers.vendors.rd4 import regmap as rm
from stepper_drivers.vendors.rd4.regmap import HR

from ..core.motion import MotionModel
from ..core.pty_line import LINK_FAULTS
from .control import Rd4ControlWord

logger = logging.getLogger(__name__)

VELOCITY_REFRESH_S = 1.0      # §8.1.2 Current velocity [0x04]: "updated at every second"
# Plausible motor currents [mA]; the manual gives only the limits (§8.1.1 Max current).
CURRENT_HOLD_MA = 400
CURRENT_RUN_MA = 1200
CURRENT_ACCEL_MA = 2500
TEMPERATURE_C = 35
STORAGE_VERSION = 1


@dataclasses.dataclass
class Rd4Options:
    """The simulator's answers to what the manual leaves open (spec §10)."""

    preset_on_write: bool = False        # §8.1.1 Preset "set ... in the moment when the value is
    #                                      entered": apply on the register write, not only bit 11
    emergency_with_alarms: bool = True   # §8.1.2 alarm bit 6: "... or alarms are active"
    hole_policy: str = 'zero'            # holding 0x1A-0x28: 'zero' (read 0, writes ignored)
    #                                      or 'exception' (02)
    ro_write_policy: str = 'ignore'      # writes to Offset/Gear ratio: 'ignore' or 'exception'
    baud_register: str = 'switch'        # Dip-switch baud rate [0x0C]: 'switch' code or 'baud'


def _ms(value: int) -> float:
    return value / 1000.0


class Rd4DriveSim(Rd4ControlWord):
    """One simulated RD4. Thread-safety is the caller's (RtuLine holds its lock)."""

    def __init__(self, name: str, node_id: int, model: str = 'T32', *,
                 options: Rd4Options | None = None, baud_switch: int = rm.BAUD_SWITCH_DEFAULT,
                 sw_version: int = 0x0102, hw_version: int = 0x0001,
                 storage_path: pathlib.Path | None = None, position_steps: float = 0.0,
                 clock: Callable[[], float] = time.monotonic):
        if model not in rm.MODELS:
            raise ValueError(f'drives.{name}.model: {model!r} is not an RD4 model '
                             f'(allowed: {", ".join(rm.MODELS)})')
        if not 1 <= node_id <= 255:
            raise ValueError(f'drives.{name}.node_id: {node_id} (allowed: 1..255; above 247 '
                             'the unit uses 247, §4.4.1)')
        self.name = name
        self.switch_node_id = node_id
        self.node_id = min(node_id, rtu.MAX_SLAVE_ADDRESS)     # §4.4.1 "set to 247"
        self.model = rm.MODELS[model]
        self.options = options or Rd4Options()
        self.baud_switch = baud_switch
        self.sw_version = sw_version
        self.hw_version = hw_version
        self.storage_path = storage_path
        self.clock = clock
        self.hr = rm.defaults(self.model)
        self.flash = {a: self.hr[a] for a in range(rm.MACHINE_DATA[1] + 1)}
        self._load_flash()
        for address, word in self.flash.items():
            self.hr[address] = word
        self.motion = MotionModel(position_steps, clock=clock)
        self.motion.set_position(position_steps + self._offset_reference())
        self.cw = 0x0000                     # §5.3: power-up "necessarily in an emergency"
        self.alarms = rm.ALARM_EMERGENCY
        self.causes = 0                      # injected conditions that persist (overcurrent...)
        self.wrong_parameters = 0
        self.move_kind: str | None = None    # 'start' | 'jog' | 'step' while commanded
        self.target_reached = False
        self.window_since: float | None = None
        now = clock()
        self.velocity_register = 0
        self.next_velocity_refresh = now + VELOCITY_REFRESH_S
        self.last_frame_at = now
        self.inputs = 0
        self.following_error = 0
        self.temperature_c = TEMPERATURE_C
        self.saves = 0
        # Another device answering at this node ID: read replies carry its words,
        # with a valid CRC; writes still reach this unit. None = off, 0 = until clear_fault.
        self.garbage_reads: int | None = None
        self._garbage = random.Random(0)
        self._validate()
        if self.wrong_parameters:
            self.alarms |= rm.ALARM_MACHINE_DATA_NOT_VALID

    # --------------------------------------------------------------------------- storage
    def _load_flash(self) -> None:
        if self.storage_path is None or not self.storage_path.exists():
            return
        try:
            data = json.loads(self.storage_path.read_text())
            words = data['machine_data']
            if len(words) != rm.MACHINE_DATA[1] + 1:
                raise ValueError(f'{len(words)} words')
        except (OSError, ValueError, KeyError, TypeError) as exc:
            logger.warning('%s: stored parameters %s unreadable (%s); using defaults',
                           self.name, self.storage_path, exc)
            return
        self.flash = {a: int(w) & 0xFFFF for a, w in enumerate(words)}
        logger.info('%s: parameters loaded from %s', self.name, self.storage_path)

    def _store_flash(self) -> None:
        if self.storage_path is None:
            return
        words = [self.flash[a] for a in range(rm.MACHINE_DATA[1] + 1)]
        named = {r.name: rm.decode(r, words[r.address:r.address + r.words])
                 for r in rm.HOLDING_REGISTERS if r.address <= rm.MACHINE_DATA[1]}
        tmp = self.storage_path.with_suffix('.tmp')
        tmp.write_text(json.dumps({'version': STORAGE_VERSION, 'node_id': self.node_id,
                                   'model': self.model.name, 'machine_data': words,
                                   'values': named}, indent=1))
        os.replace(tmp, self.storage_path)

    # ------------------------------------------------------------------------ registers
    def get(self, name: str) -> int:
        reg = HR[name]
        return rm.decode(reg, [self.hr[reg.address + i] for i in range(reg.words)])

    def set(self, name: str, value: int) -> None:
        reg = HR[name]
        for i, word in enumerate(rm.encode(reg, value)):
            self.hr[reg.address + i] = word

    def _offset_reference(self) -> float:
        """Referenced = raw - Offset (§8.1.1 Offset = real position - preset)."""
        return -float(self.get('OFFSET'))

    @property
    def position(self) -> float:
        return self.motion.position_steps

    @property
    def limits(self) -> tuple[int, int]:
        """§8.1.1: SW limit switch +/- = Preset +/- Positive/Negative delta."""
        preset = self.get('PRESET')
        return preset - self.get('NEGATIVE_DELTA'), preset + self.get('POSITIVE_DELTA')

    def _speed_cap(self) -> int:
        return rm.max_speed_pps(self.model, max(1, self.get('DISTANCE_PER_REVOLUTION')),
                                rounding='round')

    def _speed(self, name: str) -> float:
        return float(max(rm.MIN_SPEED_PPS, min(self.get(name), self._speed_cap())))

    def _ramps(self) -> tuple[float, float]:
        return float(max(1, self.get('ACCELERATION'))), float(max(1, self.get('DECELERATION')))

    def _validate(self) -> None:
        """Wrong parameters list [0x09-0x0A] from the machine data (§8.1.1 ranges, §6.4)."""
        wrong = 0
        dpr = self.get('DISTANCE_PER_REVOLUTION')
        for reg in rm.HOLDING_REGISTERS:
            if reg.wp_bit is None:
                continue
            value = self.get(reg.name)
            lo, hi = reg.min, reg.max
            if reg.name in ('JOG_SPEED', 'WORK_SPEED'):
                hi = rm.max_speed_pps(self.model, max(1, min(dpr, 1024)), rounding='round')
            elif reg.name in ('POSITIVE_DELTA', 'NEGATIVE_DELTA'):
                hi = rm.max_delta_pulses(max(1, min(dpr, 1024)))
            elif reg.name == 'GEAR_RATIO':
                lo = hi = self.model.gear_ratio
            elif reg.name == 'MAX_CURRENT':
                hi = min(hi, self.get('STARTING_TORQUE_CURRENT'))  # §8.1.1 Max current
            if not lo <= value <= hi:
                wrong |= 1 << reg.wp_bit
        self.wrong_parameters = wrong

    def input_registers(self) -> list[int]:
        self.update()
        words = [0] * (rm.INPUT_END + 1)
        words[0x00] = self.alarms
        words[0x01] = self.status_word()
        words[0x02:0x04] = rm.split32(round(self.position))
        words[0x04] = self.velocity_register & 0xFFFF
        words[0x05:0x07] = rm.split32(self.following_error)
        words[0x07] = self.current_ma() & 0xFFFF
        words[0x08] = self.temperature_c & 0xFFFF
        words[0x09:0x0B] = rm.split32(self.wrong_parameters)
        words[0x0B] = min(0xFFFF, self.current_ma() // 50)
        words[0x0C] = (self.baud_switch if self.options.baud_register == 'switch'
                       else rm.BAUD_SWITCH[self.baud_switch][0])
        words[0x0D] = self.switch_node_id
        words[0x0E] = self.sw_version
        words[0x0F] = self.hw_version
        return words

    def current_ma(self) -> int:
        if self.alarms:
            return 0
        if self.motion.moving:
            return CURRENT_ACCEL_MA if self.motion.in_ramp else CURRENT_RUN_MA
        return CURRENT_HOLD_MA if self.cw & rm.CW_AXIS_TORQUE else 0

    def status_word(self) -> int:
        sw = self.inputs
        running = self.motion.moving
        lo, hi = self.limits
        position = round(self.position)
        if self.window_since is not None and self.clock() - self.window_since >= _ms(
                self.get('POSITION_WINDOW_TIME')):
            sw |= rm.SW_AXIS_IN_POSITION
        if not self.alarms and (running or self.cw & rm.CW_AXIS_TORQUE):
            sw |= rm.SW_AXIS_ENABLED
        if position >= hi:
            sw |= rm.SW_SW_LIMIT_SWITCH_PLUS
        if position <= lo:
            sw |= rm.SW_SW_LIMIT_SWITCH_MINUS
        if self.alarms:
            sw |= rm.SW_ALARM
        if running:
            sw |= rm.SW_AXIS_RUNNING | rm.SW_EXECUTING_A_COMMAND
        if self.target_reached:
            sw |= rm.SW_TARGET_POSITION_REACHED
        if self.current_ma() >= self.get('MAX_CURRENT'):
            sw |= rm.SW_DAC_SATURATION
        return sw

    @property
    def outputs(self) -> int:
        """OUT 1-3 follow the Control Word only in the Idle (no alarm) state (§6.3)."""
        return 0 if self.alarms else self.cw & rm.CW_OUTPUTS

    # ------------------------------------------------------------------------- time
    def update(self, now: float | None = None) -> None:
        now = self.clock() if now is None else now
        self.motion.update(now)
        if self.move_kind in ('start', 'step') and not self.motion.moving:
            if self.move_kind == 'start' and round(self.position) == self.get('TARGET_POSITION'):
                self.target_reached = True                # §8.1.2 status bit 8
            self.move_kind = None
        if abs(self.get('TARGET_POSITION') - round(self.position)) <= self.get('POSITION_WINDOW'):
            if self.window_since is None:
                self.window_since = now
        else:
            self.window_since = None
        if now >= self.next_velocity_refresh:
            self.velocity_register = max(-0x8000, min(0x7FFF, round(self.motion.velocity_hz)))
            periods = math.floor((now - self.next_velocity_refresh) / VELOCITY_REFRESH_S) + 1
            self.next_velocity_refresh += periods * VELOCITY_REFRESH_S
        if (self.cw & rm.CW_WATCH_DOG_ENABLE and not self.alarms & rm.ALARM_WATCH_DOG
                and now - self.last_frame_at > rm.WATCH_DOG_TIMEOUT_S):
            logger.warning('%s: watch dog: no message for %.1f s, safety stop', self.name,
                           now - self.last_frame_at)
            self.raise_alarm(rm.ALARM_WATCH_DOG)

    def frame_received(self, now: float | None = None) -> None:
        """A valid frame addressed to this unit feeds the watchdog (spec §10 item 10)."""
        self.last_frame_at = self.clock() if now is None else now

    # ------------------------------------------------------------------------- alarms
    def raise_alarm(self, mask: int) -> None:
        """Every alarm stops the axis at once and takes the power stage off (spec §5.1)."""
        self.alarms |= mask
        if self.options.emergency_with_alarms:
            self.alarms |= rm.ALARM_EMERGENCY
        if self.motion.moving:
            self.motion.stop_immediately()
        self.move_kind = None

    def reset_alarms(self) -> None:
        """CW bit 3 rising edge: clears the alarms whose cause has ceased (§8.1.1 bit 3)."""
        keep = self.alarms & rm.NOT_RESETTABLE
        keep |= self.causes
        if self.wrong_parameters:
            keep |= rm.ALARM_MACHINE_DATA_NOT_VALID
        if not self.cw & rm.CW_EMERGENCY or (keep and self.options.emergency_with_alarms):
            keep |= rm.ALARM_EMERGENCY
        if self.alarms != keep:
            logger.info('%s: alarm reset: 0x%04X -> 0x%04X', self.name, self.alarms, keep)
        self.alarms = keep
        if not keep & rm.ALARM_FOLLOWING_ERROR:
            self.following_error = 0
        self.target_reached = False                       # §8.1.2 status bit 8

    def inject(self, kind: str, code: int, value: float) -> str:
        if kind == 'drive_fault':
            mask = code & 0xFFFF
            known = sum(a.mask for a in rm.ALARMS)
            if not mask or mask & ~known:
                names = ', '.join(f'0x{a.mask:04X} {a.name}' for a in rm.ALARMS)
                raise ValueError(f'drive_fault code 0x{code:04X}: not Alarms register bits '
                                 f'(known: {names})')
            persistent = mask & (rm.ALARM_OVERCURRENT | rm.ALARM_OVERTEMPERATURE
                                 | rm.ALARM_UNDERVOLTAGE)
            self.causes |= persistent
            if mask & rm.ALARM_FOLLOWING_ERROR:
                self.following_error = self.get('MAX_FOLLOWING_ERROR') + 1
            if mask & rm.ALARM_OVERTEMPERATURE:
                self.temperature_c = 90
            self.raise_alarm(mask)
            return f'alarms now 0x{self.alarms:04X}: {", ".join(rm.alarm_names(self.alarms))}'
        if kind == 'clear_fault':
            self.causes = 0
            self.temperature_c = TEMPERATURE_C
            self.garbage_reads = None
            return 'causes cleared: an Alarm reset (CW bit 3 edge) can now clear the alarms'
        if kind == 'garbage_reads':
            self.garbage_reads = max(0, int(code))
            self._garbage.seed(int(value))
            return (f'read replies carry pseudo-random words (seed {int(value)}, valid CRC) for '
                    + (f'the next {code} reads' if code > 0 else 'every read until clear_fault'))
        if kind == 'temperature':
            self.temperature_c = int(value)
            return f'Temperature value [0x08] = {self.temperature_c} degC'
        raise ValueError(f'unknown fault kind {kind!r} for an RD4 unit (allowed: drive_fault, '
                         'clear_fault, temperature, garbage_reads; link: '
                         + ', '.join(LINK_FAULTS) + ')')

    # ------------------------------------------------------------------------ requests
    def handle(self, request: rtu.Request, frame: bytes) -> bytes:
        fc = request.function_code
        if fc in (rtu.FC_READ_HOLDING_REGISTERS, rtu.FC_READ_INPUT_REGISTERS):
            read = self.read_holding if fc == rtu.FC_READ_HOLDING_REGISTERS else self.read_input
            words = read(request.address, request.count)
            if self.garbage_reads is not None:
                words = [self._garbage.getrandbits(16) for _ in words]
                if self.garbage_reads == 1:
                    self.garbage_reads = None
                elif self.garbage_reads > 1:
                    self.garbage_reads -= 1
            return rtu.response_for(request, frame, words)
        self.write(request.address, request.values, fc)
        return rtu.response_for(request, frame)

    def _check_range(self, fc: int, address: int, count: int, end: int) -> None:
        if address + count - 1 > end:
            raise rtu.ModbusExceptionError(
                fc, rtu.ILLEGAL_DATA_ADDRESS, f'0x{address:02X}+{count} beyond 0x{end:02X}')
        if (end == rm.HOLDING_END and self.options.hole_policy == 'exception'
                and any(a in rm.HOLES for a in range(address, address + count))):
            raise rtu.ModbusExceptionError(fc, rtu.ILLEGAL_DATA_ADDRESS,
                                           'non-existent register 0x1A-0x28')

    def read_holding(self, address: int, count: int) -> list[int]:
        self._check_range(rtu.FC_READ_HOLDING_REGISTERS, address, count, rm.HOLDING_END)
        self.update()
        return [self.hr[a] for a in range(address, address + count)]

    def read_input(self, address: int, count: int) -> list[int]:
        self._check_range(rtu.FC_READ_INPUT_REGISTERS, address, count, rm.INPUT_END)
        return self.input_registers()[address:address + count]

    def write(self, address: int, values: Sequence[int], fc: int) -> None:
        self._check_range(fc, address, len(values), rm.HOLDING_END)
        read_only = {HR['OFFSET'].address, HR['OFFSET'].address + 1, HR['GEAR_RATIO'].address}
        addresses = range(address, address + len(values))
        if self.options.ro_write_policy == 'exception' and read_only & set(addresses):
            raise rtu.ModbusExceptionError(fc, rtu.ILLEGAL_DATA_ADDRESS, 'read-only register')
        self.update()
        cw = None
        machine_data = False
        target_written = False
        preset_written = False
        for a, value in zip(addresses, values):
            if a in read_only or a in rm.HOLES:
                continue                       # acknowledged, ignored (spec §9A items 6-7)
            if a == HR['CONTROL_WORD'].address:
                cw = value
                continue
            self.hr[a] = value & 0xFFFF
            machine_data |= a <= rm.MACHINE_DATA[1]
            target_written |= a in (0x2B, 0x2C)
            preset_written |= a in (0x16, 0x17)
        if target_written:
            self.target_reached = False       # §8.1.2 bit 8: "until new Target position"
        if machine_data:
            self._machine_data_changed()
        if preset_written and self.options.preset_on_write:
            self._apply_preset()
        if cw is not None:
            self.control_word(cw)

    def _machine_data_changed(self) -> None:
        before = self.wrong_parameters
        self._validate()
        if self.wrong_parameters and self.wrong_parameters != before:
            # §5.4: an out-of-range value is accepted and forces the alarm condition.
            logger.info('%s: machine data not valid: %s', self.name,
                        ', '.join(rm.wrong_parameter_titles(self.wrong_parameters)))
            self.raise_alarm(rm.ALARM_MACHINE_DATA_NOT_VALID)
