"""Following a trajectory as one chain of constant-rate runs per joint, where the drives store
runs ahead and execute them back to back (capabilities.Chaining: the X-MIND K's RAM cells
chained by their next cell, §4.1). No rclpy.

A drive that takes no new target while it runs stops at the end of every move: followed segment
by segment, its joints stop at every point the plan keeps and stand there while the line sends
the next moves (hundreds of ms for two joints on a 9600 baud line). Chained, each drive starts
its next run the instant the one before ends, so the joint passes its knots at speed and the
line is needed only before the start.

The plan (`chain_segment`), joint by joint: the joint's position over time is approximated by
at most `runs` straight pieces (constant rates), from where it stands when its chain starts to
the trajectory's last point at the trajectory's end, so that its largest deviation from the
trajectory's points at the points' times is least (in units of the joint's path bound; of its
travel where it has none). Each joint's deviation at the same instant bounds the path's: the
joints pass within the root of the sum of their squares of the trajectory's path.

1. Dynamic programming over the trajectory's points as knots: best[r][b], the least worst
   deviation of r runs that end at point b. The candidate knots are thinned to
   KNOT_CANDIDATES evenly spaced points and the deviation is checked at up to CHECK_POINTS of
   them, so a long trajectory costs no more than a short one.
2. The knots but the last are then moved off the points where that lowers the worst deviation
   (instants and positions, a pattern search): a knot off the curve halves a chord's error.

The follower checks the chosen plan at every point (trajectory.bounded).

A run is feasible when its rate lies within the chain's limits: at most `speed_max_steps_s` and
the joint's max_velocity, at least its drive's least rate (min_velocity_steps_s) where the joint
moves; where it stays put, it waits. The chain changes speed at its knots without ramps, as the
drive's runs start and stop in its start-stop range; max_acceleration is not a bound here.
"""

from __future__ import annotations

import bisect
import math
from typing import Mapping, Sequence

from ..contract.capabilities import Chaining
from .axis import Axis
from .segments import AxisMove, JointLimits, Point, Segment, Trajectory, TrajectoryError
from .trajectory import bounded

# Before the first chain was measured (Axis.chain_lead_s), a chain starts this many times what
# its bus's moves cost after the plan: its drives store a run per WN (up to three, longer
# strings than a move's) where a move stores one (X-MIND K at 9600 baud, two drives: 0.56-0.61 s
# against moves of 0.14 s estimated)
CHAIN_LEAD = 2.0
KNOT_CANDIDATES = 24          # points considered as knots, at most (evenly spaced)
CHECK_POINTS = 60             # points the deviation is checked at while choosing, at most
MIN_RUN_S = 0.02              # the shortest run the plan chains
STILL_STEPS = 0.5             # a joint that moves less in a run waits instead
REFINE_ROUNDS = 10            # rounds of the knots' refinement


def _evenly(indices: Sequence[int], most: int) -> list[int]:
    """At most `most` of `indices`, evenly spaced, the last always among them."""
    n = len(indices)
    if n <= most:
        return list(indices)
    return sorted({indices[round(k * (n - 1) / (most - 1))] for k in range(most)})


class _Fit:
    """How far one joint's chains pass from the trajectory's points: per run, the largest
    deviation from a point at the point's time, in units of the joint's scale; inf where the
    run's rate is not feasible."""

    def __init__(self, times: list[float], positions: list[float], from_s: float, scale: float,
                 rate_min: float, rate_max: float):
        self.times = times
        self.positions = [x / scale for x in positions]
        self.from_s = from_s
        self.scale = scale
        self.rate_min = rate_min
        self.rate_max = rate_max

    def run(self, a: tuple[float, float], b: tuple[float, float], first: bool) -> float:
        """The worst deviation of the run from knot a to knot b, each (time, position [steps]),
        over the points it spans (from `from_s` for the first run: the joint stands before
        it)."""
        (ta, xa), (tb, xb) = a, b
        dt = tb - ta
        if dt < MIN_RUN_S:
            return math.inf
        if abs(xb - xa) >= STILL_STEPS and not self.rate_min <= abs(xb - xa) / dt <= self.rate_max:
            return math.inf
        lo = bisect.bisect_right(self.times, self.from_s if first else ta)
        hi = bisect.bisect_right(self.times, tb)
        x0, d = xa / self.scale, (xb - xa) / self.scale
        worst = 0.0
        for t, x in zip(self.times[lo:hi], self.positions[lo:hi]):
            worst = max(worst, abs(x - x0 - max(0.0, (t - ta) / dt) * d))
        return worst

    def chain(self, start: tuple[float, float], knots: list[tuple[float, float]]) -> float:
        return max(self.run(a, b, n == 0)
                   for n, (a, b) in enumerate(zip([start] + knots[:-1], knots)))


