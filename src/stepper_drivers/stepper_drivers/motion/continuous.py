"""The velocity-continuous plan: the moves of the joints whose drives take a new target while
they move (capabilities.Retargeting), over the segments trajectory.plan has merged
(`continuous_moves`, which plan(continuous=...) calls), and the cruise speed that passes a point
on time (`cruise`, `solve_cruise`: the follower solves it again as a move goes out).

A joint does not stop at its points (the RD4's "Position override function", the X-PLUS MT's
and the Vector Step's change set immediately in profile position). Each segment's move goes to
the drive before the one before it would start to slow down: its target is the next point where
the joint goes on the same way (the drive then never brakes for the point it passes), its speed
the one that passes the segment's point at the segment's end, found on the drive's own profile
(`motion_state`: from the speed it has, ramps of one acceleration, a cruise, a brake at the
target). It takes effect half its speed change before the segment starts, so that the change is
centred on the point between the two segments (the joint's speed then steps from one segment's
average to the next one's around each point: its position passes the points on time). The
ramps: PLAN_FRACTIONS[0] of its max_acceleration, or RAMP_SHAPE times the plan's largest
acceleration of the joint (the points' accelerations, or their positions' second differences)
where that is steeper; a drive that runs start-stop at a speed (X-PLUS MT) jumps. A joint whose
planned velocity is zero at a point, or that turns or holds there, brakes to rest on it, as the
rest-to-rest segments do. Where points were merged, the segments' ends are passed where the
polyline of the segments runs nearest the merged points (`fitted_vias`), not on the points. A
joint whose moves go out behind other joints' on its bus runs its segments that much later
(`shifts_s`, AxisMove.shift_s).

Not here: the trajectory types, the checks, the merging of points into segments and the path
bound (trajectory.py, which also plans the rest-to-rest joints), nor the profile arithmetic
(move_profile.py).
"""

from __future__ import annotations

import dataclasses

from .move_profile import motion_state, ramps
from .segments import (
    EDGE_MARGIN,
    PLAN_FRACTIONS,
    AxisMove,
    JointLimits,
    Point,
    Segment,
    Trajectory,
    TrajectoryError,
    sample,
)

# Velocity-continuous joints: ramps at PLAN_FRACTIONS[0] of the joint's max_acceleration, or at
# this many times the plan's largest acceleration of the joint where that is steeper (at most
# EDGE_MARGIN of it). One value per joint and trajectory, for speeding up and slowing down
# alike: the X-PLUS MT loads Profile Acceleration (1046) only when a move starts from rest and
# uses it both ways (§13 "Multi-Set-Point Mode", "Registers 1046-1047"), the RD4 then writes
# its ramps once, and a stop of the drive brakes as fast as a rest-to-rest move's would.
RAMP_SHAPE = 1.5
# The fit of the positions where a joint passes the merged segments' ends (fitted_vias): sweeps
# over the knots, until none moves by FIT_DONE_STEPS; steps of the bisection of one knot.
FIT_SWEEPS = 20
FIT_DONE_STEPS = 0.25
FIT_SEARCH = 30


def ramp_acceleration(traj: Trajectory, joint: str, lim: JointLimits,
                      start_steps: float | None = None) -> float:
    """The one acceleration of a continuous joint's ramps (the module's docstring); a drive
    runs a move start-stop all the same where its speed allows (`ramps`). `start_steps`: where
    the joint starts, at rest, before the first point."""
    col = traj.joints.index(joint)
    pts = list(traj.points)
    if start_steps is not None and pts and pts[0].time_s > 0:
        pts.insert(0, Point(0.0, tuple(start_steps if c == col else 0.0
                                       for c in range(len(traj.joints)))))
    given = [abs(p.accelerations_steps_s2[col]) for p in pts if p.accelerations_steps_s2]
    if not given:                                  # from the positions: second differences
        for a, b, c in zip(pts, pts[1:], pts[2:]):
            v1 = (b.positions_steps[col] - a.positions_steps[col]) / (b.time_s - a.time_s)
            v2 = (c.positions_steps[col] - b.positions_steps[col]) / (c.time_s - b.time_s)
            given.append(abs(v2 - v1) / ((c.time_s - a.time_s) / 2))
    top = lim.max_acceleration_steps_s2
    return min(EDGE_MARGIN * top, max(PLAN_FRACTIONS[0] * top,
                                      RAMP_SHAPE * max(given, default=0.0)))


