"""R.T.A. X-MIND K ASCII protocol: the numbers, names and tables of the manual, and its errors.

Section numbers (§4.1.2, Table 5) point into the *X-MIND K series Programmer's manual*
(shared/manuals/rta_xmind_k_serial.txt): addresses and memory cells (§2), the serial line timing
(§3), the step and counter limits (§4.1.1, §4.3.1), Tables 2-5 (§6) and their look-ups, the
presets (§4.2.2), the inputs and outputs, the error codes, the string codes by family (§4), and
`ProtocolError` with its kinds: what every part of the codec raises for a string the drive would
not execute. No codec here: the instructions are `xmind_k_instructions`, the strings `xmind_k`,
which re-exports all of this (driver and simulator import `xmind_k` only). No ROS, no I/O.
"""

from __future__ import annotations

import bisect

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

