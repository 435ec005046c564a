"""What an X-MIND K runs for the node, and where it is meanwhile: the drive answers nothing
while it executes a program (§3), so its position is estimated from the commanded profile
(`Estimate`) and `DriveProgram` records the program it runs. Used by the drive classes and the
group start; no I/O.
"""

from __future__ import annotations

import dataclasses
import math

from ...contract.drive import DriveError, Motion
from ...protocol import xmind_k as xk


@dataclasses.dataclass
class Estimate:
    """Position over time of the motion a drive was told to make (the drive cannot be asked).

    Pieces (t0_s, x0_steps, v0_hz, a_hz_s, t1_s) with constant acceleration; the last may
    be open-ended (t1_s = inf, a free run). Same ramp model as §6.2: linear, 24 kHz in T."""

    pieces: list[tuple[float, float, float, float, float]]

    @classmethod
    def at_rest(cls, t: float, x: float) -> 'Estimate':
        return cls([(t, x, 0.0, 0.0, math.inf)])

    @classmethod
    def index(cls, t: float, x: float, distance: float, f_hz: float, a_hz_s: float
              ) -> 'Estimate':
        s = math.copysign(1.0, distance)
        d = abs(distance)
        if d == 0:
            return cls.at_rest(t, x)
        if math.isinf(a_hz_s):
            t1 = t + d / f_hz
            return cls([(t, x, s * f_hz, 0.0, t1), (t1, x + s * d, 0.0, 0.0, math.inf)])
        fp = min(f_hz, math.sqrt(a_hz_s * d))          # triangle when short (§6.2 model)
        t_ramp = fp / a_hz_s
        cruise = (d - fp * fp / a_hz_s) / fp
        t1, t2 = t + t_ramp, t + t_ramp + cruise
        t3 = t2 + t_ramp
        x1 = x + s * fp * t_ramp / 2
        x2 = x1 + s * fp * cruise
        return cls([(t, x, 0.0, s * a_hz_s, t1), (t1, x1, s * fp, 0.0, t2),
                    (t2, x2, s * fp, -s * a_hz_s, t3), (t3, x + s * d, 0.0, 0.0, math.inf)])

    @classmethod
    def chain(cls, t: float, x: float, runs: 'list[ChainRun]') -> 'Estimate':
        """Runs without ramps one after the other (a wait: 0 steps), then at rest."""
        pieces = []
        for run in runs:
            v = run.steps / run.duration_s if run.steps else 0.0
            pieces.append((t, x, v, 0.0, t + run.duration_s))
            t, x = t + run.duration_s, x + run.steps
        pieces.append((t, x, 0.0, 0.0, math.inf))
        return cls(pieces)

    @classmethod
    def run(cls, t: float, x: float, v_hz: float, a_hz_s: float) -> 'Estimate':
        if math.isinf(a_hz_s):
            return cls([(t, x, v_hz, 0.0, math.inf)])
        t1 = t + abs(v_hz) / a_hz_s
        x1 = x + v_hz * (t1 - t) / 2
        return cls([(t, x, 0.0, math.copysign(a_hz_s, v_hz), t1), (t1, x1, v_hz, 0.0, math.inf)])

    def state(self, t: float) -> tuple[float, float]:
        for t0, x0, v0, a, t1 in self.pieces:
            if t < t1 or math.isinf(t1):
                tau = max(t - t0, 0.0)
                return x0 + v0 * tau + 0.5 * a * tau * tau, v0 + a * tau
        t0, x0, v0, a, t1 = self.pieces[-1]
        return x0, 0.0

    @property
    def end_s(self) -> float:
        """When the motion is at rest (inf for a free run that was not stopped)."""
        last = self.pieces[-1]
        return last[0] if last[2] == 0.0 and last[3] == 0.0 else math.inf

    def stop(self, t: float, a_hz_s: float) -> None:
        """Decelerate from now with a (inf: at once), unless already ending sooner."""
        x, v = self.state(t)
        if v == 0.0:
            self.pieces = [(t, x, 0.0, 0.0, math.inf)]
            return
        if math.isinf(a_hz_s):
            self.pieces = [(t, x, 0.0, 0.0, math.inf)]
            return
        t_stop = t + abs(v) / a_hz_s
        if t_stop >= self.end_s:
            return
        x_stop = x + v * (t_stop - t) / 2
        self.pieces = [(t, x, v, -math.copysign(a_hz_s, v), t_stop),
                       (t_stop, x_stop, 0.0, 0.0, math.inf)]


