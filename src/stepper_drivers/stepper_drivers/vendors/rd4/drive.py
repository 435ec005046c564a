"""The Lika RD4 drive class: the drive contract's operations on an `Rd4Unit`. No rclpy.

Every operation that takes more than one transaction is step-wise (contract/drive.py): it
yields 0.0 between transactions, so on a 19200-baud line a command waits behind one transaction
of another unit's poll, never behind a whole operation. stop() and disable() are one
transaction each.
"""

from __future__ import annotations

import math
import time

from ...contract.capabilities import Retargeting
from ...contract.drive import (
    DriveError,
    DriveState,
    Homing,
    HomingState,
    Motion,
    Operation,
    State,
)
from ...protocol.modbus_rtu import BITS_PER_CHAR, frame_time_s
from . import regmap as rm
from .regmap import HR, IR
from .settings import HOMING_METHOD_PRESET
from .unit import STEP_S, Rd4Unit

# A move_to on the line (move_time_s): FC04 Alarms/Status check, Work speed, Target position and
# Start (Acceleration/Deceleration and a Control Word 0 only when they change); about 22
# characters a request and its answer, each after t3.5 of silence (§7.3.1).
MOVE_TRANSACTIONS = 4
MOVE_CHARS_PER_TRANSACTION = 22


class Rd4Drive(Rd4Unit, Retargeting):
    """One RD4 unit on a Modbus RTU line (node ID = parameter `node_id`).

    Retargeting: §8.1.1 "Position override function", a new Target position with a Start while
    the unit is still reaching the last one."""

    min_velocity_steps_s = float(rm.MIN_SPEED_PPS)          # §6.4 Min. speed

    def move_time_s(self) -> float:
        char_s = BITS_PER_CHAR / self.rtu.baudrate
        return MOVE_TRANSACTIONS * (MOVE_CHARS_PER_TRANSACTION * char_s + 2 * self.rtu.t35_s)

    # ---------------------------------------------------------------------- state
    def read_state(self) -> Operation[DriveState]:
        first, count = rm.STATE_BLOCK
        epoch = self._epoch
        asked = time.monotonic()
        w = self._read_input(first, count)
        now = time.monotonic()
        # When the position was true: the unit took the block after the whole request reached it
        # and before its reply went out, so at least the reply's own transmission before the
        # reply arrived (FC04: 8 bytes asked, 5 + 2 a register answered; §7.3.1 11 bits a
        # character), and not before the request was out. A write later in the poll (below)
        # does not make the position younger.
        measured_at_s = min(now, max(asked + frame_time_s(8, self.rtu.baudrate),
                                     now - frame_time_s(5 + 2 * count, self.rtu.baudrate)))
        alarms, sw = w[0], w[1]
        self._examine(alarms, sw)
        self._state_seen = None if alarms else (now, epoch)
        position = rm.join32(w[2:4], signed=True)
        velocity_reg = rm.decode(IR['CURRENT_VELOCITY'], w[4:5])
        current_ma = rm.decode(IR['CURRENT_VALUE'], w[7:8])
        wrong = None
        if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID:
            yield STEP_S
            wrong = self._wrong_parameters()
        self._alarms = alarms
        running = bool(sw & rm.SW_AXIS_RUNNING)
        write = False
        if self._stop_low and not running:
            self._stop_low = False
            write = self._intent_enabled and not alarms     # standstill: moves allowed again
        elif (self._command == rm.CW_START and sw & rm.SW_TARGET_POSITION_REACHED
              and not running):
            self._command = 0                               # the move is done: Start to 0
            write = True
        if write:
            yield STEP_S
            self._write_cw(self._compose())
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
        mode = ('JOG' if self._command & rm.CW_JOG
                else 'POSITIONING' if self._command & rm.CW_START else '')
        return DriveState(
            state=state, enabled=enabled, moving=running,
            target_reached=bool(sw & rm.SW_TARGET_POSITION_REACHED),
            # A multiturn absolute encoder (§1 of the manual): referenced unless the unit
            # says the axis lost its synchronisation.
            homed=not alarms & rm.ALARM_AXIS_NOT_SYNCHRONIZED,
            homing=self._homing, fault=bool(fault_bits), fault_code=alarms if fault_bits else 0,
            fault_text=rm.describe_alarms(alarms, wrong) if fault_bits else '',
            alarms=tuple(names), mode=mode, status_word=sw, position_steps=position,
            velocity_steps_s=velocity, effort=current_ma / 1000.0, measured_at_s=measured_at_s)

    # ---------------------------------------------------------------------- power stage
    def enable(self) -> Operation[None]:
        self._epoch += 1
        epoch = self._epoch
        alarms, sw, *pos = self._read_input(0x00, 4)
        self._examine(alarms, sw)
        self._alarms = alarms
        if alarms & ~rm.ALARM_EMERGENCY:
            wrong = None
            if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID:
                yield STEP_S
                wrong = self._wrong_parameters()
            raise DriveError(f'enable: alarm 0x{alarms:04X}: {rm.describe_alarms(alarms, wrong)};'
                             ' call fault_reset first')
        yield from self._step(epoch, 'enable')
        # Nothing may move: Target position := Current position before Stop/Emergency go high
        # (and no Start is written here: only move_to starts, after its own target).
        self._write('TARGET_POSITION', rm.join32(pos, signed=True))
        yield from self._step(epoch, 'enable')
        self._intent_enabled = True
        self._command = 0
        self._stop_low = False
        self._write_cw(self._compose())
        if alarms & rm.ALARM_EMERGENCY:
            # §5.3: after power-up (or a quick stop) first Emergency high, then Reset alarm.
            yield from self._step(epoch, 'enable')
            self._write_cw(self._compose(rm.CW_ALARM_RESET))
            yield from self._step(epoch, 'enable')
            self._write_cw(self._compose())
            yield from self._step(epoch, 'enable')
            alarms = self._read_input(IR['ALARMS'].address, 1)[0]
            self._examine(alarms)
            self._alarms = alarms
            if alarms:
                wrong = None
                if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID:
                    yield STEP_S
                    wrong = self._wrong_parameters()
                raise DriveError(f'enable: alarms remain after Alarm reset: 0x{alarms:04X} '
                                 f'{rm.describe_alarms(alarms, wrong)}')

    def disable(self) -> None:
        """Stop low (a running move decelerates), Emergency high so no alarm latches, watchdog
        and hold torque off: the unit stays quiet when the master goes away."""
        self._reset_intent()
        self._write_cw(self._compose())

    # ---------------------------------------------------------------------- motion
    def _in_range(self, reg: rm.Register, value: float, what: str, hi: int | None = None,
                  why: str = '') -> int:
        """The register value for `value`, or DriveError naming the register and its range
        (§8.1.1): nothing out of range is ever written, nothing is clamped."""
        hi = reg.max if hi is None else hi
        n = round(abs(value)) if math.isfinite(value) else None
        if n is None or not reg.min <= n <= hi:
            raise DriveError(f'{what} {abs(value):g} {reg.unit} is outside {reg.title} range '
                             f'{reg.min}..{hi} {reg.unit}{why}; nothing was written')
        return n

    def _profile_values(self, motion: Motion, speed_reg: str,
                        velocity: float) -> tuple[int, int, int]:
        acc = self._in_range(HR['ACCELERATION'], motion.acceleration_steps_s2, 'acceleration')
        dec = self._in_range(HR['DECELERATION'], motion.deceleration_steps_s2, 'deceleration')
        dpr = self.md['DISTANCE_PER_REVOLUTION']
        speed = self._in_range(HR[speed_reg], velocity, 'velocity', self._max_speed(),
                               f' (Max. speed {self.model.max_speed_pps} x Distance per '
                               f'revolution {dpr} / 1024, §6.4)')
        return acc, dec, speed

    def _profile_changed(self, acc: int, dec: int, speed_reg: str, speed: int) -> bool:
        md = self.md
        return (acc, dec, speed) != (md['ACCELERATION'], md['DECELERATION'], md[speed_reg])

    def _write_profile(self, acc: int, dec: int, speed_reg: str, speed: int, epoch: int,
                       what: str) -> Operation[bool]:
        """Acceleration/Deceleration [0x06-0x07] and the speed register where they differ from
        the unit's; True when the speed register changed."""
        md = self.md
        if (acc, dec) != (md['ACCELERATION'], md['DECELERATION']):
            self.rtu.write_registers(self.node_id, HR['ACCELERATION'].address, [acc, dec])
            md['ACCELERATION'], md['DECELERATION'] = acc, dec
            yield from self._step(epoch, what)
        if speed != md[speed_reg]:
            self._write(speed_reg, speed)
            md[speed_reg] = speed
            yield from self._step(epoch, what)
            return True
        return False

    def _fresh_machine_data(self) -> Operation[None]:
        if self._md_stale:             # after Load default parameters through a raw write
            self._set_machine_data(self._reread_machine_data())
            yield STEP_S

    def move_to(self, target_steps: int, motion: Motion) -> Operation[None]:
        self._require_intent('move_to')
        yield from self._fresh_machine_data()
        target = int(target_steps)
        lo, hi = self.limits
        if not lo <= target <= hi:
            raise DriveError(f'move_to: target {target} pulses is outside the software limits '
                             f'{lo}..{hi} for Target position [0x2B-0x2C] (Preset [0x16-0x17] '
                             '-/+ Negative/Positive delta, §8.1.1); the RD4 would raise Target '
                             'not valid; nothing was written')
        acc, dec, speed = self._profile_values(motion, 'WORK_SPEED', motion.velocity_steps_s)
        epoch = self._epoch
        yield from self._check_enabled('move_to', epoch)
        yield from self._write_profile(acc, dec, 'WORK_SPEED', speed, epoch, 'move_to')
        self._write('TARGET_POSITION', target)
        yield from self._step(epoch, 'move_to')
        if self._command or self._stop_low or not self._edge_ready(rm.CW_START):
            self._command = 0
            self._stop_low = False
            self._write_cw(self._compose())       # a clean 0 -> 1 of Start (spec §10 item 4)
            yield from self._step(epoch, 'move_to')
        self._command = rm.CW_START
        self._write_cw(self._compose())

    def set_velocity(self, velocity_steps_s: float, motion: Motion) -> Operation[None]:
        if math.isfinite(velocity_steps_s) and abs(velocity_steps_s) < 0.5:
            if self._command & rm.CW_JOG:
                self._command = 0
                self._write_cw(self._compose())   # jog released: decelerates (§8.1.1 bit 0)
            return
        self._require_intent('set_velocity')
        yield from self._fresh_machine_data()
        direction = rm.CW_JOG_PLUS if velocity_steps_s > 0 else rm.CW_JOG_MINUS
        acc, dec, speed = self._profile_values(motion, 'JOG_SPEED', velocity_steps_s)
        jogging = self._command == direction and not self._stop_low
        if jogging and not self._profile_changed(acc, dec, 'JOG_SPEED', speed):
            return                                # nothing new to say
        epoch = self._epoch
        yield from self._check_enabled('set_velocity', epoch)
        speed_changed = yield from self._write_profile(acc, dec, 'JOG_SPEED', speed, epoch,
                                                       'set_velocity')
        if jogging and not speed_changed:
            return
        if jogging or not self._edge_ready(direction):
            # Whether a new Jog speed acts on a held jog is not stated: re-issue the jog.
            self._command = 0
            self._write_cw(self._compose())
            yield from self._step(epoch, 'set_velocity')
        self._command = direction
        self._stop_low = False
        self._write_cw(self._compose())

    def stop(self, quick: bool = False) -> None:
        """One Control Word write, whatever the driver believes the unit does (a unit still
        running a command of an earlier session stops too)."""
        self._epoch += 1
        self._command = 0
        if quick:
            # §8.1.1 bit 7: immediate halt; latches the Emergency alarm (enable resets it).
            cw = self._compose() & ~rm.CW_EMERGENCY
            self._reset_intent()
            self._write_cw(cw)
            return
        # §8.1.1 bit 2: Stop low decelerates with Deceleration [0x07]; back high at rest.
        self._stop_low = self._intent_enabled
        self._write_cw(self._compose())

    def start_homing(self, homing: Homing) -> Operation[str]:
        if homing.method != HOMING_METHOD_PRESET:
            raise DriveError(f'homing.method {homing.method}: the RD4 has no homing run; only '
                             f'{HOMING_METHOD_PRESET} (preset at the current position)')
        preset = int(homing.offset_steps)
        lo, hi = rm.PRESET_RANGE
        if not lo <= preset <= hi:
            raise DriveError(f'home: homing.offset = {preset} pulses is outside Preset '
                             f'[0x16-0x17] range {lo}..{hi}; nothing was written')
        epoch = self._epoch
        sw = self._check_enabled_on_wire('home')
        if sw & rm.SW_AXIS_RUNNING:
            raise DriveError('home: the axis is moving; stop it first (the preset re-references '
                             'the position the axis has at that moment)')
        self._homing = HomingState.RUNNING
        done = False
        try:
            yield from self._step(epoch, 'home')
            self._write('PRESET', preset)
            self.md['PRESET'] = preset
            yield from self._step(epoch, 'home')
            # Write and edge: right whether the firmware applies Preset on the write (§8.1.1
            # Preset) or on the rising edge of Perform counting preset (§8.1.1 bit 11).
            if not self._edge_ready(rm.CW_PERFORM_COUNTING_PRESET):
                self._write_cw(self._compose())
                yield from self._step(epoch, 'home')
            self._write_cw(self._compose(rm.CW_PERFORM_COUNTING_PRESET))
            yield from self._step(epoch, 'home')
            self._write_cw(self._compose())
            yield from self._step(epoch, 'home')
            position = rm.join32(self._read_input(IR['CURRENT_POSITION'].address, 2),
                                 signed=True)
            if position != preset:
                raise DriveError(f'home: after the preset Current position [0x02-0x03] reads '
                                 f'{position}, expected {preset}')
            done = True
        finally:
            # No write here (the owner may have closed us): only the driver's own record.
            self._homing = HomingState.ATTAINED if done else HomingState.ERROR
        lo, hi = self.limits
        return (f'RD4 has no homing run: preset used, position := {preset} pulses (Preset '
                f'[0x16-0x17] + Perform counting preset, Control Word bit 11); software limits '
                f'now {lo}..{hi}; call save_params to keep it after power-off')

    # ---------------------------------------------------------------------- maintenance
    def fault_reset(self) -> Operation[str]:
        alarms = self._read_input(IR['ALARMS'].address, 1)[0]
        self._examine(alarms)
        self._alarms = alarms
        if not alarms:
            return ''
        # Emergency high (§5.3 order), Stop low and no commands: nothing restarts by itself
        # after the reset, whether Start and Jog act on edges or levels.
        self._reset_intent()
        yield STEP_S
        self._write_cw(self._compose())
        yield STEP_S
        self._write_cw(self._compose(rm.CW_ALARM_RESET))
        yield STEP_S
        self._write_cw(self._compose())
        yield STEP_S
        alarms = self._read_input(IR['ALARMS'].address, 1)[0]
        self._examine(alarms)
        self._alarms = alarms
        if not alarms:
            return ''
        wrong = None
        if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID:
            yield STEP_S
            wrong = self._wrong_parameters()
        text = rm.describe_alarms(alarms, wrong)
        if alarms & rm.NOT_RESETTABLE:
            text += ' (cannot be reset: internal error, §8.1.2)'
        return f'0x{alarms:04X} {text}'

    def save_params(self) -> Operation[str]:
        alarms, sw = self._read_input(0x00, 2)
        self._examine(alarms, sw)
        if sw & rm.SW_AXIS_RUNNING:
            raise DriveError('save_params: the axis is moving; save at standstill')
        if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID:
            yield STEP_S
            wrong = self._wrong_parameters()
            raise DriveError('save_params: Machine data not valid (wrong parameters: '
                             + ', '.join(rm.wrong_parameter_titles(wrong))
                             + '); set valid values first, saving would store the wrong ones')
        yield STEP_S
        before = self._reread_machine_data()
        yield STEP_S
        if not self._edge_ready(rm.CW_SAVE_PARAMETERS):
            self._write_cw(self._compose())
            yield STEP_S
        self._write_cw(self._compose(rm.CW_SAVE_PARAMETERS))     # §8.1.1 bit 9: rising edge
        yield STEP_S
        expected = self.cw             # a stop may have run between the steps of a save
        echo = self._read_holding(HR['CONTROL_WORD'].address, 1)[0]
        yield STEP_S
        self._write_cw(self._compose())
        if echo != expected:
            raise DriveError(f'save_params: Control Word [0x2A] reads back 0x{echo:04X}, '
                             f'written 0x{expected:04X}')
        yield STEP_S
        after = self._reread_machine_data()
        yield STEP_S
        alarms = self._read_input(IR['ALARMS'].address, 1)[0]
        self._examine(alarms)
        if alarms & rm.ALARM_FLASH_MEMORY_ERROR:
            raise DriveError('save_params: Flash memory error after the save (alarm bit 1)')
        if after != before:
            changed = [f'0x{a:02X}' for a, (x, y) in enumerate(zip(before, after)) if x != y]
            raise DriveError(f'save_params: machine data changed during the save at '
                             f'{", ".join(changed)}')
        self._set_machine_data(after)
        md = self.md
        return (f"Save parameters (Control Word bit 9) edge read back; machine data 0x00-0x19 "
                f"read back unchanged (Distance per revolution {md['DISTANCE_PER_REVOLUTION']}, "
                f"Preset {md['PRESET']}, Work speed {md['WORK_SPEED']} PPS), no Flash memory "
                'error; the RD4 reports no save completion beyond that')
