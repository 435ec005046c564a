"""One simulated R.T.A. X-PLUS MT, its operating modes: a mixin of `XplusMtDriveSim`.

What the drive does in Operation Enabled, by mode of operation (1041): profile position with
the set-point handshake, multi-set-point (change set immediately) and halt (§13 "Profile Position
Mode", "Multi-Set-Point Mode"), profile velocity with the 1062-1065 speed windows (§13 "Profile
Velocity Mode"), homing on the SimAxis (§13 "Homing Mode", T19, T26); the limit switches that
stop a motion (§13 "Registers 1008-1009", 1088); and the statusword (1001) bits each mode shows.
The register image, lock and CiA 402 glue it works on are `xplus_mt_device.XplusMtDriveSim`'s.
"""

from __future__ import annotations

import logging

from stepper_drivers.vendors.xplus_mt import regmap as xm

from ..cia402 import slave as cia
from ..cia402.slave import (
    CW_CHANGE_SET_IMMEDIATELY,
    CW_HALT,
    CW_NEW_SET_POINT,
    CW_RELATIVE,
    FAULT,
    FRA,
    OE,
    QSA,
    SW_BIT12,
    SW_BIT13,
    SW_INTERNAL_LIMIT,
    SW_PROFILE_RAMP,
    SW_TARGET_REACHED,
)
from ..core.axis import LIMIT_NEG, LIMIT_POS, AxisEvent
from ..core.homing import HomingRun
from ..core.motion import INF

logger = logging.getLogger(__name__)

START_STOP_HZ = xm.START_STOP_MAX_HZ


