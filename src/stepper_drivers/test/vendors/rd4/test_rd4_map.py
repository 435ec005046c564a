"""RD4 register map (vendors/rd4_map.py) against the manual's tables."""

import pytest
from stepper_drivers.vendors.rd4 import regmap as rm


def test_default_block_is_the_manuals_default_list():
    # §10 default parameters list as the FC03 start 0 qty 26 payload (T32, Offset 0).
    expected = ('0400 0000 0064 0400 01F4 003C 03E8 03E8 0007 FBFF 0007 FBFF 0640 0640 07D0 '
                '0000 00C8 003C 1388 1B58 0000 0000 0000 0000 0020 0064').split()
    words = rm.defaults(rm.MODELS['T32'])
    assert [f'{words[a]:04X}' for a in range(26)] == expected
    t48 = rm.defaults(rm.MODELS['T48'])
    assert (t48[0x0C], t48[0x0D], t48[0x18]) == (1066, 1066, 48)
    assert words[0x2A] == 0      # Control Word 0x0000 at power-up (§5.3 emergency)


def test_addresses_and_register_numbers():
    assert rm.HR['CONTROL_WORD'].address == 0x2A and rm.HR['CONTROL_WORD'].reg_no == 43
    assert rm.HR['TARGET_POSITION'].reg_no == 44 and rm.HR['TARGET_POSITION'].words == 2
    assert rm.IR['CURRENT_POSITION'].address == 0x02 and rm.IR['HW_VERSION'].reg_no == 16
    assert rm.find_register('control word') is rm.HR['CONTROL_WORD']
    assert rm.find_register('CURRENT_POSITION') is rm.IR['CURRENT_POSITION']


def test_32_bit_high_word_first():
    # §9.2 Example 1: 00 00 2F F0 = 12272
    assert rm.join32([0x0000, 0x2FF0], signed=True) == 12272
    assert rm.split32(-500) == [0xFFFF, 0xFE0C]
    assert rm.join32([0xFFFF, 0xFE0C], signed=True) == -500
    assert rm.join32([0xFFFF, 0xFE0C], signed=False) == 0xFFFFFE0C


def test_control_and_status_bits():
    assert rm.CW_READY == 0x0084                    # §9.3 Example 2
    assert rm.control_word_names(0x0A80) == ['Emergency', 'Save parameters',
                                             'Perform counting preset']   # §9.3 Ex.3 literal
    assert rm.status_names(0x0144) == ['Axis enabled', 'Axis running', 'Target position reached']


def test_alarm_texts_and_wrong_parameters_list():
    # §9.2 Example 2 value 0x0081: bits 0 and 7 = Machine data not valid + Overcurrent
    assert rm.alarm_names(0x0081) == ['Machine data not valid', 'Overcurrent']
    assert rm.alarm_names(0x0840) == ['Emergency', 'Watch dog']
    text = rm.describe_alarms(0x0041, (1 << 12) | (1 << 26))
    assert 'Machine data not valid' in text and 'Work speed [0x0D]' in text
    assert 'Preset [0x16-0x17]' in text
    assert rm.wrong_parameter_titles(1 << 1) == ['Distance per revolution [0x00]']
    assert rm.wrong_parameter_titles(1 << 17) == ['Max current [0x12]']


@pytest.mark.parametrize('model, dpr, rounding, expected', [
    ('T32', 1024, 'floor', 1600), ('T48', 1024, 'floor', 1066),
    ('T32', 100, 'round', 156),     # §6.4 Example 2: 1600 * 100 / 1024 = 156.25 -> 156
    ('T48', 100, 'floor', 104), ('T48', 100, 'round', 104), ('T32', 500, 'round', 781),
    ('T32', 500, 'floor', 781), ('T48', 1, 'floor', 1)])
def test_speed_limit_follows_distance_per_revolution(model, dpr, rounding, expected):
    assert rm.max_speed_pps(rm.MODELS[model], dpr, rounding) == expected


def test_delta_limit():
    assert rm.max_delta_pulses(1024) == 523263      # §6.4 Example 1 (register maximum)
    assert rm.max_delta_pulses(100) == 51100        # §6.4 Example 2


def test_identity_texts():
    assert rm.describe_sw_version(0x0102) == '1.2'
    assert rm.describe_hw_version(0x0001) == 'HW 1, RD4, Modbus, without brake (0x0001)'
    assert rm.describe_baud_register(0x04) == '04h = 19200 8E1'
    assert rm.describe_baud_register(0x03) == '03h = 19200 8N2'
    assert rm.describe_baud_register(9600) == '9600 baud'
