"""X-PLUS MT register map and 32-bit codec against the manual (§11 "Data Format", App.1,
T15-T26)."""

import re

import pytest
from stepper_drivers.vendors.xplus_mt import regmap as m

# (value, little-endian words, big-endian words) in address order A, A+1.
WORDS = [
    (0x12345678, [0x5678, 0x1234], [0x1234, 0x5678]),   # §11 example ("0x12345687" misprint)
    (240000, [0xA980, 0x0003], [0x0003, 0xA980]),        # T17 Target Position
    (-1000, [0xFC18, 0xFFFF], [0xFFFF, 0xFC18]),
    (0, [0, 0], [0, 0]),
    (-(1 << 31), [0x0000, 0x8000], [0x8000, 0x0000]),
    ((1 << 31) - 1, [0xFFFF, 0x7FFF], [0x7FFF, 0xFFFF]),
]


@pytest.mark.parametrize('value,little,big', WORDS)
def test_encode32_both_orders(value, little, big):
    assert m.encode32(value, 'little') == little
    assert m.encode32(value, 'big') == big
    assert m.decode32(little, 'little', signed=True) == value
    assert m.decode32(big, 'big', signed=True) == value


def test_decode32_unsigned():
    assert m.decode32([0xFFFF, 0xFFFF], 'little', signed=False) == 0xFFFF_FFFF
    assert m.encode32(0xFFFF_FFFF, 'little') == [0xFFFF, 0xFFFF]
    assert m.decode32([0x0003, 0xA980], 'big', signed=False) == 240000


def test_codec_refuses_bad_input():
    with pytest.raises(ValueError, match='little, big'):
        m.encode32(1, 'middle')
    with pytest.raises(ValueError, match='32 bits'):
        m.encode32(1 << 32, 'little')
    with pytest.raises(ValueError, match='2 words'):
        m.decode32([1], 'little', signed=False)


def test_register_codec_16_bit_signed():
    reg = m.REGISTERS['MODE_OF_OPERATION_DISPLAY']
    assert m.encode(reg, -1, 'little') == [0xFFFF]
    assert m.decode(reg, [0xFFFF], 'big') == -1
    assert m.decode(m.REGISTERS['STATUS_WORD'], [0xFFFF], 'little') == 0xFFFF


def test_word_order_register_1162():
    reg = m.BY_ADDRESS[1162]
    assert (reg.default, reg.min, reg.max) == (1, 0, 1)
    assert m.WORD_ORDER_BY_1162 == {1: 'little', 0: 'big'}   # §13 "Register 1162"


# App.1 + T15 32-bit pairs (lower address), spec §1.5.
PAIRS = (1004, 1008, 1010, 1014, 1016, 1020, 1042, 1044, 1046, 1048, 1052, 1054, 1056, 1058,
         1068, 1070, 1072, 1074, 1090, 1110, 1152, 1154, 1156, 1158, 1262, 1268)


def test_32_bit_pairs():
    assert tuple(sorted(a for a, r in m.BY_ADDRESS.items() if r.words == 2)) == PAIRS


def test_addresses_do_not_overlap_and_count():
    owned = [r.address + i for r in m.REGISTERS.values() for i in range(r.words)]
    assert len(owned) == len(set(owned)) == len(m.WORD_OWNER)
    assert len(owned) == 137                      # spec §2.8: 133 in App.1 + 4 from T15
    assert len(m.REGISTERS) == 111                # logical parameters incl. 1262/1268 pairs
    assert min(owned) == 1001 and max(owned) == 1269


# Holes listed in spec §2.8 (checked against App.1: no register there).
HOLES = [1000, 1003, 1012, 1013, 1019, *range(1022, 1040), 1051, 1060, 1061,
         *range(1076, 1080), *range(1098, 1104), 1105, *range(1123, 1130), *range(1142, 1152),
         1160, 1161, *range(1163, 1220), *range(1241, 1250), *range(1253, 1260),
         *range(1264, 1268)]


def test_holes_are_not_mapped():
    assert not set(HOLES) & set(m.WORD_OWNER)
    assert set(range(1000, 1270)) == set(HOLES) | set(m.WORD_OWNER)


