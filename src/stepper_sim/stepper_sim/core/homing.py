"""CiA 402 homing on a simulated axis: `HomingRun`, the procedures and the method table.

`HomingRun` carries out a CiA 402 homing method on an axis, step by step, using only what a real
drive sees (switch transitions, motion direction, index pulses). The method table
`HOMING_METHODS` maps a method number to a procedure (a generator, see `Procedure`) and can be
extended with `register_homing_method()` for vendor methods.

HomingRun uses only the axis' public API (`HomingAxis`, which `SimAxis` of core/axis.py is) and
the AxisEvent contract (each edge delivered at its exact time and position, so a procedure can
re-plan there). Not here: the axis itself, its switches and index pulses (core/axis.py).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable, Generator, Mapping, Protocol

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
from .motion import INF, MotionModel

logger = logging.getLogger(__name__)


class HomingAxis(Protocol):
    """What a homing run needs of its axis (a `core.axis.SimAxis`)."""

    steps_per_rev: int
    motion: MotionModel

    @property
    def moving(self) -> bool: ...

    @property
    def raw_position_steps(self) -> float: ...

    def input(self, name: str) -> bool: ...

    def set_position(self, position_steps: float) -> None: ...

    def add_listener(self, listener: Listener) -> None: ...

    def remove_listener(self, listener: Listener) -> None: ...


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

    def __init__(self, axis: HomingAxis, method: int, *, speed_search_hz: float,
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
