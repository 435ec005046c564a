"""One joint the trajectory follower may move (`Axis`): its drive and bus owner, its limits,
what the bus owner's snapshots say of it, and what a move costs there (learned by the move
jobs, moves.py).

Not here: planning (trajectory.py) and following (follow.py)."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, Protocol

from ..contract.capabilities import Interpolating, Retargeting
from ..contract.drive import Drive
from ..owner import BusOwner
from .trajectory import JointLimits


@dataclasses.dataclass
class Axis:
    """One joint the follower may move."""

    joint: str
    drive_name: str
    bus_owner: BusOwner
    drive: Drive
    limits: JointLimits
    lead_s: float = 0.0     # learned: a move's own transactions before the drive runs
    move_time_s: float = 0.0   # the drive's own estimate of lead_s (Drive.move_time_s)
    # learned: the time a continuous move's steps take on the bus, all of them (a set-point
    # handshake after the motion frame too), not the waits between them
    busy_s: float = 0.0
    # learned: from the start of a chained trajectory to the string that started its last
    # drive (motion/chain.py; 0 until one was)
    chain_lead_s: float = 0.0

    @property
    def continuous(self) -> bool:
        """Followed velocity-continuously: its drive takes a new target on the way and it gets
        point-to-point moves (trajectory.plan's `continuous`)."""
        return isinstance(self.drive, Retargeting) and not self.interpolated

    @property
    def interpolated(self) -> bool:
        """Its drive follows a stream of set points (Vector Step interpolated position at
        these settings), not point-to-point moves."""
        return isinstance(self.drive, Interpolating) and \
            self.drive.interpolation_period_s is not None

    def position_steps(self) -> float:
        return float(self.bus_owner.slots[self.drive_name].state.position_steps)

    def sample(self) -> tuple[float, float]:
        """(position, when it was true): the last poll's position and the bus owner's state
        time (the poll's end, or the drive's own measurement time, DriveState.measured_at_s)."""
        position, _velocity, t = self.sample_motion()
        return position, t

    def sample_motion(self) -> tuple[float, float, float]:
        """(position, velocity, when they were true) of the last poll, as `sample`; velocity 0
        where the drive reports none (DriveState.velocity_valid)."""
        state, t = self.bus_owner.slots[self.drive_name].sample
        velocity = float(state.velocity_steps_s) if state.velocity_valid else 0.0
        return float(state.position_steps), velocity, t

    def moving(self) -> bool:
        return bool(self.bus_owner.slots[self.drive_name].state.moving)

    def move_cost_s(self) -> float:
        """What a move costs on the bus before the drive runs: as measured once one was,
        the drive's estimate before."""
        return self.lead_s if self.lead_s > 0 else self.move_time_s

    def move_busy_s(self) -> float:
        """What a continuous move takes of the bus: its steps' time as measured, its cost
        (move_cost_s) before."""
        return self.busy_s if self.busy_s > 0 else self.move_cost_s()

    def velocity_steps_s(self) -> float | None:
        """The last poll's velocity; None where the drive cannot report one."""
        state = self.bus_owner.slots[self.drive_name].state
        return float(state.velocity_steps_s) if state.velocity_valid else None


class FollowerView(Protocol):
    """What the move jobs (moves.py) and the streams (stream.py) need of their follower
    (follow.Follower): its axes, its clock and the run it follows now."""

    axes: Mapping[str, Axis]     # joint -> axis (the ROS interface may swap the mapping)
    clock: Callable[[], float]   # time.monotonic() or a test's clock
    current: Any                 # the run being followed (stream.StreamedRun), or None
