"""Joint trajectories in drive units: checking, sampling, and time-synchronized segments.

No rclpy. The node turns a trajectory_msgs/JointTrajectory into a `Trajectory` (joint units to
steps through each drive's UnitConversion); this module decides whether it can be followed and
how, before anything moves. Semantics as JointTrajectoryController's (ros2_controllers, Jazzy):
`time_from_start` of each point is honoured from the trajectory's start time; a trajectory
replaces the rest of the one before it from its own start time; an empty one stops; joints not
in the message hold their position.

Following by synchronized point-to-point segments (every drive: RD4, X-MIND K, and X-PLUS MT,
whose change-set-immediately takes each set point at once): for each segment, every moving axis
gets a trapezoidal profile with the joint's largest acceleration and the velocity that makes it
arrive exactly at the waypoint's time, so all axes start together and arrive together. A segment
that needs more than max_velocity or max_acceleration is refused before anything moves, naming
the joint and the limit.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

# A trapezoid needs a * T^2 >= 4 * d (the triangle: accelerate half the time, brake the other
# half). A segment within this fraction of that bound is refused too: the drives quantize the
# profile, and a profile at the very edge would arrive late.
EDGE_MARGIN = 0.98


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


def trapezoid(distance_steps: float, duration_s: float, max_velocity_steps_s: float,
              max_acceleration_steps_s2: float, start_stop_steps_s: float = 0.0
              ) -> tuple[float, float] | str:
    """(velocity, acceleration) of a symmetric trapezoid covering `distance_steps` in exactly
    `duration_s` with the largest acceleration; or the reason it cannot, as text. An
    acceleration of inf: the drive runs the move start-stop at d / T (no ramps).

    With acceleration a and cruise velocity v: d = v * (T - v / a), so
    v = (a T - sqrt(a^2 T^2 - 4 a d)) / 2, real when a T^2 >= 4 d.
    """
    d = abs(distance_steps)
    a = max_acceleration_steps_s2
    if d == 0:
        return 0.0, a
    if d / duration_s <= min(start_stop_steps_s, max_velocity_steps_s):
        return d / duration_s, math.inf
    need_a = 4 * d / duration_s ** 2
    if a * EDGE_MARGIN < need_a:
        return (f'needs an acceleration of at least {need_a / EDGE_MARGIN:.4g} steps/s^2 to '
                f'cover {d:.6g} steps in {duration_s:g} s (max_acceleration is {a:.4g} '
                'steps/s^2)')
    v = (a * duration_s - math.sqrt(a * a * duration_s ** 2 - 4 * a * d)) / 2
    if v > max_velocity_steps_s:
        return (f'needs {v:.4g} steps/s to cover {d:.6g} steps in {duration_s:g} s '
                f'(max_velocity is {max_velocity_steps_s:.4g} steps/s)')
    return v, a


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
        duration = point.time_s - t0
        moves = []
        for joint, target in zip(traj.joints, point.positions_steps):
            lim = limits[joint]
            if not lim.min_steps <= target <= lim.max_steps:
                raise TrajectoryError(
                    f'{joint}: point {k} at {target / lim.steps_per_unit:g} {lim.unit} is '
                    f'outside min_position..max_position ({lim.min_steps / lim.steps_per_unit:g}'
                    f'..{lim.max_steps / lim.steps_per_unit:g} {lim.unit})')
            profile = trapezoid(target - previous[joint], duration, lim.max_velocity_steps_s,
                                lim.max_acceleration_steps_s2, lim.start_stop_steps_s)
            if isinstance(profile, str):
                raise TrajectoryError(f'{joint}: segment to point {k} ({t0:g} s to '
                                      f'{point.time_s:g} s) {profile}')
            if target != previous[joint]:
                moves.append(AxisMove(joint, target, *profile))
            previous[joint] = target
        segments.append(Segment(t0, point.time_s, tuple(moves)))
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