def _choose(fit: _Fit, nodes: list[tuple[float, float]], runs: int) -> list[int] | None:
    """Dynamic programming over the nodes (0: the start; the last: the trajectory's end): the
    nodes of at most `runs` runs whose worst deviation is least, without the start; None when
    none is feasible."""
    last = len(nodes) - 1
    cost: dict[tuple[int, int], float] = {}
    best = [{0: 0.0}]                    # best[r][b]: the least worst deviation, r runs to b
    parent: list[dict[int, int]] = [{}]
    for r in range(1, runs + 1):
        row: dict[int, float] = {}
        par: dict[int, int] = {}
        for b in range(1, last + 1):
            for a, worst_a in best[r - 1].items():
                if a >= b:
                    continue
                if (a, b) not in cost:
                    cost[a, b] = fit.run(nodes[a], nodes[b], a == 0)
                worst = max(worst_a, cost[a, b])
                if worst < row.get(b, math.inf):
                    row[b], par[b] = worst, a
        best.append({b: w for b, w in row.items() if math.isfinite(w)})
        parent.append(par)
    ends = [(best[r][last], r) for r in range(1, runs + 1) if last in best[r]]
    if not ends:
        return None
    r = min(ends)[1]
    path = [last]
    while r > 1:
        path.append(parent[r][path[-1]])
        r -= 1
    return path[::-1]


def _refine(fit: _Fit, start: tuple[float, float], knots: list[tuple[float, float]],
            dt: float, dx: float) -> list[tuple[float, float]]:
    """The knots but the last moved where that lowers the chain's worst deviation (instant and
    position, one at a time; a pattern search that halves its steps when no move helps)."""
    ks = list(knots)
    runs = [fit.run(a, b, n == 0) for n, (a, b) in enumerate(zip([start] + ks[:-1], ks))]
    best = max(runs)
    for _ in range(REFINE_ROUNDS):
        improved = False
        for k in range(len(ks) - 1):
            for step in ((dt, 0.0), (-dt, 0.0), (0.0, dx), (0.0, -dx)):
                knot = (ks[k][0] + step[0], ks[k][1] + step[1])
                trial = ks[:k] + [knot] + ks[k + 1:]
                r = list(runs)             # only the two runs at knot k change
                r[k] = fit.run(start if k == 0 else trial[k - 1], knot, k == 0)
                r[k + 1] = fit.run(knot, trial[k + 1], False)
                if max(r) < best - 1e-12:
                    ks, runs, best, improved = trial, r, max(r), True
        if not improved:
            dt, dx = dt / 2, dx / 2
    return ks


def _joint_chain(points: list[Point], n: int, start: tuple[float, float], from_s: float,
                 runs: int, scale: float, rate_min: float, rate_max: float
                 ) -> tuple[list[tuple[float, float]], float] | None:
    """Joint n's knots from `start` (when its chain starts, where it stands) and its worst
    deviation; None when no chain is feasible."""
    checks = [points[i] for i in _evenly(range(len(points)), CHECK_POINTS)]
    fit = _Fit([p.time_s for p in checks], [p.positions_steps[n] for p in checks], from_s,
               scale, rate_min, rate_max)
    cands = _evenly([i for i, p in enumerate(points) if p.time_s >= start[0] + MIN_RUN_S],
                    KNOT_CANDIDATES)
    if not cands or cands[-1] != len(points) - 1:
        return None
    nodes = [start] + [(points[i].time_s, points[i].positions_steps[n]) for i in cands]
    chosen = _choose(fit, nodes, runs)
    if chosen is None:
        return None
    knots = [nodes[b] for b in chosen]
    if len(knots) > 1:
        # steps: a tenth of the shortest run, a tenth of the scale
        span = min(b[0] - a[0] for a, b in zip([start] + knots[:-1], knots))
        knots = _refine(fit, start, knots, span / 10, scale / 10)
    return knots, fit.chain(start, knots)


