"""The optional parts of the drive contract, each a named capability (no rclpy).

`Drive` and `Bus` (drive.py) are all a vendor must implement: a vendor that implements none of the
classes below works (the toy vendor of docs/adding_a_vendor.md does, and its test runs it). Each
capability is a class (abstract where it has methods to fill) that a vendor's Drive or Bus class
also derives from; the bus owner, the poll group, the node and the trajectory follower ask for it
with `isinstance` and then use what it promises. None of them is needed for safety: each makes
polling cheaper or a trajectory smoother on a link that allows it. The paragraph of each says when
to implement it.

Drives: CachedState, FreshPollState, SplitPoll, Retargeting, Interpolating.
Buses:  ChangeCounting, NonblockingPolls, GroupStarting, Chaining.
"""

from __future__ import annotations

import abc
from typing import Any, Callable, Sequence

from .drive import Drive, DriveState, Operation


# ------------------------------------------------------------------------------- drives
class CachedState(abc.ABC):
    """read_state() reads what the drive sent by itself (CANopen TxPDOs), with no transaction.

    Implement it when the link delivers the drive's state unasked and read_state() only decodes
    a cache (the Vector Step). The bus owner then polls the other drives due in the same pass
    without a wait, and in a cycle where nothing changed it counts the drives polled without
    calling them (the quiet cycle) for as long as `unchanged_until` vouches. Its bus must count
    what it receives (ChangeCounting)."""

    @abc.abstractmethod
    def unchanged_until(self, state: DriveState) -> float:
        """Until when (time.monotonic()) read_state() would return `state` (the caller's last
        result of it, or its equal) and raise nothing, as long as the bus' `changes` stays as it
        was before this call and nothing is commanded: up to the next liveness check (a
        heartbeat's deadline). Told without a transaction or a wait. 0.0 (now: it would not, or
        in doubt) makes the owner poll it."""


class FreshPollState:
    """A motion command may take "enabled, no alarm" from the last poll instead of reading it on
    the wire first, while that poll is younger than `state_fresh_s`.

    Implement it when a state read before each motion command costs a line that has little to
    spare (the RD4 at 19200 baud) and the drive's own checks refuse a motion that the state no
    longer allows. The bus owner sets `state_fresh_s` to its poll period (and again when the
    rate changes); 0 until then: read on the wire."""

    state_fresh_s: float = 0.0


class SplitPoll(abc.ABC):
    """A poll as requests that someone else sends and replies that someone else takes.

    Implement it with a NonblockingPolls bus (the X-PLUS MT on Modbus TCP, one connection per
    drive host): the node's poll group then polls the idle drives of several such buses from one
    thread, instead of waking every bus owner for each poll."""

    @abc.abstractmethod
    def state_requests(self) -> list[Any]:
        """The requests whose replies state_from_replies() decodes; [] for read_state() only,
        in the bus owner."""

    @abc.abstractmethod
    def state_from_replies(self, replies: list[Any]) -> DriveState:
        """read_state() from the replies to state_requests(), taken by someone else."""


class Retargeting:
    """move_to while a move runs takes the new target on the way, without a stop first.

    Implement it when the manual says a new target is taken during a move in the same direction
    without an intermediate stop (CiA 402 profile position with "change set immediately",
    controlword bit 5; the RD4's position override). The trajectory follower then gives a late
    axis that goes on in the same direction its next target at once, and follows a trajectory
    velocity-continuously; without it a new move stops the running one first, or waits for it
    (Drive.until_ready_for_move)."""


class Interpolating(abc.ABC):
    """The drive follows a stream of set points, one per period (CiA 402 interpolated position).

    Implement it when the drive has an interpolation buffer the link can feed in time (the Vector
    Step on SYNC): the trajectory follower (motion/) then streams set points to it instead of
    sending point-to-point moves, whenever `interpolation_period_s` is not None."""

    @property
    @abc.abstractmethod
    def interpolation_period_s(self) -> float | None:
        """The period set points are streamed at with the current settings; None: follow
        trajectories point to point."""

    @abc.abstractmethod
    def start_interpolation(self, period_s: float) -> Operation[int]:
        """Step-wise: enter the mode without moving; returns the position it holds [steps]."""

    @abc.abstractmethod
    def interpolation_point(self, position_steps: int) -> None:
        """The next set point (once per period)."""


