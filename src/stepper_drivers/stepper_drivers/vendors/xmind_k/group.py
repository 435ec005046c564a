"""X-MIND K group start: the drives of one line start a trajectory segment together, by one
broadcast 99PS where that can be made safe, else one PS per drive (`start_together`, a job for
the bus owner); `probe_line` looks for drives the node does not have; `XmindKGroupBus` is the
line with both (capabilities.GroupStarting). No ROS.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any, Callable, Mapping

from ...contract import drive
from ...contract.capabilities import GroupStarting
from ...contract.drive import DriveError, LinkError, Motion
from ...protocol import xmind_k as xk
from ...protocol.xmind_k_bus import GarbledAnswer, XmindKBus
from .drive import MOVE_CELL, XmindKDrive
from .program import DriveProgram, Estimate

logger = logging.getLogger(__name__)

# The joints of one trajectory on one line start a segment in the same instant: each drive's run
# is stored in its cell MOVE_CELL (WN, each confirmed by Y), then one broadcast stored
# instruction execution 99PS,228 starts them all (§4.2.5 "Broadcast transmission is allowed",
# §2.2.1 "recognized and executed by all X-MIND K series drives connected to serial line",
# no answer: §4.4.3). The broadcast reaches every X-MIND K on the line, driven by this node or
# not, and runs whatever its cell 228 holds: the manual says nothing of an empty cell, of a drive
# with its current off (CN) or blocked by a protection, and cells 228-230 are RAM of unknown
# content after power-on (§4.1). So it is sent only when every drive that can hear it is known
# to hold exactly what this start stored (`broadcast_refusal`); otherwise each drive gets its
# own PS, one after the other, as a single move does.
NULL_INSTRUCTION = xk.Instruction.make(0)      # §4.1.13 null: a drive that stays where it is
PROBE_ADDRESSES = range(xk.ADDRESS_MIN, xk.ADDRESS_MAX + 1)


@dataclasses.dataclass(frozen=True)
class GroupMove:
    """One drive's part of a group start: where to and with which profile (as move_to).
    `stops`: the drive's `stops` when the caller decided on this move (before it queued the
    job): a stop or disable of the drive since leaves it out. The job is queued under one drive
    of the line, so another drive's stop does not drop it as it drops that drive's own jobs."""

    drive: 'XmindKDrive'
    target_steps: int
    motion: Motion
    stops: int | None = None


@dataclasses.dataclass
class GroupStart:
    """What start_together did. `broadcast`: one 99PS started every drive of `started`;
    otherwise `why_not` says what the node could not make sure of, and each got its own PS.
    `skipped`: drive name -> why it was not started (a stop or a newer command between the
    steps, not enabled, in fault, a WN without its Y); `sent_t`: when the string that started
    the (last) drive was on the wire (time.monotonic()); `skew_s`: how far apart the started
    drives begin by their answer delays RD (§4.2.2.5: RD delays the execution too)."""

    broadcast: bool
    why_not: str
    started: tuple[str, ...]
    skipped: dict[str, str]
    sent_t: float | None
    skew_s: float = 0.0


def probe_line(bus: XmindKBus, rd_ms: float = xk.RD_MAX_MS, slack_s: float | None = None,
               addresses: Any = None) -> drive.Operation[frozenset[int]]:
    """Step-wise: ask every address 00..47 that no drive of this node has (QS,AD, §4.3.2, one
    string each, nothing that moves or writes) and return those that answered. A drive's
    answer delay RD is unknown (§4.2.2.5, up to 255 ms): each waits for that by default. Only a
    probe of all of 00..47 counts for broadcasts (bus.line_probe); any answer, full probe or
    not, blocks them until the bus is opened again (bus.foreign). A busy or switched-off drive
    is silent (§4.4.3): the probe cannot prove the line empty, which is why broadcasts also
    need the user's broadcast_start."""
    ours = set(bus.addresses.values())
    full = addresses is None
    todo = [a for a in (PROBE_ADDRESSES if full else addresses) if a not in ours]
    heard = set()
    for i, address in enumerate(todo):
        if i:
            yield 0.0
        try:
            answer = bus.request(xk.Frame(address, 'QS', ('AD',)), rd_ms, tries=1,
                                 retry_silence=False, slack_s=slack_s)
        except GarbledAnswer:
            answer = True                      # something answered at that address
        if answer is not None:
            heard.add(address)
            bus.foreign.add(address)
            logger.warning('%s: address %02d answered, no drive of this node has it: no '
                           'broadcast starts on this line', bus.url, address)
    if full:
        bus.line_probe = frozenset(heard)
    return frozenset(heard)


