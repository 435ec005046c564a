"""motion/trajectory.py: the checks and the synchronized segments, without ROS."""

import math

import pytest
from rigs_motion import quintic_line
from stepper_drivers.motion.move_profile import motion_state
from stepper_drivers.motion.trajectory import (
    EDGE_MARGIN,
    JointLimits,
    TrajectoryError,
    build,
    plan,
    planned_at,
    sample,
    trapezoid,
)

LIM = JointLimits(min_steps=-1e6, max_steps=1e6, max_velocity_steps_s=4000.0,
                  max_acceleration_steps_s2=20000.0, steps_per_unit=1000.0, unit='rad')


def profile_distance(v, a, t):
    """Distance of the symmetric trapezoid (v, a) that lasts t."""
    return v * (t - v / a)


@pytest.mark.parametrize('d, t', [(1000, 1.0), (10, 0.05), (3999, 1.0), (1, 2.0)])
def test_trapezoid_covers_the_distance_in_exactly_the_time(d, t):
    v, a = trapezoid(d, t, 1e9, 20000.0)
    assert a == pytest.approx(20000.0 * EDGE_MARGIN)     # the margin for the drives' rounding
    assert profile_distance(v, a, t) == pytest.approx(d, rel=1e-9)
    assert v <= a * t / 2                                     # a real trapezoid (or triangle)


def test_trapezoid_names_the_limit_it_would_exceed():
    # 1000 steps in 0.2 s need >= 4 * 1000 / 0.04 = 100000 steps/s^2
    why = trapezoid(1000, 0.2, 1e9, 20000.0)
    assert why.startswith('needs an acceleration of at least 1.02e+05 steps/s^2') and \
        'max_acceleration is 2e+04' in why
    # 3000 steps in 1 s with ramps of 19600 steps/s^2 need v = (a - sqrt(a^2 - 4 a d)) / 2
    a = 20000.0 * EDGE_MARGIN
    v = (a - math.sqrt(a * a - 4 * a * 3000)) / 2                    # 3737.4
    why = trapezoid(3000, 1.0, 3000.0, 20000.0)
    assert isinstance(why, str) and f'{v:.4g} steps/s' in why and 'max_velocity is 3000' in why
    assert trapezoid(3000, 1.0, 3800.0, 20000.0)[0] == pytest.approx(v)


def test_axes_of_one_segment_arrive_together_on_a_straight_path():
    traj = build(['a', 'b'], [1.0, 1.5], [[1000, -200], [1000, 300]], known=['a', 'b', 'c'])
    segs = plan(traj, {'a': 0.0, 'b': 0.0}, {'a': LIM, 'b': LIM})
    assert [(s.start_s, s.end_s) for s in segs] == [(0.0, 1.0), (1.0, 1.5)]
    first = {m.joint: m for m in segs[0].moves}
    for joint, dist in (('a', 1000), ('b', 200)):
        m = first[joint]
        assert profile_distance(m.velocity_steps_s, m.acceleration_steps_s2, 1.0) == \
            pytest.approx(dist)
    # one ramp time for both: the same curve scaled, so b / a stays -200 / 1000 throughout
    ramps = {j: m.velocity_steps_s / m.acceleration_steps_s2 for j, m in first.items()}
    assert ramps['a'] == pytest.approx(ramps['b'])
    assert first['b'].velocity_steps_s / first['a'].velocity_steps_s == pytest.approx(0.2)
    assert [m.joint for m in segs[1].moves] == ['b']          # a holds: no move sent
    assert segs[1].moves[0].target_steps == 300


def test_an_impossible_segment_is_refused_before_anything_naming_joint_point_and_limit():
    traj = build(['a', 'b'], [1.0, 1.1], [[100, 0], [100, 5000]], known=['a', 'b'])
    with pytest.raises(TrajectoryError, match=r'b: segment to point 1 \(1 s to 1.1 s\) needs an '
                                              r'acceleration .*max_acceleration'):
        plan(traj, {'a': 0.0, 'b': 0.0}, {'a': LIM, 'b': LIM})


