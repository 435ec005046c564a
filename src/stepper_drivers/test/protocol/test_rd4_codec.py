"""Modbus RTU codec (protocol/modbus_rtu.py) against the RD4 manual's literal frames.

Frames are byte literals copied from the manual §7.4.1/§9 (CRC included) and from the spec's
derived table (spec/lika_rd4.md §11.2, computed with an independent CRC routine).
"""

import pytest
from stepper_drivers.protocol import modbus_rtu as rtu


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# (request, response) from the manual: §9.1 Ex.1, §9.2 Ex.1 and Ex.2, §9.3 Ex.1-3, §9.4 Ex.1.
MANUAL_PAIRS = [
    ('01 03 00 06 00 02 24 0A', '01 03 04 03 E8 05 DC 78 8A'),
    ('01 04 00 02 00 02 D0 0B', '01 04 04 00 00 2F F0 E7 F0'),
    ('01 04 00 00 00 01 31 CA', '01 04 02 00 81 79 50'),
    ('01 06 00 06 05 DC 6B 02', '01 06 00 06 05 DC 6B 02'),
    ('01 06 00 2A 00 84 A8 61', '01 06 00 2A 00 84 A8 61'),
    ('01 06 00 2A 0A 80 AF 02', '01 06 00 2A 0A 80 AF 02'),
    ('01 10 00 06 00 02 04 05 DC 03 E8 B2 0D', '01 10 00 06 00 02 A1 C9'),
]


@pytest.mark.parametrize('request_hex, response_hex', MANUAL_PAIRS)
def test_manual_frames_have_valid_crc_low_byte_first(request_hex, response_hex):
    for frame in (h(request_hex), h(response_hex)):
        assert rtu.crc_ok(frame)
        assert rtu.add_crc(frame[:-2]) == frame


def test_crc16_modbus_check_value():
    # CRC-16/MODBUS catalogue check value over b'123456789' (0x4B37), sent low byte first
    assert rtu.add_crc(b'123456789')[-2:] == bytes((0x37, 0x4B))


def test_request_encoders_reproduce_the_manual():
    assert rtu.encode(rtu.read_request(1, 3, 0x06, 2)) == h('01 03 00 06 00 02 24 0A')
    assert rtu.encode(rtu.read_request(1, 4, 0x02, 2)) == h('01 04 00 02 00 02 D0 0B')
    assert rtu.encode(rtu.write_single_request(1, 0x2A, 0x0084)) == h('01 06 00 2A 00 84 A8 61')
    assert rtu.encode(rtu.write_multiple_request(1, 0x06, [1500, 1000])) == \
        h('01 10 00 06 00 02 04 05 DC 03 E8 B2 0D')
    # spec §11.2 derived frames
    assert rtu.encode(rtu.write_multiple_request(1, 0x2B, [0xFFFF, 0xFE0C])) == \
        h('01 10 00 2B 00 02 04 FF FF FE 0C F0 45')
    assert rtu.encode(rtu.read_request(1, 4, 0x00, 16)) == h('01 04 00 00 00 10 F1 C6')


def test_response_encoders_reproduce_the_manual():
    assert rtu.read_response(1, 3, [1000, 1500]) == h('01 03 04 03 E8 05 DC 78 8A')
    assert rtu.read_response(1, 4, [0x0000, 0x2FF0]) == h('01 04 04 00 00 2F F0 E7 F0')
    assert rtu.write_multiple_response(1, 0x06, 2) == h('01 10 00 06 00 02 A1 C9')
    frame = h('01 06 00 2A 0A 80 AF 02')
    assert rtu.write_single_response(frame) == frame


@pytest.mark.parametrize('fc, code, expected', [
    (0x01, 1, '01 81 01 81 90'), (0x05, 1, '01 85 01 83 50'), (0x03, 2, '01 83 02 C0 F1'),
    (0x03, 3, '01 83 03 01 31'), (0x04, 2, '01 84 02 C2 C1'), (0x06, 2, '01 86 02 C3 A1'),
    (0x10, 2, '01 90 02 CD C1')])
def test_exception_responses(fc, code, expected):
    assert rtu.exception_response(1, fc, code) == h(expected)


def test_parse_request_in_modbus_processing_order():
    req = rtu.parse_request(h('01 10 00 06 00 02 04 05 DC 03 E8 B2 0D'))
    assert (req.unit, req.function_code, req.address, req.count, req.values) == \
        (1, 0x10, 6, 2, (1500, 1000))
    with pytest.raises(rtu.ModbusExceptionError) as e:
        rtu.parse_request(rtu.add_crc(h('01 01 00 00 00 01')))
    assert e.value.code == rtu.ILLEGAL_FUNCTION
    for bad in ('01 03 00 00 00 00', '01 03 00 00 00 7E', '01 04 00 00 00 00'):
        with pytest.raises(rtu.ModbusExceptionError) as e:
            rtu.parse_request(rtu.add_crc(h(bad)))
        assert e.value.code == rtu.ILLEGAL_DATA_VALUE, bad
    with pytest.raises(rtu.ModbusExceptionError) as e:     # byte count != 2 * quantity
        rtu.parse_request(rtu.add_crc(h('01 10 00 06 00 02 02 05 DC')))
    assert e.value.code == rtu.ILLEGAL_DATA_VALUE
    assert rtu.parse_request(rtu.add_crc(h('01 03 00 00 00 7D'))).count == 125