def continuous_moves(traj: Trajectory, segments: list[Segment], start_steps: dict[str, float],
                     limits: dict[str, JointLimits], joints: list[str],
                     start_velocity: dict[str, float],
                     shifts_s: dict[str, float] | None = None) -> list[Segment]:
    """The segments with velocity-continuous moves for `joints` (the module's docstring);
    TrajectoryError where a joint cannot pass a point in time within its max_velocity.

    `shifts_s` (joint: s): the joints of one bus take their moves one after the other, so each
    runs its segments this much later (< 0: earlier; AxisMove.shift_s; the first segment
    begins no earlier than it does), passing where the trajectory has it then: each move's
    instant is where the bus can send it, not one it waits for the other joints' moves to
    meet."""
    moves: list[dict[str, AxisMove]] = [{m.joint: m for m in seg.moves} for seg in segments]
    for joint in joints:
        col = traj.joints.index(joint)
        lim = limits[joint]
        a = ramp_acceleration(traj, joint, lim, start_steps[joint])
        shift = (shifts_s or {}).get(joint, 0.0)
        ends = [seg.end_s + shift for seg in segments]
        starts = [max(segments[0].start_s, segments[0].start_s + shift)] + ends[:-1]
        vias = fitted_vias(traj, segments, col, start_steps, [starts[0]] + ends)
        x, u = start_steps[joint], start_velocity.get(joint, 0.0)
        # the move in effect: (when, entry position, entry velocity, target, cruise)
        effect: AxisMove | None = None          # the move in effect, since effect_s
        effect_s = 0.0
        before = start_steps[joint]
        for n, seg in enumerate(segments):
            via = vias[n]
            moves[n].pop(joint, None)
            if via == before:
                continue                                 # holds: braked here before
            way = 1.0 if via > before else -1.0
            after = vias[n + 1] if n + 1 < len(vias) else via
            planned = traj.points[seg.point].velocities_steps_s
            stops = (after - via) * way <= 0 or (bool(planned) and planned[col] * way <= 0)
            target = via if stops else after
            begin, end = starts[n], ends[n]
            average = (via - before) / (end - begin)
            if effect is None:       # (a joint taken over at speed goes on until its shift)
                at, x_e, u_e = begin, x + u * (begin - segments[0].start_s), u
            elif effect.target_steps == effect.via_steps:
                at, x_e, u_e = begin, effect.via_steps, 0.0    # at rest on its point
            else:
                t_e = effect_s
                _, u_now = effect.state(begin - t_e)
                change = a if abs(average) > abs(u_now) else deceleration(a, lim)
                quick = ramps(change, max(abs(average), abs(u_now)), lim.start_stop_steps_s)
                half = 0.0 if u_now == 0.0 else abs(average - u_now) / (2 * quick)
                at = max(t_e, begin - half)
                x_e, u_e = effect.state(at - t_e)
            if (via - x_e) * way <= 0:       # there already (a fraction of a step): cruise on
                found = (max(abs(average), lim.min_velocity_steps_s, 1e-3), a, a)
            else:
                found = cruise(x_e, u_e, via, target, end - at, a, lim)
            if found is None and effect is None and u_e != 0.0:
                # taking over a joint at speed that cannot turn in time: planned from rest (it
                # arrives late; the goal tolerance decides), as a rest-to-rest segment is
                u_e = 0.0
                found = cruise(x_e, u_e, via, target, end - at, a, lim)
            if found is None:
                u_ = lim.steps_per_unit
                raise TrajectoryError(
                    f'{joint}: point {seg.point} ({seg.end_s:g} s) cannot be reached in time '
                    f'from {x_e / u_:.6g} {lim.unit} at {u_e / u_:.4g} {lim.unit}/s with ramps '
                    f'of {a / u_:.4g} {lim.unit}/s^2 within max_velocity '
                    f'({lim.max_velocity_steps_s / u_:.4g} {lim.unit}/s)')
            v, ramp, dec = found
            effect = moves[n][joint] = AxisMove(joint, target, v, ramp, at - seg.start_s, via,
                                                x_e, u_e, lim.start_stop_steps_s, dec,
                                                shift_s=shift)
            effect_s = at
            before = via
    return [dataclasses.replace(seg, moves=tuple(ms[j] for j in traj.joints if j in ms))
            for seg, ms in zip(segments, moves)]


