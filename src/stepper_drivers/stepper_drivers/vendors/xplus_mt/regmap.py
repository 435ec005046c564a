"""R.T.A. X-PLUS MT (B4/S4) Modbus TCP register map: pure data and the 32-bit word codec.

Shared by the driver (`vendors/xplus_mt/`) and the simulator (`stepper_sim/xplus_mt/sim.py`);
no behaviour lives here. Source: manual `rta_xplus_mt_modbus_tcp.txt`, Appendix 1 "Registers
Complete Table" (App.1) merged with the chapter-13 tables (T15 configuration/identification/
service, T16 motion, T20 drive settings, T25 I/O, T26 homing). Defaults come from App.1; where
App.1 or a table contradicts the register's own description, the comment on the entry says which
source won and why (spec/xplus_mt.md §11 ambiguities A1-A30).

Addresses are entity (PDU) addresses, used unchanged by a Modbus client (§11 "Which address must
be used"): the Status Word is PDU address 1001. A 32-bit register is one entry at the lower address
of its pair; in either word order it occupies (address, address + 1) (§11 "Data Format", App.1
LE/BE columns).
"""

from __future__ import annotations

import logging
from typing import Sequence

from ...protocol.modbus import Register

logger = logging.getLogger(__name__)


def _r(address, name, dtype, access, default, lo, hi, unit='', storable=False, allowed=()):
    """One App.1 row: `access` as App.1 prints it ('RO', 'RW'); `storable`: App.1 '**', saved by
    0x6173 in 1260. A register's str() is 'NAME (address)', e.g. 'STATUS_WORD (1001)'."""
    return Register(name=name, address=address, dtype=dtype, access=access.lower(),
                    default=default, min=lo, max=hi, unit=unit, storable=storable,
                    allowed=tuple(allowed))


I32_MIN, I32_MAX = -(1 << 31), (1 << 31) - 1
U32_MAX = (1 << 32) - 1

# Output Config codes listed by T23 (S4) and T25 "B4" (the first "Table 25"); 17 is in both
# lists with different meanings. Any other code is not documented.
OUTPUT_CONFIG_S4 = (1, 5, 7, 17, 21, 23, 33, 38)
OUTPUT_CONFIG_B4 = (3, 7, 13, 17, 35, 36, 39)

