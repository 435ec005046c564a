"""One simulated R.T.A. X-PLUS MT, its faults: a mixin of `XplusMtDriveSim`.

Faults (transitions 13-14: current off, 1006/1007, §12), the alarm log 1220-1239 (A23: newest in
entry 0), fault reset only once the cause is gone (transition 15), the following-error reaction
of 1085 (§13 "Register 1085"), and what the simulator injects from outside: drive faults, HV
off/on, a lost write reply, forced inputs. The register image, lock and CiA 402 glue it works
on are `xplus_mt_device.XplusMtDriveSim`'s.
"""

from __future__ import annotations

import logging

from stepper_drivers.vendors.xplus_mt import regmap as xm

from ..cia402 import slave as cia
from ..cia402.slave import FAULT, OE, QSA
from ..core.axis import HOME, LIMIT_NEG, LIMIT_POS
from ..core.motion import INF

logger = logging.getLogger(__name__)

HV_STABLE_S = 0.5               # §12 transition 3: HV present >= 500 ms before Switch On
# 'lose_write_reply': the next write of register `code` whose word has every bit of `value`
# set takes effect, but its reply is held this long: lost to a master with a shorter timeout
LOST_REPLY_HOLD_S = 2.0
INPUT_NAMES = ('home', 'limit_neg', 'limit_pos', 'I0', 'I1', 'I2', 'I3')


class XplusMtFaults:
    """The faults of one X-PLUS MT (state and lock: XplusMtDriveSim)."""

    # ------------------------------------------------------------------ faults
    def _fault(self, code: int, now: float, persistent: bool) -> None:
        """Transitions 13-14: current off at once, Fault, 1006/1007, alarm log."""
        self._log_alarm(code, now)
        self.error_register = 1
        self.error_code = code
        if persistent:
            self._fault_causes.add(code)
        self._abort_homing()
        if not self.cia.fault(cia.CURRENT_OFF):
            self.axis.motion.stop_immediately()     # a fault during the 1085 reaction
        self.cia.settle()                           # current off: stopped, 14 at once
        self._pp_moving = False
        self._pv_started = False
        self._set_point.reset()
        self._following_error = False

    def _log_alarm(self, code: int, now: float) -> None:
        seconds = int(now - self.power_on_s) & 0xFFFF
        self.alarm_log.insert(0, (seconds, code))      # A23 [R]: newest in n°0
        del self.alarm_log[xm.ALARM_LOG_ENTRIES:]

    def _fault_reset(self) -> None:
        if self._fault_causes:
            codes = ', '.join(f'0x{c:04X}' for c in sorted(self._fault_causes))
            logger.info('%s: fault reset refused, cause still present (%s)', self.name, codes)
            return
        self.error_register = 0
        self.error_code = 0
        self._following_error = False
        self.cia.fault_reset()                          # transition 15

    def _following_error_event(self, now: float) -> tuple[bool, str]:
        reaction = self._regs[1085]
        code = 0x8611
        if reaction == 17:
            return False, '1085 = 17 (motor without encoder): no following error is possible'
        if reaction == 2:
            if self.state in (OE, QSA) and self.mode == 3 and self.axis.moving:
                # §13 "Register 1085" 0x02 in PV: Fault Reaction Active while the motor coasts.
                self._log_alarm(code, now)
                self.error_register, self.error_code = 1, code
                self._abort_homing()
                self.cia.fault(cia.SLOW_DOWN_RAMP)      # on 1072 (cia_stop)
                self._pv_started = False
                return True, 'following error: FAULT REACTION ACTIVE until the motor stops'
            self._fault(code, now, persistent=False)
            return True, 'following error: FAULT (1085 = 2)'
        # 1085 = 0 or 1: no fault [R: 1007 and a log entry, 1006 stays 0]
        self._log_alarm(code, now)
        self.error_code = code
        self._following_error = True
        if reaction == 0 and self.axis.moving:
            self._abort_homing()
            self.axis.motion.stop(self._mode_decel())
            self._pp_moving = False
        return True, f'following error: status word bit 13 set (1085 = {reaction}, no fault)'

    def inject(self, kind: str, code: int, value: float) -> tuple[bool, str]:
        with self._lock:
            now = self._clock()
            self.update(now)
            if kind == 'drive_fault':
                if code not in xm.ERROR_CODES or code == 0:
                    known = ', '.join(f'0x{c:04X}' for c in xm.ERROR_CODES if c)
                    return False, f'unknown X-PLUS MT error code 0x{code:04X}; codes: {known}'
                if code == 0x8611:
                    return self._following_error_event(now)
                if code == 0x5100:
                    self.hv_present = False
                    self._hv_since = INF
                if self.state != FAULT:
                    self._fault(code, now, persistent=True)
                else:
                    self._fault_causes.add(code)
                    self._log_alarm(code, now)
                return True, (f'{self.name}: fault 0x{code:04X} '
                              f'"{xm.ERROR_CODES[code]}" active; state {self.state}')
            if kind == 'clear_fault':
                causes = self._fault_causes
                if code:
                    causes.discard(code)
                else:
                    causes.clear()
                if 0x5100 not in causes and not self.hv_present:
                    self.hv_present, self._hv_since = True, now
                return True, (f'{self.name}: causes cleared; a fault reset can now succeed'
                              if self.state == FAULT else f'{self.name}: no cause active')
            if kind == 'hv_off':
                self.hv_present, self._hv_since = False, INF
                if self.state in (OE, QSA):
                    self._fault(0x5100, now, persistent=True)
                elif self.state == FAULT:
                    self._fault_causes.add(0x5100)
                return True, f'{self.name}: HV off; state {self.state}'
            if kind == 'lose_write_reply':
                self.lose_write_reply = (int(code), int(value))
                return True, (f'{self.name}: the next write of {int(code)} with bits '
                              f'0x{int(value):04X} set takes effect, its reply is held '
                              f'{LOST_REPLY_HOLD_S:g} s')
            if kind == 'hv_on':
                if not self.hv_present:
                    self.hv_present, self._hv_since = True, now
                self._fault_causes.discard(0x5100)
                return True, (f'{self.name}: HV on; Switch On possible after '
                              f'{HV_STABLE_S * 1000:.0f} ms')
            return False, f'unknown kind {kind!r}'

    def set_input(self, name: str, value: bool, release: bool) -> tuple[bool, str]:
        with self._lock:
            self.update()
            inverted = {'I1': LIMIT_NEG, 'I2': LIMIT_POS}   # NC limit inputs: level ON = free
            target, level = name, bool(value)
            if name == 'I0':
                target = HOME
            elif name in inverted:
                target, level = inverted[name], not value
            elif name not in INPUT_NAMES:
                return False, f'unknown input {name!r}; inputs: {", ".join(INPUT_NAMES)}'
            if release:
                self.axis.release(target)
                return True, f'{self.name}: {name} released ({self.axis.inputs.get(target)})'
            self.axis.set_input(target, level)
            return True, f'{self.name}: {name} forced to {value}'
