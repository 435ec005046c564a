"""X-MIND K chained runs: each drive of a trajectory stores its runs in the RAM cells 228-230,
chained by their next cell (§4.1), and runs them back to back after one start (`start_chained`,
a job for the bus owner); `XmindKChainBus` is the line as the node drives it, with the group
start of group.py and the chains (capabilities.Chaining). No ROS.

The plan of the chains is motion/chain.py's; docs/xmind_k.md, "Chained runs", has the strings
and the checks.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Any, Callable, Mapping

from ...contract import drive
from ...contract.capabilities import Chaining
from ...contract.drive import DriveError, LinkError
from ...protocol import xmind_k as xk
from .drive import MOVE_CELL, XmindKDrive
from .group import (
    GroupStart,
    XmindKGroupBus,
    _begin,
    _broadcast,
    _command,
    _hold,
    _live,
    _ready,
    _skew_s,
    _start_each,
    _why_not,
    line_refusal,
)
from .link import RAMPED_MIN_HZ
from .program import ChainRun, DriveProgram, Estimate, chain_runs

logger = logging.getLogger(__name__)

# A chain's runs: the RAM cells (§4.1, 228-230), each one's next cell DDD the one after it
CHAIN_CELLS = (MOVE_CELL, MOVE_CELL + 1, MOVE_CELL + 2)
# The fastest chained run: the highest Table 4 frequency below RAMPED_MIN_HZ, where moves of the
# node start and stop without ramps (§4.1.6); a faster run ramps and stops at its end
CHAIN_MAX_HZ = xk.table4_floor(RAMPED_MIN_HZ - 1)
Y_ANSWER_CHARS = 4                             # 'AAY' and its end character (§4.4.1)
# a run as WN carries it, for the time of a WN not yet built (its length is what counts)
TYPICAL_RUN = xk.Instruction.make(21, frequency_hz=1000, steps=100000, multiplier='x1')


@dataclasses.dataclass(frozen=True)
class ChainMove:
    """One drive's part of a chained start: from where it stands through `knots` ((instant,
    position_steps), ..., time.monotonic(); at most len(CHAIN_CELLS)), each run at a constant
    rate. `stops`: as GroupMove's."""

    drive: 'XmindKDrive'
    knots: tuple[tuple[float, float], ...]
    stops: int | None = None


@dataclasses.dataclass(frozen=True)
class _ChainPlan:
    """One drive's chain in a chained start: its runs, stored in CHAIN_CELLS from MOVE_CELL on
    (each WN confirmed by Y), the first run's cell last."""

    drive: XmindKDrive
    runs: tuple[ChainRun, ...]
    cells: dict[int, xk.Instruction]
    start: int

    @property
    def instr(self) -> xk.Instruction:
        return self.cells[MOVE_CELL]

    def confirmed(self) -> bool:
        """The drive confirmed every cell of this chain and holds them still: a PS of 228 runs
        on into 229 and 230 (DDD), so one cell of unknown content is a run nobody planned."""
        return all(self.drive.cells.get(c) == i for c, i in self.cells.items())

    def job(self, t: float) -> DriveProgram:
        estimate = Estimate.chain(t, self.start, list(self.runs))
        return DriveProgram('move', self.instr, estimate, math.inf, estimate.end_s,
                            target_steps=self.start + sum(r.steps for r in self.runs))


def _string_s(d: XmindKDrive, frame: xk.Frame) -> float:
    """What one string to `d` and its Y take on the line (§3): its characters, the
    turnaround, the drive's answer delay RD, the answer and the margin after it."""
    chars = len(xk.encode_request(frame)) + Y_ANSWER_CHARS
    return chars * d.bus.char_s + xk.turnaround_s(frame.code) + d.answer_delay_s + xk.MARGIN_S


def _until_run_s(order: list[XmindKDrive], i: int, broadcast: bool) -> float:
    """From now, before drive order[i]'s WN 228, until its first run begins. By broadcast:
    its WN and the later drives' (a run of typical length), then the broadcast PS. Else its
    WN, then its own PS. Each up to the execution: the turnaround and the drive's RD, which
    delays the execution too (§4.2.2.5)."""
    d = order[i]
    wn = sum(_string_s(o, xk.Frame(o.number, 'WN', (MOVE_CELL, TYPICAL_RUN)))
             for o in (order[i:] if broadcast else [d]))
    ps = xk.Frame(xk.BROADCAST if broadcast else d.number, 'PS', (MOVE_CELL,))
    return wn + len(xk.encode_request(ps)) * d.bus.char_s + xk.turnaround_s('PS') + \
        d.answer_delay_s