class XplusMtModes:
    """The modes of one X-PLUS MT (state and lock: XplusMtDriveSim, which calls these with its
    lock held)."""

    # ------------------------------------------------------------------ modes
    def _on_mode_change(self, now: float) -> None:
        if self.axis.moving and self.state == OE:
            self.axis.motion.stop(self._mode_decel())
        self._abort_homing()
        self._pv_started = False
        self._pp_moving = False
        self._set_point.reset()
        self._halt_released = False

    def _mode_bits(self, cw: int, rising: int, falling: int) -> None:
        mode = self.mode
        if rising & CW_HALT:
            self._halt()
        if falling & CW_HALT:
            if mode == 1 and self._halted:
                self._halt_released = True  # §13 bit 8: target reached -> 0, move abandoned
            self._halted = False
            if mode == 3 and self._pv_following():
                self._pv_follow()
        if falling & CW_NEW_SET_POINT:
            self._set_point.released()      # A23: CiA handshake
            if mode == 3 and self._pv_started:
                self._pv_started = False
                self._stop_motion()
            if mode == 6 and self._homing is not None and not self._homing.done:
                self._abort_homing()
        if rising & CW_NEW_SET_POINT and not cw & CW_HALT:
            if mode == 1:
                self._new_set_point(cw)
            elif mode == 3:
                self._pv_started = True
                self._pv_follow()
            elif mode == 6:
                self._start_homing()

    def _halt(self) -> None:
        mode = self.mode
        if mode == 6 and self._homing is not None and not self._homing.done:
            self._homing.abort(self._mode_decel())
        elif self.axis.moving:
            self.axis.motion.stop(self._mode_decel())
        self._halted = True

    def _stop_motion(self) -> None:
        if self.axis.moving:
            self.axis.motion.stop(self._mode_decel())

    def _mode_decel(self) -> float:
        """Deceleration of the active mode (spec §3.7 [R]: quick stop uses it too)."""
        if abs(self.axis.velocity_hz) <= START_STOP_HZ:
            return INF
        if self.mode == 3:
            return float(self._regs[1072])
        if self.mode == 6:
            return float(self._regs[1056])
        return self._move_accel if self._pp_moving else float(self._regs[1046])

    # Profile position (§13 "Profile Position Mode", "Multi-Set-Point Mode") --------------------
    def _new_set_point(self, cw: int) -> None:
        target_reg = self._regs[1042]
        busy = self._pp_moving and self.axis.moving
        immediate = bool(cw & CW_CHANGE_SET_IMMEDIATELY)
        target = None
        if busy and immediate:
            if self._halted or self.axis.motion.mode != 'position':
                return      # no change during a halt or quick stop (§13 Multi-Set-Point)
            if bool(cw & CW_RELATIVE) != self._move_relative:
                logger.info('%s: bit 6 change ignored during a multi-set-point move', self.name)
            target = self._move_origin + target_reg if self._move_relative else target_reg
        elif not busy:
            if self._regs[1044] == 0:
                logger.info('%s: set point ignored: Profile Velocity (1044) is 0', self.name)
                return
            self._move_relative = bool(cw & CW_RELATIVE)
            self._move_origin = self.axis.position_steps
            self._move_accel = float(self._regs[1046])  # §13 1046: changes apply next move
            target = self._move_origin + target_reg if self._move_relative else target_reg
            if self._regs[1085] in (0, 2):
                self._following_error = False           # §13 1086: cleared by a new PP run
        if self._set_point.new_set_point(target, busy=busy, immediate=immediate) == \
                cia.SetPointHandshake.IGNORED:
            logger.info('%s: new set point ignored while moving (CW bit 5 = 0, §13 '
                        'Multi-Set-Point)', self.name)
            return
        self._move_immediate = immediate
        self._halt_released = False
        self._pp_target = float(target)
        direction = (target > self.axis.position_steps) - (target < self.axis.position_steps)
        if self._blocked_by_limit(direction):
            logger.info('%s: set point towards an active limit switch ignored', self.name)
            return
        self._pp_moving = True
        self._replan_pp()

    def _replan_pp(self) -> None:
        pv = float(self._regs[1044])
        accel = INF if pv <= START_STOP_HZ else self._move_accel   # §13 "Motion Profiles"
        self.axis.motion.move_to(self._pp_target, pv, accel, accel)

    # Profile velocity (§13 "Profile Velocity Mode") --------------------------------------------
    def _pv_following(self) -> bool:
        return (self.state == OE and self.mode == 3 and self._pv_started
                and not self.controlword & CW_HALT)

    def _update_pv_timers(self, now: float) -> None:
        v = abs(self.axis.velocity_hz)
        if v > self._regs[1062]:                        # §13 "Register 1062"
            if self._v_above_since is None:
                self._v_above_since = now
        else:
            self._v_above_since = None
        if v < self._regs[1064]:                        # §13 "Register 1064"
            if self._v_below_since is None:
                self._v_below_since = now
        else:
            self._v_below_since = None

    def _pv_bit10(self) -> bool:
        now = self.axis.motion.time_s
        if self.config.pv_bit10 == 'cia':
            return (abs(self.axis.motion.target_velocity_hz - self.axis.velocity_hz)
                    <= self._regs[1062])
        return (self._v_above_since is not None
                and now - self._v_above_since >= self._regs[1063] / 1000.0)

    def _zero_speed(self) -> bool:
        now = self.axis.motion.time_s
        return (self._v_below_since is not None
                and now - self._v_below_since >= self._regs[1065] / 1000.0)

    def _pv_follow(self) -> None:
        tv = float(self._regs[1048])
        limit = self._regs[1074]
        if limit:
            tv = max(-limit, min(limit, tv))    # §13 "Registers 1074-1075"
        direction = (tv > 0) - (tv < 0)
        if self._blocked_by_limit(direction):
            tv = 0.0
        v = self.axis.velocity_hz
        if abs(tv) <= START_STOP_HZ and abs(v) <= START_STOP_HZ:
            acc = dec = INF
        else:
            acc, dec = float(self._regs[1046]), float(self._regs[1072])
        self.axis.motion.run_velocity(tv, acc, dec)

    # Homing (§13 "Homing Mode", T19, T26) ------------------------------------------------------
    def _start_homing(self) -> None:
        method = self._regs[1050]
        self._abort_homing()
        self._homing_attained = False
        self._homing_error = False
        self._following_error = False if self._regs[1085] in (0, 2) else self._following_error
        error = ''
        if method not in xm.HOMING_METHODS:
            error = (f'homing method {method} is not available (available: '
                     f'{", ".join(map(str, xm.HOMING_METHODS))})')
        elif method in xm.HOMING_METHODS_HOME_SWITCH and self._regs[1088] & 0x01:
            error = 'I0 is not the proximity input (1088 bit 0 = 1)'
        elif method in xm.HOMING_METHODS_NEED_INDEX and self._regs[1085] == 17:
            error = f'method {method} needs the encoder index (1085 = 17: no encoder)'
        elif method not in xm.HOMING_METHODS_CURRENT_POSITION and self._regs[1054] == 0:
            error = 'Homing Speed During Search Zero (1054-1055) is 0'
        run = HomingRun(self.axis, method, speed_search_hz=self._regs[1052],
                        speed_zero_hz=self._regs[1054], acceleration_hz_s=self._regs[1056],
                        offset_steps=self._regs[1058], start_stop_hz=START_STOP_HZ,
                        max_travel_steps=self.config.homing_max_travel_steps,
                        on_done=self._homing_done)
        self._homing = run
        if error:
            run.status = 'error'
            run.error = error
            self._homing_done(run)
            return
        run.start()

    def _homing_done(self, run: HomingRun) -> None:
        if run is not self._homing:
            return
        self._homing_attained = run.status == 'attained'
        self._homing_error = run.status == 'error'
        self._homing_message = run.error
        logger.info('%s: homing %s%s', self.name, run.status,
                    f': {run.error}' if run.error else '')

    def _abort_homing(self) -> None:
        if self._homing is not None and not self._homing.done:
            self._homing.abort(self._mode_decel())

    # Limit switches (§13 "Registers 1008-1009", 1088) ---------------------------------------
    def _limit_function(self, name: str) -> bool:
        bit = 0x02 if name == LIMIT_NEG else 0x04          # IC1 / IC2 = 0: limit switch
        return not self._regs[1088] & bit

    def _limit_active_now(self) -> bool:
        return any(self._limit_function(n) and self.axis.input(n)
                   for n in (LIMIT_NEG, LIMIT_POS))

    def _blocked_by_limit(self, direction: int) -> bool:
        name = LIMIT_POS if direction > 0 else LIMIT_NEG
        return direction != 0 and self._limit_function(name) and self.axis.input(name)

    def _on_axis_event(self, event: AxisEvent) -> None:
        if event.name not in (LIMIT_NEG, LIMIT_POS) or not self._limit_function(event.name):
            return
        if not event.active:
            self._limit_stop = self._limit_active_now()
            return
        self._limit_stop = True
        homing = self._homing is not None and not self._homing.done
        toward = (event.direction > 0) == (event.name == LIMIT_POS)
        if self.axis.moving and toward and not homing:
            self.axis.motion.stop(self._mode_decel())     # "as if Halt had been commanded"
            self._pp_moving = False

    # ------------------------------------------------------------------ statusword
    def _statusword(self) -> int:
        state = self.state
        sw = self.cia.state_word(voltage_enabled=self.hv_present)
        if state == FRA:
            return sw | SW_BIT13            # 0x201F: Remote = 0, Quick Stop = 0 (§13 1085)
        mode = self.mode
        m = self.axis.motion
        homing = cia.homing_bits(attained=self._homing_attained,
                                 error=self._homing_error and state != FAULT,
                                 running=self._homing is not None and not self._homing.done,
                                 moving=m.moving)
        if self.cia.shows_target_reached():
            if state == QSA or mode not in (1, 3, 6):
                reached = not m.moving
            elif mode == 1:
                reached = self._set_point.target_reached(m.moving) and not self._halt_released
            elif mode == 6:
                reached = bool(homing & SW_TARGET_REACHED)
            else:
                reached = self._pv_bit10()
            if reached:
                sw |= SW_TARGET_REACHED
            if self._limit_stop:
                sw |= SW_INTERNAL_LIMIT
            if self._regs[1107] and mode in (1, 6) and m.in_ramp:
                sw |= SW_PROFILE_RAMP
        if mode == 1 and state == OE and self._set_point.acknowledged:
            sw |= SW_BIT12
        elif mode == 6:
            sw |= homing & (SW_BIT12 | SW_BIT13)
        elif mode == 3 and self._zero_speed():
            sw |= SW_BIT12
        if state != FAULT and self._following_error:
            sw |= SW_BIT13
        return sw
