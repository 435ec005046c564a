"""Lika RD4 ROTADRIVE (Modbus RTU) register map, Control Word / Status word bits, alarm texts.

Pure data, shared by the driver (`vendors/rd4/`) and the simulator (`stepper_sim/rd4/sim.py`).
Source: the manual `lika_rd4_modbus_rtu.txt` (User's guide, RS-485 version, document 1.3 for
HW-SW 2-4): §8.1.1 machine data (holding registers, FC03/06/16), §8.1.2 input registers (FC04),
§10 default parameters list, §4.4.2 dip-switch table, §6.4 speed and travel limits.

`address` is the 0-based protocol address that goes on the wire, the manual's bracketed index
(`Control Word [0x2A]`); `reg_no` is the manual's 1-based register number (§7.4.1 "registers
numbered 1-16 are addressed as 0-15"). 32-bit values take two registers, high word at the lower
address (no word order is stated; §9.2 Example 1 shows it: Current position 00 00 2F F0 = 12272).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Mapping, Sequence

from ...protocol.modbus import HOLDING, INPUT, Register

logger = logging.getLogger(__name__)


def _h(address, name, title, dtype, access, default=0, lo=0, hi=0xFFFF, unit='', wp_bit=None,
       storable=True):
    """One holding register: `access` 'ro' | 'rw' (§8.1 attribute); `default` per §10 (the T32
    model's where the models differ, see MODELS); `storable`: machine data stored by Save
    parameters (CW bit 9). A register's str() is its `title`, e.g. 'Control Word [0x2A]'."""
    return Register(name=name, address=address, dtype=dtype, access=access, default=default,
                    min=lo, max=hi, unit=unit, storable=storable, table=HOLDING, title=title,
                    wp_bit=wp_bit)


def _i(address, name, title, dtype, unit=''):
    lo, hi = {'u16': (0, 0xFFFF), 'i16': (-0x8000, 0x7FFF), 'u32': (0, 0xFFFFFFFF),
              'i32': (-(1 << 31), (1 << 31) - 1)}[dtype]
    return Register(name=name, address=address, dtype=dtype, access='ro', min=lo, max=hi,
                    unit=unit, table=INPUT, title=title)


# §8.1.1 machine data; defaults §10, ranges §8.1.1, WP bits §8.1.2 Wrong parameters list.
# JOG_SPEED, WORK_SPEED and GEAR_RATIO depend on the model: the values here are the T32's.
HOLDING_REGISTERS: tuple[Register, ...] = (
    _h(0x00, 'DISTANCE_PER_REVOLUTION', 'Distance per revolution [0x00]', 'u16', 'rw', 1024, 1,
       1024, 'pulses/rev', 1),
    _h(0x01, 'POSITION_WINDOW', 'Position window [0x01]', 'u16', 'rw', 0, 0, 65535, 'pulses'),
    _h(0x02, 'POSITION_WINDOW_TIME', 'Position window time [0x02]', 'u16', 'rw', 100, 0, 10000,
       'ms'),
    _h(0x03, 'MAX_FOLLOWING_ERROR', 'Max following error [0x03]', 'u16', 'rw', 1024, 0, 65535,
       'pulses'),
    _h(0x04, 'KP_POSITION_LOOP', 'Kp position loop [0x04]', 'u16', 'rw', 500, 0, 1000),
    _h(0x05, 'KI_POSITION_LOOP', 'Ki position loop [0x05]', 'u16', 'rw', 60, 0, 1000),
    _h(0x06, 'ACCELERATION', 'Acceleration [0x06]', 'u16', 'rw', 1000, 100, 10000, 'PPS^2', 7),
    _h(0x07, 'DECELERATION', 'Deceleration [0x07]', 'u16', 'rw', 1000, 100, 10000, 'PPS^2', 8),
    _h(0x08, 'POSITIVE_DELTA', 'Positive delta [0x08-0x09]', 'u32', 'rw', 523263, 0, 523263,
       'pulses', 9),
    _h(0x0A, 'NEGATIVE_DELTA', 'Negative delta [0x0A-0x0B]', 'u32', 'rw', 523263, 0, 523263,
       'pulses', 10),
    _h(0x0C, 'JOG_SPEED', 'Jog speed [0x0C]', 'u16', 'rw', 1600, 1, 1600, 'PPS', 11),
    _h(0x0D, 'WORK_SPEED', 'Work speed [0x0D]', 'u16', 'rw', 1600, 1, 1600, 'PPS', 12),
    _h(0x0E, 'START_TORQUE_CURRENT_TIME', 'Start torque current time [0x0E]', 'u16', 'rw', 2000,
       0, 3000, 'ms', 13),
    _h(0x0F, 'CODE_SEQUENCE', 'Code sequence [0x0F]', 'u16', 'rw', 0, 0, 1, '', 14),
    _h(0x10, 'KP_CURRENT_LOOP', 'Kp current loop [0x10]', 'u16', 'rw', 200, 0, 1000),
    _h(0x11, 'KI_CURRENT_LOOP', 'Ki current loop [0x11]', 'u16', 'rw', 60, 0, 1000),
    _h(0x12, 'MAX_CURRENT', 'Max current [0x12]', 'u16', 'rw', 5000, 10, 5000, 'mA', 17),
    _h(0x13, 'STARTING_TORQUE_CURRENT', 'Starting torque current [0x13]', 'u16', 'rw', 7000, 10,
       7000, 'mA', 18),
    # Offset: "real position - preset"; ro and not in the §10 list, but it is the reference
    # the preset leaves, so it is stored with the machine data (spec §2.1 best reading).
    _h(0x14, 'OFFSET', 'Offset [0x14-0x15]', 'i32', 'ro', 0, -(1 << 31), (1 << 31) - 1,
       'pulses'),
    _h(0x16, 'PRESET', 'Preset [0x16-0x17]', 'i32', 'rw', 0, -1048576, 1048576, 'pulses', 26),
    _h(0x18, 'GEAR_RATIO', 'Gear ratio [0x18]', 'u16', 'ro', 32, 32, 48, '', 19),
    _h(0x19, 'JOG_STEP_LENGTH', 'Jog step length [0x19]', 'u16', 'rw', 100, 1, 10000, 'pulses',
       20),
    # Command registers: not machine data, not saved (not in the §10 list).
    _h(0x29, 'EXTRA_COMMANDS', 'Extra commands register [0x29]', 'u16', 'rw', 0, 0, 0xFFFF,
       storable=False),
    _h(0x2A, 'CONTROL_WORD', 'Control Word [0x2A]', 'u16', 'rw', 0, 0, 0xFFFF,
       storable=False),
    _h(0x2B, 'TARGET_POSITION', 'Target position [0x2B-0x2C]', 'i32', 'rw', 0, -(1 << 31),
       (1 << 31) - 1, 'pulses', storable=False),
)

# §8.1.2 input registers: 13 variables in 16 registers 0x00-0x0F.
INPUT_REGISTERS: tuple[Register, ...] = (
    _i(0x00, 'ALARMS', 'Alarms register [0x00]', 'u16'),
    _i(0x01, 'STATUS_WORD', 'Status word [0x01]', 'u16'),
    _i(0x02, 'CURRENT_POSITION', 'Current position [0x02-0x03]', 'i32', 'pulses'),
    _i(0x04, 'CURRENT_VELOCITY', 'Current velocity [0x04]', 'i16', 'PPS'),
    _i(0x05, 'POSITION_FOLLOWING_ERROR', 'Position following error [0x05-0x06]', 'i32',
       'pulses'),
    _i(0x07, 'CURRENT_VALUE', 'Current value [0x07]', 'i16', 'mA'),
    _i(0x08, 'TEMPERATURE_VALUE', 'Temperature value [0x08]', 'i16', 'degC'),
    _i(0x09, 'WRONG_PARAMETERS_LIST', 'Wrong parameters list [0x09-0x0A]', 'u32'),
    _i(0x0B, 'I2T', 'I2t [0x0B]', 'u16'),
    _i(0x0C, 'DIP_SWITCH_BAUD_RATE', 'Dip-switch baud rate [0x0C]', 'u16'),
    _i(0x0D, 'DIP_SWITCH_NODE_ID', 'Dip-switch node ID [0x0D]', 'u16'),
    _i(0x0E, 'SW_VERSION', 'SW Version [0x0E]', 'u16'),
    _i(0x0F, 'HW_VERSION', 'HW Version [0x0F]', 'u16'),
)

HOLDING_BY_NAME: Mapping[str, Register] = {r.name: r for r in HOLDING_REGISTERS}
INPUT_BY_NAME: Mapping[str, Register] = {r.name: r for r in INPUT_REGISTERS}
HR = HOLDING_BY_NAME
IR = INPUT_BY_NAME

HOLDING_END = 0x2C              # last holding address (Target position low word)
INPUT_END = 0x0F                # last input address (HW Version)
MACHINE_DATA = (0x00, 0x19)     # §8.1.1 machine data block, one FC03 of 26 registers
COMMAND_BLOCK = (0x29, 0x2C)    # Extra commands, Control Word, Target position
HOLES = range(0x1A, 0x29)       # not in the manual (spec §9A item 6)
# One FC04 per poll: Alarms .. Current value (0x00-0x07), contiguous.
STATE_BLOCK = (0x00, 8)
IDENTITY_BLOCK = (0x0C, 4)      # dip-switch baud, node ID, SW and HW version

# ------------------------------------------------------------------ Control Word [0x2A] (§8.1.1)
CW_JOG_PLUS = 0x0001
CW_JOG_MINUS = 0x0002
CW_STOP = 0x0004                   # active low: 0 = decelerated stop
CW_ALARM_RESET = 0x0008            # rising edge
CW_INCREMENTAL_JOG = 0x0010
CW_START = 0x0040
CW_EMERGENCY = 0x0080              # active low: 0 = immediate stop + Emergency alarm
CW_WATCH_DOG_ENABLE = 0x0100
CW_SAVE_PARAMETERS = 0x0200        # rising edge
CW_LOAD_DEFAULT_PARAMETERS = 0x0400    # rising edge
CW_PERFORM_COUNTING_PRESET = 0x0800    # rising edge
CW_AXIS_TORQUE = 0x1000
CW_OUT_1 = 0x2000
CW_OUT_2 = 0x4000
CW_OUT_3 = 0x8000
CW_OUTPUTS = CW_OUT_1 | CW_OUT_2 | CW_OUT_3
CW_JOG = CW_JOG_PLUS | CW_JOG_MINUS
CW_READY = CW_STOP | CW_EMERGENCY      # §9.3 Example 2: 0x0084 "ready to execute the motion"
CW_EDGE_BITS = (CW_ALARM_RESET | CW_SAVE_PARAMETERS | CW_LOAD_DEFAULT_PARAMETERS
                | CW_PERFORM_COUNTING_PRESET)
CW_NOT_USED = 0x0020               # bit 5 "Not used"
EXTRA_COMMANDS_DEFINED = 0x0001    # Extra commands register [0x29]: bit 0 Absolute reading only

CONTROL_WORD_BITS: tuple[tuple[int, str], ...] = (
    (CW_JOG_PLUS, 'Jog +'), (CW_JOG_MINUS, 'Jog -'), (CW_STOP, 'Stop'),
    (CW_ALARM_RESET, 'Alarm reset'), (CW_INCREMENTAL_JOG, 'Incremental jog'),
    (CW_START, 'Start'), (CW_EMERGENCY, 'Emergency'), (CW_WATCH_DOG_ENABLE, 'Watch dog enable'),
    (CW_SAVE_PARAMETERS, 'Save parameters'),
    (CW_LOAD_DEFAULT_PARAMETERS, 'Load default parameters'),
    (CW_PERFORM_COUNTING_PRESET, 'Perform counting preset'), (CW_AXIS_TORQUE, 'Axis torque'),
    (CW_OUT_1, 'OUT 1'), (CW_OUT_2, 'OUT 2'), (CW_OUT_3, 'OUT 3'),
)

# -------------------------------------------------------------------- Status word [0x01] (§8.1.2)
SW_AXIS_IN_POSITION = 0x0001
SW_AXIS_ENABLED = 0x0004
SW_SW_LIMIT_SWITCH_PLUS = 0x0008
SW_SW_LIMIT_SWITCH_MINUS = 0x0010
SW_ALARM = 0x0020
SW_AXIS_RUNNING = 0x0040
SW_EXECUTING_A_COMMAND = 0x0080
SW_TARGET_POSITION_REACHED = 0x0100
SW_DAC_SATURATION = 0x1000
SW_IN_1 = 0x2000
SW_IN_2 = 0x4000
SW_IN_3 = 0x8000

STATUS_WORD_BITS: tuple[tuple[int, str], ...] = (
    (SW_AXIS_IN_POSITION, 'Axis in position'), (SW_AXIS_ENABLED, 'Axis enabled'),
    (SW_SW_LIMIT_SWITCH_PLUS, 'SW limit switch +'),
    (SW_SW_LIMIT_SWITCH_MINUS, 'SW limit switch -'),
    (SW_ALARM, 'Alarm'), (SW_AXIS_RUNNING, 'Axis running'),
    (SW_EXECUTING_A_COMMAND, 'Executing a command'),
    (SW_TARGET_POSITION_REACHED, 'Target position reached'), (SW_DAC_SATURATION, 'DAC saturation'),
    (SW_IN_1, 'IN 1'), (SW_IN_2, 'IN 2'), (SW_IN_3, 'IN 3'),
)
INPUT_BITS = {'in1': SW_IN_1, 'in2': SW_IN_2, 'in3': SW_IN_3}
# Bits 1 and 9-11 are "Not used" (§8.1.2): a reply with one of them set is not an RD4's.
STATUS_WORD_DEFINED = sum(mask for mask, _name in STATUS_WORD_BITS)      # 0xF1FD

# -------------------------------------------------------------- Alarms register [0x00] (§8.1.2)
ALARM_MACHINE_DATA_NOT_VALID = 0x0001
ALARM_FLASH_MEMORY_ERROR = 0x0002
ALARM_FOLLOWING_ERROR = 0x0008
ALARM_AXIS_NOT_SYNCHRONIZED = 0x0010
ALARM_TARGET_NOT_VALID = 0x0020
ALARM_EMERGENCY = 0x0040
ALARM_OVERCURRENT = 0x0080
ALARM_OVERTEMPERATURE = 0x0100
ALARM_UNDERVOLTAGE = 0x0400
ALARM_WATCH_DOG = 0x0800


@dataclasses.dataclass(frozen=True)
class Alarm:
    mask: int
    name: str          # the manual's name
    text: str          # the manual's description, shortened where it repeats itself
    resettable: bool = True


ALARMS: tuple[Alarm, ...] = (
    Alarm(ALARM_MACHINE_DATA_NOT_VALID, 'Machine data not valid',
          'one or more parameters are not valid, set proper values to restore normal work '
          'condition (see Wrong parameters list [0x09-0x0A])'),
    Alarm(ALARM_FLASH_MEMORY_ERROR, 'Flash memory error', 'internal error, it cannot be restored',
          resettable=False),
    Alarm(ALARM_FOLLOWING_ERROR, 'Following error',
          'the difference between the real position and the theoretical position is greater '
          'than the value set in Max following error [0x03]; we suggest reducing the work '
          'speed'),
    Alarm(ALARM_AXIS_NOT_SYNCHRONIZED, 'Axis not synchronized',
          'internal error, it cannot be restored', resettable=False),
    Alarm(ALARM_TARGET_NOT_VALID, 'Target not valid',
          'target position is over maximum travel limits'),
    Alarm(ALARM_EMERGENCY, 'Emergency',
          'bit 7 Emergency in Control Word [0x2A] has been forced to low value (0); or alarms '
          'are active in the unit'),
    Alarm(ALARM_OVERCURRENT, 'Overcurrent',
          'the power supply current is exceeding maximum ratings allowed'),
    Alarm(ALARM_OVERTEMPERATURE, 'Overtemperature',
          'the internal temperature of the device as sensed by a probe is exceeding maximum '
          'ratings (see Temperature value [0x08])'),
    Alarm(ALARM_UNDERVOLTAGE, 'Undervoltage',
          'the power supply voltage is under minimum ratings allowed'),
    Alarm(ALARM_WATCH_DOG, 'Watch dog',
          'Watch dog enabled and no message received within 1 second: safety stop'),
)
ALARM_BY_MASK: Mapping[int, Alarm] = {a.mask: a for a in ALARMS}
# Bits 2, 9 and 12-15 are "Not used" (§8.1.2): a reply with one of them set is not an RD4's.
ALARMS_DEFINED = sum(a.mask for a in ALARMS)                                # 0x0DFB
NOT_RESETTABLE = ALARM_FLASH_MEMORY_ERROR | ALARM_AXIS_NOT_SYNCHRONIZED

# Wrong parameters list [0x09-0x0A] bits (§8.1.2 table). Read as 0-based bit positions of the
# 32-bit value, high word at 0x09 (spec §10 item 6). Gear ratio is listed although read-only.
WRONG_PARAMETER_BITS: Mapping[int, str] = {
    r.wp_bit: r.name for r in HOLDING_REGISTERS if r.wp_bit is not None}


# ------------------------------------------------------------------------- models and limits
@dataclasses.dataclass(frozen=True)
class Model:
    name: str
    max_speed_pps: int     # §6.4 Max. speed (at Distance per revolution = 1024)
    gear_ratio: int        # Gear ratio [0x18]


MODELS: Mapping[str, Model] = {
    'T32': Model('T32', 1600, 32),     # RD4-...-T32-...
    'T48': Model('T48', 1066, 48),     # RD4-...-T48-...
}
MODEL_BY_GEAR_RATIO: Mapping[int, Model] = {m.gear_ratio: m for m in MODELS.values()}
MIN_SPEED_PPS = 1                      # §6.4 Min. speed, all RD4 units
MAX_DISTANCE_PER_REVOLUTION = 1024     # §6.4 "the maximum value ... Distance per revolution"
REVOLUTIONS_EACH_WAY = 511             # §6.4 "511 in negative direction and 511 in positive"
PRESET_RANGE = (-1048576, 1048576)     # §8.1.1 Preset
WATCH_DOG_TIMEOUT_S = 1.0              # §8.1.1 bit 8 "within 1 second"


def max_speed_pps(model: Model, distance_per_revolution: int, rounding: str = 'floor') -> int:
    """§6.4: Speed <= Max. speed * Distance per revolution / 1024.

    §6.4 Example 2 says the result is 'rounded off to the nearest integer' (156.25 -> 156) but
    whether the firmware rounds or floors is unknown: a driver floors, a simulator rounds."""
    exact = model.max_speed_pps * distance_per_revolution / MAX_DISTANCE_PER_REVOLUTION
    value = int(exact) if rounding == 'floor' else int(exact + 0.5)
    return max(MIN_SPEED_PPS, value)


def max_delta_pulses(distance_per_revolution: int) -> int:
    """§6.4: 511 revolutions each way; Example 1 gives 1024 * 511 - 1 = 523263 (the register
    maximum), Example 2 gives 100 * 511 = 51100. Lenient reading: DPR * 511, capped at 523263."""
    return min(HR['POSITIVE_DELTA'].max, distance_per_revolution * REVOLUTIONS_EACH_WAY)


# ------------------------------------------------------------------ dip-switch (§4.4.2 table)
BAUD_SWITCH: Mapping[int, tuple[int, str]] = {
    0x00: (9600, 'N'), 0x01: (9600, 'E'), 0x02: (9600, 'O'),
    0x03: (19200, 'N'), 0x04: (19200, 'E'), 0x05: (19200, 'O'),
}
BAUD_SWITCH_DEFAULT = 0x01         # §4.4.2 "01h (default)", §5.2 9600 8E1


def serial_format(parity: str) -> str:
    """§7.3.1: 11-bit characters; 'No parity' replaces the parity bit by a stop bit (8N2)."""
    return '8N2' if parity == 'N' else f'8{parity}1'


def describe_baud_register(value: int) -> str:
    """Dip-switch baud rate [0x0C]: the switch code (00h..05h) or the baud number itself (the
    manual does not say which; spec §10 item 20)."""
    if value in BAUD_SWITCH:
        baud, parity = BAUD_SWITCH[value]
        return f'{value:02X}h = {baud} {serial_format(parity)}'
    if value in (9600, 19200):
        return f'{value} baud'
    return f'0x{value:04X} (not in the dip-switch table)'


# ------------------------------------------------------------------------ 32-bit values
def join32(words: Sequence[int], signed: bool) -> int:
    """Two registers, high word first (§9.2 Example 1)."""
    value = ((words[0] & 0xFFFF) << 16) | (words[1] & 0xFFFF)
    if signed and value & 0x80000000:
        value -= 1 << 32
    return value


def split32(value: int) -> list[int]:
    value &= 0xFFFFFFFF
    return [value >> 16, value & 0xFFFF]


def encode(reg: Register, value: int) -> list[int]:
    if reg.words == 2:
        return split32(value)
    return [value & 0xFFFF]


def decode(reg: Register, words: Sequence[int]) -> int:
    if reg.words == 2:
        return join32(words, reg.signed)
    word = words[0] & 0xFFFF
    return word - 0x10000 if reg.signed and word & 0x8000 else word


def defaults(model: Model) -> dict[int, int]:
    """Holding register words 0x00-0x2C after Load default parameters (§10), by address.

    The command registers (0x29-0x2C) and the holes read 0 (Control Word 0x0000 at power-up)."""
    words = {a: 0 for a in range(HOLDING_END + 1)}
    for reg in HOLDING_REGISTERS:
        value = reg.default
        if reg.name in ('JOG_SPEED', 'WORK_SPEED'):
            value = model.max_speed_pps
        elif reg.name == 'GEAR_RATIO':
            value = model.gear_ratio
        for i, word in enumerate(encode(reg, value)):
            words[reg.address + i] = word
    return words


# -------------------------------------------------------------------------------- texts
def alarm_names(alarms: int) -> list[str]:
    names = [a.name for a in ALARMS if alarms & a.mask]
    unknown = alarms & ~ALARMS_DEFINED
    if unknown:
        names.append(f'unknown alarm bits 0x{unknown:04X}')
    return names


def wrong_parameter_titles(wrong_parameters: int) -> list[str]:
    titles = [HR[name].title for bit, name in sorted(WRONG_PARAMETER_BITS.items())
              if wrong_parameters & (1 << bit)]
    unknown = wrong_parameters & ~sum(1 << b for b in WRONG_PARAMETER_BITS)
    if unknown:
        titles.append(f'unknown bits 0x{unknown:08X}')
    return titles


def describe_alarms(alarms: int, wrong_parameters: int | None = None) -> str:
    """'Overcurrent: the power supply current ...; Emergency: ...' with the WP list decoded."""
    parts = []
    for alarm in ALARMS:
        if not alarms & alarm.mask:
            continue
        text = f'{alarm.name}: {alarm.text}'
        if alarm.mask == ALARM_MACHINE_DATA_NOT_VALID and wrong_parameters is not None:
            text += (f'; wrong parameters (0x{wrong_parameters:08X}): '
                     + (', '.join(wrong_parameter_titles(wrong_parameters)) or 'none listed'))
        parts.append(text)
    unknown = alarms & ~ALARMS_DEFINED
    if unknown:
        parts.append(f'unknown alarm bits 0x{unknown:04X}')
    return '; '.join(parts)


def status_names(status_word: int) -> list[str]:
    return [name for mask, name in STATUS_WORD_BITS if status_word & mask]


def control_word_names(control_word: int) -> list[str]:
    return [name for mask, name in CONTROL_WORD_BITS if control_word & mask]


def find_register(text: str) -> Register | None:
    """A register by name ('CONTROL_WORD', 'control word') or None."""
    key = text.strip().upper().replace(' ', '_').replace('-', '_')
    return HR.get(key) or IR.get(key)


# HW Version [0x0F] fields (§8.1.2): what an RD4 with the Modbus interface reads.
HW_MODEL_SHIFT = 12                # bits 12-15 ROTADRIVE model: 00 = RD4
HW_INTERFACE_SHIFT = 8             # bits 8-11 interface: 00 = Modbus
HW_NOT_USED = 0x0070               # bits 4-6 "not used"
HW_MODEL_RD4 = 0
HW_INTERFACE_MODBUS = 0


def describe_hw_version(value: int) -> str:
    """HW Version [0x0F] fields (§8.1.2): bits 0-3 HW version, 7 brake, 8-11 interface,
    12-15 ROTADRIVE model."""
    code = (value >> 8) & 0xF
    interface = {0: 'Modbus', 1: 'Profibus', 2: 'CANopen'}.get(code, f'interface {code}')
    model = {0: 'RD4', 1: 'RD1xA', 2: 'RD5'}.get((value >> 12) & 0xF,
                                                 f'model {(value >> 12) & 0xF}')
    brake = 'with brake' if value & 0x80 else 'without brake'
    return f'HW {value & 0xF}, {model}, {interface}, {brake} (0x{value:04X})'


def describe_sw_version(value: int) -> str:
    """SW Version [0x0E]: high byte major, low byte minor (0x0102 = 1.2, §8.1.2)."""
    return f'{value >> 8}.{value & 0xFF}'