def fitted_vias(traj: Trajectory, segments: list[Segment], col: int,
                start_steps: dict[str, float], times: list[float]) -> list[float]:
    """Where the joint passes each segment's end (at `times`[1:], its segments' ends shifted
    as continuous_moves runs them; `times`[0] its first segment's start): the
    polyline through these positions (its speed steps from one segment's average to the next
    around each) passes the trajectory's points as near as it can (least largest distance,
    FIT_SWEEPS sweeps of one knot at a time). Through the points themselves a merged
    segment's chord lies on one side of a curved plan, up to an eighth of its acceleration
    times the segment's time squared; moved off them, half that on either side. On the
    trajectory (`sample`: its points, linear between them, at the knots' times; `start_steps`
    where the joints are before its first point) and not moved: the
    last segment's end, every end where the joint stops, turns or holds (a point where it
    rests is passed at rest) and, where the knots are the points' times, every end with no point
    merged into a segment beside it (the polyline is the points' own there)."""
    points = traj.points
    joint = traj.joints[col]
    ys = [start_steps[joint]] + [points[seg.point].positions_steps[col] for seg in segments]
    # the points between two knots, (time, position), per segment
    inside = [[(p.time_s, p.positions_steps[col]) for p in points
               if times[n] < p.time_s < times[n + 1]] for n in range(len(segments))]
    free = []
    for n in range(1, len(segments)):
        before, via, after = ys[n - 1], ys[n], ys[n + 1]
        planned = points[segments[n - 1].point].velocities_steps_s
        way = 1.0 if via > before else -1.0
        passes = (via - before) * way > 0 and (after - via) * way > 0 \
            and not (planned and planned[col] * way <= 0)
        if passes and (inside[n - 1] or inside[n]):
            free.append(n)
    on_knot = list(ys)
    for n in free:
        on_knot[n] = ys[n] = sample(traj, start_steps, times[n])[joint]
    for _ in range(FIT_SWEEPS if free else 0):
        moved = 0.0
        for n in free:
            # each point beside the knot: (its distance from the polyline, how much of the
            # knot's shift moves the polyline there)
            near = []
            for t, x in inside[n - 1]:
                w = (t - times[n - 1]) / (times[n] - times[n - 1])
                near.append((ys[n - 1] + (ys[n] - ys[n - 1]) * w - x, w))
            for t, x in inside[n]:
                w = (times[n + 1] - t) / (times[n + 1] - times[n])
                near.append((ys[n + 1] + (ys[n] - ys[n + 1]) * w - x, w))
            # the trajectory at the knot: it may leave it too
            near.append((ys[n] - on_knot[n], 1.0))
            shift = _least_max_shift(near)
            # the joint keeps its way: the knot moves no nearer a neighbour than a quarter of
            # the way between them, or than the trajectory at the knot lies
            lo, hi = sorted((ys[n - 1], ys[n + 1]))
            quarter = (hi - lo) / 4
            new = min(max(ys[n] + shift, min(on_knot[n], lo + quarter)),
                      max(on_knot[n], hi - quarter))
            moved = max(moved, abs(new - ys[n]))
            ys[n] = new
        if moved < FIT_DONE_STEPS:
            break
    return ys[1:]


def _least_max_shift(near: list[tuple[float, float]]) -> float:
    """The s that makes max |e + w s| over `near` [(e, w), w > 0] least: where the largest
    rising term, max(e + w s), meets the largest falling one, max(-e - w s) (bisection: their
    difference grows with s; |s| <= 2 max |e|, since the knot's own term has w = 1)."""
    reach = 2 * max(abs(e) for e, _ in near)
    lo, hi = -reach, reach
    for _ in range(FIT_SEARCH):
        s = 0.5 * (lo + hi)
        if max(e + w * s for e, w in near) < max(-e - w * s for e, w in near):
            lo = s
        else:
            hi = s
    return 0.5 * (lo + hi)


def cruise(x0: float, u0: float, via: float, target: float, left_s: float, a: float,
           lim: JointLimits) -> tuple[float, float, float] | None:
    """(cruise speed, acceleration, deceleration) of a continuous move (solve_cruise) with
    ramps of a, else of EDGE_MARGIN of the joint's max_acceleration where a cannot make it (a
    move gone out late; an X-PLUS MT under way keeps its ramps all the same: it arrives a
    little late); None where none can within max_velocity."""
    top = lim.max_acceleration_steps_s2
    for ramp in (a, EDGE_MARGIN * top):
        if ramp >= a:
            dec = deceleration(ramp, lim)
            v = solve_cruise(x0, u0, via, target, left_s, ramp,
                             max(lim.min_velocity_steps_s, 1e-3), lim.max_velocity_steps_s,
                             lim.start_stop_steps_s, dec)
            if v is not None:
                return v, ramp, dec
    return None


def deceleration(a: float, lim: JointLimits) -> float:
    """A continuous move's deceleration: its acceleration (RAMP_SHAPE's comment)."""
    return a


def solve_cruise(x0: float, u0: float, via: float, target: float, left_s: float, a: float,
                 v_lo: float, v_hi: float, start_stop_steps_s: float = 0.0,
                 dec: float | None = None) -> float | None:
    """The least cruise speed in v_lo..v_hi with which a drive at x0 moving at u0, given a move
    to `target` (beyond `via`, or `via` itself) with ramps a (`ramps`), is at `via` after
    left_s (the position then grows with the speed: bisection); v_lo where even that gets
    there; None where v_hi does not."""
    way = 1.0 if via >= x0 else -1.0

    d = a if dec is None else dec

    def reached(v: float) -> bool:
        return (motion_state(x0, u0, target, v, ramps(a, v, start_stop_steps_s), left_s,
                             ramps(d, v, start_stop_steps_s))[0] - via) * way >= -1e-6

    if left_s <= 0:
        return None
    if reached(v_lo):
        return v_lo
    # start-stop up to start_stop_steps_s, ramps above: each range grows with the speed
    jump = min(start_stop_steps_s, v_hi)
    if jump > v_lo and reached(jump):
        lo, hi = v_lo, jump
    elif reached(v_hi):
        lo, hi = max(v_lo, jump), v_hi
    else:
        return None
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if reached(mid):
            hi = mid
        else:
            lo = mid
        if hi - lo <= 1e-6 * hi:
            break
    return hi