_REGISTER_LIST = (
    # --- Motion registers: T16, App.1 page 1 -------------------------------------------------
    _r(1001, 'STATUS_WORD', 'u16', 'RO', 0, 0x0000, 0xFFFF, 'bitfield'),  # default '--'
    # T16: I16 min 1; App.1: I16 min 0. 0 = no mode selected (default 0 in both).
    _r(1002, 'MODE_OF_OPERATION_DISPLAY', 'i16', 'RO', 0, 0, 6),
    _r(1004, 'POSITION_ACTUAL_VALUE', 'i32', 'RO', 0, I32_MIN, I32_MAX, 'steps'),
    # A16: T15/App.1 print 0000..8611, a copy of the Error Code range; §13 "Register 1006": 0 or 1.
    _r(1006, 'ERROR_REGISTER', 'u16', 'RO', 0, 0, 1),
    _r(1007, 'ERROR_CODE', 'u16', 'RO', 0x0000, 0x0000, 0x8611, 'code'),  # T15 0x0000..0x8611
    # T25 U32, App.1 I32; a bitfield with bits up to 31 (§13 "Registers 1008-1009"): U32.
    _r(1008, 'DIGITAL_INPUT', 'u32', 'RO', 0, 0, U32_MAX, 'bitfield'),
    # A13: table max 0x01F0 0001 does not match the bit table (bit 0 brake, 16-19 O0-O3).
    _r(1010, 'DIGITAL_OUTPUT', 'u32', 'RO', 0, 0, U32_MAX, 'bitfield'),
    _r(1014, 'TOUCH_PROBE_NEG_VALUE', 'i32', 'RO', 0, I32_MIN, I32_MAX, 'steps'),
    _r(1016, 'TOUCH_PROBE_POS_VALUE', 'i32', 'RO', 0, I32_MIN, I32_MAX, 'steps'),
    # App.1 min 0x0087 / max 0 (swapped); T25 0..0x0087 omits bit 6, which §13 "Register 1018"
    # defines (bits 0, 1, 2, 6, 7): 0..0x00C7.
    _r(1018, 'TOUCH_PROBE_STATUS', 'u16', 'RO', 0, 0, 0x00C7, 'bitfield'),
    # A8: T16/App.1 I32 min 0, but PV changes "even the direction of the motion" (§13 "Profile
    # Velocity Mode"): signed, +-800000 Hz.
    _r(1020, 'VELOCITY_ACTUAL_VALUE', 'i32', 'RO', 0, -800_000, 800_000, 'Hz'),
    _r(1040, 'CONTROL_WORD', 'u16', 'RW', 0x0000, 0x0000, 0xFFFF, 'bitfield'),
    # App.1 U16 0..6, T16 I16 1..6. Only 1, 3, 6 are modes (§12 "Mode of Operation"); 0 is the
    # power-on value. 2, 4, 5 have no meaning: refused.
    _r(1041, 'MODE_OF_OPERATION', 'i16', 'RW', 0, 0, 6, allowed=(0, 1, 3, 6)),
    _r(1042, 'TARGET_POSITION', 'i32', 'RW', 0, I32_MIN, I32_MAX, 'steps'),
    # T17 types it U32; T16/App.1 I32 0..800000.
    _r(1044, 'PROFILE_VELOCITY', 'i32', 'RW', 24_000, 0, 800_000, 'Hz'),
    _r(1046, 'PROFILE_ACCELERATION', 'i32', 'RW', 640_000, 2000, 10_000_000, 'Hz/s'),
    # A8: App.1 min 0 (T18 even U32), signed per the PV text (see 1020).
    _r(1048, 'TARGET_VELOCITY', 'i32', 'RW', 0, -800_000, 800_000, 'Hz'),
    # --- Homing registers: T26, T19, App.1 ---------------------------------------------------
    # App.1 prints min 37 / max 0 (swapped); T26 U16 0..37; T19 types it I8. Valid methods:
    # HOMING_METHODS (§13 "Homing Mode", "Register 1050"); 0 = power-on value, no method.
    _r(1050, 'HOMING_METHOD', 'u16', 'RW', 0, 0, 37),
    _r(1052, 'HOMING_SPEED_SEARCH_SWITCH', 'u32', 'RW', 16_001, 16_001, 400_000, 'Hz'),
    _r(1054, 'HOMING_SPEED_SEARCH_ZERO', 'u32', 'RW', 0, 0, 16_000, 'Hz'),
    _r(1056, 'HOMING_ACCELERATION', 'u32', 'RW', 2000, 2000, 10_000_000, 'Hz/s'),
    # App.1 -2147483647..2147483648 is a misprint (2147483648 does not fit an I32); T26 full I32.
    _r(1058, 'HOMING_OFFSET', 'i32', 'RW', 0, I32_MIN, I32_MAX, 'steps'),
    # --- Motion registers, continued ---------------------------------------------------------
    _r(1062, 'VELOCITY_WINDOW', 'u16', 'RW', 21_300, 0, 65_535, 'Hz'),
    _r(1063, 'VELOCITY_WINDOW_TIME', 'u16', 'RW', 50, 0, 65_535, 'ms'),
    _r(1064, 'VELOCITY_THRESHOLD', 'u16', 'RW', 21_300, 0, 65_535, 'Hz'),
    _r(1065, 'VELOCITY_THRESHOLD_TIME', 'u16', 'RW', 50, 0, 65_535, 'ms'),
    # App.1 min 37 / max 40060 and T25 0..37 both disagree with the bits §13 "Register 1066"
    # defines (0 enable, 2 index source, 4 positive edge, 5 negative edge): 0..0x35.
    _r(1066, 'TOUCH_PROBE_FUNCTION', 'u16', 'RW', 0, 0, 0x35, 'bitfield'),
    _r(1067, 'CONTROL_WORD_FROM_IO', 'u16', 'RW', 0x0000, 0x0000, 0xFFFF, 'code'),
    # App.1 only; T16 calls 1068-1071 "Non Utilizzato" (not used) and no text describes them.
    _r(1068, 'MINIMUM_POSITION_RANGE_LIMIT', 'i32', 'RW', 0, I32_MIN, I32_MAX, 'steps'),
    _r(1070, 'MAXIMUM_POSITION_RANGE_LIMIT', 'i32', 'RW', 0, I32_MIN, I32_MAX, 'steps'),
    _r(1072, 'PROFILE_DECELERATION', 'i32', 'RW', 640_000, 2000, 10_000_000, 'Hz/s'),
    # A19: T16/App.1 RO although the text says "it is possible to set" it; the tables win here.
    _r(1074, 'MAX_MOTOR_SPEED', 'i32', 'RO', 0, 0, 400_000, 'Hz'),
    # --- Drive setting registers: T20, App.1 page 2 ('**' = storable) --------------------------
    _r(1080, 'CURRENT_RATIO', 'u16', 'RW', 70, 0, 120, '%', storable=True),
    _r(1081, 'STEP_REVOLUTION', 'u16', 'RW', 12_800, 12_800, 12_800, 'steps/rev', storable=True),
    # T20 0..0 and 1..1; App.1 0..1 (0=OFF 1=ON per the text).
    _r(1082, 'CURRENT_EQUALIZATION', 'u16', 'RW', 0, 0, 1, storable=True),
    _r(1083, 'CURRENT_REDUCTION', 'u16', 'RW', 1, 0, 1, storable=True),
    # T20/App.1 min 1, but §13 "Register 1084" lists code 0 (0.9 deg) as valid: 0..5.
    _r(1084, 'ENCODER_WINDOW', 'u16', 'RW', 3, 0, 5, 'code', storable=True),
    # §13 "Register 1085": codes 0x00, 0x01, 0x02, 0x11 only.
    _r(1085, 'FOLLOWING_ERROR_REACTION_CODE', 'u16', 'RW', 0, 0, 17, 'code', storable=True,
       allowed=(0, 1, 2, 17)),
    _r(1086, 'POSITION_ERROR_RESET', 'u16', 'RW', 0, 0, 2, 'code'),
    # §13 "Register 1087" tabulates 0..31 (O0..O4); tables and hardware (O0..O2): 0..15.
    _r(1087, 'SET_OUTPUT', 'u16', 'RW', 0, 0, 15, 'bitfield'),
    # A13: max 15 excludes the S4 IC7 bit (0x80, STO status in DI bit 24): 0..0x8F.
    _r(1088, 'INPUT_CONFIG', 'u16', 'RW', 15, 0, 0x8F, 'bitfield', storable=True),
    # Default "1 per S4 3 per B4" (1 for S4, 3 for B4): the S4 value here; codes per T23/T25.
    _r(1089, 'OUTPUT_CONFIG', 'u16', 'RW', 1, 0, 39, 'code', storable=True,
       allowed=tuple(sorted(set(OUTPUT_CONFIG_S4 + OUTPUT_CONFIG_B4)))),
    # App.1 default 286151, 286151..782317; T20 default 712617, 0..999999. The custom-motor form
    # 0xABCD < 0x8000 (§13 "Registers 1090-1091") lies below 286151, so T20's range is used.
    _r(1090, 'MOTOR_CODE', 'u32', 'RW', 286_151, 0, 999_999, 'code', storable=True),
    _r(1092, 'REVOLUTION_DIRECTION', 'u16', 'RW', 0, 0, 1, storable=True),
    # A19: the text says default 0 ms for 1093/1094 and 30 ms for 1096; App.1/T20 defaults kept.
    _r(1093, 'BRAKE_DELAY_LOCK', 'u16', 'RW', 100, 0, 1000, 'ms', storable=True),
    _r(1094, 'BRAKE_DELAY_UNLOCK', 'u16', 'RW', 100, 0, 1000, 'ms', storable=True),  # "RW RW"
    _r(1095, 'BRAKE_DELAY_CURRENT_ON', 'u16', 'RW', 0, 0, 1000, 'ms', storable=True),
    _r(1096, 'BRAKE_DELAY_AZIO_READY', 'u16', 'RW', 230, 0, 1000, 'ms', storable=True),
    # A19: tables 0..1; §13 "Register 1097": 0 = off, else timeout 100..32000 ms.
    _r(1097, 'COUNTER_WATCHDOG', 'u16', 'RW', 0, 0, 32_000, 'ms', storable=True),
    # App.1 0..0xFFFF; T20 and §13 "Register 1104": 10..1000 ms.
    _r(1104, 'BUSY_DELAY', 'u16', 'RW', 80, 10, 1000, 'ms'),
    _r(1106, 'ENABLE_SW_BIT_14', 'u16', 'RW', 0, 0, 1),
    _r(1107, 'ENABLE_SW_BIT_15', 'u16', 'RW', 0, 0, 1),
    # A19: tables max 1; §13 "Register 1108" defines 0..3.
    _r(1108, 'AUTO_SYNC_ENABLE', 'u16', 'RW', 0, 0, 3, 'code'),
    # §13 "Register 1109": only these values.
    _r(1109, 'AUTO_SYNC_KV', 'u16', 'RW', 100, 0, 300, allowed=(0, 50, 100, 150, 200, 250, 300)),
    _r(1110, 'AUTO_SYNC_WINDOW', 'u32', 'RW', 32_000, 1, 64_000, 'steps'),
    _r(1112, 'CURRENT_REDUCTION_RATIO', 'u16', 'RW', 50, 0, 100, '%'),
    # §13 "Register 1113": only these values (samples of 1 ms).
    _r(1113, 'VELOCITY_TOTAL_SAMPLE', 'u16', 'RW', 100, 1, 200, 'ms',
       allowed=(1, 2, 4, 5, 8, 10, 20, 25, 40, 50, 100, 200)),
    _r(1114, 'RESET_ENCODER_ON_FIRST_POWER_UP', 'u16', 'RW', 0, 0, 1),
    _r(1115, 'HARD_STOP_HOMING_DISENGAGING_STEPS', 'u16', 'RW', 64, 0, 255, 'steps'),
    _r(1116, 'POWER_UP_SPEED_LIMIT', 'u16', 'RW', 0, 0, 32_000, 'Hz'),
    # Defaults '--' (they follow from Motor Code): placeholders inside the printed ranges.
    _r(1117, 'CUSTOM_MOTOR_CURRENT_LIMIT', 'u16', 'RO', 4, 1, 4, 'A'),
    _r(1118, 'CUSTOM_MOTOR_PROPORTIONAL_GAIN', 'u16', 'RO', 100, 100, 400, '%'),
    _r(1119, 'CUSTOM_MOTOR_DYNAMIC_BALANCING', 'u16', 'RO', 0, 0, 500, '%'),
    _r(1120, 'CUSTOM_MOTOR_CURRENT_RECYCLING_ENABLE', 'u16', 'RO', 0, 0, 1),
    _r(1121, 'ENCODER_COUNT_PER_REVOLUTION', 'u16', 'RW', 400, 400, 4000, 'CPR'),
    # Default/min/max blank; §13 "Register 1122": 0 at power-on, free use.
    _r(1122, 'USER_DATA_RAM', 'u16', 'RW', 0, 0, 0xFFFF),
    # --- Configuration registers: T15, saved by signature 0x1111 in 1260 --------------------
    _r(1130, 'IP_ADDRESS_FIRST_OCTET', 'u16', 'RW', 192, 0, 255),
    _r(1131, 'IP_ADDRESS_SECOND_OCTET', 'u16', 'RW', 168, 0, 255),
    _r(1132, 'IP_ADDRESS_THIRD_OCTET', 'u16', 'RW', 1, 0, 255),
    _r(1133, 'IP_ADDRESS_FOURTH_OCTET', 'u16', 'RW', 10, 0, 255),
    _r(1134, 'SUBNET_MASK_FIRST_OCTET', 'u16', 'RW', 255, 0, 255),
    _r(1135, 'SUBNET_MASK_SECOND_OCTET', 'u16', 'RW', 255, 0, 255),
    _r(1136, 'SUBNET_MASK_THIRD_OCTET', 'u16', 'RW', 0, 0, 255),
    _r(1137, 'SUBNET_MASK_FOURTH_OCTET', 'u16', 'RW', 0, 0, 255),
    _r(1138, 'GATEWAY_FIRST_OCTET', 'u16', 'RW', 192, 0, 255),
    _r(1139, 'GATEWAY_SECOND_OCTET', 'u16', 'RW', 168, 0, 255),
    _r(1140, 'GATEWAY_THIRD_OCTET', 'u16', 'RW', 1, 0, 255),
    _r(1141, 'GATEWAY_FOURTH_OCTET', 'u16', 'RW', 1, 0, 255),
    # --- Identification registers: T15 -------------------------------------------------------
    _r(1152, 'SOFTWARE_VERSION', 'u32', 'RO', 51, 0, U32_MAX),
    _r(1154, 'PRODUCT_CODE', 'u32', 'RO', 0, 0, U32_MAX),      # default '--'
    _r(1156, 'HARDWARE_VERSION', 'u32', 'RO', 0, 0, U32_MAX),  # default blank
    _r(1158, 'SERIAL_NUMBER', 'u32', 'RO', 0, 0, U32_MAX),     # default '--', per unit
    # §13 "Register 1162": 1 = Little Endian (default), 0 = Big Endian; see encode32.
    _r(1162, 'LITTLE_ENDIAN_BIG_ENDIAN', 'u16', 'RW', 1, 0, 1, 'code'),
    # --- Service registers: T15 --------------------------------------------------------------
    *(_r(1220 + 2 * k, f'DRIVE_ALARM_TIME_{k}', 'u16', 'RO', 0, 0, 0xFFFF, 's')
      for k in range(10)),
    *(_r(1221 + 2 * k, f'DRIVE_ALARM_CODE_{k}', 'u16', 'RO', 0, 0, 0x8611, 'code')
      for k in range(10)),
    _r(1240, 'RESET_ERROR_LOGS', 'u16', 'RW', 0, 0, 1),
    # T15 RO (App.1 RW); "Read MAC Address" is read-only by its name. Modelled as three u16
    # (LSB word, middle, MSB word); App.1's BE column swaps 1250/1252, T15's does not.
    _r(1250, 'READ_MAC_ADDRESS_LSB', 'u16', 'RO', 0, 0, 0xFFFF),
    _r(1251, 'READ_MAC_ADDRESS_MID', 'u16', 'RO', 0, 0, 0xFFFF),
    _r(1252, 'READ_MAC_ADDRESS_MSB', 'u16', 'RO', 0, 0, 0xFFFF),
    # Signature registers read 0 (default 0000). App.1 min=max=0x6173 omits the IP signature
    # that T15 (0x1111..0x6173) and §13 "Register 1260" give; "storage is only executed when a
    # specific signature is written", so only the signatures are allowed.
    _r(1260, 'SAVE_ALL_PARAMETERS', 'u16', 'RW', 0, 0x1111, 0x6173, 'signature',
       allowed=(0x6173, 0x1111)),
    _r(1261, 'RESTORE_ALL_DEFAULT_PARAMETERS', 'u16', 'RW', 0, 0x6F6C, 0x6F6C, 'signature',
       allowed=(0x6F6C,)),
    # T15 only (not in App.1): typed U16 but with LE/BE addresses swapped like a 32-bit pair, so
    # modelled as U32 pairs (best reading: copies of 1152-1153 / 1156-1157; A18).
    _r(1262, 'SOFTWARE_VERSION_1262', 'u32', 'RO', 51, 0, U32_MAX),
    _r(1268, 'HARDWARE_VERSION_1268', 'u32', 'RO', 0, 0, U32_MAX),
)

