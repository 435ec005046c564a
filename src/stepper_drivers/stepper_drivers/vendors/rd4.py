"""Lika RD4 ROTADRIVE over Modbus RTU (RS-485): the drive class and the vendor description.

Several RD4 units share one serial line (`ModbusRtuBus`), each addressed by its dip-switch node
ID. Register numbers and bit meanings come from the manual `lika_rd4_modbus_rtu.txt` (§8.1.1
machine data and Control Word [0x2A], §8.1.2 input registers); the map is in `rd4_map.py`.
No rclpy.

How the contract maps to the RD4 (docs/rd4.md has the full table):
- state: one FC04 of 0x00-0x07 per poll (Alarms, Status word, Current position, Current velocity,
  Position following error, Current value); the Wrong parameters list only when its alarm is on.
- enable: Target position := Current position, Control Word with Emergency and Stop high (plus
  Watch dog enable and Axis torque as configured), and an Alarm reset edge to leave the power-up
  Emergency (§5.3). disable: Stop low, Emergency high, watchdog and hold torque off.
- move: Target position (FC16) + a clean 0 -> 1 edge of Start; Start is cleared once the target
  is reached, so the move is right whether the firmware starts on the edge or the level.
- velocity: Jog + / Jog - at Jog speed [0x0C]; a new speed re-issues the jog (clear, then set).
- stop: Stop (bit 2) low, restored at standstill; quick stop: Emergency (bit 7) low.
- home: the RD4 has no homing run: Preset [0x16-0x17] := homing.offset and a rising edge of
  Perform counting preset (bit 11), so it is right whether the register write or the edge applies.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Mapping

from ..drive import (Bus, Drive, DriveError, DriveState, Homing, HomingState, Motion, ParamSpec,
                     State, Vendor, register_type)
from ..protocol.modbus_rtu import ModbusRtuBus
from . import rd4_map as rm
from .rd4_map import HR, IR

logger = logging.getLogger(__name__)

HOMING_METHOD_PRESET = 35      # CiA 402 method 35 "current position is home": what a preset is
MIN_WATCHDOG_POLL_HZ = 5.0     # spec §9B: poll period <= 200 ms keeps the 1 s watchdog fed
_RAW_TYPES = ('u16', 'i16', 'u32', 'i32')


class Rd4Drive(Drive):
    """One RD4 unit on a Modbus RTU line (node ID = parameter `node_id`)."""

    def __init__(self, bus: Bus, name: str, params: Mapping[str, Any]):
        super().__init__(bus, name, params)
        if not isinstance(bus, ModbusRtuBus):
            raise TypeError(f'{name}: the RD4 needs a ModbusRtuBus, got {type(bus).__name__}')
        self.rtu: ModbusRtuBus = bus
        self.node_id = int(params.get('node_id', 1))
        self.address = self.node_id
        self.watchdog = bool(params.get('watchdog', True))
        self.hold_torque = bool(params.get('hold_torque', True))
        self.velocity_source = str(params.get('velocity_source', 'register'))
        self.steps_per_rev = float(params.get('steps_per_rev', 1024.0))
        self.cw: int | None = None            # shadow of Control Word [0x2A]
        self.md: dict[str, int] = {}          # machine data 0x00-0x19, decoded by name
        self.model = rm.MODELS['T32']
        self._md_stale = True
        self._stop_pending = False            # Stop (bit 2) low until the axis stands still
        self._homing = HomingState.IDLE
        self._moving = False
        self._alarms = 0
        self._last_position: tuple[int, float] | None = None
        self._velocity = 0.0
        self._notes: set[str] = set()

    # ---------------------------------------------------------------------- bus helpers
    def _read_input(self, address: int, count: int) -> list[int]:
        return self.rtu.read_input_registers(self.node_id, address, count)

    def _read_holding(self, address: int, count: int) -> list[int]:
        return self.rtu.read_holding_registers(self.node_id, address, count)

    def _write(self, name: str, value: int) -> None:
        """One register by name: FC06 for 16 bits, FC16 for a 32-bit pair (one request)."""
        reg = HR[name]
        if reg.words == 2:
            self.rtu.write_registers(self.node_id, reg.address, rm.split32(value))
        else:
            self.rtu.write_register(self.node_id, reg.address, value)

    def _write_cw(self, cw: int) -> None:
        self.rtu.write_register(self.node_id, HR['CONTROL_WORD'].address, cw & 0xFFFF)
        self.cw = cw & 0xFFFF

    def _note(self, text: str) -> None:
        """Log a notice once per distinct text (commands repeat at the command rate)."""
        if text not in self._notes:
            self._notes.add(text)
            logger.warning('%s: %s', self.name, text)

    def _machine_data(self, words: list[int] | None = None) -> dict[str, int]:
        """The cached machine data 0x00-0x19 (re-read when stale, or decoded from words)."""
        if self._md_stale or words is not None:
            first, last = rm.MACHINE_DATA
            if words is None:
                words = self._read_holding(first, last - first + 1)
            self.md = {r.name: rm.decode(r, words[r.address:r.address + r.words])
                       for r in rm.HOLDING_REGISTERS if r.address <= last}
            self.model = rm.MODEL_BY_GEAR_RATIO.get(self.md['GEAR_RATIO'], rm.MODELS['T32'])
            if self.md['GEAR_RATIO'] not in rm.MODEL_BY_GEAR_RATIO:
                self._note(f"Gear ratio [0x18] = {self.md['GEAR_RATIO']} is neither 32 nor 48; "
                           'speed limits assume the T32 model')
            self._md_stale = False
        return self.md

    @property
    def limits(self) -> tuple[int, int]:
        """SW limit switch -/+ = Preset -/+ Negative/Positive delta (§8.1.1)."""
        md = self._machine_data()
        return md['PRESET'] - md['NEGATIVE_DELTA'], md['PRESET'] + md['POSITIVE_DELTA']

    def _max_speed(self) -> int:
        dpr = self._machine_data()['DISTANCE_PER_REVOLUTION']
        return rm.max_speed_pps(self.model, max(1, dpr))

    def _base(self, enabled: bool) -> int:
        """The Control Word without commands: outputs kept; enabled = Emergency and Stop high
        (§9.3 Example 2, 0x0084) plus Watch dog enable and Axis torque as configured."""
        outputs = (self.cw or 0) & rm.CW_OUTPUTS
        if not enabled:
            return rm.CW_EMERGENCY | outputs
        return (rm.CW_READY | outputs | (rm.CW_WATCH_DOG_ENABLE if self.watchdog else 0)
                | (rm.CW_AXIS_TORQUE if self.hold_torque else 0))

    def _enabled(self) -> bool:
        cw = self.cw or 0
        return (not self._alarms and bool(cw & rm.CW_EMERGENCY)
                and bool(cw & rm.CW_STOP or self._stop_pending))

    def _require_enabled(self, what: str) -> None:
        if not self._enabled():
            raise DriveError(f'{what}: {self.name} is not enabled (Control Word '
                             f'0x{self.cw or 0:04X}'
                             + (f', alarms 0x{self._alarms:04X}' if self._alarms else '')
                             + '); call enable first')

    # ---------------------------------------------------------------------- life cycle
    def connect(self) -> dict[str, str]:
        baud_reg, node_reg, sw_version, hw_version = self._read_input(*rm.IDENTITY_BLOCK)
        self._md_stale = True
        md = self._machine_data()
        first, last = rm.COMMAND_BLOCK
        command = self._read_holding(first, last - first + 1)
        self.cw = command[HR['CONTROL_WORD'].address - first]
        target = rm.join32(command[2:4], signed=True)
        self._stop_pending = False
        self._homing = HomingState.IDLE
        self._last_position = None
        if node_reg != self.node_id and not (node_reg > 247 and self.node_id == 247):
            self._note(f'Dip-switch node ID [0x0D] reads {node_reg}, configured node_id is '
                       f'{self.node_id}')
        if (hw_version >> 8) & 0xFF != 0:
            self._note(f'HW Version [0x0F] says {rm.describe_hw_version(hw_version)}, not an RD4 '
                       'with Modbus interface')
        if self.steps_per_rev != md['DISTANCE_PER_REVOLUTION']:
            self._note(f"steps_per_rev {self.steps_per_rev:g} differs from Distance per "
                       f"revolution [0x00] = {md['DISTANCE_PER_REVOLUTION']} pulses: joint "
                       'positions are scaled by steps_per_rev')
        lo, hi = self.limits
        return {
            'vendor': 'Lika Electronic', 'product': f'RD4 ROTADRIVE {self.model.name}',
            'node_id': str(self.node_id), 'sw_version': rm.describe_sw_version(sw_version),
            'hw_version': rm.describe_hw_version(hw_version),
            'dip_switch_baud_rate': rm.describe_baud_register(baud_reg),
            'distance_per_revolution': str(md['DISTANCE_PER_REVOLUTION']),
            'sw_limits_pulses': f'{lo}..{hi}', 'max_speed_pps': str(self._max_speed()),
            'control_word': f'0x{self.cw:04X}', 'target_position': str(target),
            'watchdog': 'on when enabled' if self.watchdog else 'off',
        }

    def read_state(self) -> DriveState:
        first, count = rm.STATE_BLOCK
        w = self._read_input(first, count)
        now = time.monotonic()
        alarms, sw = w[0], w[1]
        position = rm.join32(w[2:4], signed=True)
        velocity_reg = rm.decode(IR['CURRENT_VELOCITY'], w[4:5])
        current_ma = rm.decode(IR['CURRENT_VALUE'], w[7:8])
        wrong = None
        if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID:
            reg = IR['WRONG_PARAMETERS_LIST']
            wrong = rm.join32(self._read_input(reg.address, 2), signed=False)
        self._alarms = alarms
        running = bool(sw & rm.SW_AXIS_RUNNING)
        self._moving = running
        cw = self.cw or 0
        if self._stop_pending and not running:
            self._stop_pending = False
            if not alarms:
                self._write_cw(cw | rm.CW_STOP)     # standstill: movements allowed again
        elif cw & rm.CW_START and sw & rm.SW_TARGET_POSITION_REACHED and not running:
            self._write_cw(cw & ~rm.CW_START)       # the move is done: Start back to 0
        cw = self.cw or 0
        if self.velocity_source == 'position':
            if self._last_position is not None and now - self._last_position[1] > 1e-3:
                self._velocity = ((position - self._last_position[0])
                                  / (now - self._last_position[1]))
            if not running:
                self._velocity = 0.0
            velocity = self._velocity
        else:
            # §8.1.2: "updated at every second"; Axis running (live) says when it is 0.
            velocity = float(velocity_reg) if running else 0.0
        self._last_position = (position, now)
        fault_bits = alarms & ~rm.ALARM_EMERGENCY
        enabled = self._enabled()
        if fault_bits:
            state = State.FAULT
        elif enabled:
            state = State.OPERATION_ENABLED
        else:
            state = State.SWITCH_ON_DISABLED     # power-up emergency, disabled, or quick stop
        names = rm.alarm_names(alarms)
        for mask, text in ((rm.SW_SW_LIMIT_SWITCH_PLUS, 'SW limit switch +'),
                           (rm.SW_SW_LIMIT_SWITCH_MINUS, 'SW limit switch -'),
                           (rm.SW_DAC_SATURATION, 'DAC saturation')):
            if sw & mask:
                names.append(text)
        if cw & rm.CW_JOG:
            mode = 'INCREMENTAL JOG' if cw & rm.CW_INCREMENTAL_JOG else 'JOG'
        elif cw & rm.CW_START:
            mode = 'POSITIONING'
        else:
            mode = ''
        return DriveState(
            state=state, enabled=enabled, moving=running,
            target_reached=bool(sw & rm.SW_TARGET_POSITION_REACHED),
            # A multiturn absolute encoder (§1 of the manual): referenced unless the unit
            # says the axis lost its synchronisation.
            homed=not alarms & rm.ALARM_AXIS_NOT_SYNCHRONIZED,
            homing=self._homing, fault=bool(fault_bits), fault_code=alarms if fault_bits else 0,
            fault_text=rm.describe_alarms(alarms, wrong) if fault_bits else '',
            alarms=tuple(names), mode=mode, status_word=sw, position_steps=position,
            velocity_steps_s=velocity, effort=current_ma / 1000.0)

    # ---------------------------------------------------------------------- power stage
    def enable(self) -> None:
        alarms, _sw, *pos = self._read_input(0x00, 4)
        self._alarms = alarms
        if alarms & ~rm.ALARM_EMERGENCY:
            wrong = self._wrong_parameters() if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID else None
            raise DriveError(f'enable: alarm 0x{alarms:04X}: {rm.describe_alarms(alarms, wrong)};'
                             ' call fault_reset first')
        # Nothing may move: Target position := Current position before Stop/Emergency go high.
        self._write('TARGET_POSITION', rm.join32(pos, signed=True))
        base = self._base(True)
        self._write_cw(base)
        if alarms & rm.ALARM_EMERGENCY:
            # §5.3: after power-up (or a quick stop) first Emergency high, then Reset alarm.
            self._write_cw(base | rm.CW_ALARM_RESET)
            self._write_cw(base)
            alarms = self._read_input(0x00, 1)[0]
            self._alarms = alarms
            if alarms:
                wrong = (self._wrong_parameters() if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID
                         else None)
                raise DriveError(f'enable: alarms remain after Alarm reset: 0x{alarms:04X} '
                                 f'{rm.describe_alarms(alarms, wrong)}')
        self._stop_pending = False

    def disable(self) -> None:
        """Stop low (a running move decelerates), Emergency high so no alarm latches, watchdog
        and hold torque off: the unit stays quiet when the master goes away."""
        self._write_cw(self._base(False))
        self._stop_pending = False

    def _wrong_parameters(self) -> int:
        return rm.join32(self._read_input(IR['WRONG_PARAMETERS_LIST'].address, 2), signed=False)

    # ---------------------------------------------------------------------- motion
    def _clamp(self, what: str, value: float, lo: int, hi: int, reg: str) -> int:
        result = min(hi, max(lo, int(round(abs(value)))))
        if result != int(round(abs(value))):
            self._note(f'{what} {abs(value):g} is outside {HR[reg].title} range {lo}..{hi} '
                       f'{HR[reg].unit}: {result} used')
        return result

    def _profile(self, motion: Motion, speed_reg: str, velocity: float) -> bool:
        """Write Acceleration/Deceleration [0x06-0x07] and the speed register when they differ
        from the drive's; True when the speed register changed."""
        md = self._machine_data()
        acc_reg = HR['ACCELERATION']
        acc = self._clamp('acceleration', motion.acceleration_steps_s2, acc_reg.min, acc_reg.max,
                          'ACCELERATION')
        dec = self._clamp('deceleration', motion.deceleration_steps_s2, acc_reg.min,
                          acc_reg.max, 'DECELERATION')
        speed = self._clamp('velocity', velocity, rm.MIN_SPEED_PPS, self._max_speed(),
                            speed_reg)
        if (acc, dec) != (md['ACCELERATION'], md['DECELERATION']):
            self.rtu.write_registers(self.node_id, acc_reg.address, [acc, dec])   # one FC16
            md['ACCELERATION'], md['DECELERATION'] = acc, dec
        if speed != md[speed_reg]:
            self._write(speed_reg, speed)
            md[speed_reg] = speed
            return True
        return False

    def move_to(self, target_steps: int, motion: Motion) -> None:
        self._require_enabled('move_to')
        lo, hi = self.limits
        if not lo <= target_steps <= hi:
            raise DriveError(f'move_to: target {target_steps} pulses is outside the software '
                             f'limits {lo}..{hi} (Preset [0x16-0x17] -/+ Negative/Positive '
                             'delta); the RD4 would raise Target not valid')
        self._profile(motion, 'WORK_SPEED', motion.velocity_steps_s)
        self._write('TARGET_POSITION', int(target_steps))
        base = self._base(True)
        if (self.cw or 0) & (rm.CW_START | rm.CW_JOG) or self._stop_pending:
            self._write_cw(base)          # a clean 0 -> 1 of Start (spec §10 item 4)
        self._write_cw(base | rm.CW_START)
        self._stop_pending = False

    def set_velocity(self, velocity_steps_s: float, motion: Motion) -> None:
        self._require_enabled('set_velocity')
        cw = self.cw or 0
        if abs(velocity_steps_s) < 0.5:
            if cw & rm.CW_JOG:
                self._write_cw(cw & ~rm.CW_JOG)      # jog released: decelerates (§8.1.1 bit 0)
            return
        direction = rm.CW_JOG_PLUS if velocity_steps_s > 0 else rm.CW_JOG_MINUS
        speed_changed = self._profile(motion, 'JOG_SPEED', velocity_steps_s)
        jogging = cw & rm.CW_JOG == direction and not self._stop_pending
        if jogging and not speed_changed:
            return
        base = self._base(True)
        if jogging:
            # Whether a new Jog speed acts on a held jog is not stated: re-issue the jog.
            self._write_cw(base)
        self._write_cw(base | direction)
        self._stop_pending = False

    def stop(self, quick: bool = False) -> None:
        cw = self.cw or 0
        commands = rm.CW_JOG | rm.CW_START
        if quick:
            # §8.1.1 bit 7: immediate halt; latches the Emergency alarm (enable resets it).
            self._write_cw(cw & ~(commands | rm.CW_EMERGENCY))
            self._stop_pending = False
            return
        if cw & rm.CW_START or (self._moving and cw & rm.CW_STOP):
            # §8.1.1 bit 2: Stop low decelerates with Deceleration [0x07]; back high at rest.
            self._write_cw(cw & ~(commands | rm.CW_STOP))
            self._stop_pending = bool(cw & rm.CW_STOP)
        elif cw & commands:
            self._write_cw(cw & ~commands)

    def start_homing(self, homing: Homing) -> str:
        if homing.method != HOMING_METHOD_PRESET:
            raise DriveError(f'homing.method {homing.method}: the RD4 has no homing run; only '
                             f'{HOMING_METHOD_PRESET} (preset at the current position)')
        if self._moving:
            raise DriveError('home: the axis is moving; stop it first (the preset re-references '
                             'the position the axis has at that moment)')
        preset = int(homing.offset_steps)
        lo, hi = rm.PRESET_RANGE
        if not lo <= preset <= hi:
            raise DriveError(f'home: homing.offset = {preset} pulses is outside Preset '
                             f'[0x16-0x17] range {lo}..{hi}')
        self._homing = HomingState.RUNNING
        cw = self.cw or 0
        self._write('PRESET', preset)
        # Write and edge: right whether the firmware applies Preset on the write (§8.1.1
        # Preset) or on the rising edge of Perform counting preset (§8.1.1 bit 11).
        if cw & rm.CW_PERFORM_COUNTING_PRESET:
            self._write_cw(cw & ~rm.CW_PERFORM_COUNTING_PRESET)
        self._write_cw(cw | rm.CW_PERFORM_COUNTING_PRESET)
        self._write_cw(cw & ~rm.CW_PERFORM_COUNTING_PRESET)
        self._machine_data()['PRESET'] = preset
        position = rm.join32(self._read_input(IR['CURRENT_POSITION'].address, 2), signed=True)
        if position != preset:
            self._homing = HomingState.ERROR
            raise DriveError(f'home: after the preset Current position [0x02-0x03] reads '
                             f'{position}, expected {preset}')
        self._homing = HomingState.ATTAINED
        lo, hi = self.limits
        return (f'RD4 has no homing run: preset used, position := {preset} pulses (Preset '
                f'[0x16-0x17] + Perform counting preset, Control Word bit 11); software limits '
                f'now {lo}..{hi}; call save_params to keep it after power-off')

    # ---------------------------------------------------------------------- maintenance
    def fault_reset(self) -> str:
        alarms = self._read_input(0x00, 1)[0]
        self._alarms = alarms
        if not alarms:
            return ''
        # Emergency high (§5.3 order), Stop low and no commands: nothing restarts by itself
        # after the reset, whether Start and Jog act on edges or levels.
        base = self._base(False)
        self._write_cw(base)
        self._write_cw(base | rm.CW_ALARM_RESET)
        self._write_cw(base)
        self._stop_pending = False
        alarms = self._read_input(0x00, 1)[0]
        self._alarms = alarms
        if not alarms:
            return ''
        wrong = self._wrong_parameters() if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID else None
        text = rm.describe_alarms(alarms, wrong)
        if alarms & rm.NOT_RESETTABLE:
            text += ' (cannot be reset: internal error, §8.1.2)'
        return f'0x{alarms:04X} {text}'

    def save_params(self) -> str:
        alarms, sw = self._read_input(0x00, 2)
        if sw & rm.SW_AXIS_RUNNING:
            raise DriveError('save_params: the axis is moving; save at standstill')
        if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID:
            wrong = self._wrong_parameters()
            raise DriveError('save_params: Machine data not valid (wrong parameters: '
                             + ', '.join(rm.wrong_parameter_titles(wrong))
                             + '); set valid values first, saving would store the wrong ones')
        first, last = rm.MACHINE_DATA
        before = self._read_holding(first, last - first + 1)
        cw = (self.cw or 0) & ~rm.CW_SAVE_PARAMETERS
        if self.cw != cw:
            self._write_cw(cw)
        self._write_cw(cw | rm.CW_SAVE_PARAMETERS)       # §8.1.1 bit 9: rising edge
        echo = self._read_holding(HR['CONTROL_WORD'].address, 1)[0]
        self._write_cw(cw)
        if echo != cw | rm.CW_SAVE_PARAMETERS:
            raise DriveError(f'save_params: Control Word reads back 0x{echo:04X}, written '
                             f'0x{cw | rm.CW_SAVE_PARAMETERS:04X}')
        after = self._read_holding(first, last - first + 1)
        alarms = self._read_input(0x00, 1)[0]
        if alarms & rm.ALARM_FLASH_MEMORY_ERROR:
            raise DriveError('save_params: Flash memory error after the save (alarm bit 1)')
        if after != before:
            changed = [f'0x{a:02X}' for a, (x, y) in enumerate(zip(before, after)) if x != y]
            raise DriveError(f'save_params: machine data changed during the save at '
                             f'{", ".join(changed)}')
        md = self._machine_data(after)
        return (f"Save parameters (Control Word bit 9) edge read back; machine data 0x00-0x19 "
                f"read back unchanged (Distance per revolution {md['DISTANCE_PER_REVOLUTION']}, "
                f"Preset {md['PRESET']}, Work speed {md['WORK_SPEED']} PPS), no Flash memory "
                'error; the RD4 reports no save completion beyond that')

    def _raw_register(self, address: str, data_type: str, write: bool) -> tuple[str, int, int]:
        """(table, wire address, words) from 'hr:0x2A', 'ir:2', '0x2A' or 'CONTROL_WORD'."""
        text = str(address).strip()
        table = rm.HOLDING
        for prefix, name in (('hr:', rm.HOLDING), ('holding:', rm.HOLDING), ('ir:', rm.INPUT),
                             ('input:', rm.INPUT)):
            if text.lower().startswith(prefix):
                table, text = name, text[len(prefix):].strip()
                break
        dtype = register_type(data_type).name
        if dtype not in _RAW_TYPES:
            raise DriveError(f'data type {dtype} not supported by the RD4 (allowed: '
                             f'{", ".join(_RAW_TYPES)})')
        words = 2 if dtype.endswith('32') else 1
        reg = rm.find_register(text)
        if reg is not None:
            table, number = reg.table, reg.address
        else:
            try:
                number = int(text, 0)
            except ValueError:
                raise DriveError(f'register {address!r}: not a number or an RD4 register name '
                                 "(e.g. '0x2A', 'hr:0x2A', 'ir:0x02', 'CONTROL_WORD')") from None
        registers = rm.HOLDING_REGISTERS if table == rm.HOLDING else rm.INPUT_REGISTERS
        by_address = {r.address: r for r in registers}
        second = {r.address + 1: r for r in by_address.values() if r.words == 2}
        end = rm.HOLDING_END if table == rm.HOLDING else rm.INPUT_END
        if not 0 <= number <= end - words + 1:
            raise DriveError(f'{table} register 0x{number:02X} ({dtype}) is outside the RD4 map '
                             f'(0x00-0x{end:02X}, §8.1)')
        if number in second:
            raise DriveError(f'0x{number:02X} is the low word of {second[number]}; use '
                             f'0x{second[number].address:02X} with {second[number].dtype}')
        reg = by_address.get(number)
        if reg is not None and reg.words != words:
            raise DriveError(f'{reg} is {reg.dtype}: data type {dtype} does not match')
        if write:
            if table == rm.INPUT:
                raise DriveError(f'input register 0x{number:02X} is read-only (FC04 only)')
            if reg is not None and not reg.writable:
                raise DriveError(f'{reg} is read-only (§8.1.1)')
        return table, number, words

    def read_register(self, address: str, data_type: str) -> int:
        table, number, words = self._raw_register(address, data_type, write=False)
        read = self._read_holding if table == rm.HOLDING else self._read_input
        values = read(number, words)
        signed = data_type.lower().startswith('i')
        if words == 2:
            return rm.join32(values, signed)
        return values[0] - 0x10000 if signed and values[0] & 0x8000 else values[0]

    def write_register(self, address: str, data_type: str, value: int) -> None:
        _table, number, words = self._raw_register(address, data_type, write=True)
        value = register_type(data_type).check(int(value))
        if words == 2:
            self.rtu.write_registers(self.node_id, number, rm.split32(value))
        else:
            self.rtu.write_register(self.node_id, number, value)
        if number == HR['CONTROL_WORD'].address:
            self.cw = value & 0xFFFF
        if number <= rm.MACHINE_DATA[1]:
            self._md_stale = True       # speeds, ramps, limits re-read at the next use


