"""The X-MIND K device model's program engine, on a simulated clock (no pty, no waiting).

Programs from the manual (§4.1.19 loops, §5 coordinate modes) and the behaviour of every kind of
instruction: motion on the Table 5 ramps, zero search on PX, delayed stop, recovery, cam, jumps.
"""

import pytest
from stepper_drivers.protocol import xmind_k as xk
from stepper_sim.xmind_k.sim import XmindKDriveSim


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


@pytest.fixture
def clock():
    return Clock()


def drive(clock, address=0, **kw):
    return XmindKDriveSim(f'd{address:02d}', address, clock=clock, **kw)


def send(d, *texts):
    for text in texts:
        assert d.receive(text) == f'{text[:2]}Y\r'.encode(), text


def ask(d, text):
    answer = d.receive(text)
    return None if answer is None else answer.decode().rstrip('\r')


def run_until_idle(d, clock, limit_s=100.0, step_s=0.01, each=None):
    t0 = clock.t
    while d.busy:
        clock.t += step_s
        d.update()
        if each:
            each()
        assert clock.t - t0 < limit_s, 'program did not end'
    return clock.t - t0


def test_l1_loop_five_times_back_and_forth(clock):
    d = drive(clock, 6)
    send(d, '06WN,120,61,5,121', '06WN,121,01,12,30,+12500,x1,122', '06WN,122,65,400,123',
         '06WN,123,01,12,30,-12500,x1,124', '06WN,124,65,400,125', '06WN,125,62,121,000',
         '06PS,120')
    t_start = clock.t
    clock.t += 0.5
    assert ask(d, '06QA') is None                  # busy: silent (§3)
    assert ask(d, '06ES') == '06Y'                 # heard, no effect on an indexed run
    run_until_idle(d, clock)
    busy_s = clock.t - t_start
    # §9.3 L1: 5 x (2 x 1.10 s + 2 x 0.4 s) = 15.0 s (12 kHz peak, code 30 = 200000 Hz/s)
    assert busy_s == pytest.approx(15.0, abs=0.05)
    assert ask(d, '06QA') == '06QA,+0'


def test_l2_blink_ten_times_then_index_without_ramp(clock):
    d = drive(clock, 9)
    send(d, '09WN,100,61,10,121', '09WN,121,58,O0,1,122', '09WN,122,65,500,123',
         '09WN,123,58,O0,0,124', '09WN,124,65,500,125', '09WN,125,62,121,130',
         '09WN,130,11,05,+6000,x1,000', '09PS,100')
    edges = [0]
    busy_s = run_until_idle(d, clock, step_s=0.05,
                            each=lambda: edges.append(d.outputs['O0']))
    rising = sum(1 for a, b in zip(edges, edges[1:]) if b > a)
    assert rising == 10 and busy_s == pytest.approx(10.0 + 12.0, abs=0.06)
    assert ask(d, '09QO,O0') == '09QO,O0,0' and ask(d, '09QA') == '09QA,+6000'


def test_m1_relative_mode_adds_the_steps(clock):
    d = drive(clock)
    send(d, '00WN,100,01,20,30,+2400,X1,000', '00SA,-100', '00PS,100')
    run_until_idle(d, clock)
    assert ask(d, '00QA') == '00QA,+2300'


@pytest.mark.parametrize('start, moved', [(2400, 0), (5000, -2600), (-100, 2500)])
def test_m2_absolute_mode_goes_to_the_coordinate(clock, start, moved):
    d = drive(clock)
    send(d, '00WS,CM,1', '00WN,100,01,20,30,+2400,x1,000', f'00SA,{start}', '00PS,100')
    raw0 = d.axis.raw_position_steps
    run_until_idle(d, clock)
    assert ask(d, '00QA') == '00QA,+2400' and ask(d, '00QE') == '00QE,00,000'
    assert d.axis.raw_position_steps - raw0 == pytest.approx(moved)