REGISTERS: dict[str, Register] = {reg.name: reg for reg in _REGISTER_LIST}
BY_ADDRESS: dict[int, Register] = {reg.address: reg for reg in _REGISTER_LIST}
assert len(REGISTERS) == len(BY_ADDRESS) == len(_REGISTER_LIST)

# Every occupied 16-bit address -> its register (both words of a pair).
WORD_OWNER: dict[int, Register] = {
    reg.address + i: reg for reg in _REGISTER_LIST for i in range(reg.words)}

STORABLE = tuple(reg.address for reg in _REGISTER_LIST if reg.storable)  # App.1 '**'
IP_REGISTERS = tuple(range(1130, 1142))   # saved by SAVE_IP_SIGNATURE (§13 "Register 1260")

# §13 "Register 1007". 0x0000 is printed as "Emergency end" (the CANopen EMCY "error reset"
# code); it is what 1007 reads with no error present, so it is shown as no error.
ERROR_CODES: dict[int, str] = {
    0x0000: 'No error (Emergency end)',
    0x2130: 'Error short circuit (or overcurrent on motor phase)',
    0x4310: 'Error drive excessive temperature',
    0x5100: 'Error power supply out of range',
    0x8400: 'Axis speed too high',
    0x8611: 'Motor following error',
}