# ---------------------------------------------------------------------- vendor description
BAUD_RATES = (9600, 19200)            # §4.4.2 dip-switch table
PARAMS = (
    ParamSpec('port', '/dev/ttyUSB0', 'serial port of the RS-485 line (a device path or a '
              'pyserial URL); the simulator gives a symlink to its pty', scope='bus'),
    ParamSpec('baudrate', 9600, 'baud rate, as the dip-switch of every unit on the line: 9600 '
              'or 19200 (§4.4.2; factory 9600)', scope='bus', min_value=9600, max_value=19200),
    ParamSpec('parity', 'E', 'parity as the dip-switch: E (factory), O or N; a pty accepts N '
              'only', scope='bus', choices=('N', 'E', 'O')),
    ParamSpec('stopbits', 0, 'stop bits: 0 = the RD4 format (§7.3.1: 11-bit characters, 1 stop '
              'bit with parity, 2 without)', scope='bus', min_value=0, max_value=2),
    ParamSpec('retries', 1, 'resends after a timeout, a CRC error or a reply that does not '
              'match; then the link counts as lost', scope='bus', min_value=0, max_value=5),
    ParamSpec('node_id', 1, 'node ID on the dip-switch (1..247, §4.4.1)', min_value=1,
              max_value=247),
    ParamSpec('watchdog', True, 'set Watch dog enable (Control Word bit 8) while enabled: the '
              'unit stops with an alarm when no frame reaches it for 1 s (§8.1.1)'),
    ParamSpec('hold_torque', True, 'set Axis torque (Control Word bit 12) while enabled: PWM '
              'stays on in position'),
    ParamSpec('velocity_source', 'register', "joint velocity from 'register' (Current velocity "
              "[0x04], refreshed once per second, §8.1.2; 0 when Axis running = 0) or "
              "'position' (Current position differentiated between polls)",
              choices=('register', 'position')),
)