def test_m3_cyclic_mode_takes_the_shortest_way(clock):
    d = drive(clock)
    send(d, '00WS,CM,2,999')
    for i, p in enumerate((0, 200, 400, 500, 700, 900)):
        send(d, f'00WN,10{i},11,05,{p:+d},x1,000')
    send(d, '00SA,900', '00PS,100')
    raw0 = d.axis.raw_position_steps
    run_until_idle(d, clock)
    assert ask(d, '00QA') == '00QA,+0' and d.axis.raw_position_steps - raw0 == 100
    send(d, '00PS,104')
    run_until_idle(d, clock)
    assert ask(d, '00QA') == '00QA,+700' and d.axis.raw_position_steps - raw0 == -200
    send(d, '00WN,106,11,05,-200,x1,000', '00PS,106')
    run_until_idle(d, clock)
    assert ask(d, '00QE') == '00QE,50,106' and ask(d, '00QA') == '00QA,+700'


def test_cyclic_modulus_reading_is_a_parameter(clock):
    d = drive(clock, cyclic_modulus='kkk')
    send(d, '00WS,CM,2,1000', '00WN,100,11,05,+1000,x1,000', '00PS,100')
    run_until_idle(d, clock)
    assert ask(d, '00QE') == '00QE,50,100'         # 0..kkk-1: 1000 is out of range


def test_x4_multiplies_steps_and_speed_in_relative_mode_only_where_allowed(clock):
    d = drive(clock)
    send(d, '00WN,100,11,10,+1000,x4,000', '00PS,100')
    t = run_until_idle(d, clock, step_s=0.001)
    assert ask(d, '00QA') == '00QA,+4000' and t == pytest.approx(4000 / 4000, abs=0.002)
    send(d, '00WS,RS,D1')                          # x4 not available in D1 (§4.2.2.3)
    clock.t += 0.3
    send(d, '00RA', '00PS,100')
    run_until_idle(d, clock)
    assert ask(d, '00QA') == '00QA,+1000'


def test_zero_search_stops_at_the_px_edge_then_counter_reset(clock):
    d = drive(clock, 1, px_edge_steps=5000.0)
    send(d, '01SA,777', '01WN,228,03,10,20,+,05,229', '01WN,229,60,000', '01PS,228')
    clock.t += 0.2
    assert ask(d, '01QI,PX') is None
    run_until_idle(d, clock, step_s=0.005)
    assert d.axis.raw_position_steps == pytest.approx(5000.0, abs=1e-6)
    assert ask(d, '01QA') == '01QA,+0' and ask(d, '01QI,PX') == '01QI,PX,0'
    # already on PX: only the slow approach back to the edge
    d.axis.motion.set_position(0)
    send(d, '01WN,230,11,30,+300,x1,000', '01PS,230')
    run_until_idle(d, clock)
    assert ask(d, '01QI,PX') == '01QI,PX,1'
    send(d, '01PS,228')
    run_until_idle(d, clock)
    assert d.axis.raw_position_steps == pytest.approx(5000.0, abs=1e-6)


def test_zero_search_on_a_forced_px_input_and_es_does_not_stop_it(clock):
    d = drive(clock, 1, px_edge_steps=1e9)
    send(d, '01WN,150,03,05,10,-,10,000', '01PS,150')
    clock.t += 1.0
    assert ask(d, '01ES') == '01Y'
    clock.t += 0.1
    d.update()
    assert d.busy and d.axis.velocity_hz == pytest.approx(-5000)
    d.set_input('PX', True)             # the proximity sensor comes on: ramp down, come back
    clock.t += 0.2
    d.update()
    assert d.busy and d.axis.velocity_hz == pytest.approx(1000)
    d.set_input('PX', False)
    assert not d.busy


