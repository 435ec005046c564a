"""R.T.A. X-MIND K ASCII protocol over RS-485: frames, tables, range checks, line timing.

No ROS and no I/O. Shared by the driver (`vendors/xmind_k.py`) and the simulator
(`stepper_sim/xmind_k/sim.py`); section numbers (§4.1.2, Table 5) point into the
*X-MIND K series Programmer's manual* (shared/manuals/rta_xmind_k_serial.txt).

Every string is ``AA<code>[,<params>]\\r`` (§4): a 2-digit drive address 00-47 (99 = broadcast,
§2.2.1), a 2-letter code, comma-separated ASCII decimal parameters, ASCII 13 at the end.
A parsed string is a `Frame(address, code, args)`, in both directions:

    host -> drive   WN (instruction storing), WS CY CN PS EE ES RA SA SO SC (commands),
                    QA QS QI QO QM QC QE (data requests)
    drive -> host   'Y' / 'N' (confirmation messages, §4.4) or the request code with its data

`encode_request` / `parse_request` and `encode_answer` / `parse_answer` convert both ways and
refuse what the drive would refuse: `FrameSyntaxError` and `RangeError` are what the drive answers
``AAN`` to (§4.4.2); `AddressError` is what it ignores (§4.4.3).

The canonical wire form has no '.' or ',' before the terminator: the manual's examples print one
but its own character counts in §3 leave it out (see docs/xmind_k.md). Receivers here accept one.

One file: the codec range-checks WN/QM instructions and WS/QS presets with the §4.1 instruction
table and the §4.2.2/§6 tables, one contract shared by driver and simulator.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import re
from typing import Any, Callable

logger = logging.getLogger(__name__)

# §2.1 / §2.2.1 addresses and memory ---------------------------------------------------------
ADDRESS_MIN, ADDRESS_MAX = 0, 47
BROADCAST = 99
CELL_EEPROM = range(100, 228)        # §4.1: 100..227 stored in E2prom
CELL_RAM = range(228, 231)           # §4.1: 228..230 stored in RAM
CELL_MIN, CELL_MAX = 100, 230
END_OF_PROGRAM = 0                   # DDD = 000 (§4.1)
HARDWARE_START_CELLS = range(100, 116)   # Table 1: cell = 100 + SEL0 + 2 SEL1 + 4 SEL2 + 8 SEL3

STEPS_MAX = 8388607                  # §4.1.1 +-8388607 steps per index instruction
COUNTER_MIN, COUNTER_MAX = -2147483648, 2147483647   # §4.3.1 counting limits
CYCLIC_RANGE_MAX = 8388607           # §4.2.2.6 kkk 1..8.388.607

TERMINATOR = b'\r'                   # §3 ASCII 13, the only frame terminator

# §3 serial line timing ------------------------------------------------------------------------
BAUDRATE = 9600                      # §3
BITS_PER_CHAR = 10                   # §3: start + 8 data + stop, no parity
CHAR_TIME_S = BITS_PER_CHAR / BAUDRATE   # §3 "approximately 1.04 milliseconds"
MANUAL_CHAR_TIME_S = 0.00104         # the rounded figure the §3 examples compute with
TURNAROUND_S = 0.0015                # §3: last host char -> first answer char
TURNAROUND_WN_S = 0.012              # §3: the same for WN (memory storing)
MARGIN_S = 0.004                     # §3: after the answer, before the next string
RS_SILENT_S = 0.200                  # §4.2.2.3 Note 2: current off and deaf after WS,RS
RD_DEFAULT_MS = 10                   # §4.2.2.5 answer delay default
RD_MAX_MS = 255

# §6.1 Tables 2-4, §6.2 Table 5 -------------------------------------------------------------
TABLE2_HZ = {code: code * 1000 for code in range(3, 25)}     # ramped runs, zero-search fast speed
TABLE3_HZ = {code: code * 100 for code in range(2, 31)}      # unramped runs, zero-search LL
HR_RAMPED_X100 = range(30, 241)                              # §4.1.2 FFF: Hz = FFF * 100
# Table 4: (from Hz, to Hz included, step Hz) for the high-resolution unramped runs (21, 22)
TABLE4_BANDS = ((1, 50, 1), (52, 100, 2), (105, 200, 5), (200, 500, 10), (525, 1200, 25),
                (1250, 2400, 50), (2500, 4800, 100))
TABLE4_HZ = tuple(sorted({f for lo, hi, step in TABLE4_BANDS for f in range(lo, hi + 1, step)}))
HR_UNRAMPED_MAX_HZ = 4800
# Table 5: ramp code -> (total ramp time 0..24 kHz in ms, average acceleration in Hz/s as printed)
TABLE5 = {
    10: (16, 1500000), 11: (18, 1333333), 12: (20, 1200000), 13: (22, 1090909),
    14: (24, 1000000), 15: (27, 888888), 16: (30, 800000), 17: (32, 750000),
    18: (34, 705882), 19: (37, 648640), 20: (40, 600000), 21: (44, 545454),
    22: (48, 500000), 23: (53, 452830), 24: (60, 400000), 25: (68, 352941),
    26: (80, 300000), 27: (87, 275862), 28: (96, 250000), 29: (107, 224299),
    30: (120, 200000), 31: (137, 175182), 32: (160, 150000), 33: (192, 125000),
    34: (206, 116504), 35: (240, 100000), 36: (288, 83333), 37: (320, 75000),
    38: (360, 66667), 39: (480, 50000), 40: (720, 33333), 41: (960, 25000),
    42: (1440, 16667),
}
RAMP_REFERENCE_HZ = 24000            # §6.2 NOTE: the table times are for 0 -> 24000 Hz

# §4.2.2 presets: name -> allowed values (as the wire writes them) and factory default
RESOLUTIONS = {'D0': 500, 'D1': 1000, 'D2': 2000, 'D3': 4000,      # §4.2.2.3 step/rev
               'B0': 400, 'B1': 800, 'B2': 1600, 'B3': 3200}
X4_RESOLUTIONS = ('D2', 'D3', 'B2', 'B3')                          # §4.2.2.3 Note 1
PRESETS = ('AD', 'IN', 'RS', 'EQ', 'ES', 'RD', 'CM')               # §4.3.2 order
PRESET_DEFAULTS = {'AD': 0, 'IN': 1, 'RS': 'D2', 'EQ': 0, 'RD': RD_DEFAULT_MS, 'CM': 0, 'ES': 1}
CURRENT_PERCENT = {0: 55, 1: 70, 2: 85, 3: 100}                    # §4.2.2.2
CM_RELATIVE, CM_ABSOLUTE, CM_CYCLIC = 0, 1, 2                      # §4.2.2.6

SETTABLE_OUTPUTS = ('O0', 'O1', 'O2', 'O3', 'FC') + tuple(f'F{i}' for i in range(8))  # §4.2.10
READABLE_OUTPUTS = ('FA', 'BS') + SETTABLE_OUTPUTS                                   # §4.3.4
JUMP_INPUTS = ('I0', 'I1', 'I2', 'PX', 'S0', 'S1', 'S2', 'S3') + tuple(f'F{i}' for i in range(8))
READABLE_INPUTS = ('ST', 'ES', 'EE', 'I0', 'I1', 'I2', 'PX', 'S0', 'S1', 'S2', 'S3')  # §4.3.3

ERROR_NONE = 0
ERROR_FIELD_OVERFLOW = 50            # §4.3.7 / §5.2
ERROR_TEXT = {ERROR_NONE: 'no error', ERROR_FIELD_OVERFLOW: 'FIELD overflow error'}

# Codes by family (§4) and which of them a broadcast may carry (§4.2.x, §4.3)
COMMAND_CODES = ('WS', 'CY', 'CN', 'PS', 'EE', 'ES', 'RA', 'SA', 'SO', 'SC')
REQUEST_CODES = ('QA', 'QS', 'QI', 'QO', 'QM', 'QC', 'QE')
HOST_CODES = ('WN',) + COMMAND_CODES + REQUEST_CODES
BROADCAST_CODES = frozenset(('WS', 'CY', 'CN', 'PS', 'EE', 'ES'))
BUSY_CODES = frozenset(('EE', 'ES'))  # §3 / §4.2: the only strings a busy drive answers


class ProtocolError(ValueError):
    """A string the drive would not execute; str() says why."""


class AddressError(ProtocolError):
    """No valid drive address: the drive ignores the string (no answer, §4.4.3)."""


class FrameSyntaxError(ProtocolError):
    """Unknown code or bad syntax: the drive answers AAN (§4.4.2)."""


class RangeError(ProtocolError):
    """A parameter out of its range: the drive answers AAN (§4.4.2)."""


# Tables -----------------------------------------------------------------------------------------
def table4_floor(hz: int) -> int:
    """§4.1.6 Note: a frequency is rounded to 'the nearest and lower value' of Table 4."""
    if not 1 <= hz <= HR_UNRAMPED_MAX_HZ:
        raise RangeError(f'frequency {hz} Hz outside Table 4 (1..{HR_UNRAMPED_MAX_HZ} Hz)')
    return TABLE4_HZ[bisect.bisect_right(TABLE4_HZ, hz) - 1]


def ramp_time_s(ramp_code: int) -> float:
    """Table 5 total ramp time from standstill to 24 kHz."""
    try:
        return TABLE5[ramp_code][0] / 1000.0
    except KeyError:
        raise RangeError(f'ramp code {ramp_code} not in Table 5 (10..42)') from None


def ramp_acceleration_hz_s(ramp_code: int) -> float:
    """Linear ramp model: 24000 Hz in the Table 5 time (§6.2 NOTE: time scales with frequency)."""
    return RAMP_REFERENCE_HZ / ramp_time_s(ramp_code)


# Fields -----------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class FieldKind:
    """One parameter field: its regex, its range check and how it is written back."""

    name: str
    pattern: str
    parse: Callable[[str], Any]
    check: Callable[[Any], str | None]     # None when in range, else why not
    fmt: Callable[[Any], str]

    def read(self, token: str, what: str) -> Any:
        if not re.fullmatch(self.pattern, token):
            raise FrameSyntaxError(f'{what}: {token!r} is not {self.name}')
        value = self.parse(token)
        why = self.check(value)
        if why:
            raise RangeError(f'{what}: {token} {why}')
        return value

    def write(self, value: Any, what: str) -> str:
        why = self.check(value)
        if why:
            raise RangeError(f'{what}: {value!r} {why}')
        text = self.fmt(value)
        if not re.fullmatch(self.pattern, text):
            raise RangeError(f'{what}: {value!r} cannot be written as {self.name}')
        return text


def _in(lo: int, hi: int, where: str = '') -> Callable[[int], str | None]:
    def check(v: int) -> str | None:
        return None if lo <= v <= hi else f'outside {lo}..{hi}{where}'
    return check


def _one_of(values, where: str = '') -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        return None if v in values else f'not one of {", ".join(map(str, values))}{where}'
    return check


def _signed(v: int) -> str:
    return f'{v:+d}'


FF2 = FieldKind('a 2-digit Table 2 code', r'\d{2}', int, _one_of(tuple(TABLE2_HZ), ' (Table 2)'),
                lambda v: f'{v:02d}')
FF3 = FieldKind('a 2-digit Table 3 code', r'\d{2}', int, _one_of(tuple(TABLE3_HZ), ' (Table 3)'),
                lambda v: f'{v:02d}')
FFF = FieldKind('3 digits (Hz / 100)', r'\d{3}', int, _in(30, 240, ' (x 100 Hz, §4.1.2)'),
                lambda v: f'{v:03d}')
FFFF = FieldKind('4 digits (Hz)', r'\d{4}', int, _in(1, HR_UNRAMPED_MAX_HZ, ' Hz (§4.1.6)'),
                 lambda v: f'{v:04d}')
RR = FieldKind('a 2-digit Table 5 code', r'\d{2}', int, _in(10, 42, ' (Table 5)'),
               lambda v: f'{v:02d}')
STEPS = FieldKind('a signed step count', r'[+-]\d{1,7}', int, _in(-STEPS_MAX, STEPS_MAX),
                  _signed)
DIR = FieldKind("a direction '+' or '-'", r'[+-]', str, _one_of(('+', '-')), str)
MULT = FieldKind('x1 or x4', r'[xX][14]', str.lower, _one_of(('x1', 'x4')), str)
POS32 = FieldKind('a signed position', r'[+-]\d{1,10}', int, _in(COUNTER_MIN, COUNTER_MAX),
                  _signed)
DIST = FieldKind('a step count', r'\d{1,7}', int, _in(0, STEPS_MAX), str)
DELAY = FieldKind('milliseconds', r'\d{1,5}', int, _in(0, 65535, ' ms'), str)
LOOPS = FieldKind('a repetition count', r'\d{1,5}', int, _in(1, 65535), str)
BIT = FieldKind('0 or 1', r'[01]', int, _one_of((0, 1)), str)
OUT = FieldKind('an output name', r'[A-Z][0-9A-Z]', str, _one_of(SETTABLE_OUTPUTS), str)
JMPIN = FieldKind('an input name', r'[A-Z][0-9A-Z]', str, _one_of(JUMP_INPUTS), str)
CELL = FieldKind('a 3-digit cell', r'\d{3}', int, _in(CELL_MIN, CELL_MAX), lambda v: f'{v:03d}')
NEXT = FieldKind('a 3-digit next cell', r'\d{3}', int,
                 lambda v: None if v == END_OF_PROGRAM or CELL_MIN <= v <= CELL_MAX
                 else f'is neither 000 nor {CELL_MIN}..{CELL_MAX}', lambda v: f'{v:03d}')


# Instructions (§4.1) ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class InstructionType:
    code: int
    name: str                      # the manual's title
    section: str
    fields: tuple[tuple[str, FieldKind], ...]

    @property
    def field_names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.fields)


def _it(code, name, section, *fields):
    return InstructionType(code, name, section, tuple(fields))


INSTRUCTION_TYPES = {t.code: t for t in (
    _it(1, 'INDEXED RUN WITH RAMP', '4.1.1',
        ('frequency_code', FF2), ('ramp_code', RR), ('steps', STEPS), ('multiplier', MULT)),
    _it(31, 'HIGH RESOLUTION INDEXED RUN WITH RAMP', '4.1.2',
        ('frequency_x100', FFF), ('ramp_code', RR), ('steps', STEPS), ('multiplier', MULT)),
    _it(2, 'FREE RUN WITH RAMP', '4.1.3',
        ('frequency_code', FF2), ('ramp_code', RR), ('direction', DIR), ('multiplier', MULT)),
    _it(32, 'HIGH RESOLUTION FREE RUN WITH RAMP', '4.1.4',
        ('frequency_x100', FFF), ('ramp_code', RR), ('direction', DIR), ('multiplier', MULT)),
    _it(11, 'INDEXED RUN WITHOUT RAMP', '4.1.5',
        ('frequency_code', FF3), ('steps', STEPS), ('multiplier', MULT)),
    _it(21, 'HIGH RESOLUTION INDEXED RUN WITHOUT RAMP', '4.1.6',
        ('frequency_hz', FFFF), ('steps', STEPS), ('multiplier', MULT)),
    _it(12, 'FREE RUN WITHOUT RAMP', '4.1.7',
        ('frequency_code', FF3), ('direction', DIR), ('multiplier', MULT)),
    _it(22, 'HIGH RESOLUTION FREE RUN WITHOUT RAMP', '4.1.8',
        ('frequency_hz', FFFF), ('direction', DIR), ('multiplier', MULT)),
    _it(3, 'ZERO SEARCH PROCEDURE', '4.1.9',
        ('frequency_code', FF2), ('ramp_code', RR), ('direction', DIR), ('slow_code', FF3)),
    _it(57, 'ELECTRONIC CAM SETTING', '4.1.10', ('enable', BIT), ('position', POS32)),
    _it(58, 'HARDWARE OUTPUT SETTING', '4.1.11', ('output', OUT), ('value', BIT)),
    _it(65, 'TIME DELAY', '4.1.12', ('delay_ms', DELAY)),
    _it(0, 'NULL', '4.1.13'),
    _it(63, 'CONDITIONAL JUMP', '4.1.14', ('input', JMPIN), ('value', BIT), ('jump_cell', CELL)),
    _it(69, 'INTERRUPTED PROGRAM RECOVERY', '4.1.15'),
    _it(5, 'DELAYED STOP', '4.1.16', ('frequency_code', FF2), ('ramp_code', RR),
        ('direction', DIR), ('stop_steps', DIST), ('multiplier', MULT)),
    _it(70, 'CURRENT ON / CURRENT OFF', '4.1.17', ('on', BIT)),
    _it(61, 'OPENING LOOP', '4.1.18', ('repetitions', LOOPS)),
    _it(62, 'CLOSING LOOP', '4.1.19', ('loop_cell', CELL)),
    _it(60, 'ABSOLUTE POSITION COUNTER RESET', '4.1.20'),
)}
assert len(INSTRUCTION_TYPES) == 20      # §2.1 "20 different types of recognized instructions"

INDEXED_RUNS = frozenset((1, 31, 11, 21))
FREE_RUNS = frozenset((2, 32, 12, 22))
RAMPED_RUNS = frozenset((1, 31, 2, 32, 5))
UNRAMPED_RUNS = frozenset((11, 21, 12, 22))
MOTION_CODES = INDEXED_RUNS | FREE_RUNS | {3, 5}


@dataclasses.dataclass(frozen=True)
class Instruction:
    """The content of one memory cell: code, parameters in the manual's order, next cell DDD."""

    code: int
    params: tuple
    next_cell: int = END_OF_PROGRAM

    @classmethod
    def make(cls, code: int, next_cell: int = END_OF_PROGRAM, **fields) -> 'Instruction':
        """Build from named fields (INSTRUCTION_TYPES[code].field_names); checks ranges."""
        t = instruction_type(code)
        missing = [n for n in t.field_names if n not in fields]
        extra = [n for n in fields if n not in t.field_names]
        if extra or (missing and not (code == 57 and missing == ['position'])):
            raise FrameSyntaxError(f'instruction {code:02d} ({t.name}) has fields '
                                   f'{t.field_names}, got {tuple(fields)}')
        values = [fields.get(n) for n in t.field_names]
        if code in (21, 22):
            values[0] = table4_floor(values[0])     # what the drive stores (§4.1.6 Note)
        instr = cls(code, tuple(values), next_cell)
        instr.encode()        # range check
        return instr

    @property
    def type(self) -> InstructionType:
        return instruction_type(self.code)

    def get(self, field: str) -> Any:
        return self.params[self.type.field_names.index(field)]

    @property
    def frequency_hz(self) -> int | None:
        """Step frequency of a run instruction (before x4), None for others."""
        names = self.type.field_names
        if 'frequency_x100' in names:
            return self.get('frequency_x100') * 100
        if 'frequency_hz' in names:
            return self.get('frequency_hz')
        if 'frequency_code' in names:
            table = TABLE3_HZ if self.code in (11, 12) else TABLE2_HZ
            return table[self.get('frequency_code')]
        return None

    def encode(self) -> str:
        """'CC,<params>,DDD' as in a WN string after the cell (and in a QM answer)."""
        t = self.type
        parts = [f'{self.code:02d}']
        for (name, kind), value in zip(t.fields, self.params):
            if value is None and self.code == 57 and name == 'position':
                continue      # §8 A13: cam disabled without a position
            parts.append(kind.write(value, f'{t.code:02d} {name}'))
        parts.append(NEXT.write(self.next_cell, 'next cell DDD'))
        return ','.join(parts)

    @classmethod
    def parse(cls, tokens: list[str]) -> 'Instruction':
        """From the tokens after the cell: CC, the parameters, DDD (optional for 69)."""
        if not tokens or not re.fullmatch(r'\d{2}', tokens[0]):
            raise FrameSyntaxError(f'instruction code {tokens[:1]} is not 2 digits')
        code = int(tokens[0])
        t = INSTRUCTION_TYPES.get(code)
        if t is None:
            raise FrameSyntaxError(f'instruction code {tokens[0]} does not exist (§4.1)')
        rest = tokens[1:]
        n = len(t.fields)
        if code == 69 and len(rest) == 0:
            rest = ['000']            # §4.1.15 example '14WN,220,69' has no DDD
        if code == 57 and len(rest) == n and rest[0] == '0':
            rest = [rest[0], None, rest[1]]     # §8 A13 'V=0' without a position
        if len(rest) != n + 1:
            raise FrameSyntaxError(f'instruction {tokens[0]} ({t.name}) takes {n} parameters '
                                   f'and DDD, got {len(rest)} fields')
        values = []
        for (name, kind), token in zip(t.fields, rest[:-1]):
            values.append(None if token is None else kind.read(token, f'{tokens[0]} {name}'))
        next_cell = NEXT.read(rest[-1], 'next cell DDD')
        if code in (21, 22):
            values[0] = table4_floor(values[0])     # §4.1.6 Note: stored as the real frequency
        return cls(code, tuple(values), next_cell)


