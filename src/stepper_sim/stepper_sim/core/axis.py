"""A simulated axis with switches, index pulses and CiA 402 homing procedures (no rclpy).

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

`HomingRun` carries out a CiA 402 homing method on a SimAxis, step by step, using only what a real
drive sees (switch transitions, motion direction, index pulses). The method table
`HOMING_METHODS` maps a method number to a procedure (a generator, see `Procedure`) and can be
extended with `register_homing_method()` for vendor methods.

HomingRun uses only SimAxis's public API and the AxisEvent contract (each edge delivered at its
exact time and position, so a procedure can re-plan there).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Callable, Generator, Iterable, Mapping

from .motion import INF, MotionModel, Piece

logger = logging.getLogger(__name__)

HOME = 'home'
LIMIT_NEG = 'limit_neg'
LIMIT_POS = 'limit_pos'
INDEX = 'index'
TARGET_REACHED = 'target_reached'
LIMITS = (LIMIT_NEG, LIMIT_POS)

_EPS_STEPS = 1e-6   # far below one micro-step: tells "at the index just fired" from "before it"


@dataclasses.dataclass(frozen=True)
class AxisEvent:
    """Something that happened on the axis during update() (or at set_input()).

    name: an input name ('home', 'limit_neg', 'limit_pos', vendor inputs), 'index', or
    'target_reached' (the motion plan attained its final state: at rest, or at speed).
    raw_position_steps is exact for a crossing: the switch edge or index position itself.
    """

    name: str
    active: bool
    time_s: float
    position_steps: float
    raw_position_steps: float
    direction: int
    forced: bool = False


Listener = Callable[[AxisEvent], None]


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


# Homing ---------------------------------------------------------------------------------------

class HomingError(Exception):
    """A homing procedure cannot complete; the message says why."""


# A procedure is a generator: it commands the axis through the run's helpers, yields to wait,
# receives every AxisEvent, and returns the raw position of the home point.
Procedure = Callable[['HomingRun'], Generator[None, AxisEvent, float]]

RUNNING = 'running'
ATTAINED = 'attained'
ERROR = 'error'
INTERRUPTED = 'interrupted'

_ORDER = {'below': 0, 'inside': 1, 'above': 2}


@dataclasses.dataclass(frozen=True)
class SwitchMethod:
    """A CiA 402 method that homes on an edge of a switch, optionally then on the index pulse.

    edge 'lo'/'hi' is the edge of the signal's active region; final_dir is the direction in
    which that edge is crossed at the slow speed (then the index pulse is searched further in
    that direction). initial_dir 0: the direction follows from the switch state (CiA methods
    1-6, 17-22: a half-axis switch); +-1: fixed start direction, reversed at reversal_limit
    (methods 7-14, 23-30).
    """

    signal: str
    edge: str
    final_dir: int
    use_index: bool
    initial_dir: int = 0
    reversal_limit: str | None = None

    def __call__(self, run: 'HomingRun') -> Generator[None, AxisEvent, float]:
        return _switch_procedure(run, self)


def _region_after(event: AxisEvent) -> str:
    """Where the axis is after a transition of the signal, from what a drive sees."""
    if event.active:
        return 'inside'
    return 'above' if event.direction > 0 else 'below'


def _switch_procedure(run: 'HomingRun', m: SwitchMethod) -> Generator[None, AxisEvent, float]:
    axis = run.axis
    pre = {('lo', 1): 'below', ('lo', -1): 'inside',
           ('hi', 1): 'inside', ('hi', -1): 'above'}[(m.edge, m.final_dir)]
    allowed = {m.signal}
    touched = False
    if axis.input(m.signal):
        region: str | None = 'inside'
        touched = True
    elif not m.initial_dir:
        region = 'below' if m.edge == 'lo' else 'above'
    else:
        region = None
        if m.reversal_limit and axis.input(m.reversal_limit):
            region = 'above' if m.initial_dir > 0 else 'below'
    if region is None:
        # Fixed start direction; the reversal limit tells that the switch is behind us.
        run.move(m.initial_dir, run.speed_search_hz)
        while True:
            ev = yield from run.wait_for({m.signal, m.reversal_limit},
                                         allowed | {m.reversal_limit})
            if ev.name == m.signal:
                region, touched = _region_after(ev), True
                break
            if ev.active:       # reversal limit reached
                yield from run.stop_and_wait(allowed | {m.reversal_limit})
                region = 'above' if m.initial_dir > 0 else 'below'
                break
        allowed.add(m.reversal_limit)
    if region == pre and not touched:
        # Fast approach across the edge first, so that the slow pass is a short one.
        run.move(m.final_dir, run.speed_search_hz)
        ev = yield from run.wait_for({m.signal}, allowed)
        region, touched = _region_after(ev), True
        region = yield from run.stop_and_wait(allowed, m.signal, region)
    while region != pre:
        direction = 1 if _ORDER[pre] > _ORDER[region] else -1
        run.move(direction, run.speed_search_hz if not touched else run.speed_zero_hz)
        ev = yield from run.wait_for({m.signal}, allowed)
        region, touched = _region_after(ev), True
        if region == pre:
            region = yield from run.stop_and_wait(allowed, m.signal, region)
    run.move(m.final_dir, run.speed_zero_hz)
    ev = yield from run.wait_for({m.signal}, allowed)
    home = ev.raw_position_steps
    if m.use_index:
        ev = yield from run.wait_for({INDEX}, allowed)
        home = ev.raw_position_steps
    return home


def _index_procedure(direction: int) -> Procedure:
    def procedure(run: 'HomingRun') -> Generator[None, AxisEvent, float]:
        run.move(direction, run.speed_zero_hz)
        ev = yield from run.wait_for({INDEX}, set())
        return ev.raw_position_steps
    return procedure


def _current_position(run: 'HomingRun') -> Generator[None, AxisEvent, float]:
    return run.axis.raw_position_steps
    yield   # unreachable: makes this a generator


def _cia402_methods() -> dict[int, Procedure]:
    lo, hi = 'lo', 'hi'
    table: dict[int, Procedure] = {}
    for base, index in ((0, True), (16, False)):   # 17-30 = 1-14 without the index pulse
        table.update({
            base + 1: SwitchMethod(LIMIT_NEG, hi, +1, index),
            base + 2: SwitchMethod(LIMIT_POS, lo, -1, index),
            base + 3: SwitchMethod(HOME, lo, -1, index),     # positive home switch
            base + 4: SwitchMethod(HOME, lo, +1, index),
            base + 5: SwitchMethod(HOME, hi, +1, index),     # negative home switch
            base + 6: SwitchMethod(HOME, hi, -1, index),
            base + 7: SwitchMethod(HOME, lo, -1, index, +1, LIMIT_POS),
            base + 8: SwitchMethod(HOME, lo, +1, index, +1, LIMIT_POS),
            base + 9: SwitchMethod(HOME, hi, -1, index, +1, LIMIT_POS),
            base + 10: SwitchMethod(HOME, hi, +1, index, +1, LIMIT_POS),
            base + 11: SwitchMethod(HOME, hi, +1, index, -1, LIMIT_NEG),
            base + 12: SwitchMethod(HOME, hi, -1, index, -1, LIMIT_NEG),
            base + 13: SwitchMethod(HOME, lo, +1, index, -1, LIMIT_NEG),
            base + 14: SwitchMethod(HOME, lo, -1, index, -1, LIMIT_NEG),
        })
    table[33] = _index_procedure(-1)
    table[34] = _index_procedure(+1)
    table[35] = _current_position   # DSP 402 code
    table[37] = _current_position   # CiA 402 code
    return table


HOMING_METHODS: dict[int, Procedure] = _cia402_methods()


def register_homing_method(method: int, procedure: Procedure, *, replace: bool = False) -> None:
    """Add a (vendor) method to the shared table, e.g. AEC's negative method numbers."""
    if method in HOMING_METHODS and not replace:
        raise ValueError(f'homing method {method} already defined (replace=True to override)')
    HOMING_METHODS[method] = procedure


