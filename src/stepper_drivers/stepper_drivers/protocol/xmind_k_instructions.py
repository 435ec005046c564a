"""R.T.A. X-MIND K ASCII protocol: what one memory cell of a program holds (§4.1).

The instruction table (`INSTRUCTION_TYPES`: code, the manual's title, section, parameter
fields), `Instruction` (code, parameters, next cell DDD; made, encoded and parsed with range
checks) and the parameter fields (`FieldKind`: regex, range check, wire form). Section numbers
point into the *X-MIND K series Programmer's manual* (shared/manuals/rta_xmind_k_serial.txt).
The numbers and tables the checks read, and the errors, are `xmind_k_tables`; the strings that
carry an instruction (WN, QM) are `xmind_k`, which re-exports all of this. No ROS, no I/O.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any, Callable

from .xmind_k_tables import (
    CELL_MAX,
    CELL_MIN,
    COUNTER_MAX,
    COUNTER_MIN,
    END_OF_PROGRAM,
    HR_UNRAMPED_MAX_HZ,
    JUMP_INPUTS,
    SETTABLE_OUTPUTS,
    STEPS_MAX,
    TABLE2_HZ,
    TABLE3_HZ,
    FrameSyntaxError,
    RangeError,
    table4_floor,
)


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