def instruction_type(code: int) -> InstructionType:
    try:
        return INSTRUCTION_TYPES[code]
    except KeyError:
        raise FrameSyntaxError(f'instruction code {code} does not exist (§4.1)') from None


# Frames -----------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Frame:
    """One string without its terminator. `args` by code:

    WN (cell, Instruction)         WS (preset, value, kkk|None)   PS (cell,)   SA (counter,)
    SO (output, bit)               SC (enable, position|None)     QS (preset,) QI (input,)
    QO (output,)  QM (cell,)       CY CN EE ES RA QA QC QE ()
    answers: Y N ()                QA (counter,)   QS (preset, value, kkk|None)
             QI/QO (name, bit)     QM (cell, Instruction)   QC (enable, position|None)
             QE (error_code, cell)
    """

    address: int
    code: str
    args: tuple = ()

    @property
    def broadcast(self) -> bool:
        return self.address == BROADCAST


def _address(text: str) -> int:
    if len(text) < 4 or not text[:2].isdigit():
        raise AddressError(f'{text!r} does not start with a 2-digit address')
    address = int(text[:2])
    if not (ADDRESS_MIN <= address <= ADDRESS_MAX or address == BROADCAST):
        raise AddressError(f'address {text[:2]} is neither 00..47 nor 99')
    return address


