"""xmind_k_sim against the golden strings of spec/xmind_k.md §9, over its pty.

The client here is independent of the driver: a raw file descriptor on the pty (no pyserial, no
driver code), bytes in and bytes out. Each case gives the host strings (the manual's literal and
the canonical wire form) and the exact answer, or None for silence.
"""

import time

import pytest
from stepper_sim.harness import RawLine
from stepper_sim.xmind_k.sim import XmindKDriveSim, XmindKLine

ADDRESSES = (0, 1, 2, 3, 5, 6, 7, 8, 9, 11, 12, 13, 14, 15, 23)


@pytest.fixture
def line(tmp_path):
    drives = [XmindKDriveSim(f'd{a:02d}', a) for a in ADDRESSES]
    sim = XmindKLine(drives, str(tmp_path / 'tty'))
    sim.start()
    yield sim
    sim.stop()


@pytest.fixture
def host(line):
    client = RawLine(line.link_path)
    yield client
    client.close()


def wait_idle(host, address, timeout_s=5.0):
    deadline = time.monotonic() + timeout_s
    while host.ask(f'{address:02d}QA', 0.05) is None:
        assert time.monotonic() < deadline, f'drive {address:02d} still busy'


# §9.2 instructions: (manual literal, wire, QM echo of the cell or None)
INSTRUCTIONS = [
    ('I1', '07WN,156,01,09,15,+31754,x1,121', None, '07QM,156,01,09,15,+31754,x1,121'),
    ('I2', '07WN,156,31,091,15,+31754,x1,121', None, '07QM,156,31,091,15,+31754,x1,121'),
    ('I3', '03WN,140,02,10,18,+,x1,210', '03WN,140,02,10,18,+,x1,210.',
     '03QM,140,02,10,18,+,x1,210'),
    ('I4', '03WN,140,32,113,18,+,x1,210', '03WN,140,32,113,18,+,x1,210.',
     '03QM,140,32,113,18,+,x1,210'),
    ('I5', '08WN,122,11,02,+1246,x4,188', '08WN,122,11,02,+1246,x4,188.',
     '08QM,122,11,02,+1246,x4,188'),
    ('I6', '08WN,122,21,0224,+1246,x4,188', '08WN,122,21,0224,+1246,x4,188.',
     '08QM,122,21,0220,+1246,x4,188'),          # §8 A7: 224 Hz is 220 Hz on the Table 4 grid
    ('I7', '02WN,176,12,22,+,x4,133', None, '02QM,176,12,22,+,x4,133'),
    ('I8', '02WN,176,22,2200,+,x4,133', '02WN,176,22,2200,+,x4,133.',
     '02QM,176,22,2200,+,x4,133'),
    ('I9', '11WN,146,03,20,10,+,05,182', '11WN,146,03,20,10,+,05,182.',
     '11QM,146,03,20,10,+,05,182'),
    ('I10', '06WN,177,57,1,+13000,191', None, '06QM,177,57,1,+13000,191'),
    ('I11', '06WN,170,58,O1,1,194', '06WN,170,58,O1,1,194.', '06QM,170,58,O1,1,194'),
    ('I12', '12WN,120,65,4000,192', '12WN,120,65,4000,192.', '12QM,120,65,4000,192'),
    ('I13', '15WN,135,00,196', '15WN,135,00,196.', '15QM,135,00,196'),
    ('I14', '00WN,130,00,000', None, '00QM,130,00,000'),
    ('I15', '00WN,100,00,116', None, '00QM,100,00,116'),
    ('I16', '00WN,180,63,I1,0,130,155', '00WN,180,63,I1,0,130,155.',
     '00QM,180,63,I1,0,130,155'),
    ('I17', '14WN,220,69', '14WN,220,69,', '14QM,220,69,000'),     # §8 A10: no DDD
    ('I18', '01WN,165,05,10,20,+,3000,x1,205', '01WN,165,05,10,20,+,3000,x1,205,',
     '01QM,165,05,10,20,+,3000,x1,205'),
    ('I19', '03WN,180,70,1,190', None, '03QM,180,70,1,190'),
    ('I20', '03WN,180,61,12,181', None, '03QM,180,61,12,181'),
    ('I21', '03WN,183,62,181,201', None, '03QM,183,62,181,201'),
    ('I22', '03WN,180,60,190', '03WN,180,60,190.', '03QM,180,60,190'),
]


