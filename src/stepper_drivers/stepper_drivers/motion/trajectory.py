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
while they move, Drive.retargets_on_the_way: the RD4's "Position override function", the
X-PLUS MT's and the Vector Step's change set immediately in profile position): a joint does not
stop at its points. Each segment's move goes to the drive before the one before it would start to
slow down: its target is the next point where the joint goes on the same way (the drive then
never brakes for the point it passes), its speed the one that passes the segment's point at the
segment's end, found on the drive's own profile (`motion_state`: from the speed it has, ramps of
one acceleration, a cruise, a brake at the target). It takes effect half its speed change before
the segment starts, so that the change is centred on the point between the two segments (the
joint's speed then steps from one segment's average to the next one's around each point: its
position passes the points on time). The ramps: PLAN_FRACTIONS[0] of its max_acceleration, or
RAMP_SHAPE times the plan's largest acceleration of the joint (the points' accelerations, or their
positions' second differences) where that is steeper; a drive that runs start-stop at a speed
(X-PLUS MT) jumps. A joint whose planned velocity is zero at a point, or that turns or holds
there, brakes to rest on it, as the rest-to-rest segments do.

The path is bounded: the plan (merged segments, continuous profiles) is evaluated at every point
of the trajectory and may pass no farther from any than `path_bound_steps` (per joint: the goal's
path tolerance, else the node's default); a trajectory that cannot be carried within it is
refused before anything moves, naming the joint, the point, the bound and the least segment the
bus needs.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Collection, Sequence

# A trapezoid needs a * T^2 >= 4 * d (the triangle: accelerate half the time, brake the other
# half). A segment within this fraction of that bound is refused too: the drives quantize the
# profile, and a profile at the very edge would arrive late.
EDGE_MARGIN = 0.98
# The plan's ramps use this much of each joint's max_acceleration when the segment allows, so an
# axis whose move goes out late (behind others on one serial line) can still catch up.
PLAN_FRACTIONS = (0.7, EDGE_MARGIN)
# Velocity-continuous joints: ramps at PLAN_FRACTIONS[0] of the joint's max_acceleration, or at
# this many times the plan's largest acceleration of the joint where that is steeper (at most
# EDGE_MARGIN of it). One value per joint and trajectory, for speeding up and slowing down
# alike: the X-PLUS MT loads Profile Acceleration (1046) only when a move starts from rest and
# uses it both ways (§13 "Multi-Set-Point Mode", "Registers 1046-1047"), the RD4 then writes
# its ramps once, and a stop of the drive brakes as fast as a rest-to-rest move's would.
RAMP_SHAPE = 1.5


class TrajectoryError(ValueError):
    """The trajectory cannot be followed; str() names the joint, the point and the limit."""


@dataclasses.dataclass(frozen=True)
class JointLimits:
    """One joint's limits in drive units (steps, steps/s, steps/s^2)."""

    min_steps: float
    max_steps: float
    max_velocity_steps_s: float
    max_acceleration_steps_s2: float
    steps_per_unit: float = 1.0      # for messages in joint units (rad or m)
    unit: str = 'rad'
    # A drive that jumps to velocities up to this without ramps (X-PLUS MT §13 "Motion
    # Profiles": start-stop at PV <= 16000 Hz); 0: every move ramps.
    start_stop_steps_s: float = 0.0
    # The least speed the drive runs a move at (Vector Step: 0.01 rev/s, the resolution of
    # 0x6081; X-MIND K: 1 Hz); a slower segment runs at this speed and arrives early. 0: none.
    min_velocity_steps_s: float = 0.0


@dataclasses.dataclass(frozen=True)
class Point:
    time_s: float                    # from the trajectory's start
    positions_steps: tuple[float, ...]
    # the planned velocities [steps/s] and accelerations [steps/s^2] where the message has them
    velocities_steps_s: tuple[float, ...] = ()
    accelerations_steps_s2: tuple[float, ...] = ()


@dataclasses.dataclass(frozen=True)
class Trajectory:
    joints: tuple[str, ...]
    points: tuple[Point, ...]


@dataclasses.dataclass(frozen=True)
class AxisMove:
    """One axis's part of one segment: a move to `target_steps` with this profile, starting
    `start_delay_s` after the segment's start (when its move reaches the drive: on a serial
    line, after the moves of the axes before it and its own transactions)."""

    joint: str
    target_steps: float
    velocity_steps_s: float
    acceleration_steps_s2: float
    start_delay_s: float = 0.0
    # A velocity-continuous move (None: rest to rest): the point it passes at the segment's end
    # (target_steps is then the next point where the joint goes on the same way), and the
    # planned position and velocity (signed) of the joint when it takes effect, start_delay_s
    # (< 0: before the segment starts) into the segment.
    via_steps: float | None = None
    entry_steps: float = 0.0
    entry_velocity_steps_s: float = 0.0
    start_stop_steps_s: float = 0.0      # its drive's (JointLimits): no ramps at or below
    deceleration_steps_s2: float = 0.0   # a continuous move's; 0: acceleration_steps_s2

    def state(self, tau_s: float) -> tuple[float, float]:
        """Planned (position, velocity) of a continuous move tau_s after it took effect."""
        v, ss = self.velocity_steps_s, self.start_stop_steps_s
        return motion_state(self.entry_steps, self.entry_velocity_steps_s, self.target_steps,
                            v, ramps(self.acceleration_steps_s2, v, ss), tau_s,
                            ramps(self.deceleration_steps_s2 or self.acceleration_steps_s2, v,
                                  ss))


@dataclasses.dataclass(frozen=True)
class Segment:
    """From `start_s` to `end_s` (trajectory time): the moves that start together at start_s,
    to the trajectory's point `point`; `merged` points before it were merged into it."""

    start_s: float
    end_s: float
    moves: tuple[AxisMove, ...]
    point: int = -1
    merged: int = 0
    # per joint, how far the plan passes from the points merged into this segment [steps]
    deviation_steps: tuple[tuple[str, float], ...] = ()


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
    before it and its own; its profile is planned for the time left then.

    `continuous`: joints followed velocity-continuously (the module's docstring), from
    `start_velocity_steps_s` (a trajectory that takes over from a running one; else at rest)."""
    tol = path_tolerance_steps or {}
    lines = move_times_s or {}
    cont = [j for j in traj.joints if j in continuous]
    stepwise = {j: limits[j] for j in traj.joints if j not in cont}
    due = [(k, p) for k, p in enumerate(traj.points) if p.time_s > from_s]
    for k, point in due:                             # points already past: JTC drops them too
        for joint, target in zip(traj.joints, point.positions_steps):
            lim = limits[joint]
            if not lim.min_steps <= target <= lim.max_steps:
                raise TrajectoryError(
                    f'{joint}: point {k} at {target / lim.steps_per_unit:g} {lim.unit} is '
                    f'outside min_position..max_position ({lim.min_steps / lim.steps_per_unit:g}'
                    f'..{lim.max_steps / lim.steps_per_unit:g} {lim.unit})')
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
        segments = _continuous(traj, segments, start_steps, limits, cont,
                               start_velocity_steps_s or {})
    return _bounded(traj, segments, start_steps, from_s, limits, tol, min_segment_s)


def _average_speeds(joints: list[str], targets: dict[str, float], previous: dict[str, float],
                    duration_s: float, limits: dict[str, JointLimits],
                    profiles: dict[str, tuple[float, float]]
                    ) -> dict[str, tuple[float, float]] | Unreachable:
    """`profiles` with the continuous joints' average speeds over the segment (placeholders:
    _continuous plans their moves); Unreachable where one is above its max_velocity (with the
    margin the ramps need)."""
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


def _continuous(traj: Trajectory, segments: list[Segment], start_steps: dict[str, float],
                limits: dict[str, JointLimits], joints: list[str],
                start_velocity: dict[str, float]) -> list[Segment]:
    """The segments with velocity-continuous moves for `joints` (the module's docstring);
    TrajectoryError where a joint cannot pass a point in time within its max_velocity."""
    moves: list[dict[str, AxisMove]] = [{m.joint: m for m in seg.moves} for seg in segments]
    for joint in joints:
        col = traj.joints.index(joint)
        lim = limits[joint]
        a = ramp_acceleration(traj, joint, lim, start_steps[joint])
        vias = [traj.points[seg.point].positions_steps[col] for seg in segments]
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
            average = (via - before) / (seg.end_s - seg.start_s)
            if effect is None:
                at, x_e, u_e = seg.start_s, x, u
            elif effect.target_steps == effect.via_steps:
                at, x_e, u_e = seg.start_s, effect.via_steps, 0.0    # at rest on its point
            else:
                t_e = effect_s
                _, u_now = effect.state(seg.start_s - t_e)
                change = a if abs(average) > abs(u_now) else deceleration(a, lim)
                quick = ramps(change, max(abs(average), abs(u_now)), lim.start_stop_steps_s)
                half = 0.0 if u_now == 0.0 else abs(average - u_now) / (2 * quick)
                at = max(t_e, seg.start_s - half)
                x_e, u_e = effect.state(at - t_e)
            if (via - x_e) * way <= 0:       # there already (a fraction of a step): cruise on
                found = (max(abs(average), lim.min_velocity_steps_s, 1e-3), a, a)
            else:
                found = cruise(x_e, u_e, via, target, seg.end_s - at, a, lim)
            if found is None and effect is None and u_e != 0.0:
                # taking over a joint at speed that cannot turn in time: planned from rest (it
                # arrives late; the goal tolerance decides), as a rest-to-rest segment is
                u_e = 0.0
                found = cruise(x_e, u_e, via, target, seg.end_s - at, a, lim)
            if found is None:
                u_ = lim.steps_per_unit
                raise TrajectoryError(
                    f'{joint}: point {seg.point} ({seg.end_s:g} s) cannot be reached in time '
                    f'from {x_e / u_:.6g} {lim.unit} at {u_e / u_:.4g} {lim.unit}/s with ramps '
                    f'of {a / u_:.4g} {lim.unit}/s^2 within max_velocity '
                    f'({lim.max_velocity_steps_s / u_:.4g} {lim.unit}/s)')
            v, ramp, dec = found
            effect = moves[n][joint] = AxisMove(joint, target, v, ramp, at - seg.start_s, via,
                                                x_e, u_e, lim.start_stop_steps_s, dec)
            effect_s = at
            before = via
    return [dataclasses.replace(seg, moves=tuple(ms[j] for j in traj.joints if j in ms))
            for seg, ms in zip(segments, moves)]


def _bounded(traj: Trajectory, segments: list[Segment], start_steps: dict[str, float],
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
    trapezoids of rest-to-rest moves, each from when its move reaches the drive, and the
    profiles of continuous moves from when they take effect."""
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
            tau = min(clock_s, seg.end_s) - seg.start_s
            profile = (pos[m.joint], m.target_steps, m.velocity_steps_s,
                       m.acceleration_steps_s2, tau - m.start_delay_s)
            vel[m.joint] = along_velocity(*profile) if clock_s < seg.end_s else 0.0
            pos[m.joint] = along(*profile)
    return pos, vel


def _pieces(x0: float, u0: float, target: float, vmax: float, a: float, dec: float
            ) -> list[tuple[float, float, float]]:
    """(duration, velocity at its start, acceleration) of each piece of a drive's move from x0
    at velocity u0 to `target` with cruise vmax and ramps a (inf: start-stop): a profile
    generator's, as the simulators' (stepper_sim.core.motion): too fast to stop in time, or moving
    away, it stops first; then it ramps to vmax (or less: a triangle), cruises, and brakes to
    rest on the target; speeding up at a, slowing down at dec."""
    d = target - x0
    if d == 0.0 and u0 == 0.0:
        return []
    s = (d > 0) - (d < 0) or -((u0 > 0) - (u0 < 0))
    u = u0 * s
    ia = 0.0 if math.isinf(a) else 0.5 / a
    idc = 0.0 if math.isinf(dec) else 0.5 / dec
    distance = abs(d)
    if u < 0.0 or u * u * idc > distance * (1.0 + 1e-12) + 1e-9:
        back = (u0 > 0) - (u0 < 0)
        stop = [] if math.isinf(dec) else [(abs(u0) / dec, u0, -back * dec)]
        return stop + _pieces(x0 + back * u0 * u0 * idc, 0.0, target, vmax, a, dec)
    out = []
    if u > vmax:
        if not math.isinf(dec):
            out.append(((u - vmax) / dec, s * u, -s * dec))
        distance -= (u * u - vmax * vmax) * idc
        u = vp = vmax
    elif ia + idc == 0.0:
        vp = vmax
    else:
        vp = max(u, min(vmax, math.sqrt(max((distance + u * u * ia) / (ia + idc), 0.0))))
        if vp > u and not math.isinf(a):
            out.append(((vp - u) / a, s * u, s * a))
        distance -= (vp * vp - u * u) * ia
    cruise = max(distance - vp * vp * idc, 0.0)
    if cruise > 0.0 and vp > 0.0:
        out.append((cruise / vp, s * vp, 0.0))
    if not math.isinf(dec) and vp > 0.0:
        out.append((vp / dec, s * vp, -s * dec))
    return out


def motion_state(x0: float, u0: float, target: float, vmax: float, a: float, tau_s: float,
                 dec: float | None = None) -> tuple[float, float]:
    """(position, velocity) tau_s after a drive at x0 moving at u0 (signed) took a move to
    `target` with cruise vmax, acceleration a and deceleration dec (None: a) (_pieces); at rest
    on the target after the end."""
    x, t = x0, 0.0
    if tau_s <= 0:
        return x0, u0
    for dur, v, acc in _pieces(x0, u0, target, vmax, a, a if dec is None else dec):
        if tau_s < t + dur:
            tau = tau_s - t
            return x + v * tau + 0.5 * acc * tau * tau, v + acc * tau
        x += v * dur + 0.5 * acc * dur * dur
        t += dur
    return target, 0.0


def ramps(a: float, v: float, start_stop_steps_s: float) -> float:
    """The acceleration a drive runs a move at cruise v with: inf (start-stop, no ramps) at or
    below its start-stop velocity (X-PLUS MT §13 "Motion Profiles"), else a."""
    return math.inf if v <= start_stop_steps_s else a


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


def along(p0: float, p1: float, v: float, a: float, tau: float) -> float:
    """Position tau into a symmetric trapezoid from p0 to p1 with cruise v and ramps a (inf:
    start-stop); p1 once it has arrived."""
    d = abs(p1 - p0)
    if d == 0 or v <= 0 or a <= 0:
        return p1
    sign = 1.0 if p1 > p0 else -1.0
    t_ramp = 0.0 if math.isinf(a) else v / a
    total = d / v + t_ramp
    if tau <= 0:
        return p0
    if tau >= total:
        return p1
    if t_ramp == 0.0:
        s = v * tau
    elif tau < t_ramp:
        s = 0.5 * a * tau * tau
    elif tau < total - t_ramp:
        s = 0.5 * a * t_ramp * t_ramp + v * (tau - t_ramp)
    else:
        s = d - 0.5 * a * (total - tau) ** 2
    return p0 + sign * min(s, d)


def along_velocity(p0: float, p1: float, v: float, a: float, tau: float) -> float:
    """Velocity tau into the trapezoid of `along` (signed, steps/s)."""
    d = abs(p1 - p0)
    if d == 0 or v <= 0 or a <= 0 or tau <= 0:
        return 0.0
    sign = 1.0 if p1 > p0 else -1.0
    t_ramp = 0.0 if math.isinf(a) else v / a
    total = d / v + t_ramp
    if tau >= total:
        return 0.0
    if t_ramp == 0.0:
        return sign * v
    if tau < t_ramp:
        return sign * a * tau
    if tau < total - t_ramp:
        return sign * v
    return sign * a * (total - tau)


def sample(traj: Trajectory, start_steps: dict[str, float], t_s: float) -> dict[str, float]:
    """The desired position of each joint at trajectory time `t_s`: linear between the points
    (the segments are followed point to point), `start_steps` before the first point, the last
    point after the end."""
    prev_t, prev = 0.0, [start_steps[j] for j in traj.joints]
    for point in traj.points:
        if t_s < point.time_s:
            f = (t_s - prev_t) / (point.time_s - prev_t) if point.time_s > prev_t else 1.0
            f = min(max(f, 0.0), 1.0)
            return {j: p0 + f * (p1 - p0)
                    for j, p0, p1 in zip(traj.joints, prev, point.positions_steps)}
        prev_t, prev = point.time_s, list(point.positions_steps)
    return dict(zip(traj.joints, prev))