def test_frame_lengths_from_the_head():
    assert rtu.request_length(h('01 03')) == 8
    assert rtu.request_length(h('01 10 00 06 00 02')) is None
    assert rtu.request_length(h('01 10 00 06 00 02 04')) == 13
    assert rtu.request_length(h('01 2B')) is None
    assert rtu.response_length(h('01 04 10')) == 21
    assert rtu.response_length(h('01 84 02')) == 5
    assert rtu.response_length(h('01 06 00')) == 8


def test_parse_response_checks_the_reply_answers_the_request():
    req = rtu.read_request(1, 3, 0x06, 2)
    assert rtu.parse_response(h('01 03 04 03 E8 05 DC 78 8A'), req) == [1000, 1500]
    with pytest.raises(rtu.ModbusExceptionError) as e:
        rtu.parse_response(h('01 83 02 C0 F1'), req)
    assert e.value.code == 2 and 'ILLEGAL DATA ADDRESS' in str(e.value)
    with pytest.raises(rtu.ReplyMismatch, match='address 2'):
        rtu.parse_response(rtu.read_response(2, 3, [1, 2]), req)
    with pytest.raises(rtu.ReplyMismatch, match='data bytes'):
        rtu.parse_response(rtu.read_response(1, 3, [1]), req)
    w = rtu.write_single_request(1, 0x2A, 0x84)
    with pytest.raises(rtu.ReplyMismatch, match='echo'):
        rtu.parse_response(rtu.encode(rtu.write_single_request(1, 0x2A, 0x85)), w)


def test_line_timing_numbers_of_the_manual():
    # §7.3.1: "at 9600 the silent interval is 4 ms, at 19200 2 ms" (3.5 11-bit characters)
    assert rtu.t35_s(9600) == pytest.approx(0.004, abs=0.00002)
    assert rtu.t35_s(19200) == pytest.approx(0.002, abs=0.00001)
    assert rtu.frame_time_s(8, 19200) == pytest.approx(8 * 11 / 19200)


# spec/lika_rd4.md §11.2: every derived request (FC06 replies are echoes) and the FC16 replies.
DERIVED = [
    ('01 04 00 00 00 10 F1 C6', (4, 0x00, 16)), ('01 04 00 00 00 02 71 CB', (4, 0x00, 2)),
    ('01 03 00 00 00 1A C4 01', (3, 0x00, 26)), ('01 03 00 2A 00 01 A5 C2', (3, 0x2A, 1)),
    ('01 03 00 2B 00 02 B4 03', (3, 0x2B, 2)), ('01 03 00 29 00 04 95 C1', (3, 0x29, 4)),
]
DERIVED_CW = {0x0000: 'A8 02', 0x0080: 'A9 A2', 0x008C: 'A9 A7', 0x0085: '69 A1',
              0x0086: '29 A0', 0x0094: 'A9 AD', 0x0095: '68 6D', 0x0096: '28 6C',
              0x00C4: 'A9 91', 0x0184: 'A9 F1', 0x0284: 'A9 01', 0x0280: 'A8 C2',
              0x0484: 'AA A1', 0x0884: 'AF A1', 0x1084: 'A5 A1'}


def test_spec_derived_frames():
    for frame, (fc, address, count) in DERIVED:
        assert rtu.encode(rtu.read_request(1, fc, address, count)) == h(frame)
    for cw, crc in DERIVED_CW.items():
        assert rtu.encode(rtu.write_single_request(1, 0x2A, cw)) == \
            h(f'01 06 00 2A {cw >> 8:02X} {cw & 0xFF:02X} {crc}'), hex(cw)
    assert rtu.encode(rtu.write_single_request(1, 0x0C, 800)) == h('01 06 00 0C 03 20 48 E1')
    assert rtu.encode(rtu.write_multiple_request(1, 0x2B, [0, 1000])) == \
        h('01 10 00 2B 00 02 04 00 00 03 E8 B0 BA')
    assert rtu.write_multiple_response(1, 0x2B, 2) == h('01 10 00 2B 00 02 31 C0')
    assert rtu.encode(rtu.write_multiple_request(1, 0x16, [0, 0])) == \
        h('01 10 00 16 00 02 04 00 00 00 00 72 89')
    assert rtu.write_multiple_response(1, 0x16, 2) == h('01 10 00 16 00 02 A0 0C')
