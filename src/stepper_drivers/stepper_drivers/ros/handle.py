"""DriveHandle: the ROS side of one drive, shared by the node and its parts (no node import).

The node (node.py) makes one per drive; its command topics, services, publishing and trajectory
interface (command_topics.py, services.py, publishing.py, trajectory_interface.py) take the
handles it gives them. A handle reads its drive's parameters through the node, typed here as
the one call it needs (`ParameterSource`), so this module imports nothing of the node.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import math
from typing import Any, Protocol

from ..contract.drive import Drive, DriveState, Homing, Motion
from ..owner import BusOwner, Slot
from .params import DriveConfig


class JobAwaiter(Protocol):
    """What a part of the node that runs service or action callbacks needs of it: the count of
    callbacks running (`handling`), the awaiting of an owner-thread future, and of the
    publication of the snapshots that followed a drive's writes (node.DriveNode)."""

    def handling(self) -> contextlib.AbstractContextManager: ...

    async def await_future(self, fut: concurrent.futures.Future, *,
                           bus_owner: BusOwner | None = None,
                           timeout_s: float | None = None) -> Any: ...

    async def published(self, *handles: DriveHandle, timeout_s: float = 2.0,
                        after: int | None = None) -> bool: ...


class ParameterSource(Protocol):
    """What a handle needs of its node: the rclpy Node's get_parameter."""

    def get_parameter(self, name: str) -> Any: ...


class DriveHandle:
    """The ROS side of one drive: its configuration, conversion, refusal counters, and the
    owner-side slot (snapshot, link state) of its bus owner."""

    def __init__(self, node: ParameterSource, cfg: DriveConfig, drive: Drive):
        self.node = node
        self.cfg = cfg
        self.name = cfg.name
        self.drive = drive
        self.conv = cfg.conversion
        self._sup: BusOwner | None = None   # set when the buses are built
        self.slot: Slot | None = None            # its slot in that bus owner (with it)
        self.commands_refused = 0
        self.last_refusal = ''
        self.refusal_logged = ''           # the kind of refusal logged last (see refuse)
        self.job_error_logged = ''         # the kind of failed command logged last (owner)
        self.status_key: tuple = ()        # what the last published status said (owner thread)
        self.status_due = 0.0              # time.monotonic() of the next status regardless
        # callers awaiting the publication of a snapshot newer than a change (owner thread)
        self.publish_waiters: list[concurrent.futures.Future] = []
        # (steps, slot, slot.submitted, slot.reconnects) of the last target the drive confirmed
        # (set by the owner thread in one assignment, read by the command thread): see
        # command_topics.CommandTopics._holds
        self.held_target: tuple | None = None
        # (that tuple, the job's future) of the last position job submitted (command thread)
        self.pending_target: tuple | None = None
        self.stream_t = -math.inf          # time.monotonic() of the last joint_command position

    @property
    def bus_owner(self) -> BusOwner | None:
        return self._sup

    @bus_owner.setter
    def bus_owner(self, bus_owner: BusOwner | None) -> None:
        self._sup = bus_owner
        self.slot = None if bus_owner is None else bus_owner.slots[self.name]

    @property
    def state(self) -> DriveState:
        return self.slot.state

    @property
    def connected(self) -> bool:
        return self.slot.connected

    def param(self, name: str) -> Any:
        return self.node.get_parameter(f'drives.{self.name}.{name}').value

    def motion(self) -> Motion:
        to = self.conv.to_steps
        return Motion(to(self.param('profile_velocity')), to(self.param('profile_acceleration')),
                      to(self.param('profile_deceleration')))

    def homing(self) -> Homing:
        to = self.conv.to_steps
        return Homing(int(self.param('homing.method')),
                      self.conv.to_steps_int(self.param('homing.offset')),
                      to(self.param('homing.speed_search')), to(self.param('homing.speed_zero')),
                      to(self.param('homing.acceleration')))

    @property
    def position(self) -> float:
        return self.conv.from_steps(self.state.position_steps)

    @property
    def velocity(self) -> float:
        return self.conv.from_steps(self.state.velocity_steps_s)