def make_bus(params: Mapping[str, Any]) -> ModbusRtuBus:
    port = str(params.get('port', ''))
    if not port:
        raise ValueError("port: '' (allowed: a serial device such as /dev/ttyUSB0, or a pyserial "
                         'URL)')
    baud = int(params.get('baudrate', 9600))
    if baud not in BAUD_RATES:
        raise ValueError(f'baudrate: {baud} is not an RD4 baud rate (allowed: 9600, 19200; '
                         '§4.4.2)')
    parity = str(params.get('parity', 'E')).upper()
    if parity not in ('N', 'E', 'O'):
        raise ValueError(f'parity: {parity!r} (allowed: N, E, O)')
    stopbits = int(params.get('stopbits', 0))
    need = 2 if parity == 'N' else 1
    if stopbits not in (0, need):
        raise ValueError(f'stopbits: {stopbits} with parity {parity} is not the RD4 format '
                         f'(allowed: 0 = auto or {need}; §7.3.1 11-bit characters, '
                         '"the parity bit is replaced by a stop bit")')
    return ModbusRtuBus(port, baud, parity, stopbits or need,
                        timeout_s=float(params.get('timeout_s', 0.5)),
                        retries=int(params.get('retries', 1)))


def make_drive(bus: Bus, name: str, params: Mapping[str, Any]) -> Rd4Drive:
    prefix = f'drives.{name}.'
    method = params.get('homing.method', HOMING_METHOD_PRESET)
    if method != HOMING_METHOD_PRESET:
        raise ValueError(f'{prefix}homing.method: {method} is not possible on the RD4 (allowed: '
                         f'{HOMING_METHOD_PRESET} = preset at the current position; the RD4 has '
                         'no homing run)')
    node_id = params.get('node_id', 1)
    if not isinstance(node_id, int) or not 1 <= node_id <= 247:
        raise ValueError(f'{prefix}node_id: {node_id!r} (allowed: 1..247, §4.4.1)')
    rate = float(params.get('publish_rate_hz', 50.0))
    if params.get('watchdog', True) and rate < MIN_WATCHDOG_POLL_HZ:
        raise ValueError(f'{prefix}watchdog: true needs publish_rate_hz >= '
                         f'{MIN_WATCHDOG_POLL_HZ:g} to keep the 1 s watchdog fed (now {rate:g})')
    return Rd4Drive(bus, name, params)


VENDOR = Vendor(
    name='Lika RD4',
    params=PARAMS,
    make_bus=make_bus,
    make_drive=make_drive,
    drive_defaults={'steps_per_rev': 1024.0, 'homing.method': HOMING_METHOD_PRESET},
)