def line_refusal(bus: XmindKBus, names: Any) -> str:
    """What stops a broadcast on `bus` for a start of the drives `names`, from what is known
    without the wire ('' = nothing): the user's word, the probe, and that every drive this node
    has on the line takes part (a drive of the node left out would run its cell 228 again: its
    last move, relative, §5.1)."""
    if not bus.broadcast_start:
        return ('broadcast_start is false (the line may carry X-MIND K drives this node does not '
                'drive, and a broadcast starts them all, §2.2.1)')
    if bus.foreign:
        return (f'address(es) {", ".join(f"{a:02d}" for a in sorted(bus.foreign))} answered '
                'on this line and no drive of this node has them')
    if bus.line_probe is None:
        return 'the line has not been probed for other drives since it was opened (probe_line)'
    left_out = sorted(set(bus.addresses) - set(names))
    if left_out:
        return (f'drive(s) {", ".join(left_out)} of this line take no part in the start: a '
                'broadcast would run their cell 228 too')
    return ''


def broadcast_refusal(bus: XmindKBus, stored: Mapping[str, xk.Instruction],
                      epochs: Mapping[str, int]) -> str:
    """Checked in the step that sends the broadcast (nothing else reaches the line between):
    line_refusal, and every drive of the line is one of `stored` (name -> the instruction it
    confirmed in MOVE_CELL during this start), connected to this node, idle, enabled, not in
    fault, nothing commanded to it since the start began (`epochs`), and its cell still the
    one confirmed. '' when the broadcast can go."""
    why = line_refusal(bus, stored)
    if why:
        return why
    for name in bus.addresses:
        d = bus.drives.get(name)
        if d is None:
            return f'drive {name} never connected: what it holds is unknown'
        if d.epoch != epochs.get(name) or d.job is not None or d.pending is not None:
            return f'drive {name}: a stop or another command came during the start'
        if not d.enabled or d.fault:
            return f'drive {name} is not enabled or in fault'
        if d.cells.get(MOVE_CELL) != stored[name]:
            return f'drive {name}: cell {MOVE_CELL} is not confirmed to hold this start'
    return ''


def start_together(moves: Any) -> drive.Operation[GroupStart]:
    """Step-wise, for the bus owner (one job): start the GroupMoves, all drives of one line, in
    the same instant where that can be made safe, else one after the other.

    1. As move_to would refuse (no wire): a target outside the counter, a profile outside the
       tables, a drive not enabled or in fault. A drive whose index run ends within
       QUEUE_BEHIND_S is waited for; one still busy then goes the way of move_to (stop, restart)
       and takes no part.
    2. Per drive: FA and the power-cycle flag on the wire (as every start), then WN 228 with its
       run, or the null instruction where it stays put (only when a broadcast is possible: a
       drive left with its last run in 228 would run it again).
    3. One step: broadcast_refusal; '' -> the jobs are recorded, then 99PS,228 (no answer, so
       it is taken as heard: a lost broadcast shows as a drive that did not move). Else PS,228
       to each drive whose run is confirmed, as a single move starts (a lost Y is taken as
       started). A drive that a stop or another command reached between the steps is not
       started; nor one whose WN got no Y (its cell is unknown)."""
    moves = list(moves)
    if not moves:
        return GroupStart(False, 'no moves', (), {}, None)
    bus, stops, skipped, moves = _begin(moves)
    targets = _refuse_as_move_to(moves)                  # 1. refusals, no wire
    yield from _await_index_ends(moves)
    moves = _leave_out_stopped(moves, stops, skipped)    # a stop during the waits
    group = [m for m in moves if m.drive.job is None and m.drive.pending is None]
    late = [m for m in moves if m not in group]
    epochs = _command(group, targets)
    names = [m.drive.name for m in group]
    # a broadcast is worth it for two drives that move or more; else no null runs are written
    movers = [m for m in group if targets[m.drive.name] != m.drive.position_steps]
    possible = len(movers) >= 2 and not line_refusal(bus, names)
    stored, plans = yield from _store_runs(group, targets, epochs, possible, skipped)   # 2.
    yield 0.0
    why_not = _why_not(bus, names, stored, plans, epochs, possible, skipped)
    skew_s = _skew_s(plans)
    if not why_not:                                      # 3. the broadcast, same step
        sent_t, started = _broadcast(bus, plans)
    else:
        logger.debug('%s: per-drive starts: %s', bus.url, why_not)
        sent_t, started = yield from _start_each(plans, epochs, skipped)
    yield from _move_late(late)
    return GroupStart(not why_not, why_not, tuple(started), skipped, sent_t, skew_s)


