"""The Control Word [0x2A] of a simulated RD4 (§8.1.1): a mixin of `rd4.device.Rd4DriveSim`.

The new word is compared with the previous one: the level of Emergency (bit 7), the commands of
rising edges (alarm reset, save, load defaults, preset, watchdog enable), the stops of falling
edges (Stop, a released jog), then the motion a word commands (start, jog, incremental jog).
The register image, motion, limits and alarms it works on are Rd4DriveSim's; not here: the
register map, the requests, the alarms themselves.
"""

from __future__ import annotations

import logging

from stepper_drivers.vendors.rd4 import regmap as rm
from stepper_drivers.vendors.rd4.regmap import HR

logger = logging.getLogger(__name__)


class Rd4ControlWord:
    """The Control Word logic of one RD4 (state: Rd4DriveSim)."""

    # ------------------------------------------------------------------ Control Word logic
    def control_word(self, new: int) -> None:
        """§8.1.1 Control Word [0x2A]: compare with the previous value, act on edges/levels."""
        old, self.cw = self.cw, new & 0xFFFF
        self.hr[HR['CONTROL_WORD'].address] = self.cw
        rising, falling = new & ~old, old & ~new
        now = self.clock()
        if not new & rm.CW_EMERGENCY:
            self._emergency()
        self._rising_edge_commands(rising, now)
        decel = self._ramps()[1]
        self._falling_edge_stops(new, falling, decel)
        if new & rm.CW_STOP and new & rm.CW_EMERGENCY and not self.alarms:
            self._motion_command(new, rising, now, decel)

    def _emergency(self) -> None:
        """Bit 7 low: Emergency, an immediate stop (§8.1.1)."""
        if self.motion.moving or not self.alarms & rm.ALARM_EMERGENCY:
            logger.info('%s: Emergency (CW bit 7 = 0): immediate stop', self.name)
        self.raise_alarm(rm.ALARM_EMERGENCY)

    def _rising_edge_commands(self, rising: int, now: float) -> None:
        """What a rising edge commands (§8.1.1), in this order."""
        for bit, command in ((rm.CW_ALARM_RESET, self.reset_alarms),
                             (rm.CW_SAVE_PARAMETERS, self._save),
                             (rm.CW_LOAD_DEFAULT_PARAMETERS, self._load_defaults),
                             (rm.CW_PERFORM_COUNTING_PRESET, self._apply_preset),
                             # the watch dog counts from the frame that enables it
                             (rm.CW_WATCH_DOG_ENABLE, lambda: self.frame_received(now))):
            if rising & bit:
                command()

    def _falling_edge_stops(self, new: int, falling: int, decel: float) -> None:
        if falling & rm.CW_STOP and self.motion.moving:
            self.motion.stop(decel)             # §8.1.1 bit 2: stop with Deceleration [0x07]
            self.move_kind = None
        jog = new & rm.CW_JOG
        if falling & rm.CW_JOG and self.move_kind == 'jog' and jog != rm.CW_JOG_PLUS \
                and jog != rm.CW_JOG_MINUS:
            self.motion.stop(decel)             # jog released: decelerate
            self.move_kind = None

    def _motion_command(self, new: int, rising: int, now: float, decel: float) -> None:
        """The motion a word commands once Stop (bit 2) and Emergency (bit 7) are high and no
        alarm is active: jog, or a start on the edge of Start (bit 6)."""
        jog = new & rm.CW_JOG
        if jog == rm.CW_JOG:
            # §8.1.1 NOTE: Jog + and Jog - together: no motion, or stop if moving.
            if self.motion.moving:
                self.motion.stop(decel)
            self.move_kind = None
        elif jog:
            self._jog(jog, rising, now)
        elif new & rm.CW_START:
            target_changed = self.get('TARGET_POSITION') != round(
                self.motion.target_position_steps)
            if rising & rm.CW_START or (self.move_kind == 'start' and self.motion.moving
                                        and target_changed):
                self._start()                   # start on the edge; override (§8.1.1)

    def _jog(self, jog: int, rising: int, now: float) -> None:
        if self.move_kind == 'start' and self.motion.moving:
            return                              # §8.1.1 NOTE: jog ignored while positioning
        direction = 1 if jog == rm.CW_JOG_PLUS else -1
        lo, hi = self.limits
        acc, dec = self._ramps()
        speed = self._speed('JOG_SPEED')
        if self.cw & rm.CW_INCREMENTAL_JOG:
            if rising & jog:                    # one step of Jog step length per rising edge
                step = direction * self.get('JOG_STEP_LENGTH')
                target = min(hi, max(lo, round(self.motion.target_position_steps
                                               if self.move_kind == 'step' else self.position)
                                     + step))
                self.motion.move_to(target, speed, acc, dec)
                self.move_kind = 'step'
            return
        if self.move_kind == 'jog' and not rising & jog:
            return      # a held jog: a new Jog speed acts at the next jog (spec §10 item 21)
        # Continuous jog up to the software limit, where it stops (spec §10 item 21).
        self.motion.move_to(hi if direction > 0 else lo, speed, acc, dec)
        self.move_kind = 'jog'

    def _start(self) -> None:
        target = self.get('TARGET_POSITION')
        lo, hi = self.limits
        if not lo <= target <= hi:
            logger.info('%s: target %d outside %d..%d: Target not valid', self.name, target,
                        lo, hi)
            self.raise_alarm(rm.ALARM_TARGET_NOT_VALID)
            return
        acc, dec = self._ramps()
        self.motion.move_to(target, self._speed('WORK_SPEED'), acc, dec)
        self.move_kind = 'start'
        self.target_reached = False

    def _apply_preset(self) -> None:
        """§8.1.1 Preset / CW bit 11: the current position takes the Preset value; the SW
        limits follow from Preset and the deltas; Offset = real position - preset."""
        preset = self.get('PRESET')
        self.motion.set_position(preset)
        self.set('OFFSET', round(self.motion.raw_position_steps - preset))
        logger.info('%s: preset: position := %d', self.name, preset)

    def _save(self) -> None:
        self.flash = {a: self.hr[a] for a in range(rm.MACHINE_DATA[1] + 1)}
        self.saves += 1
        self._store_flash()
        logger.info('%s: parameters saved (%d)', self.name, self.saves)

    def _load_defaults(self) -> None:
        offset = self.get('OFFSET')
        defaults = rm.defaults(self.model)
        for a in range(rm.MACHINE_DATA[1] + 1):
            self.hr[a] = defaults[a]
        self.set('OFFSET', offset)             # Offset is derived, not a default (§10 list)
        self._machine_data_changed()
        logger.info('%s: default parameters loaded (not saved)', self.name)
