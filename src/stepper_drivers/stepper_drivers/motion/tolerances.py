"""A goal's tolerances (`Tolerances`, in drive units) and the checks against them while a run
goes and at its end: the path (each joint's position and velocity against the plan's) and the
goal (position, standstill or velocity). A check says which joint is outside and by how much.

Not here: what a run does then (follow.Run stops its joints and ends with the result code), nor
the path bound the plan is held to before anything moves (trajectory.plan)."""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

from .axis import Axis

# A goal position tolerance in steps comes from joint units (step size x n is n within a few
# ulp): a position this close beyond it is within it.
ROUNDING_STEPS = 1e-6

# The plan of a run: (positions, velocities) per joint at a monotonic time (Run.desired)
Desired = Callable[[float], tuple[dict[str, float], dict[str, float]]]


@dataclasses.dataclass(frozen=True)
class Tolerances:
    """Per joint, in drive units, as JointTrajectoryController resolves a goal's tolerances
    (the node turns -1 into 'not checked' and 0 into the default).

    Path (position, velocity): absent or 0: not checked. Goal position: absent or 0: one step
    (the drive's resolution); None: not checked. Goal velocity: absent or 0: standstill (the
    drive's own moving flag); None: not checked; > 0: |velocity| within it, a drive that
    reports standstill counting as 0 (a velocity reading can be older than its moving flag:
    the RD4 refreshes it once a second) and a moving one that reports no velocity as outside.
    goal_time_s: 0 no limit (until every joint stands still, at most follow.GOAL_WAIT_MAX_S).
    path_bound_steps: how far the plan (merged segments, continuous profiles) may pass from the
    trajectory's points, per joint (the path tolerance where there is one, else the node's
    default); absent or 0: not bounded."""

    path_steps: dict[str, float] = dataclasses.field(default_factory=dict)
    goal_steps: dict[str, float | None] = dataclasses.field(default_factory=dict)
    goal_time_s: float = 0.0
    path_velocity_steps_s: dict[str, float] = dataclasses.field(default_factory=dict)
    goal_velocity_steps_s: dict[str, float | None] = dataclasses.field(default_factory=dict)
    path_bound_steps: dict[str, float] = dataclasses.field(default_factory=dict)


def off_path(tol: Tolerances, axes: dict[str, Axis], desired: Desired, now: float,
             start_t: float) -> str | None:
    """Why a joint is off its path at monotonic time `now` (the run started at start_t): its
    position beyond its path tolerance, else its velocity beyond its path velocity tolerance,
    each against the plan when its last snapshot was true; None when every joint is within."""
    return _off_path_position(tol, axes, desired, now, start_t) or \
        _off_path_velocity(tol, axes, desired, now, start_t)


def _off_path_position(tol: Tolerances, axes: dict[str, Axis], desired: Desired, now: float,
                       start_t: float) -> str | None:
    for joint, limit in tol.path_steps.items():
        if limit > 0 and joint in axes:
            # the plan at the time the position was true, not now: a position up to a poll
            # period old (and a Vector Step's TxPDO inhibit time) is no path error
            position, at = axes[joint].sample()
            at = min(at, now)
            planned = desired(at)[0].get(joint)
            if planned is None:
                continue
            err = position - planned
            if abs(err) > limit:
                return (f'{joint}: {err:+.0f} steps from the path (path tolerance {limit:g} '
                        f'steps) at {now - start_t:.3f} s, by its position of '
                        f'{at - start_t:.3f} s')
    return None


def _off_path_velocity(tol: Tolerances, axes: dict[str, Axis], desired: Desired, now: float,
                       start_t: float) -> str | None:
    for joint, limit in tol.path_velocity_steps_s.items():
        if limit > 0 and joint in axes:
            axis = axes[joint]
            velocity = axis.velocity_steps_s()
            if velocity is None:
                continue                   # refused at the goal: the drive reports none
            _, at = axis.sample()
            err = velocity - desired(min(at, now))[1].get(joint, 0.0)
            if abs(err) > limit:
                return (f"{joint}: velocity {err:+.0f} steps/s from the path's (path velocity "
                        f'tolerance {limit:g} steps/s) at {now - start_t:.3f} s')
    return None


def off_goal(tol: Tolerances, axes: dict[str, Axis], joints: Sequence[str],
             final_steps: dict[str, float]) -> list[str]:
    """Why each of `joints` that is not at its goal (`final_steps`, within its goal tolerances)
    is not, one line per joint; [] when every one is."""
    far = []
    for joint in joints:
        axis = axes[joint]
        why = []
        limit = tol.goal_steps.get(joint, 0.0)
        if limit is not None:
            limit = limit or 1.0                      # the default: the final step
            err = axis.position_steps() - final_steps[joint]
            if abs(err) > limit + ROUNDING_STEPS:
                why.append(f'{err:+.0f} steps from the goal (goal tolerance {limit:.6g} '
                           'steps)')
        vtol = tol.goal_velocity_steps_s.get(joint, 0.0)
        if vtol is None or not axis.moving():
            pass                          # not checked, or standing: at velocity 0
        elif not vtol:
            why.append('still moving')
        else:
            velocity = axis.velocity_steps_s()
            if velocity is None:
                why.append('still moving (its drive reports no velocity)')
            elif abs(velocity) > vtol:
                why.append(f'at {velocity:+.0f} steps/s (goal velocity tolerance {vtol:.6g} '
                           'steps/s)')
        if why:
            far.append(f'{joint}: {", ".join(why)}')
    return far
