"""Lika RD4 ROTADRIVE over Modbus RTU (RS-485): the drive class and the vendor description.

Several RD4 units share one serial line (`ModbusRtuBus`), each addressed by its dip-switch node
ID. Register numbers and bit meanings come from the manual `lika_rd4_modbus_rtu.txt` (§8.1.1
machine data and Control Word [0x2A], §8.1.2 input registers); the map is in `rd4_map.py`.
No rclpy.

Every operation that takes more than one transaction is step-wise (drive.py): it yields 0.0
between transactions, so on a 19200-baud line a command waits behind one transaction of another
unit's poll, never behind a whole operation. stop() and disable() are one transaction each.

Control Words are composed from the driver's intent (enabled or not, the commanded Start or Jog,
Stop held low after a stop, the outputs a raw write set), never from a Control Word read from
the unit (a reply with a valid CRC but another device's content, written back, would start a
jog). Alarms and Status word are examined before anything is based on them: bits the
manual marks "Not used", or an Alarm status bit that contradicts the Alarms register, make the
reply implausible (LinkError, the node reconnects; connect() then checks the identity).

How the contract maps to the RD4 (docs/rd4.md has the full table):
- connect: identity (HW Version: RD4 with Modbus; Dip-switch node ID = the address; Dip-switch
  baud rate = the line's; Gear ratio 32 or 48; machine data in range unless the unit lists them
  as wrong) or IdentityError; writes nothing.
- state: one FC04 of 0x00-0x07 per poll (Alarms, Status word, Current position, Current velocity,
  Position following error, Current value); the Wrong parameters list only when its alarm is on.
- enable: Target position := Current position, Control Word with Emergency and Stop high (plus
  Watch dog enable and Axis torque as configured), and an Alarm reset edge to leave the power-up
  Emergency (§5.3). disable: Stop low, Emergency high, watchdog and hold torque off.
- move, jog, preset: refused unless enabled, checked on the wire (Alarms register read first);
  values outside the registers' ranges are refused before anything is written.
- move: Target position (FC16) + a clean 0 -> 1 edge of Start; Start is cleared once the target
  is reached, so the move is right whether the firmware starts on the edge or the level.
- velocity: Jog + / Jog - at Jog speed [0x0C]; a new speed re-issues the jog (clear, then set).
- stop: Stop (bit 2) low, restored at standstill; quick stop: Emergency (bit 7) low.
- home: the RD4 has no homing run: Preset [0x16-0x17] := homing.offset and a rising edge of
  Perform counting preset (bit 11), so it is right whether the register write or the edge applies.

One class: every Rd4Drive operation composes its Control Word from the same intent (enabled,
Start/Jog, Stop low, outputs, epoch) and relies on the same examined machine data.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Callable, Mapping

from ...contract import param_rules
from ...contract.drive import (
    Bus,
    Drive,
    DriveError,
    DriveState,
    Homing,
    HomingState,
    IdentityError,
    LinkError,
    Motion,
    Operation,
    ParamSpec,
    State,
    Vendor,
    register_type,
)
from ...protocol import serial_port
from ...protocol.modbus import RawRegisterRules, parse_raw_register
from ...protocol.modbus_rtu import (
    BITS_PER_CHAR,
    ILLEGAL_DATA_ADDRESS,
    ILLEGAL_FUNCTION,
    ModbusExceptionError,
    ModbusRtuBus,
    frame_time_s,
)
from . import regmap as rm
from . import scan as rd4_scan
from .regmap import HR, IR

logger = logging.getLogger(__name__)

HOMING_METHOD_PRESET = 35      # CiA 402 method 35 "current position is home": what a preset is
MIN_WATCHDOG_POLL_HZ = 5.0     # spec §9B: poll period <= 200 ms keeps the 1 s watchdog fed
STEP_S = 0.0                   # between the transactions of one operation (drive.py contract)
# A move_to on the line (move_time_s): FC04 Alarms/Status check, Work speed, Target position and
# Start (Acceleration/Deceleration and a Control Word 0 only when they change); about 22
# characters a request and its answer, each after t3.5 of silence (§7.3.1).
MOVE_TRANSACTIONS = 4
MOVE_CHARS_PER_TRANSACTION = 22
_RAW_TYPES = ('u16', 'i16', 'u32', 'i32')
# read_register/write_register: 'hr:0x2A', 'ir:2', '0x2A' (holding) or a register name; an
# address of §8.1 where no register starts (0x1A-0x28) is read and written as it is.
_RAW_REGISTERS = RawRegisterRules(
    device='RD4', registers=rm.HOLDING_REGISTERS + rm.INPUT_REGISTERS, dtypes=_RAW_TYPES,
    not_a_number="register {address!r}: not a number or an RD4 register name (e.g. '0x2A', "
                 "'hr:0x2A', 'ir:0x02', 'CONTROL_WORD')",
    outside='{table} register 0x{number:02X} ({dtype}) is outside the RD4 map '
            '(0x00-0x{end:02X}, §8.1)',
    second_word='0x{number:02X} is the low word of {owner}; use 0x{owner.address:02X} with '
                '{owner.dtype}',
    mismatch='{reg} is {reg.dtype}: data type {dtype} does not match',
    read_only='{reg} is read-only (§8.1.1)',
    input_read_only='input register 0x{number:02X} is read-only (FC04 only)',
    ends={rm.HOLDING: rm.HOLDING_END, rm.INPUT: rm.INPUT_END},
    prefixes=(('hr:', rm.HOLDING), ('holding:', rm.HOLDING), ('ir:', rm.INPUT),
              ('input:', rm.INPUT)),
    find=rm.find_register, type_first=True)


class Rd4Drive(Drive):
    """One RD4 unit on a Modbus RTU line (node ID = parameter `node_id`)."""

    # §8.1.1 "Position override function": a new Target position with a Start while the unit
    # is still reaching the last one
    retargets_on_the_way = True

    def __init__(self, bus: Bus, name: str, params: Mapping[str, Any]):
        params = VENDOR.with_defaults(params)
        super().__init__(bus, name, params)
        if not isinstance(bus, ModbusRtuBus):
            raise TypeError(f'{name}: the RD4 needs a ModbusRtuBus, got {type(bus).__name__}')
        self.rtu: ModbusRtuBus = bus
        self.node_id = int(params['node_id'])
        self.address = self.node_id
        self.watchdog = bool(params['watchdog'])
        self.hold_torque = bool(params['hold_torque'])
        self.velocity_source = str(params['velocity_source'])
        self.steps_per_rev = float(params['steps_per_rev'])
        self.cw: int | None = None            # the Control Word [0x2A] this driver last wrote
        # The intent every Control Word is composed from (never a value read from the unit).
        self._intent_enabled = False
        self._command = 0                     # CW_START, CW_JOG_PLUS or CW_JOG_MINUS
        self._stop_low = False                # Stop (bit 2) low until the axis stands still
        self._outputs = 0                     # OUT 1-3 as a raw Control Word write set them
        self._epoch = 0                       # bumped by stop/disable/enable/fault_reset
        self._md_words: list[int] = []        # machine data 0x00-0x19 as read (examined)
        self.md: dict[str, int] = {}          # ... decoded by name
        self.model = rm.MODELS['T32']
        self._md_stale = True
        self._homing = HomingState.IDLE
        self._alarms = 0
        self._last_position: tuple[int, float] | None = None
        self._velocity = 0.0
        self._notes: set[str] = set()
        # (time, epoch) of the last poll that found no alarm (None: the last found one)
        self._state_seen: tuple[float, int] | None = None

    min_velocity_steps_s = float(rm.MIN_SPEED_PPS)          # §6.4 Min. speed

    def move_time_s(self) -> float:
        char_s = BITS_PER_CHAR / self.rtu.baudrate
        return MOVE_TRANSACTIONS * (MOVE_CHARS_PER_TRANSACTION * char_s + 2 * self.rtu.t35_s)

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
        # A lost reply is assumed to have reached the unit: the record comes first.
        self.cw = cw & 0xFFFF
        self.rtu.write_register(self.node_id, HR['CONTROL_WORD'].address, self.cw)

    def _note(self, text: str) -> None:
        """Log a notice once per distinct text (commands repeat at the command rate)."""
        if text not in self._notes:
            self._notes.add(text)
            logger.warning('%s: %s', self.name, text)

    def _step(self, epoch: int, what: str) -> Operation[None]:
        """Give the bus back between two transactions; refuse to go on when a stop, disable,
        enable or fault reset of this drive ran meanwhile (the owner normally closes us)."""
        yield STEP_S
        if epoch != self._epoch:
            raise DriveError(f'{what}: cut short by a stop, disable or enable of {self.name} '
                             'meanwhile; nothing more was written')

    # ---------------------------------------------------------------------- intent
    def _compose(self, edge: int = 0) -> int:
        """The Control Word of the driver's intent (§8.1.1) plus an edge bit being raised.

        Enabled: Emergency and Stop high (§9.3 Example 2, 0x0084), Watch dog enable and Axis
        torque as configured, the commanded Start or Jog; Stop low while a stop decelerates.
        Disabled: Emergency high only (no alarm latches; Stop low, so nothing moves)."""
        if not self._intent_enabled:
            return rm.CW_EMERGENCY | self._outputs | edge
        cw = (rm.CW_EMERGENCY | self._outputs | edge
              | (rm.CW_WATCH_DOG_ENABLE if self.watchdog else 0)
              | (rm.CW_AXIS_TORQUE if self.hold_torque else 0))
        return cw if self._stop_low else cw | rm.CW_STOP | self._command

    def _reset_intent(self) -> None:
        self._epoch += 1
        self._intent_enabled = False
        self._command = 0
        self._stop_low = False

    def _edge_ready(self, bit: int) -> bool:
        """True when the last Control Word written has `bit` low, so writing it high is a
        rising edge; unknown (nothing written yet) counts as high."""
        return self.cw is not None and not self.cw & bit

    def _enabled(self) -> bool:
        return self._intent_enabled and not self._alarms

    def _require_intent(self, what: str) -> None:
        if not self._intent_enabled:
            raise DriveError(f'{what}: {self.name} is not enabled; call enable first')

    def _check_enabled(self, what: str, epoch: int) -> Operation[None]:
        """The unit would move: known from the last poll while that is fresh (younger than
        state_fresh_s, no alarm, and no stop, disable, enable or fault reset since), so the
        motion's own frames go first; else one FC04 on the wire before them."""
        self._require_intent(what)
        seen = self._state_seen
        if seen is not None and seen[1] == self._epoch and \
                time.monotonic() - seen[0] <= self.state_fresh_s:
            return
        self._check_enabled_on_wire(what)
        yield from self._step(epoch, what)

    def _check_enabled_on_wire(self, what: str) -> int:
        """One FC04 of Alarms and Status word: any alarm (the latched Emergency of a power-up,
        a quick stop or the watchdog included) means the unit would not move. Returns the
        Status word."""
        self._require_intent(what)
        alarms, sw = self._read_input(0x00, 2)
        self._examine(alarms, sw)
        self._alarms = alarms
        if alarms:
            todo = ('call enable' if alarms == rm.ALARM_EMERGENCY
                    else 'call fault_reset, then enable')
            raise DriveError(f'{what}: {self.name} is not enabled: Alarms register [0x00] = '
                             f'0x{alarms:04X} ({", ".join(rm.alarm_names(alarms))}); {todo}')
        return sw

    # ---------------------------------------------------------------------- plausibility
    def _examine(self, alarms: int, sw: int | None = None) -> None:
        """Alarms [0x00] and Status word [0x01] as an RD4 can report them (§8.1.2), before
        anything is based on them; LinkError otherwise (the node reconnects, connect() checks
        the identity)."""
        problems = []
        if alarms & ~rm.ALARMS_DEFINED:
            problems.append(f'Alarms register [0x00] = 0x{alarms:04X} has bits '
                            f'0x{alarms & ~rm.ALARMS_DEFINED:04X} set that are "Not used"')
        if sw is not None:
            if sw & ~rm.STATUS_WORD_DEFINED:
                problems.append(f'Status word [0x01] = 0x{sw:04X} has bits '
                                f'0x{sw & ~rm.STATUS_WORD_DEFINED:04X} set that are "Not used"')
            if bool(sw & rm.SW_ALARM) != bool(alarms):
                problems.append(f'Status word [0x01] = 0x{sw:04X} says Alarm = '
                                f'{int(bool(sw & rm.SW_ALARM))} but Alarms register [0x00] = '
                                f'0x{alarms:04X}')
        if problems:
            raise LinkError(f'{self.name}: implausible reply from node {self.node_id}: '
                            + '; '.join(problems) + ' (§8.1.2); another device answers at this '
                            'address, or two units share it: nothing is based on it')

    def _needed(self, read: Callable[[int, int], list[int]], address: int, count: int,
                what: str) -> list[int]:
        """A read the driver cannot do without: exception ILLEGAL FUNCTION or ILLEGAL DATA
        ADDRESS means the device lacks the registers, so it is not an RD4 (IdentityError);
        another exception (busy, device failure) is the device's state of the moment."""
        try:
            return read(address, count)
        except ModbusExceptionError as e:
            if e.code not in (ILLEGAL_FUNCTION, ILLEGAL_DATA_ADDRESS):
                raise
            raise IdentityError(f'{self.name}: node {self.node_id} has no {what} ({e}): not an '
                                'RD4 (§8.1)') from None

    def _identity_problems(self, baud_reg: int, node_reg: int, hw_version: int) -> list[str]:
        problems = []
        model = (hw_version >> rm.HW_MODEL_SHIFT) & 0xF
        interface = (hw_version >> rm.HW_INTERFACE_SHIFT) & 0xF
        if (model != rm.HW_MODEL_RD4 or interface != rm.HW_INTERFACE_MODBUS
                or hw_version & rm.HW_NOT_USED):
            problems.append(f'HW Version [0x0F] reads {rm.describe_hw_version(hw_version)}, '
                            'expected model 0 = RD4, interface 0 = Modbus, bits 4-6 clear '
                            '(§8.1.2)')
        # §4.4.1: a switch setting above 247 makes the unit use 247.
        if node_reg != self.node_id and not (self.node_id == 247 and 247 < node_reg <= 0xFF):
            problems.append(f'Dip-switch node ID [0x0D] reads {node_reg}, expected {self.node_id}'
                            ' (the address it answers at, §4.4.1)')
        if baud_reg in rm.BAUD_SWITCH:
            reported: int | None = rm.BAUD_SWITCH[baud_reg][0]
        elif baud_reg in BAUD_RATES:                # the baud number itself (spec §10 #20)
            reported = baud_reg
        elif baud_reg <= 0xFF:
            reported = None        # a switch code the manual does not document (spec §10 #20)
            self._note(f'Dip-switch baud rate [0x0C] reads {baud_reg:02X}h, a switch code '
                       'the manual does not list (§4.4.2)')
        else:
            reported = None
            problems.append(f'Dip-switch baud rate [0x0C] reads {baud_reg} (0x{baud_reg:04X}), '
                            'neither a switch code 00h-05h nor 9600/19200 (§4.4.2)')
        if reported is not None and reported != self.rtu.baudrate:
            problems.append(f'Dip-switch baud rate [0x0C] reads '
                            f'{rm.describe_baud_register(baud_reg)}, but it answers at '
                            f'{self.rtu.baudrate} baud (§4.4.2)')
        return problems

    @staticmethod
    def _out_of_range(md: Mapping[str, int], model: rm.Model) -> list[rm.Register]:
        """Machine data with a Wrong parameters list bit outside its §8.1.1 range (speeds
        against the model's Max. speed; the DPR scaling of §6.4 is left to the unit)."""
        bad = []
        for reg in rm.HOLDING_REGISTERS:
            if reg.wp_bit is None or reg.name == 'GEAR_RATIO':
                continue
            hi = model.max_speed_pps if reg.name in ('JOG_SPEED', 'WORK_SPEED') else reg.max
            if not reg.min <= md[reg.name] <= hi:
                bad.append(reg)
        return bad

    @staticmethod
    def _decode_machine_data(words: list[int]) -> dict[str, int]:
        last = rm.MACHINE_DATA[1]
        return {r.name: rm.decode(r, words[r.address:r.address + r.words])
                for r in rm.HOLDING_REGISTERS if r.address <= last}

    def _set_machine_data(self, words: list[int]) -> None:
        """Cache machine data whose Gear ratio was examined (32 or 48)."""
        self._md_words = list(words)
        self.md = self._decode_machine_data(self._md_words)
        self.model = rm.MODEL_BY_GEAR_RATIO[self.md['GEAR_RATIO']]
        self._md_stale = False

    def _reread_machine_data(self) -> list[int]:
        """One FC03 of 0x00-0x19 after connect; the read-only Gear ratio must not change."""
        first, last = rm.MACHINE_DATA
        words = self._read_holding(first, last - first + 1)
        gear = words[HR['GEAR_RATIO'].address]
        if gear != self.model.gear_ratio:
            raise LinkError(f'{self.name}: implausible reply from node {self.node_id}: Gear ratio '
                            f'[0x18] reads {gear}, it read {self.model.gear_ratio} at connect '
                            '(read-only, §8.1.1)')
        return words

    @property
    def limits(self) -> tuple[int, int]:
        """SW limit switch -/+ = Preset -/+ Negative/Positive delta (§8.1.1)."""
        md = self.md
        return md['PRESET'] - md['NEGATIVE_DELTA'], md['PRESET'] + md['POSITIVE_DELTA']

    def _max_speed(self) -> int:
        return rm.max_speed_pps(self.model, max(1, self.md['DISTANCE_PER_REVOLUTION']))

    # ---------------------------------------------------------------------- life cycle
    def connect(self) -> Operation[dict[str, str]]:
        baud_reg, node_reg, sw_version, hw_version = self._needed(
            self._read_input, *rm.IDENTITY_BLOCK,
            'Dip-switch baud rate [0x0C] .. HW Version [0x0F] (FC04)')
        problems = self._identity_problems(baud_reg, node_reg, hw_version)
        if problems:
            raise IdentityError(f'{self.name}: node {self.node_id} is not the configured RD4: '
                                + '; '.join(problems))
        yield STEP_S
        first, last = rm.MACHINE_DATA
        words = self._needed(self._read_holding, first, last - first + 1,
                             'machine data [0x00-0x19] (FC03)')
        md = self._decode_machine_data(words)
        model = rm.MODEL_BY_GEAR_RATIO.get(md['GEAR_RATIO'])
        if model is None:
            raise IdentityError(f"{self.name}: node {self.node_id} is not an RD4: Gear ratio "
                                f"[0x18] reads {md['GEAR_RATIO']}, expected 32 (T32) or 48 "
                                '(T48), read-only (§8.1.1)')
        bad = self._out_of_range(md, model)
        if bad:
            # An RD4 takes an out-of-range value, raises Machine data not valid and lists the
            # parameter (§5.4, §8.1.2): one it does not list is not an RD4's.
            yield STEP_S
            alarms = self._read_input(IR['ALARMS'].address, 1)[0]
            wrong = 0
            if alarms & rm.ALARM_MACHINE_DATA_NOT_VALID:
                yield STEP_S
                wrong = self._wrong_parameters()
            unlisted = [r for r in bad if not wrong & (1 << r.wp_bit)]
            if unlisted:
                raise IdentityError(
                    f'{self.name}: node {self.node_id} is not the configured RD4: '
                    + '; '.join(f'{r.title} reads {md[r.name]}, outside {r.min}..'
                                f'{model.max_speed_pps if r.name.endswith("SPEED") else r.max}'
                                for r in unlisted)
                    + f' and Wrong parameters list [0x09-0x0A] = 0x{wrong:08X} does not list '
                    'it (§8.1.1, §8.1.2)')
        self._set_machine_data(words)
        yield STEP_S
        first, last = rm.COMMAND_BLOCK
        command = self._needed(self._read_holding, first, last - first + 1,
                               'Control Word [0x2A] / Target position [0x2B-0x2C] (FC03)')
        unit_cw = command[HR['CONTROL_WORD'].address - first]
        target = rm.join32(command[2:4], signed=True)
        if self.cw is not None and unit_cw != self.cw:
            # After a link loss: the unit no longer holds what this driver last wrote (power
            # cycle, another master). Nothing of the old intent is kept; enable starts afresh.
            self._note(f'Control Word [0x2A] reads 0x{unit_cw:04X}, this driver last wrote '
                       f'0x{self.cw:04X}: treated as not enabled')
            self._reset_intent()
            self.cw = None
        self._homing = HomingState.IDLE
        self._last_position = None
        if unit_cw & rm.CW_NOT_USED or command[0] & ~rm.EXTRA_COMMANDS_DEFINED:
            self._note(f'Control Word [0x2A] = 0x{unit_cw:04X} / Extra commands [0x29] = '
                       f'0x{command[0]:04X} have bits set the manual marks "Not used"')
        if self.steps_per_rev != self.md['DISTANCE_PER_REVOLUTION']:
            self._note(f"steps_per_rev {self.steps_per_rev:g} differs from Distance per "
                       f"revolution [0x00] = {self.md['DISTANCE_PER_REVOLUTION']} pulses: joint "
                       'positions are scaled by steps_per_rev')
        lo, hi = self.limits
        return {
            'vendor': 'Lika Electronic', 'product': f'RD4 ROTADRIVE {self.model.name}',
            'node_id': str(self.node_id), 'sw_version': rm.describe_sw_version(sw_version),
            'hw_version': rm.describe_hw_version(hw_version),
            'dip_switch_baud_rate': rm.describe_baud_register(baud_reg),
            'distance_per_revolution': str(self.md['DISTANCE_PER_REVOLUTION']),
            'sw_limits_pulses': f'{lo}..{hi}', 'max_speed_pps': str(self._max_speed()),
            'control_word': f'0x{unit_cw:04X}' + ('' if self._intent_enabled
                                                  else ' (not enabled by this node)'),
            'target_position': str(target),
            'watchdog': 'on when enabled' if self.watchdog else 'off',
        }

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

    def _wrong_parameters(self) -> int:
        return rm.join32(self._read_input(IR['WRONG_PARAMETERS_LIST'].address, 2), signed=False)

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

    def read_register(self, address: str, data_type: str) -> int:
        reg = parse_raw_register(_RAW_REGISTERS, address, data_type, write=False)
        read = self._read_holding if reg.table == rm.HOLDING else self._read_input
        values = read(reg.address, reg.words)
        signed = data_type.lower().startswith('i')
        if reg.words == 2:
            return rm.join32(values, signed)
        return values[0] - 0x10000 if signed and values[0] & 0x8000 else values[0]

    def write_register(self, address: str, data_type: str, value: int) -> None:
        reg = parse_raw_register(_RAW_REGISTERS, address, data_type, write=True)
        number, words = reg.address, reg.words
        value = register_type(data_type).check(int(value))
        values = rm.split32(value) if words == 2 else [value & 0xFFFF]
        if number == HR['CONTROL_WORD'].address:
            # A raw Control Word is the user's command: it becomes the intent (as written).
            self._epoch += 1
            self._outputs = values[0] & rm.CW_OUTPUTS
            self._intent_enabled = bool(values[0] & rm.CW_EMERGENCY and values[0] & rm.CW_STOP)
            self._command = values[0] & (rm.CW_JOG | rm.CW_START) if self._intent_enabled else 0
            self._stop_low = False
            self.cw = values[0]
            if values[0] & rm.CW_LOAD_DEFAULT_PARAMETERS:
                self._md_stale = True          # every machine data value may change
        if words == 2:
            self.rtu.write_registers(self.node_id, number, values)
        else:
            self.rtu.write_register(self.node_id, number, values[0])
        last = rm.MACHINE_DATA[1]
        if number <= last and self._md_words:
            # The cache takes what was written (speeds, ramps, limits of the next command).
            md_words = list(self._md_words)
            for i, word in enumerate(values):
                if number + i <= last:
                    md_words[number + i] = word
            self._set_machine_data(md_words)


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
    ParamSpec('rs485', False, serial_port.RS485_DESCRIPTION, scope='bus'),
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