# ---------------------------------------------------- the steps of start_together, in order
def _begin(moves: list[Any]) -> tuple[XmindKBus, dict[str, int], dict[str, str], list[Any]]:
    """(the line, each drive's stops when the start was decided, `skipped`, the moves of the
    drives not stopped since) of a start's moves (GroupMove or ChainMove)."""
    bus = _line_of(moves)
    skipped: dict[str, str] = {}
    stops = {m.drive.name: m.drive.stops if m.stops is None else m.stops for m in moves}
    return bus, stops, skipped, _leave_out_stopped(moves, stops, skipped)


def _line_of(moves: list[GroupMove]) -> XmindKBus:
    """The one line of `moves`, or DriveError: one move per drive, all drives on one line."""
    bus = moves[0].drive.bus
    if any(m.drive.bus is not bus for m in moves) or \
            len({m.drive.name for m in moves}) != len(moves):
        raise DriveError('start_together: one move per drive, all drives on one line')
    return bus


def _leave_out_stopped(moves: list[GroupMove], stops: Mapping[str, int],
                       skipped: dict[str, str]) -> list[GroupMove]:
    """The moves of the drives not stopped or disabled since the start was decided (`stops`:
    name -> the drive's stops then); the others go to `skipped`."""
    for m in moves:
        if m.drive.stops != stops[m.drive.name]:
            skipped[m.drive.name] = 'stopped or disabled after this start was decided'
    return [m for m in moves if m.drive.name not in skipped]


def _refuse_as_move_to(moves: list[GroupMove]) -> dict[str, int]:
    """Step 1: what move_to would refuse, without the wire (DriveError); name -> target."""
    targets = {}
    for m in moves:
        d = m.drive
        targets[d.name] = d._check_target(m.target_steps)
        d.run_instruction('move', m.motion.velocity_steps_s, m.motion, 1)
        d._require_enabled('move')
    return targets


def _await_index_ends(moves: list[GroupMove]) -> drive.Operation[None]:
    """Step 1: until the index runs that end within QUEUE_BEHIND_S have ended."""
    for m in moves:
        ready = m.drive.until_ready_for_move()
        if ready is not None:
            yield from ready


def _command(group: list[GroupMove], targets: Mapping[str, int]) -> dict[str, int]:
    """A motion command to each drive of `group`, as move_to counts one (epoch, last_target);
    name -> its epoch, which nothing else may change until its start (`_live`)."""
    epochs = {}
    for m in group:
        d = m.drive
        d.epoch += 1                                     # a motion command, as move_to
        d.last_target = targets[d.name]
        epochs[d.name] = d.epoch
    return epochs


def _live(d: XmindKDrive, epochs: Mapping[str, int]) -> bool:
    """No stop or other command reached `d` since the start began, and it runs no program."""
    return d.epoch == epochs[d.name] and d.job is None


@dataclasses.dataclass(frozen=True)
class _Plan:
    """One drive's index run in a group start, stored in its MOVE_CELL (WN confirmed by Y)."""

    drive: XmindKDrive
    instr: xk.Instruction
    start: int
    chunk: int
    f: float
    a: float
    target: int
    motion: Motion

    def confirmed(self) -> bool:
        """The drive confirmed this run in MOVE_CELL and holds it still."""
        return self.drive.cells.get(MOVE_CELL) == self.instr

    def job(self, t: float) -> DriveProgram:
        """The DriveProgram of this run started at `t` (what XmindKDrive._start_move records)."""
        estimate = Estimate.index(t, self.start, self.chunk, self.f, self.a)
        return DriveProgram('move', self.instr, estimate, self.a, estimate.end_s,
                            target_steps=self.start + self.chunk,
                            final_target_steps=self.target
                            if self.start + self.chunk != self.target else None,
                            motion=self.motion)


