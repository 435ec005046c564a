"""A simulated axis with switches, index pulses and forced inputs (no rclpy).

`SimAxis` is a `MotionModel` plus the world around the motor: a home switch, two limit switches,
an encoder index pulse every `steps_per_rev` steps, and forced inputs. Switch positions are raw
(physical) positions; re-referencing the axis (`set_position`) does not move them. During
`update()` every edge crossed is found exactly (closed-form, piece by piece) and handed to the
listeners at the time and position where it happens, so a listener (a homing run, a drive that
stops on a limit switch) can re-plan the motion at that instant, whatever the update step.

A switch is active on a region [lo, hi) of raw positions:
  home       between home_switch_steps and home_switch_steps + home_switch_width_steps
             (width may be negative or +-inf: inf is the CiA "positive home switch" covering the
             whole positive side of its edge, -inf a "negative home switch")
  limit_neg  raw position < limit_neg_steps     (active on the negative side)
  limit_pos  raw position >= limit_pos_steps    (active on the positive side)

The input and event names and `AxisEvent` are in core/axis_events.py, the CiA 402 homing
procedures (`HomingRun`, `HOMING_METHODS`, `register_homing_method()`) in core/homing.py; both
are importable from here too.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Callable, Iterable

from .axis_events import (
    HOME,
    INDEX,
    LIMIT_NEG,
    LIMIT_POS,
    LIMITS,
    TARGET_REACHED,
    AxisEvent,
    Listener,
)
from .homing import (
    ATTAINED,
    ERROR,
    HOMING_METHODS,
    INTERRUPTED,
    RUNNING,
    HomingAxis,
    HomingError,
    HomingRun,
    Procedure,
    SwitchMethod,
    register_homing_method,
)
from .motion import INF, MotionModel, Piece

__all__ = ['ATTAINED', 'ERROR', 'HOME', 'HOMING_METHODS', 'INDEX', 'INTERRUPTED', 'LIMITS',
           'LIMIT_NEG', 'LIMIT_POS', 'RUNNING', 'TARGET_REACHED', 'AxisEvent', 'HomingAxis',
           'HomingError', 'HomingRun', 'Listener', 'Procedure', 'SimAxis', 'SwitchMethod',
           'register_homing_method']

logger = logging.getLogger(__name__)

_EPS_STEPS = 1e-6   # far below one micro-step: tells "at the index just fired" from "before it"


class _Switch:
    """Region [lo, hi) with a remembered side per finite edge (robust at an edge)."""

    def __init__(self, lo: float, hi: float, x: float):
        self.lo, self.hi = lo, hi
        self.side_lo = 1 if x >= lo else -1
        self.side_hi = 1 if x >= hi else -1

    @property
    def active(self) -> bool:
        return self.side_lo > 0 and self.side_hi < 0

    def edges(self) -> Iterable[tuple[str, float]]:
        if not math.isinf(self.lo):
            yield 'lo', self.lo
        if not math.isinf(self.hi):
            yield 'hi', self.hi

    def side(self, edge: str) -> int:
        return self.side_lo if edge == 'lo' else self.side_hi

    def set_side(self, edge: str, side: int) -> None:
        if edge == 'lo':
            self.side_lo = side
        else:
            self.side_hi = side

    def reset(self, x: float) -> None:
        self.side_lo = 1 if x >= self.lo else -1
        self.side_hi = 1 if x >= self.hi else -1


class SimAxis:
    """A MotionModel with a home switch, limit switches, index pulses and forced inputs."""

    def __init__(self, *, home_switch_steps: float | None = None,
                 home_switch_width_steps: float = INF,
                 limit_neg_steps: float | None = None, limit_pos_steps: float | None = None,
                 steps_per_rev: int = 12800, index_phase_steps: float = 0.0,
                 position_steps: float = 0.0, max_velocity_hz: float = INF,
                 clock: Callable[[], float] = time.monotonic,
                 motion: MotionModel | None = None):
        self.motion = motion or MotionModel(position_steps, max_velocity_hz=max_velocity_hz,
                                            clock=clock)
        self.steps_per_rev = int(steps_per_rev)
        self.index_phase_steps = float(index_phase_steps)
        self._listeners: list[Listener] = []
        self._switches: dict[str, _Switch] = {}
        self._forced: dict[str, bool] = {}
        self._effective: dict[str, bool] = {}
        self._reported_plan = self.motion.plan_id
        self._last_index: float | None = None
        if home_switch_steps is not None:
            a, b = home_switch_steps, home_switch_steps + home_switch_width_steps
            self.add_switch(HOME, min(a, b), max(a, b))
        else:
            self._effective[HOME] = False
        if limit_neg_steps is not None:
            self.add_switch(LIMIT_NEG, -INF, float(limit_neg_steps))
        else:
            self._effective[LIMIT_NEG] = False
        if limit_pos_steps is not None:
            self.add_switch(LIMIT_POS, float(limit_pos_steps), INF)
        else:
            self._effective[LIMIT_POS] = False

    # Configuration ------------------------------------------------------------------------------
    def add_switch(self, name: str, lo_steps: float, hi_steps: float) -> None:
        """A (vendor) input active while lo_steps <= raw position < hi_steps."""
        if not lo_steps < hi_steps:
            raise ValueError(f'switch {name!r}: lo {lo_steps} must be below hi {hi_steps}')
        self._switches[name] = _Switch(float(lo_steps), float(hi_steps),
                                       self.motion.raw_position_steps)
        self._effective[name] = self._forced.get(name, self._switches[name].active)

    def switch_range(self, name: str) -> tuple[float, float] | None:
        sw = self._switches.get(name)
        return (sw.lo, sw.hi) if sw else None

    def add_listener(self, listener: Listener) -> None:
        if listener not in self._listeners:
            self._listeners.append(listener)

    def remove_listener(self, listener: Listener) -> None:
        if listener in self._listeners:
            self._listeners.remove(listener)

    # State (delegates) --------------------------------------------------------------------------
    @property
    def clock(self) -> Callable[[], float]:
        return self.motion.clock

    @property
    def position_steps(self) -> float:
        return self.motion.position_steps

    @property
    def raw_position_steps(self) -> float:
        return self.motion.raw_position_steps

    @property
    def velocity_hz(self) -> float:
        return self.motion.velocity_hz

    @property
    def moving(self) -> bool:
        return self.motion.moving

    @property
    def target_reached(self) -> bool:
        return self.motion.target_reached

    def set_position(self, position_steps: float) -> None:
        self.motion.set_position(position_steps)

    # Inputs -------------------------------------------------------------------------------------
    def input(self, name: str) -> bool:
        """Effective state of an input (forced value, else the switch)."""
        try:
            return self._effective[name]
        except KeyError:
            raise KeyError(f'unknown input {name!r}; inputs: {", ".join(self.input_names)}') \
                from None

    @property
    def input_names(self) -> list[str]:
        return sorted(set(self._effective) | set(self._forced))

    @property
    def inputs(self) -> dict[str, bool]:
        return {name: self.input(name) for name in self.input_names}

    def set_input(self, name: str, value: bool) -> None:
        """Force an input (also one with no switch, e.g. a vendor input name)."""
        self._forced[name] = bool(value)
        self._refresh(name, forced=True)

    def release(self, name: str) -> None:
        """Give a forced input back to its switch (inactive when it has none)."""
        self._forced.pop(name, None)
        self._refresh(name, forced=True)

    def _refresh(self, name: str, forced: bool) -> None:
        sw = self._switches.get(name)
        value = self._forced.get(name, sw.active if sw else False)
        if self._effective.get(name) != value:
            self._effective[name] = value
            self._emit(name, value, self.motion.raw_position_steps, forced=forced)
        else:
            self._effective[name] = value

    # Time ---------------------------------------------------------------------------------------
    def update(self, now_s: float | None = None, max_events: int = 10000) -> None:
        """Advance to now_s, firing every switch edge, index pulse and end of plan on the way."""
        now = self.motion.now() if now_s is None else float(now_s)
        for _ in range(max_events):
            event = self._next_event(now)
            if event is None:
                break
            t_event, fire = event
            self.motion.update(t_event)
            fire()
        else:
            logger.warning('axis: more than %d events in one update; time skipped', max_events)
        self.motion.update(now)

    def _next_event(self, now: float):
        m = self.motion
        best: tuple[float, Callable[[], None]] | None = None
        if m.plan_id != self._reported_plan and m.finish_time_s <= now:
            plan = m.plan_id
            best = (max(m.finish_time_s, m.time_s), lambda: self._fire_target_reached(plan))
        for piece in m.pieces(now):
            if best is not None and piece.t0_s > best[0]:
                break
            found = self._crossing_in(piece)
            if found is not None:
                if best is None or found[0] < best[0]:
                    best = found
                break
        return best

    def _crossing_in(self, piece: Piece):
        d = piece.direction
        x0, x1 = piece.x0_steps, piece.x1_steps
        best: tuple[float, Callable[[], None]] | None = None

        def consider(t: float, fire: Callable[[], None]) -> None:
            nonlocal best
            if best is None or t < best[0]:
                best = (t, fire)

        for name, sw in self._switches.items():
            for edge, b in sw.edges():
                side = sw.side(edge)
                if (d > 0 and side < 0 and x1 >= b) or (d < 0 and side > 0 and x1 < b):
                    consider(piece.time_at(b), self._make_edge_fire(name, sw, edge, b, d))
        n = self.steps_per_rev
        if n > 0:
            phase, last = self.index_phase_steps, self._last_index
            below = phase + math.floor((x0 - phase) / n) * n     # index <= x0
            if d > 0:
                p = below + n
                if last is not None and abs(p - last) < _EPS_STEPS and abs(x0 - p) < _EPS_STEPS:
                    p += n      # at the index just fired (rounding below it): not again
                hit = p <= x1
            else:
                p = below if below < x0 else below - n
                if last is not None and abs(p - last) < _EPS_STEPS and abs(x0 - p) < _EPS_STEPS:
                    p -= n
                hit = p >= x1
            if hit:
                consider(piece.time_at(p), self._make_index_fire(p, d))
        return best

    def _make_edge_fire(self, name: str, sw: _Switch, edge: str, b: float, d: int):
        def fire() -> None:
            sw.set_side(edge, 1 if d > 0 else -1)
            if name in self._forced:
                return
            value = sw.active
            if self._effective.get(name) != value:
                self._effective[name] = value
                self._emit(name, value, b, direction=d)
        return fire

    def _make_index_fire(self, p: float, d: int):
        def fire() -> None:
            self._last_index = p
            self._emit(INDEX, True, p, direction=d)
        return fire

    def _fire_target_reached(self, plan: int) -> None:
        self._reported_plan = plan
        self._emit(TARGET_REACHED, True, self.motion.raw_position_steps)

    def _emit(self, name: str, active: bool, raw: float, direction: int | None = None,
              forced: bool = False) -> None:
        m = self.motion
        if direction is None:
            v = m.velocity_hz
            direction = (v > 0) - (v < 0)
        event = AxisEvent(name, active, m.time_s, raw + m.offset_steps, raw, direction, forced)
        logger.debug('axis event %s', event)
        for listener in list(self._listeners):
            try:
                listener(event)
            except Exception:   # a broken listener must not stop time for the others
                logger.exception('axis listener %r failed on %s', listener, event)