@pytest.mark.parametrize('reg', list(m.REGISTERS.values()), ids=list(m.REGISTERS))
def test_register_sanity(reg):
    assert re.fullmatch(r'[A-Z][A-Z0-9_]*', reg.name)
    assert reg.dtype in ('u16', 'i16', 'u32', 'i32')
    assert reg.access in ('ro', 'rw', 'wo')
    assert reg.min <= reg.max
    bits = 16 * reg.words
    lo, hi = (-(1 << bits - 1), (1 << bits - 1) - 1) if reg.signed else (0, (1 << bits) - 1)
    assert lo <= reg.min and reg.max <= hi
    assert all(reg.min <= v <= reg.max for v in reg.allowed)
    if reg.unit == 'signature':
        assert reg.default == 0 and not reg.accepts(0)   # reads 0, only signatures act
    else:
        assert reg.min <= reg.default <= reg.max
        assert reg.accepts(reg.default)


def test_storable_registers_are_app1_double_star():
    # App.1 page 2 '**': 1080-1085, 1088-1097 (1090/1091 one pair); 1086/1087 are not.
    assert m.STORABLE == (1080, 1081, 1082, 1083, 1084, 1085, 1088, 1089, 1090, 1092, 1093,
                          1094, 1095, 1096, 1097)
    assert m.IP_REGISTERS == tuple(range(1130, 1142))


def test_key_registers():
    r = m.REGISTERS
    assert (r['STATUS_WORD'].address, r['CONTROL_WORD'].address) == (1001, 1040)
    assert (r['MODE_OF_OPERATION'].address, r['MODE_OF_OPERATION_DISPLAY'].address) == \
        (1041, 1002)
    assert r['TARGET_POSITION'].address == 1042 and r['TARGET_POSITION'].dtype == 'i32'
    assert r['PROFILE_VELOCITY'].default == 24_000
    assert (r['PROFILE_ACCELERATION'].min, r['PROFILE_ACCELERATION'].max) == (2000, 10_000_000)
    assert r['PROFILE_DECELERATION'].address == 1072
    assert r['TARGET_VELOCITY'].min == -800_000           # A8: signed
    assert (r['HOMING_METHOD'].min, r['HOMING_METHOD'].max) == (0, 37)   # App.1 swapped
    assert (r['HOMING_OFFSET'].min, r['HOMING_OFFSET'].max) == (-(1 << 31), (1 << 31) - 1)
    assert (r['HOMING_SPEED_SEARCH_SWITCH'].min, r['HOMING_SPEED_SEARCH_ZERO'].max) == \
        (16_001, 16_000)
    assert r['STEP_REVOLUTION'].default == m.STEPS_PER_REV == 12_800
    assert r['SAVE_ALL_PARAMETERS'].allowed == (0x6173, 0x1111)
    assert r['RESTORE_ALL_DEFAULT_PARAMETERS'].allowed == (0x6F6C,)
    assert r['MODE_OF_OPERATION'].allowed == (0, 1, 3, 6)


def test_error_codes_and_constants():
    assert set(m.ERROR_CODES) == {0x0000, 0x2130, 0x4310, 0x5100, 0x8400, 0x8611}
    assert m.ERROR_CODES[0x8611] == 'Motor following error'
    assert (m.ALARM_LOG_FIRST, m.ALARM_LOG_LAST, m.ALARM_LOG_RESET) == (1220, 1239, 1240)
    assert [m.BY_ADDRESS[a].name for a in (1220, 1221, 1238, 1239)] == [
        'DRIVE_ALARM_TIME_0', 'DRIVE_ALARM_CODE_0', 'DRIVE_ALARM_TIME_9', 'DRIVE_ALARM_CODE_9']
    assert (m.SAVE_PARAMS_SIGNATURE, m.SAVE_IP_SIGNATURE, m.RESTORE_DEFAULTS_SIGNATURE) == \
        (0x6173, 0x1111, 0x6F6C)
    assert m.HOMING_METHODS == (3, 4, 5, 6, 19, 20, 21, 22, 35, 37)
    assert m.MODES == {1: 'PROFILE POSITION', 3: 'PROFILE VELOCITY', 6: 'HOMING'}


def test_range_text_names_values():
    assert m.REGISTERS['SAVE_ALL_PARAMETERS'].range_text() == 'one of 0x6173, 0x1111'
    assert m.REGISTERS['CURRENT_RATIO'].range_text() == '0..120'
    assert str(m.REGISTERS['STATUS_WORD']) == 'STATUS_WORD (1001)'