def _strip(text: str | bytes, tolerant: bool) -> str:
    if isinstance(text, (bytes, bytearray)):
        text = bytes(text).decode('ascii', errors='replace')
    if text.endswith('\r'):
        text = text[:-1]
    if tolerant and text[-1:] in ('.', ','):
        text = text[:-1]      # §8 A1: the manual's '.'/',' before the terminator
    return text


_PRESET_VALUE = {
    'AD': (r'\d{1,2}', int, _in(ADDRESS_MIN, ADDRESS_MAX)),
    'IN': (r'\d', int, _in(0, 3)),
    'RS': (r'[DB]\d', str, _one_of(tuple(RESOLUTIONS))),
    'EQ': (r'\d', int, _in(0, 1)),
    'ES': (r'\d', int, _in(0, 1)),
    'RD': (r'\d{1,3}', int, _in(0, RD_MAX_MS, ' ms')),
    'CM': (r'\d', int, _in(0, 2)),
}


def _preset(preset: str, value_text: str, kkk_text: str | None, what: str) -> tuple:
    if preset not in _PRESET_VALUE:
        raise FrameSyntaxError(f'{what}: preset {preset!r} is not one of {", ".join(PRESETS)}')
    pattern, parse, check = _PRESET_VALUE[preset]
    if not re.fullmatch(pattern, value_text):
        raise FrameSyntaxError(f'{what}: {preset} value {value_text!r} has the wrong form')
    value = parse(value_text)
    why = check(value)
    if why:
        raise RangeError(f'{what}: {preset} {value_text} {why}')
    kkk = None
    if preset == 'CM' and value == CM_CYCLIC:
        if kkk_text is None:
            raise FrameSyntaxError(f'{what}: CM 2 needs the working range kkk (§4.2.2.6)')
        if not re.fullmatch(r'\d{1,7}', kkk_text):
            raise FrameSyntaxError(f'{what}: kkk {kkk_text!r} is not a number')
        kkk = int(kkk_text)
        if not 1 <= kkk <= CYCLIC_RANGE_MAX:
            raise RangeError(f'{what}: kkk {kkk} outside 1..{CYCLIC_RANGE_MAX}')
    elif kkk_text is not None:
        raise FrameSyntaxError(f'{what}: {preset} takes no third parameter')
    return preset, value, kkk


