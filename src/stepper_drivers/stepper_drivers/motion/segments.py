"""The plan's data: a trajectory in drive units (`Trajectory`, `Point`), a joint's limits
(`JointLimits`), and the plan made of it (`Segment`, `AxisMove`), with the margins the planners
share and the error they raise, and the trajectory's own position at a time (`sample`). No
planning here: point-to-point planning is trajectory.py's,
velocity-continuous planning continuous.py's; the profile arithmetic is move_profile.py's."""

from __future__ import annotations

import dataclasses

from .move_profile import motion_state, ramps

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
    # A velocity-continuous move (None: rest to rest): where it passes at the segment's end
    # (the point, or near it where points were merged: continuous.fitted_vias; target_steps is
    # then where it passes the next segment's end, on the same way), and the
    # planned position and velocity (signed) of the joint when it takes effect, start_delay_s
    # (< 0: before the segment starts) into the segment.
    via_steps: float | None = None
    entry_steps: float = 0.0
    entry_velocity_steps_s: float = 0.0
    start_stop_steps_s: float = 0.0      # its drive's (JointLimits): no ramps at or below
    deceleration_steps_s2: float = 0.0   # a continuous move's; 0: acceleration_steps_s2
    # A continuous move's joint runs its segments this much later (< 0: earlier) than the
    # segments' times (its bus sends the joints' moves one after the other: trajectory._shifts):
    # it passes via_steps shift_s after the segment's end
    shift_s: float = 0.0
    # A chain of constant-rate runs (capabilities.Chaining; () otherwise): (trajectory time,
    # position) where each run ends, the last (the segment's end, target_steps); the first
    # runs from where the joint is start_delay_s into the segment
    knots: tuple[tuple[float, float], ...] = ()

    def chain_state(self, start_s: float, start_steps: float, clock_s: float
                    ) -> tuple[float, float]:
        """Planned (position, velocity) of a chain at trajectory time clock_s, its first run
        from `start_steps` at trajectory time `start_s`: linear between its knots."""
        t0, x0 = start_s, start_steps
        for t1, x1 in self.knots:
            if clock_s < t1:
                if clock_s <= t0:
                    return x0, 0.0
                v = (x1 - x0) / (t1 - t0)
                return x0 + v * (clock_s - t0), v
            t0, x0 = t1, x1
        return x0, 0.0

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
