"""X-MIND K protocol module: tables, every instruction's codec, commands, answers, timing."""

import pytest
from stepper_drivers.protocol import xmind_k as xk
from stepper_drivers.protocol.xmind_k import Frame, Instruction


def test_code_tables():
    assert xk.TABLE2_HZ[3] == 3000 and xk.TABLE2_HZ[24] == 24000 and len(xk.TABLE2_HZ) == 22
    assert xk.TABLE3_HZ[2] == 200 and xk.TABLE3_HZ[30] == 3000 and len(xk.TABLE3_HZ) == 29
    assert len(xk.TABLE5) == 33 and xk.TABLE5[34] == (206, 116504)
    # §6.2 example: code 34 up to 15 kHz takes about 206 x 15/24 = 129 ms
    assert 15000 / xk.ramp_acceleration_hz_s(34) == pytest.approx(0.129, abs=0.001)
    assert xk.ramp_acceleration_hz_s(30) == pytest.approx(200000)
    with pytest.raises(xk.RangeError, match='Table 5'):
        xk.ramp_time_s(43)


@pytest.mark.parametrize('hz, real', [(1, 1), (50, 50), (51, 50), (53, 52), (101, 100),
                                      (104, 100), (107, 105), (224, 220), (499, 490),
                                      (524, 500), (530, 525), (1249, 1200), (2200, 2200),
                                      (2499, 2400), (4799, 4700), (4800, 4800)])
def test_table4_floor(hz, real):
    assert xk.table4_floor(hz) == real          # 'nearest and lower value' (§4.1.6 Note)


@pytest.mark.parametrize('hz', [0, 4801])
def test_table4_range(hz):
    with pytest.raises(xk.RangeError, match='Table 4'):
        xk.table4_floor(hz)


# Every instruction (§4.1): named fields -> the body after 'WN,BBB,'
INSTRUCTIONS = [
    (1, dict(frequency_code=9, ramp_code=15, steps=31754, multiplier='x1'), 121,
     '01,09,15,+31754,x1,121'),
    (31, dict(frequency_x100=91, ramp_code=15, steps=31754, multiplier='x1'), 121,
     '31,091,15,+31754,x1,121'),
    (2, dict(frequency_code=10, ramp_code=18, direction='+', multiplier='x1'), 210,
     '02,10,18,+,x1,210'),
    (32, dict(frequency_x100=113, ramp_code=18, direction='+', multiplier='x1'), 210,
     '32,113,18,+,x1,210'),
    (11, dict(frequency_code=2, steps=1246, multiplier='x4'), 188, '11,02,+1246,x4,188'),
    (21, dict(frequency_hz=224, steps=1246, multiplier='x4'), 188, '21,0220,+1246,x4,188'),
    (12, dict(frequency_code=22, direction='+', multiplier='x4'), 133, '12,22,+,x4,133'),
    (22, dict(frequency_hz=2200, direction='+', multiplier='x4'), 133, '22,2200,+,x4,133'),
    (3, dict(frequency_code=20, ramp_code=10, direction='+', slow_code=5), 182,
     '03,20,10,+,05,182'),
    (57, dict(enable=1, position=13000), 191, '57,1,+13000,191'),
    (58, dict(output='O1', value=1), 194, '58,O1,1,194'),
    (65, dict(delay_ms=4000), 192, '65,4000,192'),
    (0, dict(), 196, '00,196'),
    (63, dict(input='I1', value=0, jump_cell=130), 155, '63,I1,0,130,155'),
    (69, dict(), 0, '69,000'),
    (5, dict(frequency_code=10, ramp_code=20, direction='+', stop_steps=3000,
             multiplier='x1'), 205, '05,10,20,+,3000,x1,205'),
    (70, dict(on=1), 190, '70,1,190'),
    (61, dict(repetitions=12), 181, '61,12,181'),
    (62, dict(loop_cell=181), 201, '62,181,201'),
    (60, dict(), 190, '60,190'),
]


