"""SimAxis switch/index events and the CiA 402 homing procedures, in simulated time."""

import pytest
from stepper_sim.core.axis import (
    HOMING_METHODS,
    AxisEvent,
    HomingRun,
    SimAxis,
    SwitchMethod,
    register_homing_method,
)
from stepper_sim.core.motion import INF

N = 12_800          # steps per revolution: an index pulse every N steps
PHASE = 100.0       # index pulses at 100 + k * 12800
CAM = (50_000.0, 70_000.0)      # home switch active on [50000, 70000)
LIMIT_NEG, LIMIT_POS = -100_000.0, 200_000.0
OFFSET = 1_000.0


class FakeClock:
    def __init__(self, t: float = 0.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def make_axis(start: float, clock: FakeClock, **kw) -> SimAxis:
    args = dict(home_switch_steps=CAM[0], home_switch_width_steps=CAM[1] - CAM[0],
                limit_neg_steps=LIMIT_NEG, limit_pos_steps=LIMIT_POS, steps_per_rev=N,
                index_phase_steps=PHASE, position_steps=start, clock=clock)
    args.update(kw)
    return SimAxis(**args)


def run_homing(method: int, start: float, step_s: float = 0.05, speed_zero: float = 3_200,
               **kw) -> tuple[HomingRun, SimAxis, FakeClock]:
    clock = FakeClock()
    axis = make_axis(start, clock, **kw.pop('axis', {}))
    kw.setdefault('start_stop_hz', 16_000)
    run = HomingRun(axis, method, speed_search_hz=40_000, speed_zero_hz=speed_zero,
                    acceleration_hz_s=100_000, offset_steps=OFFSET, **kw)
    run.start()
    while not run.done and clock.t < 120:
        clock.t += step_s
        axis.update()
    return run, axis, clock


def index_left_of(x):      # first index pulse below x
    k = (x - PHASE) // N
    p = PHASE + k * N
    return p if p < x else p - N


def index_right_of(x):
    return index_left_of(x) + N


LO, HI = CAM
# method -> (expected raw home position, start positions from which it must succeed)
EXPECTED = {
    1: (index_right_of(LIMIT_NEG), (0.0, 60_000.0, 120_000.0)),
    2: (index_left_of(LIMIT_POS), (0.0, 60_000.0, 120_000.0)),
    3: (index_left_of(LO), (0.0, 60_000.0)),      # positive home switch: CiA assumes the
    4: (index_right_of(LO), (0.0, 60_000.0)),     # switch covers the positive side
    5: (index_right_of(HI), (60_000.0, 120_000.0)),
    6: (index_left_of(HI), (60_000.0, 120_000.0)),
    7: (index_left_of(LO), (0.0, 60_000.0, 120_000.0)),
    8: (index_right_of(LO), (0.0, 60_000.0, 120_000.0)),
    9: (index_left_of(HI), (0.0, 60_000.0, 120_000.0)),
    10: (index_right_of(HI), (0.0, 60_000.0, 120_000.0)),
    11: (index_right_of(HI), (0.0, 60_000.0, 120_000.0)),
    12: (index_left_of(HI), (0.0, 60_000.0, 120_000.0)),
    13: (index_right_of(LO), (0.0, 60_000.0, 120_000.0)),
    14: (index_left_of(LO), (0.0, 60_000.0, 120_000.0)),
    17: (LIMIT_NEG, (0.0, 120_000.0)),
    18: (LIMIT_POS, (0.0, 120_000.0)),
    19: (LO, (0.0, 60_000.0)),
    20: (LO, (0.0, 60_000.0)),
    21: (HI, (60_000.0, 120_000.0)),
    22: (HI, (60_000.0, 120_000.0)),
    23: (LO, (0.0, 120_000.0)),
    24: (LO, (0.0, 120_000.0)),
    25: (HI, (0.0, 120_000.0)),
    26: (HI, (0.0, 120_000.0)),
    27: (HI, (0.0, 120_000.0)),
    28: (HI, (0.0, 120_000.0)),
    29: (LO, (0.0, 120_000.0)),
    30: (LO, (0.0, 120_000.0)),
    33: (index_left_of(60_000.0), (60_000.0,)),
    34: (index_right_of(60_000.0), (60_000.0,)),
    35: (60_000.0, (60_000.0,)),
    37: (60_000.0, (60_000.0,)),
}


def test_index_helpers_match_the_world():
    assert index_left_of(LO) == 38_500 and index_right_of(LO) == 51_300
    assert index_left_of(HI) == 64_100 and index_right_of(HI) == 76_900


@pytest.mark.parametrize('method,start', [(m, s) for m, (_, starts) in EXPECTED.items()
                                          for s in starts])
def test_method_ends_on_its_switch_or_index_with_the_offset(method, start):
    home, _ = EXPECTED[method]
    run, axis, _ = run_homing(method, start)
    assert run.status == 'attained', run.error
    assert run.home_raw_steps == pytest.approx(home, abs=1e-6)
    # the slow phase is start-stop (3200 Hz <= 16000 Hz): the axis stops on the home point
    assert axis.raw_position_steps == pytest.approx(home, abs=1e-6)
    assert axis.position_steps == pytest.approx(OFFSET, abs=1e-6)
    assert not axis.moving


def test_all_cia402_methods_are_in_the_table():
    assert set(EXPECTED) == set(HOMING_METHODS)


def test_one_huge_time_step_still_homes_exactly():
    run, axis, clock = run_homing(7, 120_000.0, step_s=200.0)
    assert run.status == 'attained'
    assert axis.position_steps == pytest.approx(OFFSET, abs=1e-6)
    assert axis.raw_position_steps == pytest.approx(index_left_of(LO), abs=1e-6)


def test_ramped_final_stop_keeps_the_home_point_at_the_offset():
    # slow speed above the start-stop limit: the axis decelerates past the home point
    run, axis, _ = run_homing(19, 0.0, speed_zero=20_000, start_stop_hz=0.0)
    assert run.status == 'attained'
    overshoot = axis.raw_position_steps - LO
    assert overshoot == pytest.approx(-(20_000 ** 2) / (2 * 100_000))   # moving negative
    assert axis.position_steps == pytest.approx(OFFSET + overshoot)


def test_limit_reached_where_not_expected_is_an_error():
    run, axis, clock = run_homing(3, 120_000.0)  # above the cam: CiA 3 searches positive
    assert run.status == 'error'
    assert 'limit_pos switch reached at 200000 steps while searching for home' in run.error
    assert axis.moving                          # stopping on the homing ramp
    clock.t += 1.0
    axis.update()
    assert not axis.moving
    assert axis.raw_position_steps < LIMIT_POS + 40_000 ** 2 / (2 * 100_000) + 1


def test_switch_never_found_is_an_error():
    run, axis, _ = run_homing(19, 0.0, max_travel_steps=30_000,
                              axis=dict(home_switch_steps=None, limit_neg_steps=None,
                                        limit_pos_steps=None))
    assert run.status == 'error'
    assert run.error == 'home not found within 30000 steps (method 19)'
    assert axis.position_steps == pytest.approx(30_000)


def test_active_limit_blocks_the_search_direction():
    run, _, _ = run_homing(19, 250_000.0)       # starts on the positive limit
    assert run.status == 'error'
    assert 'limit_pos switch is active: cannot search in the positive direction' in run.error


def test_unknown_method_and_abort():
    run, _, _ = run_homing(15, 0.0)
    assert run.status == 'error'
    assert 'homing method 15 is not supported' in run.error and '37' in run.error
    clock = FakeClock()
    axis = make_axis(0.0, clock)
    run = HomingRun(axis, 19, speed_search_hz=40_000, speed_zero_hz=3_200,
                    acceleration_hz_s=100_000)
    run.start()
    clock.t = 0.2
    axis.update()
    assert run.status == 'running' and axis.moving
    run.abort()
    clock.t = 5.0
    axis.update()
    assert run.status == 'interrupted' and not axis.moving


def test_vendor_methods_plug_into_the_table():
    def hard_stop_negative(run):            # e.g. a vendor "drive to the negative limit"
        run.move(-1, run.speed_zero_hz)
        ev = yield from run.wait_for({'limit_neg'}, {'limit_neg'})
        return ev.raw_position_steps

    table = dict(HOMING_METHODS)
    table[-2] = hard_stop_negative
    run, axis, _ = run_homing(-2, 0.0, methods=table)
    assert run.status == 'attained', run.error
    assert run.home_raw_steps == LIMIT_NEG and axis.position_steps == pytest.approx(OFFSET)
    with pytest.raises(ValueError, match='already defined'):
        register_homing_method(19, SwitchMethod('home', 'lo', -1, False))


def test_edges_and_index_pulses_are_reported_where_they_happen():
    clock = FakeClock()
    axis = make_axis(0.0, clock)
    events: list[AxisEvent] = []
    axis.add_listener(events.append)
    axis.motion.move_to(80_000, 16_000, INF)           # 5 s at constant speed
    clock.t = 10.0
    axis.update()                                       # one update over everything
    names = [(e.name, e.active) for e in events]
    home = [e for e in events if e.name == 'home']
    assert [(e.active, e.raw_position_steps) for e in home] == [(True, LO), (False, HI)]
    assert home[0].time_s == pytest.approx(LO / 16_000)
    assert home[0].direction == 1
    index = [e.raw_position_steps for e in events if e.name == 'index']
    assert index == [PHASE + k * N for k in range(7)]
    assert names[-1] == ('target_reached', True)
    assert events[-1].time_s == pytest.approx(5.0)
    # back down: the edges again, in reverse order
    events.clear()
    axis.motion.move_to(0, 16_000, INF)
    clock.t = 20.0
    axis.update()
    home = [(e.active, e.raw_position_steps, e.direction) for e in events if e.name == 'home']
    assert home == [(True, HI, -1), (False, LO, -1)]


def test_forced_inputs_and_release():
    clock = FakeClock()
    axis = make_axis(0.0, clock)
    events = []
    axis.add_listener(events.append)
    axis.set_input('limit_pos', True)
    assert axis.input('limit_pos') and events[-1].forced and events[-1].active
    axis.set_input('limit_pos', True)               # no change, no event
    assert len(events) == 1
    axis.release('limit_pos')
    assert not axis.input('limit_pos') and not events[-1].active
    axis.set_input('I3', True)                      # a vendor input without a switch
    assert axis.inputs['I3'] is True
    with pytest.raises(KeyError, match='unknown input'):
        axis.input('nope')
    # a forced home switch hides the real one during motion
    axis.set_input('home', False)
    axis.motion.move_to(60_000, 16_000, INF)
    clock.t = 10.0
    axis.update()
    assert not axis.input('home')
    axis.release('home')
    assert axis.input('home')                       # at 60000: inside the cam
