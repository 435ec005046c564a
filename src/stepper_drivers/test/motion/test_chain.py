"""The chain planner (motion/chain.py): per joint, at most `runs` constant-rate runs from where
the joint stands when its chain starts to the trajectory's end, passing as close as they can to
the trajectory's points. No bus."""

import itertools
import math

from rigs_motion import quintic_line
from stepper_drivers.motion.chain import MIN_RUN_S, chain_segment
from stepper_drivers.motion.trajectory import JointLimits, build, planned_at

LIMITS = JointLimits(min_steps=-1e6, max_steps=1e6, max_velocity_steps_s=20000.0,
                     max_acceleration_steps_s2=1e6, min_velocity_steps_s=1.0)
JOINTS = ('j1', 'j2')
TRAVEL = (636.0, 318.0)
SPEED_MAX = 2900.0


def plan(traj, lead_s=0.3, runs=3, together=True, scale=TRAVEL, start=(0.0, 0.0)):
    return chain_segment(traj, dict(zip(traj.joints, start)),
                         {j: LIMITS for j in traj.joints}, 0.0, lead_s, runs, SPEED_MAX,
                         dict(zip(traj.joints, scale)), together)


def worst_at_points(traj, seg, scale=TRAVEL):
    """The plan's largest deviation from the points, per joint in units of `scale`."""
    start = {j: 0.0 for j in traj.joints}
    worst = 0.0
    for p in traj.points:
        at, _ = planned_at([seg], start, p.time_s)
        for n, j in enumerate(traj.joints):
            worst = max(worst, abs(at[j] - p.positions_steps[n]) / scale[n])
    return worst


def best_on_points(traj, n, lead_s, runs, scale):
    """Brute force: the least worst deviation of joint n over every choice of knots on the
    trajectory's points (the last point last), from (lead_s, 0)."""
    pts = [(p.time_s, p.positions_steps[n]) for p in traj.points]
    inner = [q for q in pts[:-1] if q[0] >= lead_s + MIN_RUN_S]
    best = math.inf
    for r in range(runs):
        for knots in itertools.combinations(inner, r):
            ks = [(lead_s, 0.0), *knots, pts[-1]]
            worst = 0.0
            for t, x in pts:
                if t <= lead_s:
                    at = 0.0
                else:
                    k = next(i for i in range(1, len(ks)) if t <= ks[i][0])
                    (t0, x0), (t1, x1) = ks[k - 1], ks[k]
                    at = x0 + (x1 - x0) * (t - t0) / (t1 - t0)
                worst = max(worst, abs(at - x) / scale[n])
            best = min(best, worst)
    return best


def test_a_dense_line_runs_as_three_runs_per_joint_no_worse_than_the_best_knots_on_points():
    traj = quintic_line(JOINTS, TRAVEL, 3.0, 0.1)
    seg, worst = plan(traj)
    assert [len(m.knots) for m in seg.moves] == [3, 3]
    assert all(m.knots[-1] == (3.0, travel) for m, travel in zip(seg.moves, TRAVEL))
    # what it reports is what the plan does, and the refinement beats every choice on points
    assert worst_at_points(traj, seg) <= worst + 1e-9
    assert worst <= max(best_on_points(traj, n, 0.3, 3, TRAVEL) for n in range(2)) + 1e-9
    assert worst < 0.05                    # a quintic by three runs: about 3 % of the travel


def test_fewer_runs_deviate_more():
    traj = quintic_line(JOINTS, TRAVEL, 3.0, 0.1)
    assert plan(traj, runs=1)[1] > plan(traj, runs=2)[1] > plan(traj, runs=3)[1]


def test_joints_start_one_after_the_other_the_one_the_plan_moves_farthest_first():
    # j2 moves most by the start (in units of its scale): it starts first, then j1
    traj = quintic_line(JOINTS, TRAVEL, 3.0, 0.1)
    seg, _ = plan(traj, lead_s=0.6, together=False, scale=(TRAVEL[0], TRAVEL[1] / 2))
    assert [m.joint for m in seg.moves] == ['j2', 'j1']
    assert [m.start_delay_s for m in seg.moves] == [0.3, 0.6]
    seg, _ = plan(traj, lead_s=0.6, together=True)
    assert [m.start_delay_s for m in seg.moves] == [0.6, 0.6]


def test_a_joint_that_stays_put_gets_no_chain_and_a_pause_is_a_run_at_rest():
    traj = build(list(JOINTS), [1.0, 2.0, 3.0], [[100, 0], [100, 0], [200, 0]], list(JOINTS))
    seg, worst = plan(traj, lead_s=0.2, scale=(200, 1))
    assert [m.joint for m in seg.moves] == ['j1']
    assert seg.moves[0].knots == ((1.0, 100), (2.0, 100), (3.0, 200)) and worst == 0.0


def test_a_run_faster_than_the_chain_allows_leaves_no_chain():
    traj = build(list(JOINTS), [1.0], [[SPEED_MAX * 0.8, 0]], list(JOINTS))   # from 0.3 s
    assert plan(traj, scale=(1000, 1)) is None
    assert plan(traj, lead_s=0.1, scale=(1000, 1)) is not None
