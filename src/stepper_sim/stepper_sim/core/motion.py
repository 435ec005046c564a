"""Kinematics of one simulated axis, vendor-neutral, no rclpy.

`MotionModel` holds a plan of segments with constant acceleration and evaluates it exactly
(closed-form, not Euler) at the times given to `update(now_s)`, so a test can run it in simulated
time by injecting a clock. Units are the drives' own: steps, steps/s (Hz), steps/s^2 (Hz/s).

Every command re-plans from the state at the time of the last `update()` (position and velocity),
so a target changed during a move, even one behind the axis, gives a continuous profile: the axis
decelerates, reverses if it has to, and arrives at rest on the new target.

An acceleration of `math.inf` means a start-stop (jump) velocity change, as a stepper drive does
below its start-stop frequency.

Two coordinates: the raw position (the physical one, where simulated switches sit) and the
referenced position (`position_steps` = raw + offset) that a drive reports; `set_position()` only
moves the reference, and commanded targets are referenced positions.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Callable, Iterator

logger = logging.getLogger(__name__)

INF = math.inf

MODE_IDLE = 'idle'
MODE_POSITION = 'position'
MODE_VELOCITY = 'velocity'
MODE_STOP = 'stop'
MODE_QUICK_STOP = 'quick_stop'


def _sign(value: float) -> int:
    return (value > 0) - (value < 0)


def _half_inverse(acceleration: float) -> float:
    """1 / (2 a): the distance per v^2 of a ramp; 0 for a start-stop (infinite) acceleration."""
    return 0.0 if math.isinf(acceleration) else 0.5 / acceleration


def _ramp_time(dv: float, acceleration: float) -> float:
    return 0.0 if math.isinf(acceleration) else abs(dv) / acceleration


@dataclasses.dataclass(frozen=True)
class AccelSegment:
    """Constant acceleration from t0_s to t1_s (t1_s may be inf); raw position."""

    t0_s: float
    t1_s: float
    x0_steps: float
    v0_hz: float
    a_hz_s: float

    def state_at(self, t_s: float) -> tuple[float, float]:
        tau = t_s - self.t0_s
        return (self.x0_steps + self.v0_hz * tau + 0.5 * self.a_hz_s * tau * tau,
                self.v0_hz + self.a_hz_s * tau)

    def end_state(self) -> tuple[float, float]:
        return self.state_at(self.t1_s)


@dataclasses.dataclass(frozen=True)
class Piece:
    """A part of the plan in which the axis moves in one direction only (for crossing searches)."""

    t0_s: float
    t1_s: float
    x0_steps: float
    v0_hz: float
    a_hz_s: float

    @property
    def x1_steps(self) -> float:
        tau = self.t1_s - self.t0_s
        return self.x0_steps + self.v0_hz * tau + 0.5 * self.a_hz_s * tau * tau

    @property
    def direction(self) -> int:
        return _sign(self.v0_hz) or _sign(self.a_hz_s)

    def time_at(self, x_steps: float) -> float:
        """Time at which the (monotonic) piece passes x_steps, clamped into the piece."""
        dx = x_steps - self.x0_steps
        v0, a = self.v0_hz, self.a_hz_s
        if dx == 0.0:
            return self.t0_s
        if a == 0.0:
            tau = dx / v0 if v0 else 0.0
        else:
            disc = max(v0 * v0 + 2.0 * a * dx, 0.0)
            denom = v0 + self.direction * math.sqrt(disc)
            tau = 2.0 * dx / denom if denom else 0.0   # stable root of x0 + v0 t + a t^2 / 2 = x
        return min(max(self.t0_s + tau, self.t0_s), self.t1_s)


class MotionModel:
    """One axis: trapezoidal/triangular moves, velocity mode, stops; exact kinematics.

    Commands act at the time of the last `update()`; call `update(now_s)` first when time passed.
    Properties report the state at that time.
    """

    def __init__(self, position_steps: float = 0.0, *, max_velocity_hz: float = INF,
                 clock: Callable[[], float] = time.monotonic):
        self._clock = clock
        self._t = clock()
        self._x = float(position_steps)     # raw position
        self._v = 0.0
        self._offset = 0.0                  # referenced = raw + offset
        self._segments: list[AccelSegment] = []
        self._final_x: float | None = None  # exact raw end position of a move plan
        self._mode = MODE_IDLE
        self._target_raw = self._x
        self._target_velocity = 0.0
        self._plan_id = 0
        self._max_velocity = float(max_velocity_hz)

    # Time -------------------------------------------------------------------------------------
    @property
    def clock(self) -> Callable[[], float]:
        return self._clock

    @property
    def time_s(self) -> float:
        """Time of the last update()."""
        return self._t

    def now(self) -> float:
        return self._clock()

    def update(self, now_s: float | None = None) -> None:
        """Advance the state to now_s (default: the clock) along the plan, exactly."""
        now = self._clock() if now_s is None else float(now_s)
        if now < self._t:
            return      # time never goes back; a late caller sees the newer state
        while self._segments and self._segments[0].t1_s <= now:
            seg = self._segments.pop(0)
            self._x, self._v = seg.end_state()
        if self._segments:
            self._x, self._v = self._segments[0].state_at(now)
        else:
            if self._final_x is not None:
                self._x = self._final_x     # no rounding drift at the end of a move
                self._final_x = None
            self._v = 0.0                   # an empty plan is rest (cruising has an inf segment)
        self._t = now

    # State ------------------------------------------------------------------------------------
    @property
    def position_steps(self) -> float:
        """Referenced position (what the drive reports)."""
        return self._x + self._offset

    @property
    def raw_position_steps(self) -> float:
        """Physical position (where simulated switches are placed)."""
        return self._x

    @property
    def offset_steps(self) -> float:
        return self._offset

    @property
    def velocity_hz(self) -> float:
        return self._v

    @property
    def acceleration_hz_s(self) -> float:
        if self._segments and self._segments[0].t0_s <= self._t:
            return self._segments[0].a_hz_s
        return 0.0

    @property
    def in_ramp(self) -> bool:
        return self.acceleration_hz_s != 0.0

    @property
    def target_reached(self) -> bool:
        """The commanded final state is attained (at rest on target, at speed, or stopped)."""
        return not any(not math.isinf(s.t1_s) for s in self._segments)

    @property
    def moving(self) -> bool:
        return self._v != 0.0 or not self.target_reached

    @property
    def mode(self) -> str:
        return self._mode

    @property
    def target_position_steps(self) -> float:
        return self._target_raw + self._offset

    @property
    def target_velocity_hz(self) -> float:
        return self._target_velocity

    @property
    def plan_id(self) -> int:
        """Changes with every command (lets observers tell plans apart)."""
        return self._plan_id

    @property
    def finish_time_s(self) -> float:
        """When the current plan attains its final state (time_s when it already has)."""
        finite = [s.t1_s for s in self._segments if not math.isinf(s.t1_s)]
        return max(finite) if finite else self._t

    @property
    def max_velocity_hz(self) -> float:
        return self._max_velocity

    @max_velocity_hz.setter
    def max_velocity_hz(self, value: float) -> None:
        """Clamp for later commands (a running plan is not changed)."""
        if not value > 0:
            raise ValueError(f'max_velocity_hz must be > 0, got {value}')
        self._max_velocity = float(value)

    # Commands ---------------------------------------------------------------------------------
    def move_to(self, target_steps: float, velocity_hz: float, acceleration_hz_s: float,
                deceleration_hz_s: float | None = None) -> None:
        """Absolute move to a referenced target; trapezoid, or triangle when short."""
        vmax = min(abs(float(velocity_hz)), self._max_velocity)
        acc = self._check_accel('acceleration_hz_s', acceleration_hz_s)
        dec = acc if deceleration_hz_s is None else self._check_accel(
            'deceleration_hz_s', deceleration_hz_s)
        target_raw = float(target_steps) - self._offset
        if vmax <= 0.0 and target_raw != self._x:
            raise ValueError(f'move to {target_steps} needs a velocity > 0, got {velocity_hz}')
        pieces = self._plan_move(self._x, self._v, target_raw, vmax, acc, dec)
        self._mode = MODE_POSITION
        self._target_raw = target_raw
        self._target_velocity = 0.0
        self._install(pieces, final_x=target_raw)

    def move_by(self, distance_steps: float, velocity_hz: float, acceleration_hz_s: float,
                deceleration_hz_s: float | None = None) -> None:
        """Relative move from the current position."""
        self.move_to(self.position_steps + distance_steps, velocity_hz, acceleration_hz_s,
                     deceleration_hz_s)

    def run_velocity(self, velocity_hz: float, acceleration_hz_s: float,
                     deceleration_hz_s: float | None = None) -> None:
        """Ramp to a signed velocity, hold it: acceleration while |v| grows, else deceleration."""
        acc = self._check_accel('acceleration_hz_s', acceleration_hz_s)
        dec = acc if deceleration_hz_s is None else self._check_accel(
            'deceleration_hz_s', deceleration_hz_s)
        vt = max(-self._max_velocity, min(self._max_velocity, float(velocity_hz)))
        self._mode = MODE_VELOCITY
        self._target_velocity = vt
        self._install(self._plan_velocity(self._v, vt, acc, dec), final_x=None)

    def stop(self, deceleration_hz_s: float) -> None:
        """Controlled stop on a deceleration ramp (halt)."""
        self._stop(MODE_STOP, deceleration_hz_s)

    def quick_stop(self, deceleration_hz_s: float) -> None:
        """Quick stop with its own deceleration."""
        self._stop(MODE_QUICK_STOP, deceleration_hz_s)

    def stop_immediately(self) -> None:
        """Velocity to 0 at once (fault: current off, the shaft is not driven any more)."""
        self._segments = []
        self._final_x = None
        self._v = 0.0
        self._mode = MODE_STOP
        self._target_velocity = 0.0
        self._target_raw = self._x
        self._plan_id += 1

    def set_position(self, position_steps: float) -> None:
        """Re-reference: the current position now reads position_steps (nothing moves)."""
        self._offset = float(position_steps) - self._x

    # Crossing support (for SimAxis) -------------------------------------------------------------
    def pieces(self, t_end_s: float) -> Iterator[Piece]:
        """Monotonic parts of the plan from time_s to t_end_s (none while at rest)."""
        t = self._t
        for seg in self._segments:
            if seg.t1_s <= t:
                continue
            if seg.t0_s >= t_end_s:
                break
            start = max(seg.t0_s, t)
            end = min(seg.t1_s, t_end_s)
            x0, v0 = seg.state_at(start)
            a = seg.a_hz_s
            if a != 0.0 and v0 != 0.0 and _sign(a) != _sign(v0):
                t_zero = start - v0 / a
                if start < t_zero < end:
                    if v0 != 0.0:
                        yield Piece(start, t_zero, x0, v0, a)
                    x_zero, _ = seg.state_at(t_zero)
                    yield Piece(t_zero, end, x_zero, 0.0, a)
                    t = end
                    continue
            if v0 != 0.0 or a != 0.0:
                yield Piece(start, end, x0, v0, a)
            t = end

    # Planning ---------------------------------------------------------------------------------
    def _stop(self, mode: str, deceleration_hz_s: float) -> None:
        dec = self._check_accel('deceleration_hz_s', deceleration_hz_s)
        self._mode = mode
        self._target_velocity = 0.0
        self._install(self._plan_velocity(self._v, 0.0, dec, dec), final_x=None)
        self._target_raw = self._segments[-1].end_state()[0] if self._segments else self._x

    @staticmethod
    def _check_accel(name: str, value: float) -> float:
        value = float(value)
        if not value > 0.0:
            raise ValueError(f'{name} must be > 0 (inf = start-stop), got {value}')
        return value

    def _install(self, pieces: list[tuple[float, float, float]], final_x: float | None) -> None:
        """Turn (duration_s, v0_hz, a_hz_s) pieces starting now into absolute segments."""
        t, x = self._t, self._x
        segments = []
        for duration, v0, a in pieces:
            if duration <= 0.0:
                continue
            seg = AccelSegment(t, t + duration, x, v0, a)
            segments.append(seg)
            if math.isinf(duration):
                break
            x, _ = seg.end_state()
            t = seg.t1_s
        self._segments = segments
        self._final_x = final_x
        self._plan_id += 1
        if segments:
            self._v = segments[0].v0_hz     # a start-stop jump applies at once
        else:
            self._v = 0.0
            if final_x is not None:
                self._x = final_x
                self._final_x = None

    def _plan_velocity(self, v0: float, vt: float, acc: float,
                       dec: float) -> list[tuple[float, float, float]]:
        pieces: list[tuple[float, float, float]] = []
        if v0 != 0.0 and (_sign(vt) != _sign(v0) or abs(vt) < abs(v0)):
            stop_to = vt if _sign(vt) == _sign(v0) else 0.0
            pieces.append((_ramp_time(v0 - stop_to, dec), v0, -_sign(v0) * dec))
            v0 = stop_to
        if vt != v0:
            pieces.append((_ramp_time(vt - v0, acc), v0, _sign(vt - v0) * acc))
        if vt != 0.0:
            pieces.append((INF, vt, 0.0))
        return [(d, v, 0.0 if math.isinf(a) else a) for d, v, a in pieces]

    def _plan_move(self, x0: float, v0: float, target: float, vmax: float, acc: float,
                   dec: float) -> list[tuple[float, float, float]]:
        d = target - x0
        if d == 0.0 and v0 == 0.0:
            return []
        s = _sign(d) or -_sign(v0)
        u = v0 * s                        # speed towards the target
        ia, idc = _half_inverse(acc), _half_inverse(dec)
        distance = abs(d)
        if u < 0.0 or u * u * idc > distance * (1.0 + 1e-12) + 1e-9:
            # Moving away, or too fast to stop in time: stop first, then plan from rest.
            stop = [(_ramp_time(v0, dec), v0, -_sign(v0) * dec)] if not math.isinf(dec) else []
            x_stop = x0 + _sign(v0) * v0 * v0 * idc
            return stop + self._plan_move(x_stop, 0.0, target, vmax, acc, dec)
        pieces: list[tuple[float, float, float]] = []
        if u > vmax:
            pieces.append((_ramp_time(u - vmax, dec), s * u, -s * dec))
            distance -= (u * u - vmax * vmax) * idc
            u = vp = vmax
        elif ia + idc == 0.0:
            vp = vmax
        else:
            vp = min(vmax, math.sqrt(max((distance + u * u * ia) / (ia + idc), 0.0)))
            vp = max(vp, u)
            if vp > u:
                pieces.append((_ramp_time(vp - u, acc), s * u, s * acc))
            distance -= (vp * vp - u * u) * ia
        cruise = max(distance - vp * vp * idc, 0.0)
        if cruise > 0.0 and vp > 0.0:
            pieces.append((cruise / vp, s * vp, 0.0))
        if not math.isinf(dec) and vp > 0.0:
            pieces.append((vp / dec, s * vp, -s * dec))
        return [(dur, v, 0.0 if math.isinf(a) else a) for dur, v, a in pieces]