def test_the_table_covers_all_twenty_instructions():
    assert {c for c, *_ in INSTRUCTIONS} == set(xk.INSTRUCTION_TYPES)
    assert len(xk.INSTRUCTION_TYPES) == 20


@pytest.mark.parametrize('code, fields, next_cell, body', INSTRUCTIONS,
                         ids=[f'{c:02d}' for c, *_ in INSTRUCTIONS])
def test_instruction_encode_and_parse(code, fields, next_cell, body):
    instr = Instruction.make(code, next_cell, **fields)
    assert instr.encode() == body
    assert Instruction.parse(body.split(',')) == instr
    wire = xk.encode_request(Frame(7, 'WN', (156, instr)))
    assert wire == f'07WN,156,{body}\r'.encode()
    assert xk.parse_request(wire) == Frame(7, 'WN', (156, instr))
    answer = xk.encode_answer(Frame(7, 'QM', (156, instr)))
    assert answer == f'07QM,156,{body}\r'.encode()
    assert xk.parse_answer(answer, Frame(7, 'QM', (156,))) == Frame(7, 'QM', (156, instr))


def test_instruction_fields_and_frequencies():
    i = Instruction.make(31, frequency_x100=91, ramp_code=15, steps=-5, multiplier='x1')
    assert i.frequency_hz == 9100 and i.get('steps') == -5
    assert i.type.name == 'HIGH RESOLUTION INDEXED RUN WITH RAMP' and i.type.section == '4.1.2'
    assert Instruction.make(11, frequency_code=5, steps=1, multiplier='x1').frequency_hz == 500
    assert Instruction.make(3, frequency_code=20, ramp_code=10, direction='-',
                            slow_code=5).frequency_hz == 20000
    with pytest.raises(xk.FrameSyntaxError, match='fields'):
        Instruction.make(65, delay=3)


@pytest.mark.parametrize('text, why', [
    ('07WN,156,01,02,15,+31754,x1,121', 'Table 2'),
    ('07WN,156,01,09,09,+31754,x1,121', 'Table 5'),
    ('07WN,231,01,09,15,+31754,x1,121', '100..230'),
    ('07WN,156,01,09,15,+8388608,x1,121', '8388607'),
    ('07WN,156,31,029,15,+100,x1,000', '30..240'),
    ('07WN,156,31,241,15,+100,x1,000', '30..240'),
    ('07WN,156,21,4801,+100,x1,000', '4800'),
    ('07WN,156,21,0000,+100,x1,000', '4800'),
    ('07WN,156,61,0,157', '1..65535'),
    ('07WN,156,65,65536,000', '65535'),
    ('07WN,156,58,FA,1,000', 'O0'),
    ('07WN,156,63,O1,1,100,000', 'I0'),
    ('07WN,156,01,09,15,+100,x1,099', '000 nor'),
    ('07WN,156,01,09,15,100,x1,000', 'signed'),
    ('07WN,156,44,000', 'does not exist'),
    ('07WN,156,65,100', 'parameters'),
    ('13WS,IN,4', '0..3'),
    ('13WS,AD,48', '0..47'),
    ('13WS,RD,256', '0..255'),
    ('13WS,RS,D4', 'D0'),
    ('13WS,CM,2', 'kkk'),
    ('13WS,CM,2,0', '8388607'),
    ('13WS,CM,0,5', 'no third'),
    ('13SO,BS,1', 'O0'),
    ('13SA,2147483648', '2147483647'),
    ('13PS,99', 'cell'),
    ('13QS,XX', 'AD'),
    ('13XX', 'unknown code'),
    ('13CY,1', 'takes 0'),
])
def test_what_the_drive_answers_n_to(text, why):
    with pytest.raises((xk.FrameSyntaxError, xk.RangeError), match=why):
        xk.parse_request(text)


@pytest.mark.parametrize('text', ['48QA', '1QA', 'QA', 'xxWS,CM,1'])
def test_what_the_drive_ignores(text):
    with pytest.raises(xk.AddressError):
        xk.parse_request(text)