def _store_later_runs(m: ChainMove, epochs: Mapping[str, int], possible: bool,
                      stored: dict[str, xk.Instruction], skipped: dict[str, str]
                      ) -> drive.Operation[tuple | None]:
    """Step 2 for one drive: FA and the power-cycle flag on the wire (as every start), its
    runs (chain_runs) from now, and WN of the runs after the first into 229 and 230, the
    last first. Returns (start, (when, where) the first run ends, runs); None where the drive
    stays put (then the null instruction into 228 where a broadcast is possible) or is not
    started (`skipped` says why)."""
    d = m.drive
    try:
        if not (yield from _ready(d, epochs, skipped)):
            return None
        start = d.position_steps
        if all(round(x) == start for _, x in m.knots):
            _hold(d, possible, stored)
            return None
        now = time.monotonic()
        runs = chain_runs(start, now, m.knots, CHAIN_MAX_HZ)
        for k in range(len(runs) - 1, 0, -1):
            d._store(CHAIN_CELLS[k], runs[k].instruction(
                CHAIN_CELLS[k + 1] if k + 1 < len(runs) else xk.END_OF_PROGRAM))
            yield 0.0
            if not _live(d, epochs):
                skipped[d.name] = 'a stop or a newer command came first'
                return None
    except (DriveError, LinkError) as e:                 # this drive only
        skipped[d.name] = str(e)
        return None
    # the first run ends at its knot's instant (within the grid): the later runs follow
    return start, (now + runs[0].duration_s, start + runs[0].steps), runs


def _store_first_run(d: XmindKDrive, stored_later: tuple, begins: float,
                     epochs: Mapping[str, int], stored: dict[str, xk.Instruction],
                     skipped: dict[str, str]) -> _ChainPlan | None:
    """Step 3 for one drive: its first run again, for a start at `begins`, to end where and
    when it was planned to; WN 228 (its next cell 229 where more runs follow). The drive's
    _ChainPlan, or None where it is not started (`skipped` says why)."""
    start, (t1, x1), runs = stored_later
    if not _live(d, epochs):
        skipped[d.name] = 'a stop or a newer command came first'
        return None
    try:
        first = chain_runs(start, begins, [(t1, x1)], CHAIN_MAX_HZ)
        if not first:                                    # it waits first
            first = [ChainRun(0, 0, max(0, round((t1 - begins) * 1000)) / 1000.0)]
        chain = first + runs[1:]
        cells = {c: r.instruction(CHAIN_CELLS[k + 1] if k + 1 < len(chain)
                                  else xk.END_OF_PROGRAM)
                 for k, (c, r) in enumerate(zip(CHAIN_CELLS, chain))}
        if not first[0].steps and not first[0].duration_s:
            cells[MOVE_CELL] = xk.Instruction.make(
                0, CHAIN_CELLS[1] if len(chain) > 1 else xk.END_OF_PROGRAM)
        d._store(MOVE_CELL, cells[MOVE_CELL])
    except (DriveError, LinkError) as e:
        skipped[d.name] = str(e)
        return None
    stored[d.name] = cells[MOVE_CELL]
    return _ChainPlan(d, tuple(chain), cells, start)


def _refuse_chains(moves: list[ChainMove], skipped: dict[str, str]) -> dict[str, int]:
    """Step 1, no wire: DriveError where move_to would refuse (a last knot outside the
    counter, a drive not enabled or in fault) or a chain does not fit the cells; a drive that
    runs a program goes to `skipped` (it answers nothing, §3). Name -> the last knot."""
    targets = {}
    for m in moves:
        if not 1 <= len(m.knots) <= len(CHAIN_CELLS):
            raise DriveError(f'a chain of {len(m.knots)} runs: the RAM cells '
                             f'{CHAIN_CELLS[0]}-{CHAIN_CELLS[-1]} hold 1..{len(CHAIN_CELLS)}')
        targets[m.drive.name] = m.drive._check_target(m.knots[-1][1])
        m.drive._require_enabled('move')
    for m in moves:
        job = m.drive.job
        if job is not None or m.drive.pending is not None:
            skipped[m.drive.name] = (f'drive {m.drive.address} is busy ('
                                     f'{job.kind if job else "a command waits"}): a chain '
                                     'starts only from rest (§3)')
    return targets