def test_a_point_beyond_the_position_limits_is_refused_in_joint_units():
    lim = JointLimits(-1000, 1000, 4000, 20000, steps_per_unit=1000.0, unit='rad')
    traj = build(['a'], [1.0], [[1500]], known=['a'])
    with pytest.raises(TrajectoryError, match=r'a: point 0 at 1.5 rad is outside '
                                              r'min_position..max_position \(-1..1 rad\)'):
        plan(traj, {'a': 0.0}, {'a': lim})


@pytest.mark.parametrize('joints, times, positions, why', [
    (['x'], [1.0], [[0]], r"joints \['x'\] are not driven by this node"),
    (['a', 'a'], [1.0], [[0, 0]], 'name a joint twice'),
    (['a'], [1.0, 1.0], [[0], [1]], r'point 1: time_from_start 1 s does not increase'),
    (['a'], [-0.5], [[0]], r'point 0: time_from_start -0.5 s'),
    (['a'], [1.0], [[0, 1]], r'point 0: 2 positions for 1 joints'),
    (['a'], [1.0], [[math.nan]], r"point 0: position of \['a'\] is not a number"),
])
def test_malformed_trajectories_are_refused(joints, times, positions, why):
    with pytest.raises(TrajectoryError, match=why):
        build(joints, times, positions, known=['a', 'b'])


def test_a_trajectory_started_in_the_past_skips_the_points_already_due():
    traj = build(['a'], [1.0, 2.0, 3.0], [[100], [200], [300]], known=['a'])
    segs = plan(traj, {'a': 150.0}, {'a': LIM}, from_s=1.5)
    assert [(s.start_s, s.end_s) for s in segs] == [(1.5, 2.0), (2.0, 3.0)]
    assert segs[0].moves[0].target_steps == 200


def test_sample_is_linear_between_points_and_holds_at_the_ends():
    traj = build(['a', 'b'], [1.0, 2.0], [[100, 10], [300, 10]], known=['a', 'b'])
    start = {'a': 0.0, 'b': 10.0}
    assert sample(traj, start, 0.5) == {'a': 50.0, 'b': 10.0}
    assert sample(traj, start, 1.5) == {'a': 200.0, 'b': 10.0}
    assert sample(traj, start, 9.0) == {'a': 300.0, 'b': 10.0}


def test_the_ramp_is_the_one_the_most_loaded_axis_needs():
    """b has a tenth of a's acceleration: its ramp decides, a follows the same ramp time."""
    slow = JointLimits(-1e6, 1e6, 4000.0, 2000.0)
    traj = build(['a', 'b'], [1.0], [[1000, 400]], known=['a', 'b'])
    (seg,) = plan(traj, {'a': 0.0, 'b': 0.0}, {'a': LIM, 'b': slow})
    m = {x.joint: x for x in seg.moves}
    assert m['b'].acceleration_steps_s2 == pytest.approx(2000.0 * EDGE_MARGIN)
    assert m['a'].acceleration_steps_s2 < 20000.0 * EDGE_MARGIN
    for j, d in (('a', 1000), ('b', 400)):
        assert profile_distance(m[j].velocity_steps_s, m[j].acceleration_steps_s2, 1.0) == \
            pytest.approx(d)


def test_start_stop_drives_move_without_ramps_when_every_axis_can():
    ss = JointLimits(-1e6, 1e6, 50_000.0, 200_000.0, start_stop_steps_s=16_000.0)
    (seg,) = plan(build(['a', 'b'], [0.5], [[4000, -2000]], known=['a', 'b']),
                  {'a': 0.0, 'b': 0.0}, {'a': ss, 'b': ss})
    assert {(m.joint, m.velocity_steps_s, m.acceleration_steps_s2) for m in seg.moves} == \
        {('a', 8000.0, math.inf), ('b', 4000.0, math.inf)}


def test_the_plan_leaves_acceleration_headroom_when_the_segment_allows():
    (seg,) = plan(build(['a'], [1.0], [[1000]], known=['a']), {'a': 0.0}, {'a': LIM})
    (m,) = seg.moves
    assert m.acceleration_steps_s2 == pytest.approx(0.7 * 20000.0)
    assert profile_distance(m.velocity_steps_s, m.acceleration_steps_s2, 1.0) == \
        pytest.approx(1000)