# -------------------------------------------------------------------------------- buses
class ChangeCounting:
    """The bus counts what its drives sent by themselves that may change a CachedState drive's
    state (a frame that is not a repeat): `changes` +1 each, counted after what it changed is
    stored. While it is unchanged, what CachedState.unchanged_until vouched for still holds."""

    changes: int = 0


class NonblockingPolls(abc.ABC):
    """Requests can be sent now and their replies taken later without blocking.

    Implement it on a bus whose drives are SplitPoll (Modbus TCP): the node then lends the idle
    polls of several such buses to one thread (owner/poll_group.py)."""

    @abc.abstractmethod
    def send_request(self, request: Any) -> None: ...

    @abc.abstractmethod
    def take_reply(self, request: Any) -> Any:
        """The reply to `request`, or None when it has not come yet."""

    @abc.abstractmethod
    def fileno(self) -> int:
        """What select() waits on for the replies."""


class GroupStarting(abc.ABC):
    """Moves of several drives of this bus that begin in one instant (the X-MIND K: one
    broadcast string).

    Implement it when the protocol can start several drives with one frame; the trajectory
    follower then starts a segment's joints of this bus together."""

    @abc.abstractmethod
    def group_start(self, drives: Sequence[Drive]) -> Callable[[list], Operation[Any]] | None:
        """How to start moves of `drives` (two or more of this bus) together, or None when it
        cannot now (a check has not passed). The caller runs `starter(moves)` in ONE job of the
        bus owner (Command.move under one of the drives, `also` the others: owner/), moves
        being (drive, target_steps, Motion) as move_to takes them, one per drive of `drives`.
        Step-wise; it refuses as move_to does (DriveError, nothing sent) and returns an object
        with `started` (the names of the drives whose move went out), `skipped` (name -> why
        that drive's move did not go out) and `sent_t` (time.monotonic() when the string that
        started the last drive was on the wire, None when none was). Where it cannot start them
        together it starts each drive on its own, one after the other, in the same job."""

    @abc.abstractmethod
    def group_start_check(self) -> Callable[[], Operation[str]] | None:
        """What the bus must check on the link before group_start may start drives together
        (X-MIND K: the line probe for drives of no node), as the fn of a MAINTENANCE job of the
        bus owner, which the node queues once a drive of the bus connected; it returns a line
        for the log. None: nothing to check now (the check has run since the link was opened,
        or is under way)."""


class Chaining(abc.ABC):
    """Runs stored in the drives ahead and executed back to back, each at a constant step rate
    with no ramp, without the bus between them (the X-MIND K: its RAM cells chained by their
    next-cell field). A drive that takes no new target while it runs can then pass a
    trajectory's points at speed.

    Implement it when the drives of this bus can store several runs that follow each other
    without a stop; the trajectory follower then follows a trajectory of this bus's joints as
    one chain per joint where the chain keeps to the path bound (motion/chain.py)."""

    chain_runs: int = 0                    # how many runs one start chains
    chain_speed_max_steps_s: float = 0.0   # the fastest chained run (above, runs ramp and stop)

    @abc.abstractmethod
    def chains_start_together(self, drives: Sequence[Drive]) -> bool:
        """chain_start would start the chains of `drives` in one instant now (else one drive
        after the other, each once its own chain is stored)."""

    @abc.abstractmethod
    def chain_start(self, drives: Sequence[Drive]) -> Callable[[list], Operation[Any]]:
        """How to store and start chains on `drives` (one or more of this bus). The caller runs
        `starter(moves)` in ONE job of the bus owner (Command.move under one of the drives,
        `also` the others), moves being (drive, knots), knots ((instant, position_steps), ...):
        the drive is at each position at that instant (time.monotonic()), moving at a constant
        rate from the one before (from where it stands now to the first), at most chain_runs
        of them. Step-wise; it refuses as move_to does (DriveError, nothing sent) and returns
        what GroupStarting.group_start's starter returns (`started`, `skipped`, `sent_t`). A
        drive whose chain is not confirmed whole is not started."""
