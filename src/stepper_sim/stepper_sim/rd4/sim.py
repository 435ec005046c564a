"""Simulated Lika RD4 ROTADRIVE units on a Modbus RTU line (a pseudo-terminal it creates).

Two layers, no rclpy below `main()`:
- `Rd4DriveSim`: one RD4 by node id: the register map of the manual §8.1 with the §10 defaults,
  the Control Word [0x2A] logic of §8.1.1 (edges and levels), positioning and jog on a
  `MotionModel`, software limits, alarms and alarm reset, watchdog, save/load defaults/preset.
- `RtuLine`: the serial line: a `pty_line.PtyLine` (an `os.openpty()` pair, the slave side's
  path handed to the driver through a symlink) whose bytes it frames as RTU itself. Every
  frame's CRC is checked; a bad CRC, a broadcast or a frame for another node id gets silence
  (§7.3.1, §8.2), which pymodbus's server does not do (research/transports.md §B1 item 4). With
  `line_timing` the replies come as late as a real line at the dip-switch baud rate delivers them:
  11 bits per character and t3.5 silences (§7.3.1).

Behaviour the manual leaves open is decided as in the spec's best readings (spec/lika_rd4.md §10),
most of them switchable (see `Rd4Options`); docs/rd4.md lists them.

RtuLine uses only a unit's node_id, handle(), update() and frame_received(); Rd4DriveSim's parts
(map, Control Word, motion, alarms, flash) share its register image.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import pathlib
import random
import sys
import termios
import time
from typing import Callable, Mapping, Sequence

from stepper_drivers.protocol import modbus_rtu as rtu
from stepper_drivers.vendors.rd4 import regmap as rm
from stepper_drivers.vendors.rd4.regmap import HR

from ..core.motion import MotionModel
from ..core.pty_line import LINK_FAULTS, PtyLine, PtyLineBackend

logger = logging.getLogger(__name__)

TICK_S = 0.01                 # model update period of the line thread (watchdog, arrival)
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


class Rd4DriveSim:
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

    # ------------------------------------------------------------------ Control Word logic
    def control_word(self, new: int) -> None:
        """§8.1.1 Control Word [0x2A]: compare with the previous value, act on edges/levels."""
        old, self.cw = self.cw, new & 0xFFFF
        self.hr[HR['CONTROL_WORD'].address] = self.cw
        rising, falling = new & ~old, old & ~new
        now = self.clock()
        if not new & rm.CW_EMERGENCY:
            if self.motion.moving or not self.alarms & rm.ALARM_EMERGENCY:
                logger.info('%s: Emergency (CW bit 7 = 0): immediate stop', self.name)
            self.raise_alarm(rm.ALARM_EMERGENCY)
        if rising & rm.CW_ALARM_RESET:
            self.reset_alarms()
        if rising & rm.CW_SAVE_PARAMETERS:
            self._save()
        if rising & rm.CW_LOAD_DEFAULT_PARAMETERS:
            self._load_defaults()
        if rising & rm.CW_PERFORM_COUNTING_PRESET:
            self._apply_preset()
        if rising & rm.CW_WATCH_DOG_ENABLE:
            self.last_frame_at = now
        decel = self._ramps()[1]
        if falling & rm.CW_STOP and self.motion.moving:
            self.motion.stop(decel)             # §8.1.1 bit 2: stop with Deceleration [0x07]
            self.move_kind = None
        jog = new & rm.CW_JOG
        if falling & rm.CW_JOG and self.move_kind == 'jog' and jog != rm.CW_JOG_PLUS \
                and jog != rm.CW_JOG_MINUS:
            self.motion.stop(decel)             # jog released: decelerate
            self.move_kind = None
        can_move = (new & rm.CW_STOP and new & rm.CW_EMERGENCY and not self.alarms)
        if not can_move:
            return
        if jog == rm.CW_JOG:
            # §8.1.1 NOTE: Jog + and Jog - together: no motion, or stop if moving.
            if self.motion.moving:
                self.motion.stop(decel)
            self.move_kind = None
        elif jog:
            self._jog(jog, rising, now)
        elif new & rm.CW_START:
            target_changed = self.get('TARGET_POSITION') != round(
                self.motion.target_position_steps)
            if rising & rm.CW_START or (self.move_kind == 'start' and self.motion.moving
                                        and target_changed):
                self._start()                   # start on the edge; override (§8.1.1)

    def _jog(self, jog: int, rising: int, now: float) -> None:
        if self.move_kind == 'start' and self.motion.moving:
            return                              # §8.1.1 NOTE: jog ignored while positioning
        direction = 1 if jog == rm.CW_JOG_PLUS else -1
        lo, hi = self.limits
        acc, dec = self._ramps()
        speed = self._speed('JOG_SPEED')
        if self.cw & rm.CW_INCREMENTAL_JOG:
            if rising & jog:                    # one step of Jog step length per rising edge
                step = direction * self.get('JOG_STEP_LENGTH')
                target = min(hi, max(lo, round(self.motion.target_position_steps
                                               if self.move_kind == 'step' else self.position)
                                     + step))
                self.motion.move_to(target, speed, acc, dec)
                self.move_kind = 'step'
            return
        if self.move_kind == 'jog' and not rising & jog:
            return      # a held jog: a new Jog speed acts at the next jog (spec §10 item 21)
        # Continuous jog up to the software limit, where it stops (spec §10 item 21).
        self.motion.move_to(hi if direction > 0 else lo, speed, acc, dec)
        self.move_kind = 'jog'

    def _start(self) -> None:
        target = self.get('TARGET_POSITION')
        lo, hi = self.limits
        if not lo <= target <= hi:
            logger.info('%s: target %d outside %d..%d: Target not valid', self.name, target,
                        lo, hi)
            self.raise_alarm(rm.ALARM_TARGET_NOT_VALID)
            return
        acc, dec = self._ramps()
        self.motion.move_to(target, self._speed('WORK_SPEED'), acc, dec)
        self.move_kind = 'start'
        self.target_reached = False

    def _apply_preset(self) -> None:
        """§8.1.1 Preset / CW bit 11: the current position takes the Preset value; the SW
        limits follow from Preset and the deltas; Offset = real position - preset."""
        preset = self.get('PRESET')
        self.motion.set_position(preset)
        self.set('OFFSET', round(self.motion.raw_position_steps - preset))
        logger.info('%s: preset: position := %d', self.name, preset)

    def _save(self) -> None:
        self.flash = {a: self.hr[a] for a in range(rm.MACHINE_DATA[1] + 1)}
        self.saves += 1
        self._store_flash()
        logger.info('%s: parameters saved (%d)', self.name, self.saves)

    def _load_defaults(self) -> None:
        offset = self.get('OFFSET')
        defaults = rm.defaults(self.model)
        for a in range(rm.MACHINE_DATA[1] + 1):
            self.hr[a] = defaults[a]
        self.set('OFFSET', offset)             # Offset is derived, not a default (§10 list)
        self._machine_data_changed()
        logger.info('%s: default parameters loaded (not saved)', self.name)


def corrupt_crc(reply: bytes) -> bytes:
    """A reply whose CRC is wrong (last byte flipped): framed like a real one."""
    return reply[:-1] + bytes((reply[-1] ^ 0xFF,)) if reply else reply


_BAUD_CONSTANTS = {getattr(termios, f'B{b}'): b for b in
                   (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400)
                   if hasattr(termios, f'B{b}')}


class RtuLine(PtyLine):
    """A Modbus RTU line on a pty: the units answer the master on the other side.

    `link_path` is a symlink to the pty's slave side (the driver's `port`), replaced atomically
    when the pty is re-created. `tap(direction, frame, t)` sees every frame ('rx' from the
    master, 'tx' to it).
    """

    label = 'RTU'
    thread_name = 'rd4-line'
    tick_s = TICK_S

    def __init__(self, units: Sequence[Rd4DriveSim], link_path: str | os.PathLike | None = None,
                 baud_switch: int = rm.BAUD_SWITCH_DEFAULT, line_timing: bool = False,
                 turnaround_s: float = 0.0, check_baud: bool = True,
                 tap: Callable[[str, bytes, float], None] | None = None):
        if baud_switch not in rm.BAUD_SWITCH:
            raise ValueError(f'baud_switch: {baud_switch} is not in the dip-switch table '
                             '(allowed: 0..5, §4.4.2)')
        by_id: dict[int, Rd4DriveSim] = {}
        for unit in units:
            unit.baud_switch = baud_switch     # every unit on a line has the line's setting
            if unit.node_id in by_id:
                raise ValueError(f'drives.{unit.name}.node_id: {unit.node_id} is also '
                                 f"{by_id[unit.node_id].name}'s (node ids are unique on "
                                 'a line, §7.1)')
            by_id[unit.node_id] = unit
        baud, parity = rm.BAUD_SWITCH[baud_switch]
        super().__init__(link_path or f'/tmp/rd4_sim_{os.getpid()}', corrupt=corrupt_crc,
                         pty_baud=baud, line_timing=line_timing, tap=tap)
        self.units = by_id
        self.by_name = {u.name: u for u in units}
        self.baud, self.parity = baud, parity
        self.turnaround_s = turnaround_s
        self.check_baud = check_baud
        self.t35_s = rtu.t35_s(self.baud)
        self.counters.update({'frames': 0, 'replies': 0, 'crc_errors': 0, 'other_node': 0,
                              'broadcast': 0, 'exceptions': 0, 'baud_mismatch': 0})
        self._line_free_at = 0.0
        self._warned_baud = False
        self._buf = bytearray()            # the frame being received
        self._first_rx = self._last_rx = 0.0
        self._pending: tuple[float, bytes] | None = None    # (due time, reply)

    def _settings(self) -> str:
        return (f'{self.baud} baud {rm.serial_format(self.parity)}, '
                f'line timing {"on" if self.line_timing else "off"}')

    # ------------------------------------------------------------------- framing (§7.3.1)
    def _received_bytes(self, data: bytes, now: float) -> None:
        if not self._buf:
            self._first_rx = now
        self._buf += data
        self._last_rx = now

    def _deadline_s(self) -> float | None:
        due = [self._last_rx + self.t35_s] if self._buf else []
        if self._pending is not None:
            due.append(self._pending[0])
        return min(due, default=None)

    def _service(self, now: float) -> None:
        buf = self._buf
        if buf:
            n = rtu.request_length(buf)
            if n is not None and len(buf) >= n and rtu.crc_ok(bytes(buf[:n])):
                frame = bytes(buf[:n])
                del buf[:n]
                self._pending = self._frame(frame, self._first_rx, now) or self._pending
                self._first_rx = now
            elif now - self._last_rx >= self.t35_s or len(buf) > rtu.MAX_FRAME_BYTES:
                frame = bytes(buf)       # t3.5 of silence ends a frame (§7.3.1)
                buf.clear()
                self._pending = self._frame(frame, self._first_rx, now) or self._pending
        if self._pending is not None and time.monotonic() >= self._pending[0]:
            self._send(self._pending[1])
            self._pending = None

    def _tick(self, now: float) -> None:
        with self.lock:
            for unit in self.units.values():
                unit.update(now)

    def _master_baud(self) -> int | None:
        try:
            attrs = termios.tcgetattr(self._slave)
        except (termios.error, TypeError):
            return None
        return _BAUD_CONSTANTS.get(attrs[5])

    def _frame(self, frame: bytes, start_s: float, now: float) -> tuple[float, bytes] | None:
        """Handle one received frame; return (due time, reply) when the reply must wait."""
        if self.tap:
            self.tap('rx', frame, now)
        with self.lock:
            self.counters['frames'] += 1
            reply = self._answer(frame, now)
            if reply is not None:
                reply, extra = self._apply_link_faults(reply)
            else:
                extra = 0.0
        # Line timing: the request takes its time on the wire (starting when the line is free),
        # then t3.5, the turnaround, and the reply's own characters (§7.3.1).
        begin = max(start_s, self._line_free_at) if self.line_timing else now
        request_s = rtu.frame_time_s(len(frame), self.baud) if self.line_timing else 0.0
        if reply is None:
            self._line_free_at = begin + request_s + self.t35_s
            return None
        due = now + extra
        if self.line_timing:
            due = max(due, begin + request_s + self.t35_s + self.turnaround_s
                      + rtu.frame_time_s(len(reply), self.baud) + extra)
            self._line_free_at = due + self.t35_s
        self.counters['replies'] += 1
        if due <= time.monotonic():
            self._send(reply)
            return None
        return due, reply

    def _answer(self, frame: bytes, now: float) -> bytes | None:
        """The reply to one frame, or None for silence (§7.3.1 receiver, §8.2)."""
        if len(frame) < 4 or not rtu.crc_ok(frame):
            self.counters['crc_errors'] += 1
            return None
        address = frame[0]
        if address == rtu.BROADCAST_ADDRESS:
            self.counters['broadcast'] += 1     # §7.1: broadcast not implemented
            return None
        unit = self.units.get(address)
        if unit is None:
            self.counters['other_node'] += 1
            return None
        if self.check_baud:
            baud = self._master_baud()
            if baud is not None and baud != self.baud:
                # On a real line the characters would be garbage to the unit: no reply.
                self.counters['baud_mismatch'] += 1
                if not self._warned_baud:
                    logger.warning('master opened the line at %d baud, the units are set to %d '
                                   'by the dip-switch (§4.4.2): no reply', baud, self.baud)
                    self._warned_baud = True
                return None
        unit.frame_received(now)
        try:
            request = rtu.parse_request(frame)
            return unit.handle(request, frame)
        except rtu.ModbusExceptionError as exc:
            self.counters['exceptions'] += 1
            return rtu.exception_response(address, frame[1], exc.code)
        except rtu.FrameError:
            return None
        except Exception:   # noqa: BLE001 - a device fault is exception 04, not a dead line
            logger.exception('%s: request %s', unit.name, frame.hex(' '))
            self.counters['exceptions'] += 1
            return rtu.exception_response(address, frame[1], rtu.SERVER_DEVICE_FAILURE)

    # ------------------------------------------------------------------------- access
    def unit(self, name: str) -> Rd4DriveSim:
        return self.device(name)


# ------------------------------------------------------------------------------ ROS backend
def _storage_path(storage_dir: str, name: str, node_id: int) -> pathlib.Path | None:
    if not storage_dir:
        return None
    path = pathlib.Path(storage_dir)
    path.mkdir(parents=True, exist_ok=True)
    return path / f'rd4_{name}_node{node_id}.json'


def build_line(params: Mapping, drives: Mapping[str, Mapping]) -> RtuLine:
    """An RtuLine from the simulator's parameters (also used by scripts/bench_rd4.py)."""
    options = Rd4Options(preset_on_write=bool(params.get('preset_on_write', False)),
                         emergency_with_alarms=bool(params.get('emergency_with_alarms', True)),
                         hole_policy=str(params.get('hole_policy', 'zero')),
                         ro_write_policy=str(params.get('ro_write_policy', 'ignore')),
                         baud_register=str(params.get('baud_register', 'switch')))
    for key, allowed in (('hole_policy', ('zero', 'exception')),
                         ('ro_write_policy', ('ignore', 'exception')),
                         ('baud_register', ('switch', 'baud'))):
        if getattr(options, key) not in allowed:
            raise ValueError(f'parameter {key}: {getattr(options, key)!r} (allowed: '
                             f'{", ".join(allowed)})')
    baud_switch = int(params.get('baud_switch', rm.BAUD_SWITCH_DEFAULT))
    units = []
    for name, p in drives.items():
        node_id = int(p.get('node_id', 1))
        units.append(Rd4DriveSim(
            name, node_id, str(p.get('model', 'T32')), options=options, baud_switch=baud_switch,
            sw_version=int(p.get('sw_version', 0x0102)),
            hw_version=int(p.get('hw_version', 0x0001)),
            storage_path=_storage_path(str(params.get('storage_dir', '')), name, node_id),
            position_steps=float(p.get('position_steps', 0.0))))
    return RtuLine(units, str(params.get('port', '')) or None, baud_switch=baud_switch,
                   line_timing=bool(params.get('line_timing', False)),
                   turnaround_s=float(params.get('turnaround_s', 0.0)),
                   check_baud=bool(params.get('check_baud', True)))


