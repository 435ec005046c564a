"""The homing of a simulated AEC Vector Step: a mixin of `vector_step.device.VectorStepDriveSim`.

The AEC homing methods on a SimAxis [HOMING METHOD] (BLS/FLS limit switches, TOP = encoder
index), the start of a run from the homing objects (method, speeds, acceleration, 0x607C home
offset) and Rhmaxspc, and its end: attained, error (Rhsts, Ralarm bit 13, EMCY), interrupted.
The object dictionary, axis and fault reaction it works on are VectorStepDriveSim's; not here:
the homing run itself (core/homing.py), the statusword bits of homing (device.py), the mode
change that aborts it (modes.py).
"""

from __future__ import annotations

import logging
import math
from typing import Generator

from stepper_drivers.vendors.vector_step import regmap as vm

from ..core.axis import INDEX, LIMIT_NEG, LIMIT_POS, AxisEvent
from ..core.homing import HomingRun, SwitchMethod

logger = logging.getLogger(__name__)

DEFAULT_MAX_TRAVEL_STEPS = 50 * 3200


# --- AEC homing methods on a SimAxis [HOMING METHOD] --------------------------------------------
def _top_only(direction: int):
    def procedure(run: HomingRun) -> Generator[None, AxisEvent, float]:
        run.move(direction, run.speed_zero_hz)
        ev = yield from run.wait_for({INDEX}, set())
        return ev.raw_position_steps
    return procedure


def _on_the_spot(run: HomingRun) -> Generator[None, AxisEvent, float]:
    return run.axis.raw_position_steps
    yield   # unreachable: makes this a generator


# "direction" read as the direction in which the home edge is crossed (see docs/vector_step.md).
AEC_HOMING_PROCEDURES = {
    -16: SwitchMethod(LIMIT_POS, 'lo', +1, True), -15: SwitchMethod(LIMIT_POS, 'lo', -1, True),
    -14: SwitchMethod(LIMIT_POS, 'lo', +1, False), -13: SwitchMethod(LIMIT_POS, 'lo', -1, False),
    -6: _top_only(+1), -5: _top_only(-1),
    -4: SwitchMethod(LIMIT_NEG, 'hi', +1, True), -3: SwitchMethod(LIMIT_NEG, 'hi', -1, True),
    -2: SwitchMethod(LIMIT_NEG, 'hi', +1, False), -1: SwitchMethod(LIMIT_NEG, 'hi', -1, False),
    0: _on_the_spot, 35: _on_the_spot, 37: _on_the_spot,
}


def _rhsts_for(message: str) -> int:
    """Rhsts bit for a homing failure, from what stopped the search."""
    if 'not found within' in message:
        return vm.RHSTS_MAX_TRAVEL
    if 'limit_neg' in message:
        return vm.RHSTS_BLS
    if 'limit_pos' in message:
        return vm.RHSTS_FLS
    return vm.RHSTS_UNKNOWN


class VectorStepHoming:
    """The homing of one Vector Step (state: VectorStepDriveSim)."""

    def _start_homing(self) -> None:
        method = self._stored(vm.HOMING_METHOD)
        self.homing_abort(interrupted=False)
        self.homing_result = ''
        self.home_error_latched = False
        self.rhsts = vm.RHSTS_IN_PROGRESS
        if method in vm.HARD_STOP_METHODS:
            self._homing_failed(vm.RHSTS_FOC_OPEN, f'method {method} needs SmartMode or closed '
                                'loop (simulated drive is open loop)')
            return
        search = self._stored(vm.HOMING_SPEEDS, 1)
        zero = self._stored(vm.HOMING_SPEEDS, 2)
        start_stop = self._hz(self._stored(vm.END_VELOCITY))
        if search <= zero:                                  # "le rampe vengono disabilitate"
            start_stop = math.inf
        travel = self._stored(vm.RHMAXSPC, vm.AEC_SUB) or DEFAULT_MAX_TRAVEL_STEPS
        run = HomingRun(self.axis, method, speed_search_hz=self._hz(search),
                        speed_zero_hz=self._hz(zero),
                        acceleration_hz_s=self._hz_s(self._stored(vm.HOMING_ACCELERATION)),
                        offset_steps=float(self._stored(vm.HOME_OFFSET)),
                        start_stop_hz=start_stop, max_travel_steps=float(travel),
                        methods=AEC_HOMING_PROCEDURES, on_done=self._homing_done)
        self.homing = run
        logger.info('%s: homing method %d (%s)', self.name, method, vm.HOMING_METHODS[method])
        run.start()

    def _homing_done(self, run: HomingRun) -> None:
        if run is not self.homing:
            return
        self.homing = None
        if run.status == 'attained':
            self.homing_result = 'attained'
            self.homed = True
            self.rhsts = 0
            self.pp_target = self.axis.position_steps
            logger.info('%s: homing attained, position %.0f', self.name,
                        self.axis.position_steps)
        elif run.status == 'error':
            self._homing_failed(_rhsts_for(run.error), run.error)
        else:
            self.homing_result = 'interrupted'
            self.rhsts = vm.RHSTS_INTERRUPTED

    def _homing_failed(self, rhsts: int, why: str) -> None:
        self.homing = None
        self.homing_result = 'error'
        self.home_error_latched = True
        self.rhsts = rhsts
        self.alarms |= 1 << 13                # Ralarm bit 13 "Homing Error"
        logger.info('%s: homing error: %s', self.name, why)
        self.nmt.emcy(vm.EMCY_HOME_ERROR, bytes([rhsts & 0xFF]))
        if self.cfg.homing_error_faults:
            self._enter_fault()

    def homing_abort(self, interrupted: bool, deceleration_hz_s: float | None = None) -> None:
        run, self.homing = self.homing, None
        if run is not None and not run.done:
            run.abort(deceleration_hz_s)
            if interrupted:
                self.homing_result = 'interrupted'
                self.rhsts = vm.RHSTS_INTERRUPTED
