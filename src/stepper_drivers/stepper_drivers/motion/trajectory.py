"""Joint trajectories in drive units: checking, sampling, and time-synchronized segments.

No rclpy. The node turns a trajectory_msgs/JointTrajectory into a `Trajectory` (joint units to
steps through each drive's UnitConversion); this module decides whether it can be followed and
how, before anything moves. Semantics as JointTrajectoryController's (ros2_controllers, Jazzy):
`time_from_start` of each point is honoured from the trajectory's start time; a trajectory
replaces the rest of the one before it from its own start time; an empty one stops; joints not
in the message hold their position.

Following by synchronized point-to-point segments (every drive: RD4, X-MIND K, and X-PLUS MT,
whose change-set-immediately takes each set point at once): for each segment, every moving axis
gets a trapezoidal profile with one common ramp time, scaled by its distance, that makes it arrive
exactly at the waypoint's time: all axes start together, keep their proportions (a straight path
between the points) and arrive together. A segment that needs more than a joint's max_velocity
or max_acceleration is refused before anything moves, naming the joint and the limit.

Dense trajectories (a planner's point every 10-100 ms, with tiny segments where its timing
starts and ends): a segment must last at least `min_segment_s`, the time the bus needs to send
the moves of its axes (a serial line at 9600-19200 baud takes tens of ms a transaction), so
consecutive points are merged into one segment until it does, or until a longer segment fits
the joints' max_acceleration. The merged plan is checked against every point it skips: beyond a
joint's path tolerance the trajectory is refused before anything moves. An axis whose segment
is slower than its drive's least speed (`min_velocity_steps_s`) runs at that speed and arrives
early: it is off the path by less than that speed times the segment's duration.

Velocity-continuous following (`plan(continuous=...)`: the joints whose drives take a new target
while they move, capabilities.Retargeting): a joint does not stop at its points; continuous.py
plans those moves over the merged segments (its docstring has how).

The path is bounded: the plan (merged segments, continuous profiles) is evaluated at every point
of the trajectory and may pass no farther from any than `path_bound_steps` (per joint: the goal's
path tolerance, else the node's default); a trajectory that cannot be carried within it is
refused before anything moves, naming the joint, the point, the bound and the least segment the
bus needs.

The moves' profiles over time (a trapezoid from rest to rest, a drive's profile from the speed
it has) are move_profile.py's.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Collection, Sequence

# (motion_state and along: other modules import them from here too)
from .continuous import continuous_moves
from .move_profile import along, along_velocity
from .segments import (  # noqa: F401 - the plan's types and sample: callers take them here
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


def build(joints: Sequence[str], times_s: Sequence[float],
          positions_steps: Sequence[Sequence[float]], known: Sequence[str],
          velocities_steps_s: Sequence[Sequence[float]] | None = None,
          accelerations_steps_s2: Sequence[Sequence[float]] | None = None) -> Trajectory:
    """A Trajectory from message fields already converted to steps; TrajectoryError for joints
    that are not this node's, repeated joints, times that do not increase, a point whose
    position count does not match the joints, or a value that is not a number. Velocities and
    accelerations (per point, as the message has them: empty or one per joint) shape the
    velocity-continuous segments; a point without them has ()."""
    unknown = [j for j in joints if j not in known]
    if unknown:
        raise TrajectoryError(f'joints {unknown} are not driven by this node (its joints: '
                              f'{list(known)})')
    if len(set(joints)) != len(joints):
        raise TrajectoryError(f'joint_names {list(joints)} name a joint twice')
    points = []
    last_t = -math.inf
    for k, (t, pos) in enumerate(zip(times_s, positions_steps)):
        if len(pos) != len(joints):
            raise TrajectoryError(f'point {k}: {len(pos)} positions for {len(joints)} joints')
        if not math.isfinite(t) or t < 0 or t <= last_t:
            raise TrajectoryError(f'point {k}: time_from_start {t:g} s does not increase (the '
                                  f'point before is at {last_t:g} s)')
        bad = [j for j, p in zip(joints, pos) if not math.isfinite(p)]
        if bad:
            raise TrajectoryError(f'point {k}: position of {bad} is not a number')
        extra = []
        for what, rows in (('velocities', velocities_steps_s),
                           ('accelerations', accelerations_steps_s2)):
            row = tuple(float(x) for x in rows[k]) if rows is not None and k < len(rows) else ()
            if row and len(row) != len(joints):
                raise TrajectoryError(f'point {k}: {len(row)} {what} for {len(joints)} joints')
            if not all(math.isfinite(x) for x in row):
                raise TrajectoryError(f'point {k}: {what} of {list(joints)} are not numbers')
            extra.append(row)
        points.append(Point(float(t), tuple(float(p) for p in pos), *extra))
        last_t = t
    return Trajectory(tuple(joints), tuple(points))


@dataclasses.dataclass(frozen=True)
class Unreachable:
    """A segment a joint cannot make within its limits: which joint, and why."""

    joint: str
    why: str


def trapezoid(distance_steps: float, duration_s: float, max_velocity_steps_s: float,
              max_acceleration_steps_s2: float, start_stop_steps_s: float = 0.0
              ) -> tuple[float, float] | str:
    """(velocity, acceleration) of one axis's symmetric trapezoid covering `distance_steps` in
    exactly `duration_s`, with the shortest ramps its max acceleration allows; or the reason it
    cannot, as text. An acceleration of inf: start-stop at d / T (no ramps)."""
    profiles = segment_profiles({'': distance_steps}, duration_s, {'': JointLimits(
        -math.inf, math.inf, max_velocity_steps_s, max_acceleration_steps_s2,
        start_stop_steps_s=start_stop_steps_s)})
    return profiles.why if isinstance(profiles, Unreachable) else \
        profiles.get('', (0.0, max_acceleration_steps_s2))


def ramp_time(distance_steps: float, duration_s: float, acceleration_steps_s2: float) -> float:
    """The shortest ramp t of a symmetric trapezoid over d in T with ramps of at most a:
    d = a t (T - t), so t = (T - sqrt(T^2 - 4 d / a)) / 2; inf when a T^2 < 4 d."""
    disc = duration_s ** 2 - 4 * abs(distance_steps) / acceleration_steps_s2
    return math.inf if disc < 0 else (duration_s - math.sqrt(disc)) / 2


def segment_profiles(distances: dict[str, float], duration_s: float,
                     limits: dict[str, JointLimits],
                     fractions: tuple[float, ...] = (EDGE_MARGIN,)
                     ) -> dict[str, tuple[float, float]] | Unreachable:
    """(velocity, acceleration) per moving joint for one segment, or which joint cannot and
    why.

    Every axis gets the same ramp time t_r (the longest any of them needs within its
    max_acceleration): each one's profile is then the same curve scaled by its distance, so the
    axes keep their proportions all the way and the path between two points is a straight line,
    not a dog-leg. v_i = d_i / (T - t_r), a_i = v_i / t_r. When every axis can run start-stop
    (X-PLUS MT at or below its start-stop velocity) there are no ramps: v_i = d_i / T.
    `fractions` of each joint's max_acceleration are tried in turn: the plan leaves headroom
    (PLAN_FRACTIONS) that an axis whose move goes out late uses to catch up.
    """
    moving = {j: abs(d) for j, d in distances.items() if d != 0}
    if not moving:
        return {}
    T = duration_s
    if all(d / T <= min(limits[j].start_stop_steps_s, limits[j].max_velocity_steps_s)
           for j, d in moving.items()):
        return {j: (max(d / T, limits[j].min_velocity_steps_s), math.inf)
                for j, d in moving.items()}
    for fraction in fractions[:-1]:
        found = _common_ramp(moving, T, limits, fraction)
        if not isinstance(found, Unreachable):
            return found
    return _common_ramp(moving, T, limits, fractions[-1])


def _common_ramp(moving: dict[str, float], T: float, limits: dict[str, JointLimits],
                 fraction: float) -> dict[str, tuple[float, float]] | Unreachable:
    t_r = 0.0
    for j, d in moving.items():
        a = limits[j].max_acceleration_steps_s2
        t_j = ramp_time(d, T, a * fraction)
        if math.isinf(t_j):
            need = 4 * d / T ** 2 / EDGE_MARGIN
            return Unreachable(j, f'needs an acceleration of at least {need:.4g} steps/s^2 to '
                               f'cover {d:.6g} steps in {T:g} s (max_acceleration is {a:.4g} '
                               'steps/s^2)')
        t_r = max(t_r, t_j)
    out = {}
    for j, d in moving.items():
        v = d / (T - t_r)
        if v > limits[j].max_velocity_steps_s:
            return Unreachable(j, f'needs {v:.4g} steps/s to cover {d:.6g} steps in {T:g} s '
                               f'(max_velocity is {limits[j].max_velocity_steps_s:.4g} '
                               'steps/s)')
        # slower than the drive can run: at its least speed, with the same ramp (arrives early)
        v = max(v, limits[j].min_velocity_steps_s)
        out[j] = (v, min(v / t_r, limits[j].max_acceleration_steps_s2) if t_r > 0 else math.inf)
    return out


def retimed(distance_steps: float, left_s: float, planned: tuple[float, float],
            lim: JointLimits) -> tuple[float, float] | None:
    """The profile that covers `distance_steps` in the `left_s` really left of a segment planned
    as `planned` (velocity, acceleration): with the planned ramp time when that fits the
    joint's limits (the axes keep their proportions), else the shortest ramp its
    max_acceleration allows; None when it cannot arrive in time."""
    d = abs(distance_steps)
    if d == 0:
        return planned
    if left_s <= 0:
        return None
    ramp_s = 0.0 if math.isinf(planned[1]) else planned[0] / planned[1]
    if ramp_s == 0:
        v = max(d / left_s, lim.min_velocity_steps_s)
        # faster than start-stop would make the drive ramp: later, not earlier
        return (v, math.inf) if v <= min(lim.start_stop_steps_s,
                                         lim.max_velocity_steps_s) else None
    if left_s > 2 * ramp_s:
        v = max(d / (left_s - ramp_s), lim.min_velocity_steps_s)
        if v <= lim.max_velocity_steps_s and v / ramp_s <= lim.max_acceleration_steps_s2:
            return v, v / ramp_s
    fastest = trapezoid(d, left_s, lim.max_velocity_steps_s, lim.max_acceleration_steps_s2)
    if isinstance(fastest, str):
        return None
    return max(fastest[0], lim.min_velocity_steps_s), fastest[1]


def plan(traj: Trajectory, start_steps: dict[str, float], limits: dict[str, JointLimits],
         from_s: float = 0.0, min_segment_s: float = 0.0,
         path_tolerance_steps: dict[str, float] | None = None,
         move_times_s: dict[str, tuple[object, float]] | None = None,
         continuous: Collection[str] = (),
         start_velocity_steps_s: dict[str, float] | None = None) -> list[Segment]:
    """The synchronized segments of `traj` from trajectory time `from_s` (0: its start; later
    when it starts in the past), each axis from `start_steps` (where the drives are now);
    TrajectoryError naming the joint, the point and the limit when any segment cannot be met:
    then nothing is sent.

    Points are merged into one segment while it is shorter than `min_segment_s` (the bus's time
    to send a segment's moves) or needs more than a joint's max_acceleration; the last point is
    always a segment's end, and no segment is left shorter than `min_segment_s` at the end of
    the trajectory. The plan is checked at each point of the trajectory against
    `path_tolerance_steps` (per joint, the path bound; 0 or absent: not bounded).

    `move_times_s` (joint: (its bus, what a move costs there)): the moves of a segment go out
    at its start one after the other on each bus, so each axis starts later by the moves
    before it and its own; its profile is planned for the time left then. A continuous joint
    runs its segments later by the moves of the continuous joints before it, centred
    (`_shifts`).

    `continuous`: joints followed velocity-continuously (continuous.py), from
    `start_velocity_steps_s` (a trajectory that takes over from a running one; else at rest)."""
    tol = path_tolerance_steps or {}
    lines = move_times_s or {}
    cont = [j for j in traj.joints if j in continuous]
    stepwise = {j: limits[j] for j in traj.joints if j not in cont}
    due = [(k, p) for k, p in enumerate(traj.points) if p.time_s > from_s]
    check_positions(traj.joints, due, limits)      # points already past: JTC drops them too
    # the last segment: at least min_segment_s, half that where every joint is continuous (a
    # move that goes out late there only shifts its speed change; a longer tail would pass far
    # from the points where the plan slows down)
    tail_s = min_segment_s if stepwise else min_segment_s / 2
    segments: list[Segment] = []
    previous = {j: start_steps[j] for j in traj.joints}
    t0 = from_s
    end_s = due[-1][1].time_s if due else from_s
    i = 0
    while i < len(due):
        first_problem = None
        for j in range(i, len(due)):
            k, point = due[j]
            last = j == len(due) - 1
            if not last and (point.time_s - t0 < min_segment_s
                             or end_s - point.time_s < tail_s):
                continue                  # too short for the bus, or leaves a too short tail
            targets = dict(zip(traj.joints, point.positions_steps))
            duration_s = point.time_s - t0
            profiles = segment_profiles({jn: targets[jn] - previous[jn] for jn in stepwise},
                                        duration_s, stepwise, PLAN_FRACTIONS)
            if not isinstance(profiles, Unreachable):
                profiles = _average_speeds(cont, targets, previous, duration_s, limits,
                                           profiles)
            if isinstance(profiles, Unreachable):
                if first_problem is None:
                    first_problem = TrajectoryError(
                        f'{profiles.joint}: segment to point {k} ({t0:g} s to {point.time_s:g} '
                        f's) {profiles.why}')
                if last:
                    raise first_problem
                continue                  # a longer segment needs less acceleration
            moves = _delayed(traj.joints, profiles, targets, previous, duration_s, limits,
                             {jn: v for jn, v in lines.items() if jn not in cont})
            if isinstance(moves, Unreachable):
                if first_problem is None:
                    first_problem = TrajectoryError(
                        f'{moves.joint}: segment to point {k} ({t0:g} s to {point.time_s:g} '
                        f's) {moves.why}')
                if not last:
                    continue              # a longer segment leaves it more time
                moves = tuple(AxisMove(jn, targets[jn], *profiles[jn]) for jn in traj.joints
                              if jn in profiles)      # it arrives late: the goal decides
            segments.append(Segment(t0, point.time_s, moves, k, j - i))
            previous.update(targets)
            t0 = point.time_s
            i = j + 1
            break
    if cont and segments:
        segments = continuous_moves(traj, segments, start_steps, limits, cont,
                                    start_velocity_steps_s or {}, _shifts(cont, lines))
    return bounded(traj, segments, start_steps, from_s, limits, tol, min_segment_s)


def _shifts(cont: list[str], lines: dict[str, tuple[object, float]]) -> dict[str, float]:
    """Per continuous joint, how much later (< 0: earlier) it runs its segments
    (continuous_moves): the continuous joints of one bus take their moves one after the other
    (in the trajectory's order), each the time on the bus of the moves before it later than the
    first, and the instants are centred on the segments' (the first joint as early as the last
    is late: each passes a point where its speed changes half as far off the plan as the last
    one would alone)."""
    sent: dict[object, float] = {}
    after: dict[str, float] = {}
    for joint in cont:
        if joint in lines:
            bus, cost_s = lines[joint]
            after[joint] = sent.get(bus, 0.0)
            sent[bus] = after[joint] + cost_s
    last = {lines[j][0]: after[j] for j in after}          # the bus's last joint's
    return {j: t - last[lines[j][0]] / 2 for j, t in after.items()}


def check_positions(joints: Sequence[str], due: Sequence[tuple[int, Point]],
                     limits: dict[str, JointLimits]) -> None:
    """TrajectoryError at the first of the `due` points (index, point) that puts a joint
    outside its min_position..max_position."""
    for k, point in due:
        for joint, target in zip(joints, point.positions_steps):
            lim = limits[joint]
            if not lim.min_steps <= target <= lim.max_steps:
                raise TrajectoryError(
                    f'{joint}: point {k} at {target / lim.steps_per_unit:g} {lim.unit} is '
                    f'outside min_position..max_position ({lim.min_steps / lim.steps_per_unit:g}'
                    f'..{lim.max_steps / lim.steps_per_unit:g} {lim.unit})')


def _average_speeds(joints: list[str], targets: dict[str, float], previous: dict[str, float],
                    duration_s: float, limits: dict[str, JointLimits],
                    profiles: dict[str, tuple[float, float]]
                    ) -> dict[str, tuple[float, float]] | Unreachable:
    """`profiles` with the continuous joints' average speeds over the segment (placeholders:
    continuous.continuous_moves plans their moves); Unreachable where one is above its
    max_velocity (with the margin the ramps need)."""
    out = dict(profiles)
    for jn in joints:
        d = abs(targets[jn] - previous[jn])
        if d == 0:
            continue
        v, vmax = d / duration_s, limits[jn].max_velocity_steps_s
        if v > EDGE_MARGIN * vmax:
            return Unreachable(jn, f'needs {v:.4g} steps/s on average to cover {d:.6g} steps in '
                               f'{duration_s:g} s (max_velocity is {vmax:.4g} steps/s)')
        out[jn] = (v, limits[jn].max_acceleration_steps_s2)
    return out


def bounded(traj: Trajectory, segments: list[Segment], start_steps: dict[str, float],
             from_s: float, limits: dict[str, JointLimits], tol: dict[str, float],
             min_segment_s: float) -> list[Segment]:
    """The segments with how far their plan passes from the trajectory's points (per joint,
    Segment.deviation_steps, at the points merged into each segment and at its end point);
    TrajectoryError at the first point farther than its joint's path bound in `tol`."""
    out = []
    for n, seg in enumerate(segments):
        first = segments[n - 1].point + 1 if n else 0
        worst: dict[str, float] = {}
        for k in range(first, seg.point + 1):
            point = traj.points[k]
            if point.time_s <= from_s:
                continue
            planned = planned_at(segments, start_steps, point.time_s)
            for joint, want in zip(traj.joints, point.positions_steps):
                err = abs(planned[0].get(joint, start_steps[joint]) - want)
                worst[joint] = max(worst.get(joint, 0.0), err)
                bound = tol.get(joint, 0.0)
                if bound > 0 and err > bound + 1e-6:
                    lim = limits[joint]
                    u = lim.steps_per_unit
                    raise TrajectoryError(
                        f'{joint}: point {k} ({point.time_s:g} s) cannot be followed within the '
                        f'path bound {bound / u:.4g} {lim.unit}: the plan passes '
                        f'{err / u:.4g} {lim.unit} from it (segment {seg.start_s:g} s to '
                        f'{seg.end_s:g} s; {seg.merged} points merged into it: the bus needs '
                        f'segments of at least {min_segment_s:.3g} s). Widen the bound (the '
                        f"goal's path_tolerance, constraints.{joint}.trajectory or "
                        f'constraints.{joint}.path_bound), send points at least '
                        f"{min_segment_s:.3g} s apart (MoveIt's resample_dt), or give the bus "
                        'more time per move (a faster line: a higher baud rate)')
        out.append(dataclasses.replace(seg, deviation_steps=tuple(worst.items())))
    return out