@dataclasses.dataclass(frozen=True)
class ChainRun:
    """One run of a chain: `steps` (signed) at `frequency_hz` of Table 4 without a ramp
    (§4.1.6), or a wait (steps 0, frequency 0: §4.1.12, whole ms); `duration_s` it takes."""

    steps: int
    frequency_hz: int
    duration_s: float

    def instruction(self, next_cell: int) -> xk.Instruction:
        if not self.steps:
            return xk.Instruction.make(65, next_cell, delay_ms=round(self.duration_s * 1000))
        return xk.Instruction.make(21, next_cell, frequency_hz=self.frequency_hz,
                                   steps=self.steps, multiplier='x1')


def _grid_near(hz: float, most_hz: int) -> int:
    """The Table 4 frequency nearest to `hz` within 1..most_hz (itself on the table)."""
    hz = min(max(hz, 1.0), most_hz)
    lower = xk.table4_floor(int(hz))
    i = xk.TABLE4_HZ.index(lower)
    upper = xk.TABLE4_HZ[i + 1] if i + 1 < len(xk.TABLE4_HZ) else lower
    if upper > most_hz:
        upper = lower
    return upper if upper - hz < hz - lower else lower


def chain_runs(start_steps: int, start_t: float, knots, most_hz: int) -> list[ChainRun]:
    """The runs that take a drive from `start_steps` at `start_t` through `knots` ((instant,
    position_steps), ...; the last is where it stops), each on the Table 4 grid (§4.1.6 Note)
    within 1..most_hz. A run's time is kept and its steps follow from its frequency: the
    position it misses by a step or so is carried into the next run, which the last run
    ends exactly on the last knot (at the grid frequency nearest to its rate: it may end a
    little early or late). A run whose instant has passed already is left out (the next one
    starts from here), and so is a wait shorter than a ms. DriveError when a run needs more
    steps than one instruction holds (±8388607, §4.1.6) or a wait longer than §4.1.12
    allows."""
    runs: list[ChainRun] = []
    x, t = start_steps, start_t
    knots = list(knots)
    for n, (t1, x1) in enumerate(knots):
        last = n == len(knots) - 1
        span = t1 - t
        if span <= 0 and not last:
            continue
        want = int(round(x1)) - x
        if not last:
            if want == 0:
                ms = round(span * 1000)
                if ms > 65535:
                    raise DriveError(f'a wait of {span:.3f} s: more than §4.1.12 allows '
                                     '(65535 ms)')
                if ms:
                    runs.append(ChainRun(0, 0, ms / 1000.0))
                    t += runs[-1].duration_s
                continue
            f = _grid_near(abs(want) / span, most_hz)
            steps = int(math.copysign(max(1, round(f * span)), want))
        else:
            if want == 0:
                break
            f = _grid_near(abs(want) / max(span, 1e-3), most_hz)
            steps = want
        if abs(steps) > xk.STEPS_MAX:
            raise DriveError(f'a run of {steps} steps: more than one instruction holds '
                             f'(±{xk.STEPS_MAX}, §4.1.6)')
        runs.append(ChainRun(steps, f, abs(steps) / f))
        x, t = x + steps, t + runs[-1].duration_s
    return runs


@dataclasses.dataclass
class DriveProgram:
    """The program the drive runs for us (it is silent until it ends)."""

    kind: str                      # 'move', 'velocity', 'homing', 'program' (raw PS)
    instruction: xk.Instruction | None
    estimate: Estimate
    accel_hz_s: float              # of the ramp (inf: unramped), for the stop estimate
    next_poll_s: float             # do not ask before (the drive is silent while busy)
    target_steps: int | None = None         # move: end of this index; homing: the offset
    final_target_steps: int | None = None   # a move longer than one index (+-8388607) continues
    motion: Motion | None = None
    stopping: bool = False
    pinged_s: float = 0.0

    @property
    def goal(self) -> int | None:
        return self.final_target_steps if self.final_target_steps is not None \
            else self.target_steps