def quintic(length_steps, duration_s, dt_s, joints=2):
    """A straight line in joint space with quintic timing (rest to rest), a point every dt_s, as
    a planner's time parameterisation gives it: tiny segments at both ends."""
    n = int(round(duration_s / dt_s))
    times, positions = [], []
    for k in range(1, n + 1):
        s = k / n
        x = length_steps * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
        times.append(k * dt_s)
        positions.append([x * (1 - 0.5 * j) for j in range(joints)])
    return build(['a', 'b'][:joints], times, positions, known=['a', 'b'])


def test_dense_points_merge_into_segments_as_long_as_the_bus_needs():
    traj = quintic(2000, 3.0, 0.05)
    segs = plan(traj, {'a': 0.0, 'b': 0.0}, {'a': LIM, 'b': LIM}, min_segment_s=0.3)
    assert all(s.end_s - s.start_s >= 0.3 - 1e-9 for s in segs)
    assert segs[-1].end_s == pytest.approx(3.0) and segs[-1].point == len(traj.points) - 1
    assert sum(s.merged for s in segs) + len(segs) == len(traj.points)
    for s in segs:                       # every segment ends on a point of the trajectory
        assert s.end_s == pytest.approx(traj.points[s.point].time_s)
        assert {m.joint: m.target_steps for m in s.moves} == \
            dict(zip(traj.joints, traj.points[s.point].positions_steps))
    # without a bus time nothing is merged that the joints can take ...
    stiff = JointLimits(-1e6, 1e6, 1e5, 1e7)
    assert len(plan(traj, {'a': 0.0, 'b': 0.0}, {'a': stiff, 'b': stiff})) == len(traj.points)
    # ... and what they cannot (stop and go at 1250 steps/s in 50 ms) is merged until they can
    segs = plan(traj, {'a': 0.0, 'b': 0.0}, {'a': LIM, 'b': LIM})
    assert 1 < len(segs) < len(traj.points)


def test_a_segment_too_steep_for_the_joint_is_merged_with_the_next_not_refused():
    # 6.5 steps in 50 ms as a triangle need 1.06e4 steps/s^2 against 1e4: two points (100 ms)
    # need a quarter of that
    lim = JointLimits(-1e6, 1e6, 1600.0, 10_000.0)
    traj = build(['a'], [0.05, 0.1, 0.15, 0.2], [[6.5], [13], [19.5], [26]], known=['a'])
    segs = plan(traj, {'a': 0.0}, {'a': lim})
    assert [s.point for s in segs] == [1, 3] and all(s.merged == 1 for s in segs)
    # what no merge can make: the last point too far for the time left
    far = build(['a'], [0.05, 0.1], [[6.5], [400]], known=['a'])
    with pytest.raises(TrajectoryError, match=r'a: segment to point 0 \(0 s to 0.05 s\) needs '
                                              r'an acceleration'):
        plan(far, {'a': 0.0}, {'a': lim})


def test_merging_beyond_the_path_tolerance_is_refused_naming_joint_point_and_tolerance():
    # a corner at 0.2 s: merged into one 0.4 s segment, the plan passes 50 steps from it
    traj = build(['a', 'b'], [0.2, 0.4], [[100, 0], [100, 100]], known=['a', 'b'])
    lims = {'a': LIM, 'b': LIM}
    segs = plan(traj, {'a': 0.0, 'b': 0.0}, lims, min_segment_s=0.3,
                path_tolerance_steps={'a': 60.0, 'b': 60.0})
    (seg,) = segs
    dev = dict(seg.deviation_steps)
    assert 40 <= dev['a'] <= 60 and 40 <= dev['b'] <= 60
    with pytest.raises(TrajectoryError, match=r'(a|b): point 0 \(0.2 s\) cannot be followed '
                                              r'within the path bound 0.03 rad: the plan passes '
                                              r'0.05 rad from it .*the bus needs segments of at '
                                              r'least 0.3 s'):
        plan(traj, {'a': 0.0, 'b': 0.0}, lims, min_segment_s=0.3,
             path_tolerance_steps={'a': 30.0, 'b': 30.0})


def test_a_segment_slower_than_the_drive_can_run_goes_at_its_least_speed():
    slow = JointLimits(-1e6, 1e6, 4000.0, 20000.0, min_velocity_steps_s=32.0)
    (seg,) = plan(build(['a'], [1.0], [[10]], known=['a']), {'a': 0.0}, {'a': slow})
    (m,) = seg.moves
    assert m.velocity_steps_s == pytest.approx(32.0)
    assert m.acceleration_steps_s2 <= 20000.0
    # it arrives early and stays: never past the target
    assert profile_distance(m.velocity_steps_s, m.acceleration_steps_s2, 1.0) >= 10


