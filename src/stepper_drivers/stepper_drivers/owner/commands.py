"""What a command means to the bus owner, named once.

A job's kind sets where it queues (JobKind); its flags say what a stop or a disable does to it
while it waits or runs (`motion`) and whether its success ends a velocity run's watchdog
(`disarms`). Every caller builds its command with one of Command's constructors, so these
rules live here and nowhere else; the bus owner (owner.BusOwner) only applies them.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any, Callable


class CommandRefused(Exception):
    """A command the node does not send to the drive (it failed the node's checks); str() is
    the reason."""


class JobKind(enum.Enum):
    URGENT = 'urgent'            # before everything: stop, quick stop, disable, watchdog stop
    COMMAND = 'command'          # in order per drive: enable, move, homing, fault reset
    STREAM = 'stream'            # a newer one of the same topic replaces the one still waiting
    MAINTENANCE = 'maintenance'  # save, register access: a disable drops only what can move
    CONNECT = 'connect'          # the owner's own connection attempt


@dataclasses.dataclass(frozen=True)
class Command:
    """One job for one drive: `fn` runs in the owner thread (it may return an Operation)."""

    kind: JobKind
    fn: Callable[[], Any]
    label: str
    disarms: bool = False   # its confirmed success disarms the velocity watchdog
    motion: bool = True     # a stop of the drive drops it while it waits, or cuts it short
    topic: str = ''         # STREAM: which stream ('position', 'velocity')
    # step-wise, and the drive is still polled between its steps (a stream of set points that
    # lasts seconds: the drive's state must stay fresh meanwhile)
    polled: bool = False
    # other drives of the bus the job also writes (a group start queued under one drive): the
    # owner counts its start and end as writes of each of them too (snapshot provenance); only
    # the job's own drive orders, drops or cuts it short (a stop of another drive does not)
    also: tuple[str, ...] = ()

    # The constructors: one per kind of command.
    @classmethod
    def stop(cls, fn: Callable[[], Any], label: str = 'stop') -> Command:
        """The drive's own stop (profile deceleration): first, and it ends a velocity run."""
        return cls(JobKind.URGENT, fn, label, disarms=True)

    @classmethod
    def disable(cls, fn: Callable[[], Any], label: str = 'disable') -> Command:
        """First; drops every waiting job that could move or change the drive."""
        return cls(JobKind.URGENT, fn, label, disarms=True, motion=False)

    @classmethod
    def enable(cls, fn: Callable[[], Any], label: str = 'enable') -> Command:
        """Moves nothing (the drives set their target to the actual position first)."""
        return cls(JobKind.COMMAND, fn, label, motion=False)

    @classmethod
    def fault_reset(cls, fn: Callable[[], Any], label: str = 'fault_reset') -> Command:
        return cls(JobKind.COMMAND, fn, label, motion=False)

    @classmethod
    def move(cls, fn: Callable[[], Any], label: str, polled: bool = False,
             also: tuple[str, ...] = ()) -> Command:
        """A move or a homing: it replaces any velocity run, so it disarms the watchdog (of
        its own drive: not of the `also` drives, whose part the job may leave out)."""
        return cls(JobKind.COMMAND, fn, label, disarms=True, polled=polled, also=tuple(also))

    @classmethod
    def homing(cls, fn: Callable[[], Any], label: str = 'home') -> Command:
        """The homing's start: a move as far as a stop and the watchdog are concerned."""
        return cls.move(fn, label)

    @classmethod
    def position_stream(cls, fn: Callable[[], Any], label: str) -> Command:
        return cls(JobKind.STREAM, fn, label, disarms=True, topic='position')

    @classmethod
    def velocity_stream(cls, fn: Callable[[], Any], label: str, velocity: float) -> Command:
        """A non-zero velocity runs under the watchdog (armed by the caller before it is sent:
        a write whose reply is lost still ran); zero ends the run."""
        return cls(JobKind.STREAM, fn, label, disarms=velocity == 0.0, topic='velocity')

    @classmethod
    def maintenance(cls, fn: Callable[[], Any], label: str) -> Command:
        """Cannot move the drive (save, a register read): a disable does not drop it."""
        return cls(JobKind.MAINTENANCE, fn, label, motion=False)

    @classmethod
    def raw_write(cls, fn: Callable[[], Any], label: str) -> Command:
        """A raw register write may be a controlword: a stop drops it like any motion."""
        return cls(JobKind.MAINTENANCE, fn, label)