def planned_at(segments: Sequence[Segment], start_steps: dict[str, float], clock_s: float
               ) -> tuple[dict[str, float], dict[str, float]]:
    """The planned position and velocity of each joint at trajectory time clock_s: the
    trapezoids of rest-to-rest moves, each from when its move reaches the drive, the
    profiles of continuous moves from when they take effect, and the runs of chains."""
    pos = dict(start_steps)
    vel = {j: 0.0 for j in start_steps}
    for seg in segments:
        for m in seg.moves:
            te = seg.start_s + m.start_delay_s
            if m.via_steps is not None:
                if clock_s > te:
                    pos[m.joint], vel[m.joint] = m.state(clock_s - te)
                continue
            if clock_s <= seg.start_s:
                continue
            if m.knots:
                pos[m.joint], vel[m.joint] = m.chain_state(te, pos[m.joint], clock_s)
                continue
            tau = min(clock_s, seg.end_s) - seg.start_s
            profile = (pos[m.joint], m.target_steps, m.velocity_steps_s,
                       m.acceleration_steps_s2, tau - m.start_delay_s)
            vel[m.joint] = along_velocity(*profile) if clock_s < seg.end_s else 0.0
            pos[m.joint] = along(*profile)
    return pos, vel


def _delayed(joints, profiles: dict[str, tuple[float, float]], targets: dict[str, float],
             previous: dict[str, float], duration_s: float, limits: dict[str, JointLimits],
             lines: dict[str, tuple[object, float]]) -> tuple[AxisMove, ...] | Unreachable:
    """The segment's moves, each starting when its move will have reached its drive: the bus
    owner finishes one drive's move before it takes the next one's (a running operation goes
    first), so an axis starts after the moves of the axes before it on its bus and its own."""
    sent: dict[object, float] = {}
    moves = []
    for jn in joints:
        if jn not in profiles:
            continue
        v, a = profiles[jn]
        delay = 0.0
        if jn in lines:
            bus, cost_s = lines[jn]
            delay = sent[bus] = sent.get(bus, 0.0) + cost_s
        if delay > 0:
            again = retimed(targets[jn] - previous[jn], duration_s - delay, (v, a), limits[jn])
            if again is None:
                return Unreachable(jn, f'cannot arrive in time: its move reaches the drive '
                                   f'{delay:.3g} s into the segment (after the moves before it '
                                   'on its bus and its own transactions)')
            v, a = again
        moves.append(AxisMove(jn, targets[jn], v, a, delay))
    return tuple(moves)