# ------------------------------------------------------------ velocity-continuous segments
RD4 = JointLimits(min_steps=-1e6, max_steps=1e6, max_velocity_steps_s=1600.0,
                  max_acceleration_steps_s2=9940.0, steps_per_unit=1024 / (2 * math.pi),
                  unit='rad', min_velocity_steps_s=1.0)


def test_a_continuous_joint_passes_its_points_on_time_and_at_speed():
    traj = quintic_line(['a'], [326.0], 3.0, 0.1)                # 2 rad of an RD4 joint in 3 s
    segs = plan(traj, {'a': 0.0}, {'a': RD4}, min_segment_s=0.3, continuous={'a'})
    assert all(s.end_s - s.start_s >= 0.3 - 1e-9 for s in segs)
    for n, seg in enumerate(segs):
        (m,) = seg.moves
        planned = traj.points[seg.point].velocities_steps_s[0]
        if n < len(segs) - 1:
            # towards where it passes the next segment's end: it never brakes for this one
            assert m.target_steps == segs[n + 1].moves[0].via_steps
        else:
            assert m.target_steps == m.via_steps == 326.0     # the end: at rest on it
        if n:
            assert m.start_delay_s < 0                        # before its segment starts
        pos, vel = planned_at(segs, {'a': 0.0}, seg.end_s)
        assert pos['a'] == pytest.approx(m.via_steps, abs=0.5)   # on time within half a step
        if 0.5 <= seg.end_s <= 2.5:
            assert vel['a'] >= 0.25 * planned > 0               # not stopped at its point
    # between the points too: never below a quarter of the plan in the middle 80 %
    for k in range(30, 271):
        t = k / 100
        s = t / 3.0
        want = 326.0 * (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / 3.0
        assert planned_at(segs, {'a': 0.0}, t)[1]['a'] >= 0.25 * want, t


def test_merged_points_are_passed_nearer_than_by_chords_through_the_points():
    """Where points are merged, the knots leave the points: the plan passes them on either
    side, its largest distance well under that of the chords through the points."""
    traj = quintic_line(['a'], [326.0], 3.0, 0.05)
    segs = plan(traj, {'a': 0.0}, {'a': RD4}, min_segment_s=0.36, continuous={'a'})
    at = [p.positions_steps[0] for p in traj.points]
    knots = [(0.0, 0.0)] + [(s.end_s, at[s.point]) for s in segs]

    def chords(t):
        for (t0, x0), (t1, x1) in zip(knots, knots[1:]):
            if t <= t1:
                return x0 + (x1 - x0) * (t - t0) / (t1 - t0)
        return knots[-1][1]

    off = [planned_at(segs, {'a': 0.0}, p.time_s)[0]['a'] - x
           for p, x in zip(traj.points, at)]
    through = max(abs(chords(p.time_s) - x) for p, x in zip(traj.points, at))
    assert max(off) > 0.5 and min(off) < -0.5, off              # ahead and behind
    assert max(map(abs, off)) < 0.75 * through, (max(map(abs, off)), through)
    assert segs[-1].moves[0].via_steps == 326.0


def test_a_continuous_joint_behind_another_on_its_bus_runs_its_segments_later():
    """Two continuous joints on one serial line, a move 70 ms of it each: the second joint's
    moves go out after the first's, so its segments run 70 ms after the first's (shift_s),
    centred on the segments' (35 ms early, 35 ms late; the first segment begins no earlier),
    each passing where the trajectory has it then, within a step or two of every point.
    Planned at the segments' own instants, the second joint's moves met the first's on the
    line and went out up to 85 ms off their instants (2.7-3.4 % of its travel)."""
    traj = quintic_line(['a', 'b'], [326.0, 163.0], 3.0, 0.05)
    lines = {'a': ('line', 0.07), 'b': ('line', 0.07)}
    start = {'a': 0.0, 'b': 0.0}
    segs = plan(traj, start, {'a': RD4, 'b': RD4}, min_segment_s=0.28, continuous={'a', 'b'},
                move_times_s=lines)
    assert len(segs) > 5
    for n, seg in enumerate(segs):
        a, b = seg.moves
        assert (a.shift_s, b.shift_s) == (pytest.approx(-0.035), pytest.approx(0.035))
        assert b.start_delay_s - a.start_delay_s == pytest.approx(0.035 if n == 0 else 0.07,
                                                                  abs=0.01)
        for m in (a, b):
            assert planned_at(segs, start, seg.end_s + m.shift_s)[0][m.joint] == \
                pytest.approx(m.via_steps, abs=0.5)
    for p in traj.points:
        pos = planned_at(segs, start, p.time_s)[0]
        assert pos['a'] == pytest.approx(p.positions_steps[0], abs=2.0), p.time_s
        assert pos['b'] == pytest.approx(p.positions_steps[1], abs=2.0), p.time_s


def test_rest_to_rest_segments_stop_at_every_point():
    """The same trajectory planned for a drive that takes no target on the way (X-MIND K):
    standing at the end of every segment."""
    traj = quintic_line(['a'], [326.0], 3.0, 0.1)
    segs = plan(traj, {'a': 0.0}, {'a': RD4}, min_segment_s=0.3)
    for seg in segs[:-1]:
        assert planned_at(segs, {'a': 0.0}, seg.end_s - 1e-6)[1]['a'] == pytest.approx(0, abs=1)


def test_a_continuous_joint_brakes_to_rest_where_it_turns():
    traj = build(['a'], [0.5, 1.0, 1.5], [[200], [400], [100]], ['a'])
    segs = plan(traj, {'a': 0.0}, {'a': RD4}, continuous={'a'})
    first, turn, back = (s.moves[0] for s in segs)
    assert first.target_steps == 400 and turn.target_steps == 400 == turn.via_steps
    assert back.start_delay_s == 0 and back.entry_velocity_steps_s == 0
    pos, vel = planned_at(segs, {'a': 0.0}, 1.0)
    assert pos['a'] == pytest.approx(400, abs=0.5) and vel['a'] == pytest.approx(0, abs=1.0)


def test_the_profile_model_is_the_simulated_drives():
    """motion_state against stepper_sim's MotionModel (the simulators' profile generator):
    a move taken on the way, faster and slower, and one that has to turn first."""
    from stepper_sim.core.motion import MotionModel
    for x0, u0, target, v, a in ((0, 0, 1000, 400, 3000), (100, 300, 900, 500, 2000),
                                 (100, 300, 900, 150, 2000), (500, 400, 200, 300, 2500)):
        t = [0.0]
        sim = MotionModel(0.0, clock=lambda t=t: t[0])
        if u0:
            sim.run_velocity(u0, math.inf)
        sim.set_position(x0)
        sim.move_to(target, v, a, a)
        for tau in (0.05, 0.2, 0.5, 1.0, 3.0):
            t[0] = tau
            sim.update(tau)
            x, vel = motion_state(x0, u0, target, v, a, tau)
            assert x == pytest.approx(sim.position_steps, abs=1e-6), (x0, u0, target, tau)
            assert vel == pytest.approx(sim.velocity_hz, abs=1e-6)


def test_a_path_bound_the_merged_continuous_plan_breaks_is_refused_naming_what_to_change():
    traj = quintic_line(['a'], [326.0], 3.0, 0.05)
    lims = {'a': RD4}
    segs = plan(traj, {'a': 0.0}, lims, min_segment_s=0.3, continuous={'a'},
                path_tolerance_steps={'a': 0.05 * RD4.steps_per_unit})
    worst = max(d for s in segs for _j, d in s.deviation_steps)
    assert 1.0 < worst < 0.05 * RD4.steps_per_unit          # steps: merged, within 0.05 rad
    bound = 0.5 * worst
    with pytest.raises(TrajectoryError) as e:
        plan(traj, {'a': 0.0}, lims, min_segment_s=0.3, continuous={'a'},
             path_tolerance_steps={'a': bound})
    text = str(e.value)
    assert text.startswith('a: point ') and f'path bound {bound / RD4.steps_per_unit:.4g} rad' \
        in text
    for what in ('at least 0.3 s', "MoveIt's resample_dt", 'baud rate',
                 'constraints.a.path_bound'):
        assert what in text, text