def test_free_run_stops_on_es_and_the_program_goes_on(clock):
    d = drive(clock)
    send(d, '00WN,140,32,100,20,+,x1,141', '00WN,141,58,F3,1,000', '00PS,140')
    clock.t += 2.0
    d.update()
    assert d.axis.velocity_hz == pytest.approx(10000)
    assert ask(d, '00ES') == '00Y'
    run_until_idle(d, clock, step_s=0.001)
    assert ask(d, '00QO,F3') == '00QO,F3,1'         # continued at DDD after the stop
    # an unramped free run stops at once
    send(d, '00WN,142,22,0777,-,x1,000', '00PS,142')
    clock.t += 1.0
    assert ask(d, '00ES') == '00Y' and not d.busy
    assert ask(d, '00QM,142') == '00QM,142,22,0775,-,x1,000'      # Table 4 grid: 775 Hz


def test_delayed_stop_brakes_in_exactly_n_steps_and_ignores_es_while_accelerating(clock):
    d = drive(clock, 1)
    send(d, '01WN,165,05,10,20,+,3000,x1,000', '01PS,165')
    clock.t += 0.005
    assert ask(d, '01ES') == '01Y'                  # accelerating: ignored (§4.1.16 Note 4)
    clock.t += 1.0
    d.update()
    assert d.busy
    p0 = d.axis.position_steps
    assert ask(d, '01ES') == '01Y'
    run_until_idle(d, clock, step_s=0.001)
    assert d.axis.position_steps - p0 == pytest.approx(3000)
    # fewer steps than the ramp needs: slower first (Fig. 3b), still exactly n steps
    send(d, '01WN,166,05,10,20,-,0,x1,000', '01PS,166')
    clock.t += 1.0
    d.update()
    p0 = d.axis.position_steps
    d.set_input('ES', True)                         # the hardware STOP sensor
    run_until_idle(d, clock, step_s=0.001)
    assert d.axis.position_steps - p0 == pytest.approx(-1)       # Note 2: 0 is one step


def test_emergency_stop_ramps_down_and_69_recovers_the_rest(clock):
    d = drive(clock, 14)
    send(d, '14WN,100,31,050,10,+20000,x1,000', '14WN,220,69,221', '14WN,221,58,F0,1,000',
         '14PS,100')
    clock.t += 1.0
    assert ask(d, '14EE') == '14Y'
    assert d.busy                                     # still ramping down
    run_until_idle(d, clock, step_s=0.001)
    stopped = d.counter
    assert 0 < stopped < 20000
    send(d, '14PS,220')
    run_until_idle(d, clock)
    assert ask(d, '14QA') == '14QA,+20000' and ask(d, '14QO,F0') == '14QO,F0,1'
    send(d, '14PS,220')                               # nothing left to recover: null, 000
    assert not d.busy and ask(d, '14QA') == '14QA,+20000'


def test_conditional_jump_waits_on_an_input_then_goes_on(clock):
    d = drive(clock)
    send(d, '00WN,180,63,I1,0,180,181', '00WN,181,58,O2,1,000', '00PS,180')
    clock.t += 5.0
    d.update()
    assert d.busy and ask(d, '00QA') is None          # a jump loop on I1 = 0 is busy
    d.set_input('I1', True)
    assert not d.busy and ask(d, '00QO,O2') == '00QO,O2,1'


def test_hardware_start_selects_the_cell_and_is_refused_while_ee(clock):
    d = drive(clock)
    send(d, '00WN,105,58,F5,1,000', '00WN,100,58,F0,1,000')
    d.set_input('S0', True)
    d.set_input('S2', True)                           # Table 1: SEL0 + SEL2 = cell 105
    d.set_input('EE', True)
    d.set_input('ST', True)
    assert ask(d, '00QO,F5') == '00QO,F5,0'           # refused while EE is on (§2.2.2)
    d.set_input('ST', False)
    d.set_input('EE', False)
    d.set_input('ST', True)
    assert ask(d, '00QO,F5') == '00QO,F5,1' and ask(d, '00QO,F0') == '00QO,F0,0'


