"""The operating modes of a simulated AEC Vector Step: a mixin of
`vector_step.device.VectorStepDriveSim`.

A change of 0x6060 (an abort on the emergency ramp), `_run_mode`'s dispatch on it in OPERATION
ENABLED (1 PP, 6 homing, -1 JOG, 7 interpolated position), profile position (absolute/relative,
change set immediately, one buffered set-point), AEC JOG velocity mode, the stop ramp of 0x605D,
and the quick stop at a limit switch outside homing. The object dictionary, axis and CiA 402
state they work on are VectorStepDriveSim's; not here: homing (homing.py), interpolated position
(interpolation.py), the statusword bits of each mode (device.py).
"""

from __future__ import annotations

import logging

from stepper_drivers.vendors.vector_step import regmap as vm

from ..cia402 import slave as cia
from ..core.axis import LIMIT_NEG, LIMIT_POS, AxisEvent

logger = logging.getLogger(__name__)


class VectorStepModes:
    """The operating modes of one Vector Step (state: VectorStepDriveSim)."""

    def _change_mode(self, mode: int) -> None:
        """A new 0x6060: moving -> Abort on the emergency ramp, state unchanged [MODES OF...]."""
        logger.info('%s: mode %s -> %s', self.name, vm.MODE_NAMES.get(self.mode),
                    vm.MODE_NAMES.get(mode))
        if self.axis.moving:
            self.axis.motion.quick_stop(self._hz_s(self._stored(vm.QUICK_STOP_DECELERATION)))
        self.homing_abort(interrupted=True)
        self.jog_running = False
        self.jog_inhibit = True
        self.set_point.reset()
        self._ip_reset()
        self.homing_result = ''
        self.mode = mode

    def _run_mode(self, cw: int, prev: int) -> None:
        """The operating mode's part of the controlword, in OPERATION ENABLED (one branch per
        0x6060 value)."""
        rising = cw & cia.CW_NEW_SET_POINT and not prev & cia.CW_NEW_SET_POINT
        falling = prev & cia.CW_NEW_SET_POINT and not cw & cia.CW_NEW_SET_POINT
        if self.mode == vm.MODE_PROFILE_POSITION:
            if rising:
                self._new_setpoint(cw)
            elif falling:
                self.set_point.released()
        elif self.mode == vm.MODE_JOG:
            self._jog(cw, prev)
        elif self.mode == vm.MODE_HOMING:
            if rising:
                self._start_homing()
            elif falling and self.homing is not None:
                self.homing_abort(interrupted=True)
        elif self.mode == vm.MODE_INTERPOLATED:
            self._interpolation_control(rising, bool(cw & vm.CW_BIT_IP_ENABLE))

    def _profile(self) -> tuple[float, float, float]:
        return (self._hz(self._stored(vm.PROFILE_VELOCITY)),
                self._hz_s(self._stored(vm.PROFILE_ACCELERATION)),
                self._hz_s(self._stored(vm.PROFILE_DECELERATION)))

    def _new_setpoint(self, cw: int) -> None:
        target = float(self._stored(vm.TARGET_POSITION))
        if cw & cia.CW_RELATIVE:
            base = self.pp_target if self.pp_target is not None and self.axis.moving \
                else self.axis.position_steps
            target += base
        started = self.set_point.new_set_point(
            target, busy=self.axis.moving, immediate=bool(cw & cia.CW_CHANGE_SET_IMMEDIATELY))
        if started == cia.SetPointHandshake.START:
            self._start_move(target)

    def _start_move(self, target: float) -> None:
        velocity, acc, dec = self._profile()
        self.pp_target = target
        if velocity <= 0:
            logger.info('%s: profile velocity 0: set-point %d not run', self.name, target)
            return
        blocked = LIMIT_POS if target > self.axis.position_steps else LIMIT_NEG
        if self._input(blocked):
            logger.info('%s: %s active, move to %d refused', self.name, blocked, target)
            return
        self.axis.motion.move_to(target, velocity, acc, dec)

    def _jog(self, cw: int, prev: int) -> None:
        start = bool(cw & vm.CW_BIT_JOG_START)
        if not start:
            self.jog_inhibit = False
            if self.jog_running:
                self.jog_running = False
                self.axis.motion.stop(self._stop_deceleration())
            return
        if self.jog_inhibit:
            return
        speed = self._hz(self._stored(vm.PROFILE_VELOCITY))
        if self.jog_running and not cw & vm.CW_BIT_JOG_SPEED_CONTINUOUS:
            speed = abs(self.jog_velocity_hz)      # bit 6 = 0: speed taken at the jog start
        velocity = -speed if cw & vm.CW_BIT_JOG_CCW else speed     # bit 5 applies at any time
        if self.jog_running and velocity == self.jog_velocity_hz:
            return
        blocked = LIMIT_POS if velocity > 0 else LIMIT_NEG
        if self._input(blocked):
            self.jog_inhibit = True
            return
        _, acc, dec = self._profile()
        self.jog_running = True
        self.jog_velocity_hz = velocity
        self.axis.motion.run_velocity(velocity, acc, dec)

    def _stop_deceleration(self) -> float:
        option = self._stored(vm.STOP_OPTION_CODE)          # [STOP OPTION CODE]
        index = vm.QUICK_STOP_DECELERATION if option == 2 else vm.PROFILE_DECELERATION
        return self._hz_s(self._stored(index))

    def _on_axis_event(self, event: AxisEvent) -> None:
        """Limit switch reached while moving towards it (outside homing): stop on the ramp."""
        if self.homing is not None or not event.active or \
                event.name not in (LIMIT_NEG, LIMIT_POS):
            return
        toward = (event.name == LIMIT_POS and event.direction > 0) or \
            (event.name == LIMIT_NEG and event.direction < 0)
        if toward and self.axis.moving:
            logger.info('%s: %s reached at %.0f: quick stop', self.name, event.name,
                        event.position_steps)
            self.axis.motion.quick_stop(self._hz_s(self._stored(vm.QUICK_STOP_DECELERATION)))
            self.jog_running = False
            self.jog_inhibit = True
            self.set_point.queued = None
            self._ip_reset()