def chain_segment(traj: Trajectory, start_steps: Mapping[str, float],
                  limits: Mapping[str, JointLimits], from_s: float, lead_s: float, runs: int,
                  speed_max_steps_s: float, scale_steps: Mapping[str, float],
                  together: bool = True) -> tuple[Segment, float] | None:
    """The chains of at most `runs` runs per joint that pass closest to `traj`'s points from
    trajectory time `from_s`, and their largest deviation from a point at the point's time (in
    units of `scale_steps`, per joint); None when a joint that moves has no feasible chain.
    Every joint starts from `start_steps`: `lead_s` after `from_s` where the chains start
    `together`, else one after the other, by an equal share of `lead_s` each (the drive's
    strings), the joint first that the trajectory moves farthest before the start. The
    Segment's moves are in the order they start."""
    joints = traj.joints
    due = [p for p in traj.points if p.time_s > from_s]
    start_t = from_s + lead_s
    if not due or runs < 1:
        return None
    x0 = [float(start_steps[j]) for j in joints]
    scale = [max(float(scale_steps.get(j, 0.0)), 1.0) for j in joints]
    before = [p for p in traj.points if p.time_s <= start_t]
    ahead = [abs(before[-1].positions_steps[n] - x0[n]) / scale[n] if before else 0.0
             for n in range(len(joints))]
    order = sorted(range(len(joints)), key=lambda n: -ahead[n])
    moves, worst = [], 0.0
    for k, n in enumerate(order):
        joint, lim = joints[n], limits[joints[n]]
        if all(abs(p.positions_steps[n] - x0[n]) < STILL_STEPS for p in due):
            continue                                     # stays put: no chain
        starts_s = lead_s if together else lead_s * (k + 1) / len(joints)
        found = _joint_chain(due, n, (from_s + starts_s, x0[n]), from_s, runs, scale[n],
                             lim.min_velocity_steps_s,
                             min(speed_max_steps_s, lim.max_velocity_steps_s))
        if found is None:
            return None
        knots, dev = found
        worst = max(worst, dev)
        rates, (t0, xp) = [], (from_s + starts_s, x0[n])
        for t1, x1 in knots:
            rates.append(abs(x1 - xp) / (t1 - t0))
            t0, xp = t1, x1
        moves.append(AxisMove(joint, knots[-1][1], max(rates), lim.max_acceleration_steps_s2,
                              start_delay_s=starts_s, knots=tuple(knots)))
    if not moves:
        return None
    knots_used = max(len(m.knots) for m in moves)
    seg = Segment(from_s, due[-1].time_s, tuple(moves), len(traj.points) - 1,
                  merged=len(due) - knots_used)
    return seg, worst


def chained_plan(traj: Trajectory, axes: list[Axis], start_steps: dict[str, float],
             from_s: float, bound: dict[str, float], segments: list[Segment] | None
             ) -> list[Segment] | None:
    """`traj` as one chain per joint (chain_segment) for the follower, its `axes` those of
    traj.joints, or None: where every joint's drive is on one bus that chains
    (capabilities.Chaining) and none is moving (a chain is stored in drives at rest; the
    caller asks only where no trajectory runs), the chain keeps to the path bound, and either
    the segments merge points too or it passes them no farther than the segments do
    (`segments`: the plan of segments; None: that one was refused). Its first run starts
    after the plan by what the chains before took (Axis.chain_lead_s), before the first by
    CHAIN_LEAD times what the bus's moves cost (a WN per run)."""
    bus = getattr(axes[0].drive, 'bus', None) if axes else None
    if not isinstance(bus, Chaining) or not bus.chain_runs or any(
            a.interpolated or a.continuous or getattr(a.drive, 'bus', None) is not bus
            or a.moving() for a in axes):
        return None
    travel = {j: max((abs(p.positions_steps[n] - start_steps[j]) for p in traj.points),
                     default=0.0) for n, j in enumerate(traj.joints)}
    scale = {j: bound[j] if bound[j] > 0 else travel[j] for j in traj.joints}
    limits = {a.joint: a.limits for a in axes}
    lead_s = max(a.chain_lead_s for a in axes) or \
        CHAIN_LEAD * sum(a.move_cost_s() for a in axes)
    found = chain_segment(traj, start_steps, limits, from_s, lead_s, bus.chain_runs,
                          bus.chain_speed_max_steps_s, scale,
                          bus.chains_start_together([a.drive for a in axes]))
    if found is None:
        return None
    seg, worst = found
    if segments is not None and not any(sg.merged for sg in segments):
        plain = max((d / max(scale[j], 1.0) for sg in segments
                     for j, d in sg.deviation_steps), default=0.0)
        if worst > plain + 1e-9:
            return None            # the segments keep every point, the chain would not
    try:
        return bounded(traj, [seg], start_steps, from_s, limits, bound, 0.0)
    except TrajectoryError:
        return None