def _fmt_preset(preset: str, value: Any, kkk: int | None, what: str) -> str:
    text = f'{value:02d}' if preset == 'AD' else str(value)
    _preset(preset, text, None if kkk is None else str(kkk), what)        # range check
    return f'{preset},{text}' + ('' if kkk is None else f',{kkk}')


def _name(token: str, allowed: tuple[str, ...], what: str) -> str:
    if token not in allowed:
        raise FrameSyntaxError(f'{what}: {token!r} is not one of {", ".join(allowed)}')
    return token


def parse_request(text: str | bytes, tolerant: bool = True) -> Frame:
    """A host string as the drive reads it; raises AddressError / FrameSyntaxError / RangeError."""
    text = _strip(text, tolerant)
    address = _address(text)
    body = text[2:]
    code = body[:2]
    if code not in HOST_CODES:
        raise FrameSyntaxError(f'unknown code {code!r}')
    tokens = body.split(',')
    if tokens[0] != code:
        raise FrameSyntaxError(f'{code}: expected a comma after the code')
    p = tokens[1:]
    what = code

    def count(n: int) -> None:
        if len(p) != n:
            raise FrameSyntaxError(f'{code} takes {n} parameter(s), got {len(p)}')

    if code == 'WN':
        if len(p) < 2:
            raise FrameSyntaxError('WN needs BBB, CC, parameters and DDD')
        cell = CELL.read(p[0], 'WN cell BBB')
        return Frame(address, code, (cell, Instruction.parse(p[1:])))
    if code == 'WS':
        if len(p) not in (2, 3):
            raise FrameSyntaxError(f'WS takes VV,nnn[,kkk], got {len(p)} parameters')
        return Frame(address, code, _preset(p[0], p[1], p[2] if len(p) == 3 else None, what))
    if code in ('CY', 'CN', 'EE', 'ES', 'RA', 'QA', 'QC', 'QE'):
        count(0)
        return Frame(address, code)
    if code in ('PS', 'QM'):
        count(1)
        return Frame(address, code, (CELL.read(p[0], f'{code} cell'),))
    if code == 'SA':
        count(1)
        if not re.fullmatch(r'[+-]?\d{1,10}', p[0]):
            raise FrameSyntaxError(f'SA value {p[0]!r} is not a number')
        value = int(p[0])
        if not COUNTER_MIN <= value <= COUNTER_MAX:
            raise RangeError(f'SA value {value} outside {COUNTER_MIN}..{COUNTER_MAX}')
        return Frame(address, code, (value,))
    if code == 'SO':
        count(2)
        return Frame(address, code, (_name(p[0], SETTABLE_OUTPUTS, 'SO output'),
                                     BIT.read(p[1], 'SO value')))
    if code == 'SC':
        if len(p) == 1 and p[0] == '0':
            return Frame(address, code, (0, None))       # §8 A13
        count(2)
        return Frame(address, code, (BIT.read(p[0], 'SC V'), POS32.read(p[1], 'SC position')))
    if code == 'QS':
        count(1)
        return Frame(address, code, (_name(p[0], PRESETS, 'QS preset'),))
    if code == 'QI':
        count(1)
        return Frame(address, code, (_name(p[0], READABLE_INPUTS, 'QI input'),))
    if code == 'QO':
        count(1)
        return Frame(address, code, (_name(p[0], READABLE_OUTPUTS, 'QO output'),))
    raise FrameSyntaxError(f'unknown code {code!r}')       # pragma: no cover