def test_cam_complements_o3_once_when_the_counter_passes(clock):
    d = drive(clock, 6)
    send(d, '06SO,O3,1', '06WN,177,57,1,+13000,178', '06WN,178,31,240,10,+20000,x1,000',
         '06PS,177')
    run_until_idle(d, clock)
    assert ask(d, '06QO,O3') == '06QO,O3,0' and ask(d, '06QC') == '06QC,0'
    send(d, '06SC,1,+117500', '06SA,200000')          # loading the counter is no motion
    assert ask(d, '06QC') == '06QC,1,+117500'


def test_current_counter_reset_and_closing_loop_instructions(clock):
    d = drive(clock)
    send(d, '00SA,55', '00WN,200,70,0,201', '00WN,201,60,000', '00PS,200')
    assert not d.current_on and ask(d, '00QA') == '00QA,+0'
    send(d, '00CY')
    assert d.current_on


def test_protection_stops_the_motor_and_power_cycle_clears_ram(clock):
    d = drive(clock, 2)
    send(d, '02WN,228,32,100,10,+,x1,000', '02PS,228')
    clock.t += 1.0
    d.inject_protection()
    assert not d.busy and ask(d, '02QO,FA') == '02QO,FA,0'
    assert ask(d, '02PS,228') == '02Y' and not d.busy      # nothing runs while blocked
    d.power_cycle()
    assert ask(d, '02QO,FA') == '02QO,FA,1' and ask(d, '02QA') == '02QA,+0'
    assert ask(d, '02QM,228') == '02QM,228,00,000'


def test_eeprom_persists_presets_and_cells_with_write_counters(clock, tmp_path):
    path = tmp_path / 'xmind_k_d.json'
    d = drive(clock, 3, storage_path=path)
    send(d, '03WN,150,65,100,000', '03WN,228,65,1,000', '03WS,RD,0', '03WS,AD,21')
    assert d.eeprom_cell_writes == 1 and d.eeprom_preset_writes == 2
    again = drive(clock, 3, storage_path=path)        # power cycle: EEPROM kept, RAM not
    assert again.address == 21 and again.presets['RD'] == 0
    assert ask(again, '21QM,150') == '21QM,150,65,100,000'
    assert ask(again, '21QM,228') == '21QM,228,00,000'
    assert again.eeprom_writes == 3


def test_every_instruction_code_executes(clock):
    """Each of the 20 codes stored and run once, in one program."""
    d = drive(clock, 1, px_edge_steps=100.0)
    program = ['00,101', '61,2,102', '01,03,10,+10,x1,103', '31,030,10,-10,x1,104',
               '11,02,+5,x1,105', '21,0100,-5,x1,106', '62,102,107', '57,1,+999999,108',
               '58,F1,1,109', '65,1,110', '63,F1,1,112,111', '70,0,000', '70,1,113',
               '60,114', '03,03,10,+,05,115', '02,03,10,+,x1,116', '32,030,10,-,x1,117',
               '12,02,+,x1,118', '22,0050,-,x1,119', '05,03,10,+,10,x1,120',
               '69']                       # nothing to recover: the program ends (§4.1.15)
    for i, body in enumerate(program):
        send(d, f'01WN,{100 + i},{body}')
    assert {int(b.split(',')[0]) for b in program} == set(xk.INSTRUCTION_TYPES)
    send(d, '01PS,100')
    for _ in range(5):                                 # each free run ends on ES
        clock.t += 0.5
        d.update()
        assert d.busy
        assert ask(d, '01ES') == '01Y'
        clock.t += 0.5
        d.update()
    run_until_idle(d, clock)
    assert ask(d, '01QO,F1') == '01QO,F1,1' and ask(d, '01QC') == '01QC,1,+999999'
    assert d.current_on and ask(d, '01QE') == '01QE,00,000'