# §13 "Registers 1220 ÷ 1239": 10 entries, time (s since power-on) at 1220+2k, code at 1221+2k.
ALARM_LOG_FIRST = 1220
ALARM_LOG_LAST = 1239
ALARM_LOG_ENTRIES = 10
ALARM_LOG_RESET = 1240                    # write 1 (§13 "Register 1240")

SAVE_PARAMS_REGISTER = 1260
RESTORE_DEFAULTS_REGISTER = 1261
SAVE_PARAMS_SIGNATURE = 0x6173            # §13 "Register 1260": MSB 0x61, LSB 0x73
SAVE_IP_SIGNATURE = 0x1111                # §13 "Register 1260": store IP, mask, gateway
RESTORE_DEFAULTS_SIGNATURE = 0x6F6C       # §13 "Register 1261": MSB 0x6F, LSB 0x6C
SAVE_HOLD_24V_S = 5.0                     # "Keep the control power (24V) ON more than 5 s"

# §13 "Homing Mode" and "Register 1050". -1/-2 (hard stop, §13 "Register 1115") are named but
# not listed (A7): not offered.
HOMING_METHODS = (3, 4, 5, 6, 19, 20, 21, 22, 35, 37)
HOMING_METHODS_NEED_INDEX = (3, 4, 5, 6)  # "With no encoder motors ... must not be used"
HOMING_METHODS_HOME_SWITCH = (3, 4, 5, 6, 19, 20, 21, 22)
HOMING_METHODS_CURRENT_POSITION = (35, 37)

