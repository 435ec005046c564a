"""MotionModel kinematics in simulated time (exact closed-form, no wall clock)."""

import math

import pytest
from stepper_sim.core.motion import INF, MotionModel


class FakeClock:
    def __init__(self, t: float = 0.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def sample(m: MotionModel, t_end: float, dt: float = 0.001):
    """(t, x, v) every dt up to t_end (a slow cross-check of the closed form)."""
    out = []
    t = m.time_s
    while t <= t_end + 1e-12:
        m.update(t)
        out.append((t, m.position_steps, m.velocity_hz))
        t += dt
    return out


def test_trapezoid_reaches_target_at_the_right_time():
    # Manual T17 / spec G6: 240000 steps at 100000 Hz, 80000 Hz/s: 1.25 + 1.15 + 1.25 = 3.65 s.
    m = MotionModel(clock=FakeClock())
    m.move_to(240_000, 100_000, 80_000)
    assert m.finish_time_s == pytest.approx(3.65, abs=1e-9)
    m.update(1.25)
    assert m.position_steps == pytest.approx(62_500)          # end of the acceleration ramp
    assert m.velocity_hz == pytest.approx(100_000)
    assert m.in_ramp is False                                 # cruising at the boundary
    m.update(3.64)
    assert m.moving and not m.target_reached
    assert m.position_steps < 240_000
    m.update(3.65)
    assert m.position_steps == 240_000                        # exact, no rounding drift
    assert m.velocity_hz == 0.0
    assert not m.moving and m.target_reached


def test_triangular_when_the_distance_is_short():
    # Spec G8: PV 100000, PA 640000, 10000 steps -> triangle, peak sqrt(6.4e9) = 80000 Hz, 0.25 s.
    m = MotionModel(clock=FakeClock())
    m.move_to(10_000, 100_000, 640_000)
    assert m.finish_time_s == pytest.approx(0.25)
    m.update(0.125)
    assert m.velocity_hz == pytest.approx(80_000)
    assert m.position_steps == pytest.approx(5_000)
    peak = max(v for _, _, v in sample(m, 0.25))
    assert peak == pytest.approx(80_000, rel=1e-3)
    m.update(0.25)
    assert m.position_steps == 10_000 and not m.moving


def test_asymmetric_ramps_and_negative_direction():
    m = MotionModel(position_steps=10_000, clock=FakeClock())
    # acc 1000, dec 2000, 1000 Hz: 1 s / 500 steps up, 0.5 s / 250 down, 9250 cruise = 9.25 s.
    m.move_to(0, 1_000, 1_000, 2_000)
    assert m.finish_time_s == pytest.approx(10.75)
    m.update(1.0)
    assert m.velocity_hz == pytest.approx(-1_000)
    assert m.position_steps == pytest.approx(9_500)
    m.update(10.75)
    assert m.position_steps == 0


def test_start_stop_profile_with_infinite_acceleration():
    # Spec G8: PV 16000 Hz start-stop, 12800 steps -> constant 16000 Hz for 0.8 s.
    m = MotionModel(clock=FakeClock())
    m.move_to(12_800, 16_000, INF)
    assert m.velocity_hz == 16_000          # jumps at once
    m.update(0.4)
    assert m.position_steps == pytest.approx(6_400)
    m.update(0.8)
    assert m.position_steps == 12_800 and m.velocity_hz == 0.0


def test_retarget_ahead_continues_without_stopping():
    clock = FakeClock()
    m = MotionModel(clock=clock)
    m.move_to(100_000, 10_000, 10_000)
    m.update(2.0)                            # 5000 steps of ramp + 10000 cruise
    assert m.position_steps == pytest.approx(15_000)
    m.move_to(50_000, 10_000, 10_000)
    trace = sample(m, m.finish_time_s)
    velocities = [v for _, _, v in trace[:-1]]
    assert min(velocities) > 0               # monotonic: no intermediate stop
    positions = [x for _, x, _ in trace]
    assert all(b >= a for a, b in zip(positions, positions[1:]))
    m.update(m.finish_time_s)
    assert m.position_steps == 50_000
    # 15000 -> 50000 at 10000 Hz: 3.5 s minus half the 1 s stop ramp... = 35000/10000 + 0.5
    assert m.finish_time_s == pytest.approx(2.0 + 3.0 + 0.5 + 0.5)


def test_retarget_behind_reverses_through_a_stop():
    m = MotionModel(clock=FakeClock())
    m.move_to(100_000, 10_000, 10_000)
    m.update(2.0)                            # at 15000, +10000 Hz
    m.move_to(0, 10_000, 10_000)
    trace = sample(m, m.finish_time_s)
    top = max(x for _, x, _ in trace)
    assert top == pytest.approx(20_000, abs=1)          # 15000 + v^2 / 2a = 20000
    assert min(v for _, _, v in trace) == pytest.approx(-10_000)
    m.update(m.finish_time_s)
    assert m.position_steps == 0 and not m.moving
    # 1 s to stop, then 20000 steps: 1 s ramp + 1 s cruise + 1 s ramp
    assert m.finish_time_s == pytest.approx(2.0 + 1.0 + 3.0)


def test_retarget_too_close_to_stop_overshoots_and_returns():
    m = MotionModel(clock=FakeClock())
    m.move_to(100_000, 10_000, 10_000)
    m.update(2.0)
    m.move_to(16_000, 10_000, 10_000)        # needs 5000 steps to stop, has 1000
    trace = sample(m, m.finish_time_s)
    assert max(x for _, x, _ in trace) == pytest.approx(20_000, abs=1)
    m.update(m.finish_time_s)
    assert m.position_steps == 16_000


def test_velocity_mode_ramps_and_reverses():
    m = MotionModel(clock=FakeClock())
    m.run_velocity(5_000, 1_000, 2_000)
    m.update(2.5)
    assert m.velocity_hz == pytest.approx(2_500) and not m.target_reached
    m.update(5.0)
    assert m.velocity_hz == pytest.approx(5_000) and m.target_reached and m.moving
    m.update(6.0)
    assert m.position_steps == pytest.approx(12_500 + 5_000)
    m.run_velocity(-5_000, 1_000, 2_000)     # decelerate at 2000 (2.5 s), accelerate at 1000
    assert m.finish_time_s == pytest.approx(6.0 + 2.5 + 5.0)
    m.update(8.5)
    assert m.velocity_hz == pytest.approx(0.0, abs=1e-6)
    m.update(13.5)
    assert m.velocity_hz == pytest.approx(-5_000)


def test_stop_and_quick_stop_ramps():
    m = MotionModel(clock=FakeClock())
    m.run_velocity(5_000, INF)
    m.update(1.0)
    m.stop(2_500)
    assert m.mode == 'stop'
    assert m.finish_time_s == pytest.approx(3.0)
    m.update(3.0)
    assert m.position_steps == pytest.approx(5_000 + 5_000)   # v^2 / 2d = 5000
    assert not m.moving and m.target_reached
    m.run_velocity(5_000, INF)
    m.update(4.0)
    m.quick_stop(10_000)
    assert m.mode == 'quick_stop'
    assert m.finish_time_s == pytest.approx(4.5)
    m.update(10.0)
    assert m.position_steps == pytest.approx(10_000 + 5_000 + 1_250)


def test_immediate_stop_freezes_the_position():
    m = MotionModel(clock=FakeClock())
    m.move_to(100_000, 10_000, 10_000)
    m.update(1.0)
    x = m.position_steps
    m.stop_immediately()
    assert m.velocity_hz == 0.0 and not m.moving
    m.update(5.0)
    assert m.position_steps == x


def test_set_position_re_references_targets():
    m = MotionModel(position_steps=500, clock=FakeClock())
    m.set_position(0)
    assert m.position_steps == 0 and m.raw_position_steps == 500
    m.move_to(1_000, 1_000, INF)
    m.update(1.0)
    assert m.position_steps == 1_000 and m.raw_position_steps == 1_500


def test_max_velocity_clamp_and_bad_arguments():
    m = MotionModel(max_velocity_hz=2_000, clock=FakeClock())
    m.move_to(10_000, 50_000, INF)
    assert m.velocity_hz == 2_000
    m.run_velocity(-9_000, INF)
    assert m.velocity_hz == -2_000
    with pytest.raises(ValueError, match='acceleration_hz_s must be > 0'):
        m.move_to(0, 1_000, 0)
    with pytest.raises(ValueError, match='needs a velocity > 0'):
        m.move_to(5, 0, 1_000)


def test_one_large_step_equals_many_small_ones():
    a, b = MotionModel(clock=FakeClock()), MotionModel(clock=FakeClock())
    for m in (a, b):
        m.move_to(123_456, 30_000, 40_000, 70_000)
    sample(a, 2.0, dt=0.0007)
    a.update(2.0)
    b.update(2.0)
    assert a.position_steps == pytest.approx(b.position_steps, abs=1e-6)
    assert a.velocity_hz == pytest.approx(b.velocity_hz, abs=1e-6)
    b.update(1.0)                                   # time never goes back
    assert b.time_s == 2.0
    assert math.isclose(b.finish_time_s, a.finish_time_s)
