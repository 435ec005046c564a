"""One Lika RD4 unit as the driver knows it: the base of `drive.Rd4Drive`.

Its registers on the line (read_register/write_register included), the Control Word intent, the
examination of replies and machine data, and the identity checks of connect(); the contract's
other operations, on top of them, are in drive.py. No rclpy.

Control Words are composed from the driver's intent (enabled or not, the commanded Start or Jog,
Stop held low after a stop, the outputs a raw write set), never from a Control Word read from
the unit (a reply with a valid CRC but another device's content, written back, would start a
jog). Alarms and Status word are examined before anything is based on them: bits the
manual marks "Not used", or an Alarm status bit that contradicts the Alarms register, make the
reply implausible (LinkError, the node reconnects; connect() then checks the identity).
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable, Mapping

from ...contract.capabilities import FreshPollState
from ...contract.drive import (
    Bus,
    Drive,
    DriveError,
    HomingState,
    IdentityError,
    LinkError,
    Operation,
    register_type,
)
from ...protocol.modbus import RawRegisterRules, parse_raw_register
from ...protocol.modbus_rtu import (
    ILLEGAL_DATA_ADDRESS,
    ILLEGAL_FUNCTION,
    ModbusExceptionError,
    ModbusRtuBus,
)
from . import regmap as rm
from . import settings
from .regmap import HR, IR

logger = logging.getLogger(__name__)

STEP_S = 0.0                   # between the transactions of one operation (contract/drive.py)
BAUD_RATES = (9600, 19200)            # §4.4.2 dip-switch table
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


class Rd4Unit(Drive, FreshPollState):
    """What every Rd4Drive operation relies on: the line, the Control Word intent (enabled,
    Start/Jog, Stop low, outputs, epoch) and the examined machine data.

    Split from Rd4Drive for size only: the two work on one record, and only Rd4Drive is made.
    """

    def __init__(self, bus: Bus, name: str, params: Mapping[str, Any]):
        params = settings.with_defaults(params)
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

    def _wrong_parameters(self) -> int:
        return rm.join32(self._read_input(IR['WRONG_PARAMETERS_LIST'].address, 2), signed=False)

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

    # ---------------------------------------------------------------------- raw registers
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