def _number(params: Mapping[str, Any], name: str, kind: type, allowed: str,
            default: Any = None) -> Any:
    """A numeric parameter, or ValueError naming it in one line (`default` only for the
    node's common parameters: the RD4's own come from VENDOR.with_defaults)."""
    value = params.get(name, default)
    try:
        if isinstance(value, bool) or (kind is int and float(value) != int(float(value))):
            raise ValueError
        return kind(value)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f'parameter {name}: {value!r} is not a number (allowed: {allowed})') \
            from None


def _line_settings(params: Mapping[str, Any]) -> tuple:
    """(port, baud, parity, stopbits, timeout_s, retries) of the line, or ValueError."""
    params = VENDOR.with_defaults(params)
    port = str(params['port'])
    if not port:
        raise ValueError("parameter port: '' (allowed: a serial device such as /dev/ttyUSB0, "
                         'or a pyserial URL)')
    allowed_bauds = ', '.join(str(b) for b in BAUD_RATES)
    baud = _number(params, 'baudrate', int, allowed_bauds)
    if baud not in BAUD_RATES:
        raise ValueError(f'parameter baudrate: {baud} is not an RD4 baud rate (allowed: '
                         f'{allowed_bauds}; §4.4.2 dip-switch)')
    parity = str(params['parity']).upper()
    if parity not in ('N', 'E', 'O'):
        raise ValueError(f'parameter parity: {parity!r} (allowed: N, E, O)')
    stopbits = _number(params, 'stopbits', int, '0, 1 or 2')
    need = 2 if parity == 'N' else 1
    if stopbits not in (0, need):
        raise ValueError(f'parameter stopbits: {stopbits} with parity {parity} is not the RD4 '
                         f'format (allowed: 0 = auto or {need}; §7.3.1 11-bit characters, '
                         '"the parity bit is replaced by a stop bit")')
    timeout_s = _number(params, 'timeout_s', float, 'seconds > 0', 0.5)
    retries = _number(params, 'retries', int, '0..5')
    if not timeout_s > 0 or not 0 <= retries <= 5:
        raise ValueError(f'parameter timeout_s/retries: {timeout_s:g} s / {retries} (allowed: '
                         'timeout_s > 0, retries 0..5)')
    return port, baud, parity, stopbits or need, timeout_s, retries


