"""A chain's runs as the X-MIND K stores them (vendors/xmind_k/program.py chain_runs,
Estimate.chain): frequencies on the Table 4 grid (§4.1.6 Note), each run ending at its knot's
instant and a step or so off its position (carried into the next run), the last exactly on the
last knot; waits in whole ms (§4.1.12); the instructions chained by their next cell. No wire."""

import pytest
from stepper_drivers.contract.drive import DriveError
from stepper_drivers.protocol import xmind_k as xk
from stepper_drivers.vendors.xmind_k.program import ChainRun, Estimate, chain_runs

MOST_HZ = 2900
T0 = 100.0
KNOTS = [(T0 + 0.7, 55.2), (T0 + 2.3, 581.4), (T0 + 3.0, 636.6)]


def test_each_run_is_on_the_grid_and_ends_at_its_knot():
    runs = chain_runs(0, T0, KNOTS, MOST_HZ)
    assert len(runs) == 3
    assert all(r.frequency_hz in xk.TABLE4_HZ for r in runs)
    t, x = T0, 0
    for k, (run, (tk, xk_)) in enumerate(zip(runs, KNOTS)):
        assert run.duration_s == pytest.approx(abs(run.steps) / run.frequency_hz)
        span = tk - t
        t, x = t + run.duration_s, x + run.steps
        if k < len(KNOTS) - 1:
            # its time kept within half a step, its position within a step (then carried)
            assert abs(t - tk) <= 0.5 / run.frequency_hz + 1e-9
            assert abs(x - xk_) <= 1.0
        else:
            # the last: its steps exact, its rate the nearest grid value (1 Hz apart here)
            assert abs(t - tk) <= span * 0.5 / run.frequency_hz + 1e-9
    assert x == round(KNOTS[-1][1])


def test_a_run_whose_instant_has_passed_is_left_out():
    runs = chain_runs(0, T0 + 0.8, KNOTS, MOST_HZ)
    assert len(runs) == 2 and sum(r.steps for r in runs) == round(KNOTS[-1][1])


def test_a_knot_where_the_joint_stays_is_a_wait_in_whole_ms():
    runs = chain_runs(10, T0, [(T0 + 0.5004, 10), (T0 + 1.0, 110)], MOST_HZ)
    assert runs[0] == ChainRun(0, 0, 0.5)
    assert runs[1].steps == 100
    instr = runs[0].instruction(229)
    assert (instr.code, instr.get('delay_ms'), instr.next_cell) == (65, 500, 229)


def test_rates_stay_within_the_grid_limits():
    fast = chain_runs(0, T0, [(T0 + 0.1, 1000)], MOST_HZ)       # 10 kHz asked
    assert fast[0].frequency_hz == xk.table4_floor(MOST_HZ) and fast[0].steps == 1000
    slow = chain_runs(0, T0, [(T0 + 10.0, 2)], MOST_HZ)         # 0.2 Hz asked
    assert slow[0].frequency_hz == 1


def test_more_steps_than_one_instruction_holds_is_refused():
    with pytest.raises(DriveError, match='8388607'):
        chain_runs(0, T0, [(T0 + 3600.0, xk.STEPS_MAX + 10)], MOST_HZ)


def test_the_estimate_follows_the_runs_and_rests_after():
    runs = chain_runs(0, T0, KNOTS, MOST_HZ)
    est = Estimate.chain(T0, 0, runs)
    t = T0
    x = 0
    for run in runs:
        mid = est.state(t + run.duration_s / 2)
        assert mid[0] == pytest.approx(x + run.steps / 2)
        assert mid[1] == pytest.approx(run.steps / run.duration_s)
        t, x = t + run.duration_s, x + run.steps
    assert est.end_s == pytest.approx(t)
    assert est.state(t + 5.0) == (x, 0.0)
