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
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

# A trapezoid needs a * T^2 >= 4 * d (the triangle: accelerate half the time, brake the other
# half). A segment within this fraction of that bound is refused too: the drives quantize the
# profile, and a profile at the very edge would arrive late.
EDGE_MARGIN = 0.98
# The plan's ramps use this much of each joint's max_acceleration when the segment allows, so an
# axis whose move goes out late (behind others on one serial line) can still catch up.
PLAN_FRACTIONS = (0.7, EDGE_MARGIN)


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


@dataclasses.dataclass(frozen=True)
class Point:
    time_s: float                    # from the trajectory's start
    positions_steps: tuple[float, ...]


@dataclasses.dataclass(frozen=True)
class Trajectory:
    joints: tuple[str, ...]
    points: tuple[Point, ...]


@dataclasses.dataclass(frozen=True)
class AxisMove:
    """One axis's part of one segment: a move to `target_steps` with this profile."""

    joint: str
    target_steps: float
    velocity_steps_s: float
    acceleration_steps_s2: float


@dataclasses.dataclass(frozen=True)
class Segment:
    """From `start_s` to `end_s` (trajectory time): the moves that start together at start_s."""

    start_s: float
    end_s: float
    moves: tuple[AxisMove, ...]


def build(joints: Sequence[str], times_s: Sequence[float],
          positions_steps: Sequence[Sequence[float]], known: Sequence[str]) -> Trajectory:
    """A Trajectory from message fields already converted to steps; TrajectoryError for joints
    that are not this node's, repeated joints, times that do not increase, a point whose
    position count does not match the joints, or a value that is not a number."""
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
        points.append(Point(float(t), tuple(float(p) for p in pos)))
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
        return {j: (d / T, math.inf) for j, d in moving.items()}
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
        out[j] = (v, v / t_r if t_r > 0 else math.inf)
    return out


def plan(traj: Trajectory, start_steps: dict[str, float], limits: dict[str, JointLimits],
         from_s: float = 0.0) -> list[Segment]:
    """The synchronized segments of `traj` from trajectory time `from_s` (0: its start; later
    when it starts in the past), each axis from `start_steps` (where the drives are now);
    TrajectoryError naming the joint, the point and the limit when any segment cannot be met:
    then nothing is sent."""
    segments = []
    previous = {j: start_steps[j] for j in traj.joints}
    t0 = from_s
    for k, point in enumerate(traj.points):
        if point.time_s <= from_s:
            continue                                  # already past: JTC drops them too
        targets = dict(zip(traj.joints, point.positions_steps))
        for joint, target in targets.items():
            lim = limits[joint]
            if not lim.min_steps <= target <= lim.max_steps:
                raise TrajectoryError(
                    f'{joint}: point {k} at {target / lim.steps_per_unit:g} {lim.unit} is '
                    f'outside min_position..max_position ({lim.min_steps / lim.steps_per_unit:g}'
                    f'..{lim.max_steps / lim.steps_per_unit:g} {lim.unit})')
        profiles = segment_profiles({j: targets[j] - previous[j] for j in traj.joints},
                                    point.time_s - t0, limits, PLAN_FRACTIONS)
        if isinstance(profiles, Unreachable):
            raise TrajectoryError(f'{profiles.joint}: segment to point {k} ({t0:g} s to '
                                  f'{point.time_s:g} s) {profiles.why}')
        moves = tuple(AxisMove(j, targets[j], *profiles[j]) for j in traj.joints
                      if j in profiles)
        segments.append(Segment(t0, point.time_s, moves))
        previous.update(targets)
        t0 = point.time_s
    return segments


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