@pytest.mark.parametrize('case, wire, literal, echo', INSTRUCTIONS,
                         ids=[c[0] for c in INSTRUCTIONS])
def test_instruction_golden(host, line, case, wire, literal, echo):
    address = wire[:2]
    for text in filter(None, (literal, wire)):
        assert host.ask(text) == f'{address}Y', text
    cell = wire.split(',')[1]
    assert host.ask(f'{address}QM,{cell}') == echo
    assert line.by_name[f'd{address}'].eeprom_cell_writes == (2 if literal else 1)


def test_all_twenty_instruction_codes_are_golden_cases():
    codes = {int(w.split(',')[2]) for _, w, _, _ in INSTRUCTIONS}
    codes.add(31)
    assert len(codes) == 20


# §9.4 commands and §9.5 data requests: (id, setup strings, request, expected answer)
EXCHANGES = [
    ('C2', ['13WS,IN,3'], '13QS,IN', '13QS,IN,3'),
    ('C4', ['23WS,EQ,0'], '23QS,EQ', '23QS,EQ,0'),
    ('C5', ['03WS,RD,98,'], '03QS,RD', '03QS,RD,98'),
    ('C6', ['03WS,CM,0,'], '03QS,CM', '03QS,CM,0'),
    ('C7', ['00WS,CM,1,'], '00QS,CM', '00QS,CM,1'),
    ('C8', ['00WS,CM,2,999.'], '00QS,CM', '00QS,CM,2,999'),
    ('C9', ['23WS,ES,1,'], '23QS,ES', '23QS,ES,1'),
    ('C10', ['12CY'], '12QO,FA', '12QO,FA,1'),
    ('C11', ['08CN'], '08QO,FA', '08QO,FA,1'),
    ('C15', ['08SA,77', '08RA'], '08QA', '08QA,+0'),
    ('C16', ['03SA,3200'], '03QA', '03QA,+3200'),
    ('C17', ['14SO,O1,1,'], '14QO,O1', '14QO,O1,1'),
    ('C18', ['06SC,1,+117500,'], '06QC', '06QC,1,+117500'),
    ('Q1', ['14SA,5121'], '14QA.', '14QA,+5121'),
    ('Q2', ['14WS,IN,0'], '14QS,IN.', '14QS,IN,0'),
    ('Q4', ['14WS,RD,102'], '14QS,RD.', '14QS,RD,102'),
    ('Q5', [], '14QS,ES.', '14QS,ES,1'),
    ('Q6', [], '14QS,CM.', '14QS,CM,0'),
    ('Q7', ['14WS,EQ,1'], '14QS,EQ.', '14QS,EQ,1'),
    ('Q9', [], '14QO,O1,', '14QO,O1,0'),
    ('Q10', ['11WN,172,01,09,15,+31754,X1,121'], '11QM,172,', '11QM,172,01,09,15,+31754,x1,121'),
    ('Q11', ['11WN,172,65,3400,159'], '11QM,172,', '11QM,172,65,3400,159'),
    ('Q12', ['14SC,1,+56564'], '14QC,', '14QC,1,+56564'),
    ('Q13', [], '14QC,', '14QC,0'),
    ('Q14', [], '11QE.', '11QE,00,000'),
    ('Q15', ['11WS,CM,1', '11WN,212,01,20,30,+2400,x1,000', '11SA,-8388607', '11PS,212'],
     '11QE.', '11QE,50,212'),
    ('Q16', [], '14QO,BS', '14QO,BS,0'),
    ('T4', ['08SA,10854000'], '08QA.', '08QA,+10854000'),
    ('T5', [], '08QA.', '08QA,+0'),
    ('T3', ['00WN,140,01,05,15,+100000,x1,141'], '00QM,140.',
     '00QM,140,01,05,15,+100000,x1,141'),
    ('M2', ['00WS,CM,1', '00WN,100,01,20,30,+2400,X1,000,', '00SA,-8388607', '00PS,100'],
     '00QA', '00QA,-8388607'),
]


@pytest.mark.parametrize('case, setup, request_, answer', EXCHANGES,
                         ids=[c[0] for c in EXCHANGES])
def test_command_and_request_golden(host, case, setup, request_, answer):
    for text in setup:
        assert host.ask(text) == f'{text[:2]}Y', text
    assert host.ask(request_) == answer