@pytest.mark.parametrize('frame, wire', [
    (Frame(3, 'WS', ('AD', 38)), '03WS,AD,38'),
    (Frame(0, 'WS', ('CM', 2, 999)), '00WS,CM,2,999'),
    (Frame(13, 'WS', ('RS', 'B2')), '13WS,RS,B2'),
    (Frame(99, 'WS', ('RD', 0)), '99WS,RD,0'),
    (Frame(12, 'CY'), '12CY'), (Frame(8, 'CN'), '08CN'), (Frame(5, 'PS', (147,)), '05PS,147'),
    (Frame(99, 'EE'), '99EE'), (Frame(2, 'ES'), '02ES'), (Frame(8, 'RA'), '08RA'),
    (Frame(3, 'SA', (3200,)), '03SA,3200'), (Frame(3, 'SA', (-5,)), '03SA,-5'),
    (Frame(14, 'SO', ('O1', 1)), '14SO,O1,1'), (Frame(6, 'SC', (1, 117500)), '06SC,1,+117500'),
    (Frame(6, 'SC', (0, None)), '06SC,0,+0'),
    (Frame(8, 'QA'), '08QA'), (Frame(14, 'QS', ('IN',)), '14QS,IN'),
    (Frame(14, 'QI', ('I0',)), '14QI,I0'), (Frame(14, 'QO', ('BS',)), '14QO,BS'),
    (Frame(11, 'QM', (172,)), '11QM,172'), (Frame(14, 'QC'), '14QC'), (Frame(11, 'QE'), '11QE'),
])
def test_commands_and_requests_canonical(frame, wire):
    assert xk.encode_request(frame) == wire.encode() + b'\r'
    parsed = xk.parse_request(wire)
    assert parsed.address == frame.address and parsed.code == frame.code


@pytest.mark.parametrize('literal, canonical', [
    ('08QA.', '08QA'), ('14QI,I0,', '14QI,I0'), ('03WS,RD,98,', '03WS,RD,98'),
    ('01WN,165,05,10,20,+,3000,x1,205,', '01WN,165,05,10,20,+,3000,x1,205'),
    ('00WN,100,01,20,30,+2400,X1,000', '00WN,100,01,20,30,+2400,x1,000'),
])
def test_manual_literals_are_read_as_their_canonical_form(literal, canonical):
    """§8 A1/A8: one '.' or ',' before the terminator and 'X1' are accepted, never sent."""
    assert xk.encode_request(xk.parse_request(literal + '\r')) == canonical.encode() + b'\r'
    with pytest.raises(xk.ProtocolError):
        xk.parse_request('08QA.', tolerant=False)


def test_broadcast_only_where_allowed():
    assert xk.encode_request(Frame(99, 'PS', (100,))) == b'99PS,100\r'
    for code, args in (('RA', ()), ('QA', ()), ('SA', (1,)), ('WN', (100, Instruction(0, ())))):
        with pytest.raises(xk.RangeError, match='broadcast'):
            xk.encode_request(Frame(99, code, args))


@pytest.mark.parametrize('request_, answer, args', [
    (Frame(14, 'QA'), '14QA,+5121.', (5121,)),
    (Frame(8, 'QA'), '08QA,-2147483648', (-2147483648,)),
    (Frame(14, 'QS', ('RS',)), '14QS,RS,B1.', ('RS', 'B1', None)),
    (Frame(14, 'QS', ('RD',)), '14QS,RD,102', ('RD', 102, None)),
    (Frame(0, 'QS', ('CM',)), '00QS,CM,2,999', ('CM', 2, 999)),
    (Frame(0, 'QS', ('CM',)), '00QS,CM,2', ('CM', 2, None)),
    (Frame(38, 'QS', ('AD',)), '38QS,AD,38', ('AD', 38, None)),
    (Frame(14, 'QI', ('I0',)), '14QI,I0,1,', ('I0', 1)),
    (Frame(14, 'QO', ('O1',)), '14QO,O1,0,', ('O1', 0)),
    (Frame(14, 'QC'), '14QC,1,+56564,', (1, 56564)),
    (Frame(14, 'QC'), '14QC,0,', (0, None)),
    (Frame(11, 'QE'), '11QE,00,000.', (0, 0)),
    (Frame(11, 'QE'), '11QE,50,212', (50, 212)),
])
def test_answers(request_, answer, args):
    parsed = xk.parse_answer(answer + '\r', request_)
    assert parsed == Frame(request_.address, request_.code, args)
    if args != ('CM', 2, None):           # §8 A12: a drive may not echo kkk; we always do
        assert xk.encode_answer(parsed) == answer.rstrip('.,').encode() + b'\r'