def encode_request(frame: Frame) -> bytes:
    """Canonical bytes of a host string; refuses what the drive would answer N to."""
    a, code, args = frame.address, frame.code, frame.args
    if not (ADDRESS_MIN <= a <= ADDRESS_MAX or a == BROADCAST):
        raise RangeError(f'address {a} is neither 0..47 nor 99')
    if a == BROADCAST and code not in BROADCAST_CODES:
        raise RangeError(f'{code} may not be broadcast (§4.2/§4.3); only '
                         f'{", ".join(sorted(BROADCAST_CODES))}')
    if code == 'WN':
        cell, instr = args
        body = f'WN,{CELL.write(cell, "WN cell")},{instr.encode()}'
    elif code == 'WS':
        preset, value, kkk = (tuple(args) + (None,))[:3]
        body = 'WS,' + _fmt_preset(preset, value, kkk, 'WS')
    elif code in ('CY', 'CN', 'EE', 'ES', 'RA', 'QA', 'QC', 'QE'):
        body = code
    elif code in ('PS', 'QM'):
        body = f'{code},{CELL.write(args[0], code + " cell")}'
    elif code == 'SA':
        value = int(args[0])
        if not COUNTER_MIN <= value <= COUNTER_MAX:
            raise RangeError(f'SA value {value} outside {COUNTER_MIN}..{COUNTER_MAX}')
        body = f'SA,{value}'          # §8 A6: plain digits, '-' for negatives
    elif code == 'SO':
        body = f'SO,{_name(args[0], SETTABLE_OUTPUTS, "SO output")},{BIT.write(args[1], "SO")}'
    elif code == 'SC':
        enable, position = args
        body = f'SC,{BIT.write(enable, "SC V")},{POS32.write(position or 0, "SC position")}'
    elif code == 'QS':
        body = f'QS,{_name(args[0], PRESETS, "QS preset")}'
    elif code == 'QI':
        body = f'QI,{_name(args[0], READABLE_INPUTS, "QI input")}'
    elif code == 'QO':
        body = f'QO,{_name(args[0], READABLE_OUTPUTS, "QO output")}'
    else:
        raise FrameSyntaxError(f'unknown code {code!r}')
    return f'{a:02d}{body}'.encode('ascii') + TERMINATOR