MODES = {1: 'PROFILE POSITION', 3: 'PROFILE VELOCITY', 6: 'HOMING'}   # §12, §13 "Register 1041"
MODE_PROFILE_POSITION = 1
MODE_PROFILE_VELOCITY = 3
MODE_HOMING = 6

STEPS_PER_REV = 12_800                    # §13 "Register 1081": the only valid value
START_STOP_MAX_HZ = 16_000                # §13 "Motion Profiles": PV <= 16000 Hz -> no ramps

# Register 1162 value <-> word order name (§13 "Register 1162"; A1: the §11 bullet list has the
# names the other way round, the register description, the tables and the example agree with this).
WORD_ORDER_BY_1162 = {1: 'little', 0: 'big'}
REGISTER_1162_BY_WORD_ORDER = {'little': 1, 'big': 0}
WORD_ORDERS = ('little', 'big')


def _check_order(word_order: str) -> None:
    if word_order not in WORD_ORDERS:
        raise ValueError(f'word order {word_order!r}: allowed are little, big')


def encode32(value: int, word_order: str) -> list[int]:
    """Two 16-bit words in address order (A, A+1) for a signed or unsigned 32-bit value.

    'little' (1162 = 1, default): low word at the lower address, so 0x12345678 -> [0x5678,
    0x1234], the manual's example in §11 "Data Format". 'big' (1162 = 0): high word first.
    """
    _check_order(word_order)
    if not I32_MIN <= value <= U32_MAX:
        raise ValueError(f'{value} does not fit 32 bits')
    raw = value & 0xFFFF_FFFF
    low, high = raw & 0xFFFF, raw >> 16
    return [low, high] if word_order == 'little' else [high, low]


def decode32(words: Sequence[int], word_order: str, signed: bool) -> int:
    """Inverse of encode32: words in address order (A, A+1) -> integer."""
    _check_order(word_order)
    if len(words) != 2:
        raise ValueError(f'need 2 words, got {len(words)}')
    first, second = (int(w) & 0xFFFF for w in words)
    low, high = (first, second) if word_order == 'little' else (second, first)
    raw = (high << 16) | low
    if signed and raw & 0x8000_0000:
        raw -= 1 << 32
    return raw


def encode(reg: Register, value: int, word_order: str) -> list[int]:
    """Words for `reg` holding `value` (16-bit: two's complement for i16)."""
    if reg.words == 2:
        return encode32(value, word_order)
    if not -0x8000 <= value <= 0xFFFF:
        raise ValueError(f'{value} does not fit 16 bits')
    return [value & 0xFFFF]


def decode(reg: Register, words: Sequence[int], word_order: str) -> int:
    """Value of `reg` from its words in address order."""
    if reg.words == 2:
        return decode32(words, word_order, reg.signed)
    raw = int(words[0]) & 0xFFFF
    return raw - 0x10000 if reg.signed and raw & 0x8000 else raw
