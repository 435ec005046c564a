"""R.T.A. X-MIND K ASCII protocol over RS-485: frames, tables, range checks, line timing.

No ROS and no I/O. Shared by the driver (`vendors/xmind_k/`) and the simulator
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

Three files, one contract shared by driver and simulator: the codec range-checks WN/QM
instructions and WS/QS presets with the §4.1 instruction table (`xmind_k_instructions`) and the
§4.2.2/§6 tables (`xmind_k_tables`). This one holds the strings (`Frame`, the request and answer
codecs) and the §3 timing of a transaction, and re-exports the other two: driver and simulator
import `xmind_k` only.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from typing import Any, Callable

from .xmind_k_instructions import (  # noqa: F401 - re-exported: driver and simulator use xk.*
    BIT,
    CELL,
    DELAY,
    DIR,
    DIST,
    FF2,
    FF3,
    FFF,
    FFFF,
    FREE_RUNS,
    INDEXED_RUNS,
    INSTRUCTION_TYPES,
    JMPIN,
    LOOPS,
    MOTION_CODES,
    MULT,
    NEXT,
    OUT,
    POS32,
    RAMPED_RUNS,
    RR,
    STEPS,
    UNRAMPED_RUNS,
    FieldKind,
    Instruction,
    InstructionType,
    _in,
    _one_of,
    instruction_type,
)
from .xmind_k_tables import (  # noqa: F401 - re-exported, as are the instructions
    ADDRESS_MAX,
    ADDRESS_MIN,
    BAUDRATE,
    BITS_PER_CHAR,
    BROADCAST,
    BROADCAST_CODES,
    BUSY_CODES,
    CELL_EEPROM,
    CELL_MAX,
    CELL_MIN,
    CELL_RAM,
    CHAR_TIME_S,
    CM_ABSOLUTE,
    CM_CYCLIC,
    CM_RELATIVE,
    COMMAND_CODES,
    COUNTER_MAX,
    COUNTER_MIN,
    CURRENT_PERCENT,
    CYCLIC_RANGE_MAX,
    END_OF_PROGRAM,
    ERROR_FIELD_OVERFLOW,
    ERROR_NONE,
    ERROR_TEXT,
    HARDWARE_START_CELLS,
    HOST_CODES,
    HR_RAMPED_X100,
    HR_UNRAMPED_MAX_HZ,
    JUMP_INPUTS,
    MANUAL_CHAR_TIME_S,
    MARGIN_S,
    PRESET_DEFAULTS,
    PRESETS,
    RAMP_REFERENCE_HZ,
    RD_DEFAULT_MS,
    RD_MAX_MS,
    READABLE_INPUTS,
    READABLE_OUTPUTS,
    REQUEST_CODES,
    RESOLUTIONS,
    RS_SILENT_S,
    SETTABLE_OUTPUTS,
    STEPS_MAX,
    TABLE2_HZ,
    TABLE3_HZ,
    TABLE4_BANDS,
    TABLE4_HZ,
    TABLE5,
    TERMINATOR,
    TURNAROUND_S,
    TURNAROUND_WN_S,
    X4_RESOLUTIONS,
    AddressError,
    FrameSyntaxError,
    ProtocolError,
    RangeError,
    ramp_acceleration_hz_s,
    ramp_time_s,
    table4_floor,
)

logger = logging.getLogger(__name__)


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


def _count(code: str, p: list[str], n: int) -> None:
    if len(p) != n:
        raise FrameSyntaxError(f'{code} takes {n} parameter(s), got {len(p)}')


def _req_wn(code: str, p: list[str]) -> tuple:
    if len(p) < 2:
        raise FrameSyntaxError('WN needs BBB, CC, parameters and DDD')
    return (CELL.read(p[0], 'WN cell BBB'), Instruction.parse(p[1:]))


def _req_ws(code: str, p: list[str]) -> tuple:
    if len(p) not in (2, 3):
        raise FrameSyntaxError(f'WS takes VV,nnn[,kkk], got {len(p)} parameters')
    return _preset(p[0], p[1], p[2] if len(p) == 3 else None, code)


def _req_bare(code: str, p: list[str]) -> tuple:
    _count(code, p, 0)
    return ()


def _req_cell(code: str, p: list[str]) -> tuple:
    _count(code, p, 1)
    return (CELL.read(p[0], f'{code} cell'),)


def _req_sa(code: str, p: list[str]) -> tuple:
    _count(code, p, 1)
    if not re.fullmatch(r'[+-]?\d{1,10}', p[0]):
        raise FrameSyntaxError(f'SA value {p[0]!r} is not a number')
    value = int(p[0])
    if not COUNTER_MIN <= value <= COUNTER_MAX:
        raise RangeError(f'SA value {value} outside {COUNTER_MIN}..{COUNTER_MAX}')
    return (value,)


def _req_so(code: str, p: list[str]) -> tuple:
    _count(code, p, 2)
    return (_name(p[0], SETTABLE_OUTPUTS, 'SO output'), BIT.read(p[1], 'SO value'))


def _req_sc(code: str, p: list[str]) -> tuple:
    if len(p) == 1 and p[0] == '0':
        return (0, None)                                 # §8 A13
    _count(code, p, 2)
    return (BIT.read(p[0], 'SC V'), POS32.read(p[1], 'SC position'))


def _req_named(allowed: tuple[str, ...], what: str) -> Callable[[str, list[str]], tuple]:
    def parse(code: str, p: list[str]) -> tuple:
        _count(code, p, 1)
        return (_name(p[0], allowed, f'{code} {what}'),)
    return parse


# A host string's parameters by its code: code -> (code, parameters) -> the Frame's args.
_REQUEST_ARGS: dict[str, Callable[[str, list[str]], tuple]] = {
    'WN': _req_wn, 'WS': _req_ws, 'SA': _req_sa, 'SO': _req_so, 'SC': _req_sc,
    **{c: _req_bare for c in ('CY', 'CN', 'EE', 'ES', 'RA', 'QA', 'QC', 'QE')},
    'PS': _req_cell, 'QM': _req_cell,
    'QS': _req_named(PRESETS, 'preset'), 'QI': _req_named(READABLE_INPUTS, 'input'),
    'QO': _req_named(READABLE_OUTPUTS, 'output'),
}


def parse_request(text: str | bytes, tolerant: bool = True) -> Frame:
    """A host string as the drive reads it; raises AddressError / FrameSyntaxError / RangeError."""
    text = _strip(text, tolerant)
    address = _address(text)
    body = text[2:]
    code = body[:2]
    if code not in HOST_CODES or code not in _REQUEST_ARGS:
        raise FrameSyntaxError(f'unknown code {code!r}')
    tokens = body.split(',')
    if tokens[0] != code:
        raise FrameSyntaxError(f'{code}: expected a comma after the code')
    return Frame(address, code, _REQUEST_ARGS[code](code, tokens[1:]))


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


def _ans_qa(text: str, request: Frame, p: list[str]) -> tuple:
    if len(p) != 1 or not re.fullmatch(r'[+-]?\d{1,10}', p[0]):
        raise FrameSyntaxError(f'QA answer {text!r} has no signed counter')
    return (int(p[0]),)


def _ans_qs(text: str, request: Frame, p: list[str]) -> tuple:
    if len(p) not in (2, 3) or p[0] != request.args[0]:
        raise FrameSyntaxError(f'QS answer {text!r} does not fit QS,{request.args[0]}')
    kkk = p[2] if len(p) == 3 else None
    if p[0] == 'CM' and p[1] == '2' and kkk is None:
        return ('CM', 2, None)                           # §8 A12: kkk not echoed
    return _preset(p[0], p[1], kkk, 'QS answer')


def _ans_io(text: str, request: Frame, p: list[str]) -> tuple:
    code = request.code
    if len(p) != 2 or p[0] != request.args[0]:
        raise FrameSyntaxError(f'{code} answer {text!r} does not fit the request')
    return (p[0], BIT.read(p[1], f'{code} value'))


def _ans_qm(text: str, request: Frame, p: list[str]) -> tuple:
    cell = CELL.read(p[0], 'QM cell')
    if cell != request.args[0]:
        raise FrameSyntaxError(f'QM answer for cell {cell}, asked {request.args[0]}')
    return (cell, Instruction.parse(p[1:]))


def _ans_qc(text: str, request: Frame, p: list[str]) -> tuple:
    if p == ['0']:
        return (0, None)
    if len(p) != 2 or p[0] != '1':
        raise FrameSyntaxError(f'QC answer {text!r} has the wrong form')
    return (1, POS32.read(p[1], 'QC position'))


def _ans_qe(text: str, request: Frame, p: list[str]) -> tuple:
    if len(p) != 2 or not re.fullmatch(r'\d{2}', p[0]) or not re.fullmatch(r'\d{3}', p[1]):
        raise FrameSyntaxError(f'QE answer {text!r} has the wrong form')
    return (int(p[0]), int(p[1]))


# A data request's answer by the request's code: (the answer, the request, its parameters) ->
# the Frame's args.
_ANSWER_ARGS: dict[str, Callable[[str, Frame, list[str]], tuple]] = {
    'QA': _ans_qa, 'QS': _ans_qs, 'QI': _ans_io, 'QO': _ans_io, 'QM': _ans_qm, 'QC': _ans_qc,
    'QE': _ans_qe,
}


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
    if code not in REQUEST_CODES or code not in _ANSWER_ARGS or not body.startswith(code + ','):
        raise FrameSyntaxError(f'answer {text!r} does not fit the request {code}')
    try:
        return Frame(address, code, _ANSWER_ARGS[code](text, request, body.split(',')[1:]))
    except RangeError as e:
        raise FrameSyntaxError(f'answer {text!r}: {e}') from None


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