def test_q3_and_c3_resolution_preset_is_silent_for_200_ms(host):
    t0 = time.monotonic()
    assert host.ask('13WS,RS,B2') == '13Y'          # C3
    assert host.ask('13QS,RS', 0.05) is None        # current off, deaf (§4.2.2.3 Note 2)
    deadline = t0 + 1.0
    while (answer := host.ask('13QS,RS', 0.05)) is None:
        assert time.monotonic() < deadline
    assert answer == '13QS,RS,B2' and time.monotonic() - t0 >= 0.2
    assert host.ask('14WS,RS,B1') == '14Y'          # Q3
    time.sleep(0.21)     # the drive's own dead time (§4.2.2.3), not a synchronisation
    assert host.ask('14QS,RS.') == '14QS,RS,B1'


def test_c1_address_preset_answers_with_the_old_address(host):
    assert host.ask('03WS,AD,38') == '03Y'
    assert host.ask('38QS,AD') == '38QS,AD,38'
    assert host.ask('03QA') is None


def test_q8_input_status(host, line):
    line.by_name['d14'].set_input('I0', True)
    assert host.ask('14QI,I0,') == '14QI,I0,1'
    assert host.ask('14QI,PX') == '14QI,PX,0'


def test_c12_to_c14_busy_drive_hears_only_ee_and_es(host):
    assert host.ask('05WN,147,31,030,42,+100000,x1,000') == '05Y'
    assert host.ask('05PS,147') == '05Y'                      # C12, then busy
    for text in ('05QA', '05QO,BS', '05CY', '05PS,147', '05WN,150,00,000', '05XX'):
        assert host.ask(text, 0.05) is None, text              # §3 silence while busy
    assert host.ask('05ES') == '05Y'                          # no effect on an indexed run
    assert host.ask('05QA', 0.05) is None
    assert host.ask('05EE') == '05Y'                          # C13: aborted, ramps down
    wait_idle(host, 5)
    assert host.ask('05QO,BS') == '05QO,BS,0'
    # C14: a free run stops on ES, then the drive answers again
    assert host.ask('02WN,140,32,030,10,+,x1,000') == '02Y'
    assert host.ask('02PS,140') == '02Y'
    assert host.ask('02QA', 0.05) is None
    assert host.ask('02ES') == '02Y'
    wait_idle(host, 2)


# §9.7 negative cases: (wire, expected answer or None for silence)
NEGATIVE = [
    ('07WN,156,01,02,15,+31754,x1,121', '07N'),     # FF 02 not in Table 2
    ('07WN,156,01,09,09,+31754,x1,121', '07N'),     # RR 09 < 10
    ('07WN,231,01,09,15,+31754,x1,121', '07N'),     # BBB > 230
    ('07WN,156,01,09,15,+8388608,x1,121', '07N'),   # steps out of range
    ('07WN,156,31,029,15,+100,x1,000', '07N'),      # FFF < 030
    ('07WN,156,21,4801,+100,x1,000', '07N'),        # FFFF > 4800
    ('07WN,156,61,0,157', '07N'),                   # loop count 0
    ('07WN,156,65,65536,000', '07N'),               # delay too long
    ('07WN,156,58,FA,1,000', '07N'),                # FA cannot be set
    ('07WN,156,01,09,15,+31754,x1', '07N'),         # no DDD
    ('07WN,156,01,09,15,+31754,x2,121', '07N'),     # multiplier x2
    ('07WN,156,44,121', '07N'),                     # instruction 44 does not exist
    ('13WS,IN,4', '13N'),
    ('13WS,AD,48', '13N'),
    ('13WS,CM,2', '13N'),                           # cyclic mode needs kkk
    ('13WS,CM,2,8388608', '13N'),
    ('13SO,BS,1', '13N'),
    ('13PS,099', '13N'),
    ('13XX', '13N'),
    ('99CY', None), ('99EE', None), ('99PS,100', None),
    ('99RA', None), ('99QA', None),
    ('48QA', None), ('16QA', None), ('AAQA', None),
]


@pytest.mark.parametrize('wire, answer', NEGATIVE, ids=[n[0] for n in NEGATIVE])
def test_negative_golden(host, wire, answer):
    assert host.ask(wire, 0.1 if answer is None else 0.3) == answer


