"""Interpolated position (mode 7) of a simulated AEC Vector Step: a mixin of
`vector_step.device.VectorStepDriveSim`.

[INTERPOLATION SUBMODE SELECT] .. [INTERPOLATION DATA CONFIGURATION]: the two-position buffer
0x60C1 (filled by SDO or RxPDO), the start once IP is enabled and both elements are written, one
linear segment per SYNC (`ip_on_sync`, called by the PDO engine's `on_sync`) over the period of
0x60C2, and the EMCYs FF03 (underflow), FF04/FF05 (SYNC early/late). The object dictionary, axis,
CiA 402 state and fault reaction it works on are VectorStepDriveSim's; not here: the other modes
(modes.py), the SYNC itself (pdo.py).
"""

from __future__ import annotations

import collections
import logging
import math

from canopen.sdo.exceptions import SdoAbortedError
from stepper_drivers.vendors.vector_step import regmap as vm

from ..cia402.slave import OE
from ..core.axis import LIMIT_NEG, LIMIT_POS

logger = logging.getLogger(__name__)

# Interpolated position: each SYNC is expected one period of 0x60C2 after the one before, on a
# grid that follows the SYNCs' phase (each one moves it by IP_SYNC_PHASE_GAIN of its error); a
# SYNC more than IP_SYNC_TOLERANCE_PERIODS periods before its time is "too early" (FF04), after
# it "too late" (FF05). The manual gives no tolerance: the simulator's choice. A grid instead of
# the distance to the previous SYNC: a master whose period is off by more than a quarter drifts
# off it within a few dozen SYNCs, while one SYNC late and the next on time is no alarm (a
# python-can thread on a loaded 2-core machine: 14 ms late at a 10 ms period measured here,
# 20 ms and more now and then). Measured on the frames' receive stamps.
IP_SYNC_TOLERANCE_PERIODS = 5.0
IP_SYNC_PHASE_GAIN = 0.05