def test_qm_answer_of_the_manual_with_x_upper_case():
    answer = '11QM,172,01,09,15,+31754,X1,121,'
    parsed = xk.parse_answer(answer, Frame(11, 'QM', (172,)))
    assert parsed.args[1] == Instruction.make(1, 121, frequency_code=9, ramp_code=15,
                                              steps=31754, multiplier='x1')


@pytest.mark.parametrize('answer, request_, error', [
    ('07QA,+1', Frame(8, 'QA'), xk.AddressError),
    ('08QS,RD,10', Frame(8, 'QA'), xk.FrameSyntaxError),
    ('08?A,+1', Frame(8, 'QA'), xk.FrameSyntaxError),
    ('08QA,1x', Frame(8, 'QA'), xk.FrameSyntaxError),
    ('08QM,173,00,000', Frame(8, 'QM', (172,)), xk.FrameSyntaxError),
    ('08QI,I1,1', Frame(8, 'QI', ('I0',)), xk.FrameSyntaxError),
])
def test_answers_that_do_not_fit(answer, request_, error):
    with pytest.raises(error):
        xk.parse_answer(answer, request_)


def test_confirmations():
    assert xk.parse_answer(b'03Y\r', Frame(3, 'SA', (1,))) == Frame(3, 'Y')
    assert xk.parse_answer('13N.', Frame(13, 'WS', ('IN', 3))) == Frame(13, 'N')


@pytest.mark.parametrize('tx, rx, code, total_ms', [
    ('00PS,100', '00Y', 'PS', 19.02),
    ('00WN,100,01,10,18,+10000,x1,000', '00Y', 'WN', 53.44),
    ('00QM,140', '00QM,140,01,05,15,+100000,x1,141', 'QM', 49.18),
    ('08QA', '08QA,+10854000', 'QA', 26.3),
    ('08QA', '08QA,+0', 'QA', 19.02),
])
def test_manual_timing_examples(tx, rx, code, total_ms):
    """§3 examples 1-4, counted with the terminator and the manual's 1.04 ms per character."""
    t = xk.transaction_time_s(len(tx) + 1, len(rx) + 1, code, char_s=xk.MANUAL_CHAR_TIME_S)
    assert t * 1000 == pytest.approx(total_ms, abs=0.005)
    exact = xk.transaction_time_s(len(tx) + 1, len(rx) + 1, code)
    assert exact == pytest.approx(t, rel=0.01)


def test_longest_answers_bound_the_timeouts():
    longest = {
        'QA': '08QA,-2147483648', 'QC': '14QC,1,-2147483648', 'QE': '11QE,50,212',
        'QI': '14QI,I0,1', 'QO': '14QO,BS,0',
        'QM': xk.encode_answer(Frame(0, 'QM', (200, Instruction.make(
            31, 200, frequency_x100=240, ramp_code=42, steps=-8388607, multiplier='x1')))),
    }
    for code, text in longest.items():
        n = len(text if isinstance(text, bytes) else text + '\r')
        args = {'QI': ('I0',), 'QO': ('BS',), 'QM': (200,)}.get(code, ())
        assert xk.max_answer_chars(Frame(8, code, args)) == n, code
    assert xk.max_answer_chars(Frame(8, 'QS', ('CM',))) == len('08QS,CM,2,8388607\r')
    assert xk.max_answer_chars(Frame(8, 'PS', (100,))) == 4
    assert xk.max_answer_chars(Frame(99, 'EE')) == 0