class Rd4SimBackend(PtyLineBackend):
    """rd4_sim's `sim_node.SimBackend` (duck-typed, so this module imports no rclpy)."""

    line: RtuLine

    def true_position_steps(self, drive: str) -> float:
        with self.line.lock:
            unit = self.line.unit(drive)
            unit.update()
            return unit.position

    def inject_fault(self, drive: str, kind: str, code: int, value: float) -> tuple[bool, str]:
        if kind in LINK_FAULTS:
            return True, self.line.set_link_fault(kind, code, value)
        with self.line.lock:
            try:
                return True, self.line.unit(drive).inject(kind, code, value)
            except ValueError as exc:
                return False, str(exc)

    def set_input(self, drive: str, name: str, value: bool, release: bool) -> tuple[bool, str]:
        key = name.strip().lower().replace(' ', '')
        if key not in rm.INPUT_BITS:
            return False, f'unknown input {name!r} (RD4 inputs: IN 1, IN 2, IN 3)'
        with self.line.lock:
            unit = self.line.unit(drive)
            mask = rm.INPUT_BITS[key]
            unit.inputs = (unit.inputs | mask) if value and not release else unit.inputs & ~mask
            return True, f'{name} = {int(bool(unit.inputs & mask))}'


def build(node) -> Rd4SimBackend:
    from ..core.sim_node import declare, declare_drives
    params = {
        'port': declare(node, 'port', '', 'symlink the simulator creates to its pty (the '
                        "driver's port); '' = /tmp/rd4_sim_<pid>"),
        'baud_switch': declare(node, 'baud_switch', rm.BAUD_SWITCH_DEFAULT,
                               'baud/parity dip-switch code 0..5 (§4.4.2): 1 = 9600 8E1, '
                               '3 = 19200 8N2, 4 = 19200 8E1'),
        'line_timing': declare(node, 'line_timing', False, 'delay replies as a real line at '
                               'the baud rate (11-bit characters, t3.5 silences)'),
        'turnaround_s': declare(node, 'turnaround_s', 0.0, 'unit processing time before a '
                                'reply when line_timing is on [s]'),
        'check_baud': declare(node, 'check_baud', True, 'no reply when the master opened the '
                              'pty at another baud rate than the dip-switch'),
        'storage_dir': declare(node, 'storage_dir', '', "folder for the units' saved "
                               "parameters ('' = kept in memory only)"),
        'preset_on_write': declare(node, 'preset_on_write', False, 'apply Preset on the '
                                   'register write too, not only on CW bit 11'),
        'emergency_with_alarms': declare(node, 'emergency_with_alarms', True, 'set alarm bit 6 '
                                         'Emergency with every other alarm'),
        'hole_policy': declare(node, 'hole_policy', 'zero', "holding 0x1A-0x28: 'zero' or "
                               "'exception'"),
        'ro_write_policy': declare(node, 'ro_write_policy', 'ignore', "writes to Offset/Gear "
                                   "ratio: 'ignore' or 'exception'"),
        'baud_register': declare(node, 'baud_register', 'switch', "Dip-switch baud rate "
                                 "[0x0C] holds the 'switch' code or the 'baud' number"),
    }
    drives = declare_drives(node, ['axis1'], {
        'node_id': (1, 'node ID on the dip-switch (1..247; above 247 the unit uses 247)'),
        'model': ('T32', 'RD4 model: T32 (1600 PPS, gear 32) or T48 (1066 PPS, gear 48)'),
        'sw_version': (0x0102, 'SW Version [0x0E] (major << 8 | minor)'),
        'hw_version': (0x0001, 'HW Version [0x0F]'),
        'position_steps': (0.0, 'position at power-up [pulses]'),
    })
    return Rd4SimBackend(build_line(params, drives))


def main(args=None) -> None:
    from ..core.sim_node import run_sim
    sys.exit(run_sim('rd4_sim', build, args))


if __name__ == '__main__':
    main()
