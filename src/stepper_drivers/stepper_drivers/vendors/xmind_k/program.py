"""What an X-MIND K runs for the node, and where it is meanwhile: the drive answers nothing
while it executes a program (§3), so its position is estimated from the commanded profile
(`Estimate`) and `DriveProgram` records the program it runs. Used by the drive classes and the
group start; no I/O.
"""

from __future__ import annotations

import dataclasses
import math

from ...contract.drive import Motion
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