def _store_runs(group: list[GroupMove], targets: Mapping[str, int],
                epochs: Mapping[str, int], possible: bool, skipped: dict[str, str]
                ) -> drive.Operation[tuple[dict[str, xk.Instruction], dict[str, _Plan]]]:
    """Step 2, drive after drive (`_store_run`): name -> what each drive confirmed in
    MOVE_CELL during this start, and name -> the run of each drive that moves."""
    stored: dict[str, xk.Instruction] = {}
    plans: dict[str, _Plan] = {}
    for i, m in enumerate(group):
        if i:
            yield 0.0
        plan = yield from _store_run(m, targets[m.drive.name], epochs, possible, stored,
                                     skipped)
        if plan is not None:
            plans[m.drive.name] = plan
    return stored, plans


def _ready(d: XmindKDrive, epochs: Mapping[str, int], skipped: dict[str, str]
           ) -> drive.Operation[bool]:
    """FA and the power-cycle flag on the wire (as every start); then whether `d` takes part
    still: False where a stop or a newer command reached it since the start began (`skipped`
    says so), DriveError where it is not enabled."""
    yield from d._read_status()
    yield 0.0
    if not _live(d, epochs):
        skipped[d.name] = 'a stop or a newer command came first'
        return False
    d._require_enabled('move')
    return True


def _hold(d: XmindKDrive, possible: bool, stored: dict[str, xk.Instruction]) -> None:
    """A drive of the start that stays where it is: the null instruction (§4.1.13) into
    MOVE_CELL where a broadcast is possible (it would run its cell 228 too), nothing
    otherwise."""
    if possible:
        d._store(MOVE_CELL, NULL_INSTRUCTION)
        stored[d.name] = NULL_INSTRUCTION


def _store_run(m: GroupMove, target: int, epochs: Mapping[str, int], possible: bool,
               stored: dict[str, xk.Instruction], skipped: dict[str, str]
               ) -> drive.Operation[_Plan | None]:
    """Step 2 for one drive: FA and the power-cycle flag on the wire (as every start), then WN
    228 with its run (its _Plan), or the null instruction where it stays put and a broadcast is
    possible (None). What it confirmed goes to `stored`; why it is not started to `skipped`."""
    d = m.drive
    try:
        if not (yield from _ready(d, epochs, skipped)):
            return None
        start = d.position_steps
        chunk = max(-xk.STEPS_MAX, min(xk.STEPS_MAX, target - start))
        if chunk == 0:
            _hold(d, possible, stored)
            return None
        instr, f, a = d.run_instruction('move', m.motion.velocity_steps_s, m.motion, chunk)
        d._store(MOVE_CELL, instr)
    except (DriveError, LinkError) as e:                 # this drive only; its poll sees a loss
        skipped[d.name] = str(e)
        return None
    stored[d.name] = instr
    return _Plan(d, instr, start, chunk, f, a, target, m.motion)


def _why_not(bus: XmindKBus, names: list[str], stored: Mapping[str, xk.Instruction],
             plans: Mapping[str, _Plan], epochs: Mapping[str, int], possible: bool,
             skipped: Mapping[str, str]) -> str:
    """Step 3, in the step of the broadcast: '' when it can go, else why not."""
    if len(plans) < 2:
        return 'fewer than two drives move' + ''.join(
            f'; {name} not started: {why}' for name, why in skipped.items())
    if not possible:
        return line_refusal(bus, names) or 'fewer than two drives move'
    return broadcast_refusal(bus, stored, epochs)


def _skew_s(plans: Mapping[str, _Plan]) -> float:
    """How far apart the drives of `plans` begin by their answer delays RD (§4.2.2.5)."""
    rd_s = [(plan.drive.rd_ms or 0) / 1000.0 for plan in plans.values()]
    return max(rd_s) - min(rd_s) if rd_s else 0.0