def encode_answer(frame: Frame) -> bytes:
    """Canonical bytes of a drive answer (simulator side)."""
    a, code, args = frame.address, frame.code, frame.args
    head = f'{a:02d}{code}'
    if code in ('Y', 'N'):
        body = ''
    elif code == 'QA':
        body = f',{args[0]:+d}'
    elif code == 'QS':
        preset, value, kkk = args
        body = ',' + _fmt_preset(preset, value, kkk, 'QS answer')
    elif code in ('QI', 'QO'):
        body = f',{args[0]},{args[1]}'
    elif code == 'QM':
        body = f',{args[0]:03d},{args[1].encode()}'
    elif code == 'QC':
        body = ',0' if not args[0] else f',1,{args[1]:+d}'
    elif code == 'QE':
        body = f',{args[0]:02d},{args[1]:03d}'
    else:
        raise FrameSyntaxError(f'no answer form for {code!r}')
    return (head + body).encode('ascii') + TERMINATOR


def parse_answer(text: str | bytes, request: Frame, tolerant: bool = True) -> Frame:
    """A drive answer to `request` (host side); raises ProtocolError when it does not fit."""
    text = _strip(text, tolerant)
    if len(text) < 3 or not text[:2].isdigit():
        raise FrameSyntaxError(f'answer {text!r} does not start with an address')
    address = int(text[:2])
    if address != request.address:
        raise AddressError(f'answer {text!r} from address {address:02d}, '
                           f'expected {request.address:02d}')
    body = text[2:]
    code = request.code
    if body == 'Y' and code in REQUEST_CODES:
        # §4.4.1: Y confirms a command or an instruction; a data request is answered with its
        # data (§4.3), or N (§4.4.2)
        raise FrameSyntaxError(f'answer {text!r} to the data request {code}: Y confirms '
                               'commands only (§4.4.1)')
    if body in ('Y', 'N'):
        return Frame(address, body)
    if code not in REQUEST_CODES or not body.startswith(code + ','):
        raise FrameSyntaxError(f'answer {text!r} does not fit the request {code}')
    p = body.split(',')[1:]
    try:
        if code == 'QA':
            if len(p) != 1 or not re.fullmatch(r'[+-]?\d{1,10}', p[0]):
                raise FrameSyntaxError(f'QA answer {text!r} has no signed counter')
            return Frame(address, code, (int(p[0]),))
        if code == 'QS':
            if len(p) not in (2, 3) or p[0] != request.args[0]:
                raise FrameSyntaxError(f'QS answer {text!r} does not fit QS,{request.args[0]}')
            kkk = p[2] if len(p) == 3 else None
            if p[0] == 'CM' and p[1] == '2' and kkk is None:
                return Frame(address, code, ('CM', 2, None))     # §8 A12: kkk not echoed
            return Frame(address, code, _preset(p[0], p[1], kkk, 'QS answer'))
        if code in ('QI', 'QO'):
            if len(p) != 2 or p[0] != request.args[0]:
                raise FrameSyntaxError(f'{code} answer {text!r} does not fit the request')
            return Frame(address, code, (p[0], BIT.read(p[1], f'{code} value')))
        if code == 'QM':
            cell = CELL.read(p[0], 'QM cell')
            if cell != request.args[0]:
                raise FrameSyntaxError(f'QM answer for cell {cell}, asked {request.args[0]}')
            return Frame(address, code, (cell, Instruction.parse(p[1:])))
        if code == 'QC':
            if p == ['0']:
                return Frame(address, code, (0, None))
            if len(p) != 2 or p[0] != '1':
                raise FrameSyntaxError(f'QC answer {text!r} has the wrong form')
            return Frame(address, code, (1, POS32.read(p[1], 'QC position')))
        if code == 'QE':
            if len(p) != 2 or not re.fullmatch(r'\d{2}', p[0]) or not re.fullmatch(r'\d{3}', p[1]):
                raise FrameSyntaxError(f'QE answer {text!r} has the wrong form')
            return Frame(address, code, (int(p[0]), int(p[1])))
    except RangeError as e:
        raise FrameSyntaxError(f'answer {text!r}: {e}') from None
    raise FrameSyntaxError(f'answer {text!r} does not fit the request {code}')  # pragma: no cover