def make_bus(params: Mapping[str, Any]) -> ModbusRtuBus:
    port, baud, parity, stopbits, timeout_s, retries = _line_settings(params)
    return ModbusRtuBus(port, baud, parity, stopbits, timeout_s=timeout_s, retries=retries,
                        rs485=bool(VENDOR.with_defaults(params)['rs485']))


def _check_drive(name: str, params: Mapping[str, Any]) -> None:
    """The rules of one unit's parameters (with the bus-level ones), or ValueError."""
    prefix = f'parameter drives.{name}.'
    params = VENDOR.with_defaults(params)
    method = params['homing.method']
    if method != HOMING_METHOD_PRESET:
        raise ValueError(f'{prefix}homing.method: {method} is not possible on the RD4 (allowed: '
                         f'{HOMING_METHOD_PRESET} = preset at the current position; the RD4 has '
                         'no homing run)')
    node_id = params['node_id']
    if isinstance(node_id, bool) or not isinstance(node_id, int) or not 1 <= node_id <= 247:
        raise ValueError(f'{prefix}node_id: {node_id!r} (allowed: 1..247, §4.4.1)')
    rate = _number(params, 'publish_rate_hz', float, 'Hz > 0', 50.0)
    if params['watchdog'] and rate < MIN_WATCHDOG_POLL_HZ:
        raise ValueError(f'{prefix}watchdog: true needs publish_rate_hz >= '
                         f'{MIN_WATCHDOG_POLL_HZ:g} to keep the 1 s watchdog fed (now {rate:g})')


def make_drive(bus: Bus, name: str, params: Mapping[str, Any]) -> Rd4Drive:
    _check_drive(name, params)
    return Rd4Drive(bus, name, params)


def validate(params: Mapping[str, Any]) -> list[str]:
    """The RD4's parameter rules on the node's parameters (param_rules), at start-up and for
    every run-time change: the line settings, and per unit homing, node ID and watchdog."""
    return param_rules.check_each(params, _line_settings, _check_drive)


VENDOR = Vendor(
    name='Lika RD4',
    params=PARAMS,
    make_bus=make_bus,
    make_drive=make_drive,
    drive_defaults={'steps_per_rev': 1024.0, 'homing.method': HOMING_METHOD_PRESET},
    validate=validate,
    scanner=rd4_scan.SCANNER,
)