class VectorStepInterpolation:
    """Interpolated position of one Vector Step (state: VectorStepDriveSim)."""

    def _ip_reset(self) -> None:
        """End of an interpolation (IP disabled, mode or state left, a stop, a fault): the
        buffer is emptied, so a new start needs both elements written again."""
        self.ip_buffer: collections.deque[int] = collections.deque()
        self.ip_written: set[int] = set()  # sub-indexes of 0x60C1 written since
        self.ip_enabled = False            # CW bit 4 rising edge seen in OE, mode 7
        self.ip_started = False            # ... and both buffer elements written
        self.ip_sync_expected: float | None = None   # when the next SYNC is due (stamp clock)

    def _ip_period_s(self) -> float:
        """0x60C2: ip_time_units x 10^ip_time_index s (index 0xFD = -3, as an INTEGER8)."""
        units = self._stored(vm.INTERPOLATION_TIME_PERIOD, 1)
        index = self._stored(vm.INTERPOLATION_TIME_PERIOD, 2)
        return units * 10.0 ** (index - 256 if index > 127 else index)

    def _ip_write(self, sub: int, value: int) -> None:
        """0x60C1:01/02 by SDO or RxPDO: one target into the two-position buffer, first in first
        out (0x60C4:03 buffer_organisation 0). A full buffer refuses it (the manual is silent:
        keeping the queued points is the simulator's choice); so does a cleared one (0x60C4:06)."""
        if not self.ip_access:
            raise SdoAbortedError(vm.ABORT_DEVICE_STATE)
        if len(self.ip_buffer) >= vm.IP_BUFFER_SIZE:
            logger.info('%s: interpolation buffer full: 0x60C1:%02X = %d refused', self.name, sub,
                        value)
            raise SdoAbortedError(vm.ABORT_DEVICE_STATE)
        self.ip_buffer.append(value)
        self.ip_written.add(sub)

    def _ip_configure(self, sub: int, value: int) -> None:
        """0x60C4:06 buffer access: disabled clears the buffer; other sub-indexes: stored."""
        if sub == 6:
            self.ip_access = value == vm.IP_BUFFER_ENABLE
            if not self.ip_access:    # "Cancello il buffer (accesso al buffer disabilitato)"
                self.ip_buffer.clear()
                self.ip_written.clear()

    def _interpolation_control(self, rising: bool, enable: bool) -> None:
        """CW bit 4 in mode 7 (CiA 402 "enable ip mode"; the manual's [CONTROLWORD] has no IP
        column). A rising edge enables; the motion starts "dopo aver abilitato il profilo
        interpolazione e aver scritto entrambi gli elementi del buffer" [INTERPOLATION DATA
        RECORD], at the next SYNC. Bit 4 low ends it: the axis stops on the stop ramp (0x605D,
        as Rcmdwr STOP; the manual is silent) and the buffer is emptied."""
        if not enable:
            if self.ip_enabled:
                logger.info('%s: interpolation disabled (controlword bit 4 = 0)', self.name)
                self._ip_reset()
                if self.axis.moving:
                    self.axis.motion.stop(self._stop_deceleration())
            return
        if rising:
            self.ip_enabled = True
        if self.ip_enabled and not self.ip_started and self.ip_written >= {1, 2}:
            self.ip_started = True
            logger.info('%s: interpolation starts (buffer %s, period %g ms)', self.name,
                        list(self.ip_buffer), self._ip_period_s() * 1e3)

    def ip_on_sync(self, stamp_s: float) -> None:
        """A SYNC in interpolated position mode (stamp_s: its receive time): check its time
        against the period of 0x60C2 (FF04 too early, FF05 too late), take the next buffer
        element (none: FF03) and run the linear segment to it."""
        if not self.ip_started or self.state != OE or self.mode != vm.MODE_INTERPOLATED:
            return
        period_s = self._ip_period_s()
        expected = self.ip_sync_expected
        self.ip_sync_expected = stamp_s + period_s
        if expected is not None:
            error_s = stamp_s - expected
            tolerance_s = IP_SYNC_TOLERANCE_PERIODS * period_s
            if abs(error_s) > tolerance_s:
                code = vm.EMCY_IP_SYNC_EARLY if error_s < 0 else vm.EMCY_IP_SYNC_LATE
                self._ip_alarm(code, f'SYNC {abs(error_s) * 1e3:.1f} ms '
                               f'{"before" if error_s < 0 else "after"} its time (period '
                               f'{period_s * 1e3:g} ms, tolerance {tolerance_s * 1e3:g} ms)')
                return
            self.ip_sync_expected = expected + period_s + IP_SYNC_PHASE_GAIN * error_s
        if not self.ip_buffer:
            self._ip_alarm(vm.EMCY_IP_NO_DATA, 'buffer empty at a SYNC')
            return
        self._ip_segment(float(self.ip_buffer.popleft()), period_s)

    def _ip_segment(self, point: float, period_s: float) -> None:
        """Linear interpolation: from where the axis is to `point` at constant speed, arriving
        one period later, resting there if the next SYNC is late. No ramps of 0x6083/0x6084: the
        interpolator is the position demand (CiA 402), and the manual has no IP limit objects
        (no 0x60C5/0x60C6); the axis' own maximum velocity still clamps it, as in every mode."""
        distance = point - self.axis.position_steps
        if distance == 0.0:
            if self.axis.moving:
                self.axis.motion.stop_immediately()     # on the point now
            return
        blocked = LIMIT_POS if distance > 0 else LIMIT_NEG
        if self._input(blocked):
            logger.info('%s: %s active, interpolation to %d not run', self.name, blocked, point)
            return
        self.axis.motion.move_to(point, abs(distance) / period_s, math.inf, math.inf)

    def _ip_alarm(self, code: int, why: str) -> None:
        """FF03/FF04/FF05 with the manual's data bytes. The manual names no reaction; the
        simulator treats it as the drive alarm it calls it ("Allarme interpolazione"): the
        fault reaction of Ralarmreact 0x471E, then FAULT."""
        logger.info('%s: interpolation: %s', self.name, why)
        self.nmt.emcy(code, vm.IP_EMCY_DATA)
        self._enter_fault()