# Timing (§3) ------------------------------------------------------------------------------------
def char_time_s(baudrate: int = BAUDRATE, bits_per_char: int = BITS_PER_CHAR) -> float:
    return bits_per_char / baudrate


def turnaround_s(code: str) -> float:
    """§3: 1.5 ms from the last host character to the first answer character, 12 ms for WN."""
    return TURNAROUND_WN_S if code == 'WN' else TURNAROUND_S


_QS_MAX = {'AD': 11, 'IN': 10, 'RS': 11, 'EQ': 10, 'ES': 10, 'RD': 12, 'CM': 18}


def max_answer_chars(request: Frame) -> int:
    """Longest answer to `request`, terminator included (§3: 'consider the maximum length');
    0 for a broadcast, which nobody answers."""
    if request.broadcast:
        return 0
    code = request.code
    if code not in REQUEST_CODES:
        return 4                                   # 'AAY\r'
    return {'QA': 17,                              # 'AAQA,-2147483648\r'
            'QS': _QS_MAX.get(request.args[0] if request.args else 'CM', 18),
            'QI': 10, 'QO': 10,                    # 'AAQI,I0,1\r'
            'QM': 35,                              # 'AAQM,BBB,31,FFF,RR,-8388607,x1,DDD\r'
            'QC': 19,                              # 'AAQC,1,-2147483648\r'
            'QE': 12}[code]                        # 'AAQE,50,212\r'


def transaction_time_s(tx_chars: int, rx_chars: int, code: str = 'QA', rd_ms: float = 0.0,
                       char_s: float = CHAR_TIME_S, margin: bool = True) -> float:
    """§3: T = N_tx * t_char + turnaround (+ RD, §4.2.2.5) + N_rx * t_char + 4 ms margin.

    With char_s=MANUAL_CHAR_TIME_S and rd_ms=0 this gives the manual's figures (19.02 ms for
    '00PS,100' -> '00Y', 26.3 ms for '08QA' -> '08QA,+10854000')."""
    t = tx_chars * char_s + (turnaround_s(code) + rd_ms / 1000.0 if rx_chars else 0.0)
    return t + rx_chars * char_s + (MARGIN_S if margin else 0.0)