def start_chained(moves: Any) -> drive.Operation[GroupStart]:
    """Step-wise, for the bus owner (one job): store each ChainMove's runs in its drive's RAM
    cells 228, 229, 230 chained by their next cell (§4.1: "the syntax of all the instructions
    includes the address of the next instruction in the sequence") and start them: one
    PS,228 runs the whole chain, each run the instant the one before ended (runs without
    ramps, §4.1.6; a wait, §4.1.12).

    1. Refusals as move_to's, no wire (_refuse_chains); a drive that runs a program takes no
       part: a chain starts only from rest.
    2. Per drive: FA and the power-cycle flag on the wire, and the runs after the first into
       229 and 230 (_store_later_runs).
    3. Per drive: the first run for when the drive will start, from the strings still to go
       (_until_run_s), into 228 (_store_first_run).
    4. A drive is started only where every cell of its chain is confirmed (_ChainPlan
       .confirmed: a WN without its Y leaves a cell unknown, and PS runs on into it).

    Where start_together would broadcast (broadcast_refusal, and every chain confirmed),
    steps 2 and 3 go drive after drive, then one 99PS,228 starts every drive in one instant.
    Otherwise each drive is stored and started (PS,228) before the next, in the order of
    `moves` (the follower puts the joint first that the plan moves most before the start):
    a drive need not wait for the others' strings."""
    moves = list(moves)
    if not moves:
        return GroupStart(False, 'no moves', (), {}, None)
    bus, _, skipped, moves = _begin(moves)
    targets = _refuse_chains(moves, skipped)             # 1.
    group = [m for m in moves if m.drive.name not in skipped]
    epochs = _command(group, targets)
    names = [m.drive.name for m in group]
    possible = len(group) >= 2 and not line_refusal(bus, names)
    stored: dict[str, xk.Instruction] = {}
    if not possible:                                     # 2-4 drive after drive
        sent_t, started = None, []
        for i, m in enumerate(group):
            if i:
                yield 0.0
            later = yield from _store_later_runs(m, epochs, False, stored, skipped)
            if later is None:
                continue
            yield 0.0
            plan = _store_first_run(m.drive, later, time.monotonic() + _until_run_s(
                [m.drive], 0, False), epochs, stored, skipped)
            if plan is None:
                continue
            yield 0.0
            sent, names_started = yield from _start_each({m.drive.name: plan}, epochs,
                                                         skipped)
            sent_t = sent if sent is not None else sent_t
            started += names_started
        return GroupStart(False, line_refusal(bus, names) or 'fewer than two drives move',
                          tuple(started), skipped, sent_t)
    laters = {}
    for i, m in enumerate(group):                        # 2.
        if i:
            yield 0.0
        later = yield from _store_later_runs(m, epochs, True, stored, skipped)
        if later is not None:
            laters[m.drive.name] = later
    order = [m.drive for m in group if m.drive.name in laters]
    plans: dict[str, _ChainPlan] = {}
    for i, d in enumerate(order):                        # 3.
        yield 0.0
        plan = _store_first_run(d, laters[d.name], time.monotonic() + _until_run_s(
            order, i, True), epochs, stored, skipped)
        if plan is not None:
            plans[d.name] = plan
    yield 0.0
    why_not = _why_not(bus, names, stored, plans, epochs, possible, skipped)
    if not why_not and not all(p.confirmed() for p in plans.values()):
        why_not = 'a chain is not confirmed in every cell'
    if not why_not:                                      # 4. the broadcast, same step
        sent_t, started = _broadcast(bus, plans)
    else:
        logger.debug('%s: per-drive starts: %s', bus.url, why_not)
        sent_t, started = yield from _start_each(plans, epochs, skipped)
    return GroupStart(not why_not, why_not, tuple(started), skipped, sent_t, _skew_s(plans))


class XmindKChainBus(XmindKGroupBus, Chaining):
    """The line as the node drives it: XmindKGroupBus (group start, line probe) and chained runs
    (Chaining.chain_start: start_chained, by broadcast where start_together would broadcast,
    else drive after drive)."""

    chain_runs = len(CHAIN_CELLS)
    chain_speed_max_steps_s = float(CHAIN_MAX_HZ)

    def chain_start(self, drives: Any) -> Callable[[Any], drive.Operation[GroupStart]]:
        drives = list(drives)
        if any(not isinstance(d, XmindKDrive) or d.bus is not self for d in drives):
            raise DriveError('chain_start: X-MIND K drives of this line only')
        stops = {d.name: d.stops for d in drives}     # noted before the job queues

        def starter(moves: Any) -> drive.Operation[GroupStart]:
            return start_chained([ChainMove(d, tuple(knots), stops=stops[d.name])
                                  for d, knots in moves])
        return starter

    def chains_start_together(self, drives: Any) -> bool:
        names = [d.name for d in drives]
        return len(names) >= 2 and not line_refusal(self, names)