def _broadcast(bus: XmindKBus, plans: Mapping[str, Any]) -> tuple[float, list[str]]:
    """Step 3, same step as its check: the jobs, then 99PS,228; when it was sent, and who."""
    t = time.monotonic()
    for plan in plans.values():
        plan.drive.job = plan.job(t)                     # recorded before it leaves (§3)
    sent_t = bus.broadcast(xk.Frame(xk.BROADCAST, 'PS', (MOVE_CELL,)))
    started = []
    for name, plan in plans.items():
        d = plan.drive
        d.job = plan.job(sent_t + xk.TURNAROUND_S + (d.rd_ms or 0) / 1000.0)
        d.motion_sent_t = sent_t
        started.append(name)
    return sent_t, started


def _start_each(plans: Mapping[str, Any], epochs: Mapping[str, int], skipped: dict[str, str]
                ) -> drive.Operation[tuple[float | None, list[str]]]:
    """Step 3 without the broadcast: PS,228 to each drive whose run (or chain) is confirmed,
    one a step, as a single move starts; when the last was sent, and who."""
    sent_t = None
    started = []
    for i, (name, plan) in enumerate(plans.items()):
        d = plan.drive
        if i:
            yield 0.0
        if not _live(d, epochs) or d.fault or not d.enabled or not plan.confirmed():
            skipped[name] = 'a stop or a newer command came first, or it is not enabled'
            continue
        try:
            d._launch(MOVE_CELL, plan.job)
        except (DriveError, LinkError) as e:
            if d.job is None:                            # refused (N)
                skipped[name] = str(e)
                continue
            logger.warning('%s: %s', name, e)            # no Y: taken as started (_launch)
        sent_t = time.monotonic()
        started.append(name)
    return sent_t, started


def _move_late(late: list[GroupMove]) -> drive.Operation[None]:
    """The drives still busy past their index run's end: each as move_to (stop, restart)."""
    for m in late:
        yield 0.0
        result = m.drive.move_to(m.target_steps, m.motion)
        if drive.is_operation(result):
            yield from result


class XmindKGroupBus(XmindKBus, GroupStarting):
    """The line with this module's group start (GroupStarting.group_start: start_together,
    which decides between one broadcast and per-drive starts) and the check it needs
    (GroupStarting.group_start_check: probe_line, once per opening of the line); both only
    where broadcast_start is true. The node's bus adds chained runs (chain.py)."""

    def __init__(self, params: Mapping[str, Any]):
        super().__init__(params)
        # how long the probe waits for an answer at each address: the largest answer delay RD
        # of a drive on the line (§4.2.2.5, up to 255 ms; unknown: the largest)
        self.probe_wait_ms = float(params.get('broadcast_probe_wait_ms', xk.RD_MAX_MS))
        self.probing = False

    def group_start(self, drives: Any) -> Callable[[Any], drive.Operation[GroupStart]] | None:
        drives = list(drives)
        if not self.broadcast_start or len(drives) < 2 or any(
                not isinstance(d, XmindKDrive) or d.bus is not self for d in drives):
            return None      # not opted in: each joint its own move job, as without this
        stops = {d.name: d.stops for d in drives}     # noted before the job queues

        def starter(moves: Any) -> drive.Operation[GroupStart]:
            return start_together([GroupMove(d, target, motion, stops=stops[d.name])
                                   for d, target, motion in moves])
        return starter

    def group_start_check(self) -> Callable[[], drive.Operation[str]] | None:
        if not self.broadcast_start or self.line_probe is not None or self.probing:
            return None
        return self._probe

    def _probe(self) -> drive.Operation[str]:
        if self.line_probe is not None or self.probing:
            return 'line probe: done already or under way'
        self.probing = True
        try:
            heard = yield from probe_line(self, rd_ms=self.probe_wait_ms)
        finally:
            self.probing = False
        if heard:
            return (f'line probe: address(es) {", ".join(f"{a:02d}" for a in sorted(heard))} '
                    'answered and no drive of this node has them: no broadcast starts on this '
                    'line, each drive is started with its own PS')
        return ('line probe: no answer from the addresses no drive of this node has: the '
                'joints of a trajectory on this line start their segments by one broadcast '
                '99PS where every check of docs/xmind_k.md holds')