def test_m1_and_m3_coordinate_modes_over_the_pty(host):
    """§9.6 M1 (relative) and M3 (cyclic, 0..999); M2 is in EXCHANGES."""
    assert host.ask('00WN,100,01,20,30,+2400,X1,000,') == '00Y'
    assert host.ask('00SA,-100') == '00Y' and host.ask('00PS,100') == '00Y'
    wait_idle(host, 0)
    assert host.ask('00QA') == '00QA,+2300'
    assert host.ask('00WS,CM,2,999') == '00Y'
    for i, p in enumerate((0, 200, 400, 500, 700, 900)):
        assert host.ask(f'00WN,10{i},11,05,{p:+d},x1,000.') == '00Y'
    assert host.ask('00SA,900') == '00Y' and host.ask('00PS,100') == '00Y'
    wait_idle(host, 0)
    assert host.ask('00QA') == '00QA,+0'
    assert host.ask('00PS,104') == '00Y'
    wait_idle(host, 0)
    assert host.ask('00QA') == '00QA,+700'


def test_broadcast_executes_only_what_the_manual_allows(host, line):
    assert host.ask('00SA,500') == '00Y'
    assert host.ask('99RA', 0.05) is None              # not allowed: not executed either
    assert host.ask('00QA') == '00QA,+500'
    assert host.ask('99WS,EQ,1', 0.05) is None         # allowed: every drive, no answer
    assert all(d.presets['EQ'] == 1 for d in line.drives)
    assert host.ask('99CN', 0.05) is None
    assert not any(d.current_on for d in line.drives)


@pytest.mark.parametrize('case, request_, answer, setup, manual_ms', [
    ('T1', '00PS,100', '00Y', [], 19.02),
    ('T2', '00WN,100,01,10,18,+10000,x1,000', '00Y', [], 53.44),
    ('T3', '00QM,140', '00QM,140,01,05,15,+100000,x1,141',
     ['00WN,140,01,05,15,+100000,x1,141'], 49.18),
    ('T4', '08QA', '08QA,+10854000', ['08SA,10854000'], 26.3),
    ('T5', '08QA', '08QA,+0', [], 19.02),
])
def test_line_timing_matches_the_manual_arithmetic(tmp_path, case, request_, answer, setup,
                                                   manual_ms):
    """§3 with RD = 0: the answer is complete manual_ms - 4 ms margin after the write (the
    manual rounds a character to 1.04 ms; 10 bits at 9600 baud are 1.0417 ms)."""
    drives = [XmindKDriveSim(f'd{a:02d}', a, factory={'RD': 0}) for a in (0, 8)]
    line = XmindKLine(drives, str(tmp_path / 'tty'), line_timing=True)
    line.start()
    host = RawLine(line.link_path)
    try:
        for text in setup:
            assert host.ask(text) == f'{text[:2]}Y'
        times = []
        for _ in range(5):
            time.sleep(0.005)      # the §3 margin before the next string
            t0 = time.monotonic()
            assert host.ask(request_) == answer
            times.append((time.monotonic() - t0) * 1000.0)
        expected_ms = (manual_ms - 4.0) * (10 / 9600) / 0.00104
        best = min(times)
        assert expected_ms - 0.3 <= best <= expected_ms + 3.0, (times, expected_ms)
    finally:
        host.close()
        line.stop()


def test_answer_delay_rd_adds_to_the_turnaround(tmp_path):
    drives = [XmindKDriveSim('d03', 3, factory={'RD': 98})]       # C5: 98 ms later
    line = XmindKLine(drives, str(tmp_path / 'tty'), line_timing=True)
    line.start()
    host = RawLine(line.link_path)
    try:
        t0 = time.monotonic()
        assert host.ask('03QS,RD') == '03QS,RD,98'
        elapsed_ms = (time.monotonic() - t0) * 1000.0
        expected_ms = (8 + 11) * 1000 / 960 + 1.5 + 98        # '03QS,RD\r', '03QS,RD,98\r'
        assert expected_ms - 0.3 <= elapsed_ms < expected_ms + 5.0, elapsed_ms
    finally:
        host.close()
        line.stop()


def test_link_faults_on_the_pty(host, line):
    line.set_link_fault('corrupt_reply', 1)
    assert host.ask('00QA') == '00?A,+0'                  # noise, terminator intact
    assert host.ask('00QA') == '00QA,+0'
    line.set_link_fault('no_reply', 1)
    assert host.ask('00SA,7', 0.1) is None                 # executed, answer lost
    assert host.ask('00QA') == '00QA,+7'