class HomingRun:
    """One homing run of `method` on `axis`: start(), then the axis' update() drives it.

    At the home point the position is set so that it reads offset_steps; the axis stops there
    (start-stop at speeds <= start_stop_hz, else on the acceleration ramp, past the point).
    status: 'running', 'attained', 'error' (message in .error), 'interrupted' (abort()).
    """

    def __init__(self, axis: SimAxis, method: int, *, speed_search_hz: float,
                 speed_zero_hz: float, acceleration_hz_s: float, offset_steps: float = 0.0,
                 start_stop_hz: float = 0.0, max_travel_steps: float | None = None,
                 methods: Mapping[int, Procedure] | None = None,
                 on_done: Callable[['HomingRun'], None] | None = None):
        self.axis = axis
        self.method = int(method)
        self.speed_search_hz = abs(float(speed_search_hz))
        self.speed_zero_hz = abs(float(speed_zero_hz))
        self.acceleration_hz_s = float(acceleration_hz_s)
        self.offset_steps = float(offset_steps)
        self.start_stop_hz = float(start_stop_hz)
        self.max_travel_steps = float(max_travel_steps if max_travel_steps is not None
                                      else 50 * max(axis.steps_per_rev, 1))
        self._methods = HOMING_METHODS if methods is None else methods
        self._on_done = on_done
        self.status = ''
        self.error = ''
        self.home_raw_steps: float | None = None
        self._gen: Generator[None, AxisEvent, float] | None = None
        self._finishing = False
        self._allowed_limits: set = set()

    @property
    def done(self) -> bool:
        return self.status in (ATTAINED, ERROR, INTERRUPTED)

    @property
    def attained(self) -> bool:
        return self.status == ATTAINED

    def start(self) -> None:
        """Begin at the axis' current time; errors in the set-up end the run at once."""
        self.status = RUNNING
        procedure = self._methods.get(self.method)
        if procedure is None:
            self._fail(f'homing method {self.method} is not supported; methods: '
                       f'{", ".join(str(k) for k in sorted(self._methods))}')
            return
        if not self.acceleration_hz_s > 0:
            self._fail(f'homing acceleration must be > 0, got {self.acceleration_hz_s}')
            return
        self.axis.add_listener(self._on_event)
        self._gen = procedure(self)
        self._advance(None)

    def abort(self, deceleration_hz_s: float | None = None) -> None:
        """Halt: stop on a ramp (default: the homing acceleration); status 'interrupted'."""
        if self.done:
            return
        self._close()
        if self.axis.moving:
            self.axis.motion.stop(deceleration_hz_s or self.acceleration_hz_s)
        self.status = INTERRUPTED
        self._notify()

    # Helpers for procedures -------------------------------------------------------------------
    def accel_for(self, speed_hz: float) -> float:
        return INF if speed_hz <= self.start_stop_hz else self.acceleration_hz_s

    def move(self, direction: int, speed_hz: float) -> None:
        """Search move in a direction, bounded by max_travel_steps."""
        if not speed_hz > 0:
            raise HomingError(f'homing speed must be > 0 (method {self.method}), got {speed_hz}')
        blocked = LIMIT_POS if direction > 0 else LIMIT_NEG
        if self.axis.input(blocked) and blocked not in self._allowed_limits:
            raise HomingError(f'{blocked} switch is active: cannot search in the '
                              f'{"positive" if direction > 0 else "negative"} direction')
        m = self.axis.motion
        target = m.position_steps + direction * self.max_travel_steps
        m.move_to(target, speed_hz, self.accel_for(speed_hz), self.accel_for(speed_hz))

    def stop(self) -> None:
        m = self.axis.motion
        if m.moving:
            m.stop(self.accel_for(abs(m.velocity_hz)))

    def wait_for(self, names: set, allowed_limits: set) -> Generator[None, AxisEvent, AxisEvent]:
        """Wait for an event named in `names`; an unexpected active limit or the end of the
        search travel raises HomingError."""
        self._allowed_limits = set(allowed_limits)
        while True:
            ev = yield
            if ev.name in names:
                return ev
            self._check(ev, names)

    def stop_and_wait(self, allowed_limits: set, signal: str | None = None,
                      region: str | None = None) -> Generator[None, AxisEvent, str | None]:
        """Stop and wait for rest; transitions of `signal` on the way update the region."""
        self._allowed_limits = set(allowed_limits)
        self.stop()
        while self.axis.moving:
            ev = yield
            if ev.name == signal:
                region = _region_after(ev)
            elif ev.name == TARGET_REACHED:
                continue
            else:
                self._check(ev, {signal})
        return region

    def _check(self, ev: AxisEvent, names: set) -> None:
        if ev.name in LIMITS and ev.active and ev.name not in self._allowed_limits:
            raise HomingError(f'{ev.name} switch reached at {ev.position_steps:.0f} steps '
                              f'while searching for {"/".join(sorted(map(str, names)))} '
                              f'(method {self.method})')
        if ev.name == TARGET_REACHED and not self.axis.moving:
            raise HomingError(f'{"/".join(sorted(map(str, names)))} not found within '
                              f'{self.max_travel_steps:.0f} steps (method {self.method})')

    # Machinery --------------------------------------------------------------------------------
    def _on_event(self, event: AxisEvent) -> None:
        if self.done:
            return
        if self._finishing:
            if not self.axis.moving:
                self._finish()
            return
        self._advance(event)

    def _advance(self, event: AxisEvent | None) -> None:
        assert self._gen is not None
        try:
            if event is None:
                next(self._gen)
            else:
                self._gen.send(event)
        except StopIteration as stop:
            self.home_raw_steps = float(stop.value)
            self._finishing = True
            self.stop()
            if not self.axis.moving:
                self._finish()
        except HomingError as exc:
            self._fail(str(exc))

    def _finish(self) -> None:
        raw = self.axis.raw_position_steps
        self.axis.set_position(self.offset_steps + (raw - self.home_raw_steps))
        self._close()
        self.status = ATTAINED
        logger.debug('homing method %d attained: home at raw %.3f', self.method,
                     self.home_raw_steps)
        self._notify()

    def _fail(self, message: str) -> None:
        self._close()
        self.stop()
        self.status = ERROR
        self.error = message
        logger.info('homing error: %s', message)
        self._notify()

    def _close(self) -> None:
        self.axis.remove_listener(self._on_event)
        if self._gen is not None:
            self._gen.close()
            self._gen = None

    def _notify(self) -> None:
        if self._on_done is not None:
            self._on_done(self)
