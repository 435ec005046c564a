"""The Vector Step's modes of operation and their commands [MODES OF OPERATION].

Profile position (`move_to`), the AEC JOG velocity mode (`JogMode`, `set_velocity`), homing
(`start_homing`, the AEC homing bits in `_homing_state`), interpolated position (mode 7:
`start_interpolation`, which is step-wise like the rest; then the bus owner sends one point per
SYNC period, `interpolation_point`, one RxPDO4 frame) and `stop` (one frame, two during homing;
never waits). `ModeCommands` is a base of `drive.VectorStepDrive`, split from it for size: the
two work on one record, and only VectorStepDrive is made; it relies on the drive's controlword
access (`_command`, `_barrier`), on `Cia402Drive`'s `_require_enabled`/`_ensure_mode` and on the
SDO helpers of node.py.

Not here: the CiA 402 mode objects (profiles/cia402/modes.py), the power stage, the state and
the mode switch (drive.py), the TxPDO image (pdo.py). No rclpy.
"""

from __future__ import annotations

import logging

from ...contract.drive import (
    DriveError,
    Homing,
    HomingState,
    LinkError,
    Motion,
    Operation,
    State,
)
from ...profiles.cia402 import state_machine as cia402
from ...profiles.cia402.modes import HomingMode, Mode
from ...profiles.cia402.state_machine import CW_BIT_NEW_SET_POINT, CW_ENABLE_OPERATION
from . import regmap as vm

# the vendor's one logger (the package's name, as before the package was split into modules)
logger = logging.getLogger(__package__)

IP_START_TIMEOUT_S = 0.5       # statusword bit 12 (ip mode active) after the enable, by TxPDO
ON_THE_SPOT_METHODS = (0, 35, 37)    # no search, no speed: nothing moves


class JogMode(Mode):
    """AEC velocity mode (JOG, -1) [MODES OF OPERATION]: the manual's own mode, no CiA 402 one.
    Controlword [CONTROLWORD] bit 4 "1 = Start, 0 = Stop" (a level, not an edge), bit 5 the
    direction, bit 6 the speed taken continuously; statusword [STATUSWORD] bit 12 "1 = Motore
    fermo"."""

    code = vm.MODE_JOG
    name = vm.MODE_NAMES[vm.MODE_JOG]
    START_BIT = 'start (a level: 0 = stop)'
    SW_BIT_12 = 'motor stopped'

    def stops_by_start_bit(self, cw: int) -> bool:
        return True           # "0 = Stop": the level is written again in every case

    def run_controlword(self, reverse: bool) -> int:
        cw = CW_ENABLE_OPERATION | vm.CW_BIT_JOG_START | vm.CW_BIT_JOG_SPEED_CONTINUOUS
        return cw | vm.CW_BIT_JOG_CCW if reverse else cw   # CCW = negative counting (assumption)

    def stopped(self, sw: int) -> bool:
        """Stopped by the drive (bit 12), and the theoretical motion is over (bit 8)."""
        return bool(sw & vm.SW_BIT_JOG_STOPPED) and not sw & vm.SW_BIT_MOTOR_MOVING


class ModeCommands:
    """move_to, set_velocity, stop, start_homing and interpolated position (see the module)."""

    # ------------------------------------------------------------------ motion
    def _rps100(self, velocity_steps_s: float, index: int, sub: int, what: str) -> int:
        """A speed in the drive's unit (0.01 rev/s, always positive), checked for the object."""
        value = vm.rps100_from_hz(abs(velocity_steps_s), self.steps_per_rev)
        if velocity_steps_s and value == 0:
            raise DriveError(f"{what} {velocity_steps_s:.4g} steps/s is below the drive's "
                             f'resolution of 0.01 rev/s ({self.steps_per_rev / 100.0:g} steps/s)')
        return self._checked(index, sub, value, f'{what} {velocity_steps_s:.6g} steps/s')

    def _rps2x10(self, acceleration_steps_s2: float, index: int, what: str) -> int:
        """An acceleration in the drive's unit (0.1 rev/s^2), checked for the object."""
        value = vm.rps2x10_from_hz_s(acceleration_steps_s2, self.steps_per_rev)
        if acceleration_steps_s2 > 0 and value == 0:
            raise DriveError(f'{what} {acceleration_steps_s2:.4g} steps/s^2 is below the '
                             f"drive's resolution of 0.1 rev/s^2 "
                             f'({self.steps_per_rev / 10.0:g} steps/s^2)')
        return self._checked(index, 0, value, f'{what} {acceleration_steps_s2:.6g} steps/s^2')

    def _profile(self, motion: Motion) -> tuple[int, int]:
        return (self._rps2x10(motion.acceleration_steps_s2, vm.PROFILE_ACCELERATION,
                              'profile acceleration'),
                self._rps2x10(motion.deceleration_steps_s2, vm.PROFILE_DECELERATION,
                              'profile deceleration'))

    def move_to(self, target_steps: int, motion: Motion) -> Operation[None]:
        target = self._checked(vm.TARGET_POSITION, 0, int(target_steps),
                               'target position [steps]')
        velocity = self._rps100(motion.velocity_steps_s, vm.PROFILE_VELOCITY, 0,
                                'profile velocity')
        if velocity == 0:
            raise DriveError('profile velocity is 0: the move would not run')
        acceleration, deceleration = self._profile(motion)
        self._require_enabled('move')
        pp = yield from self._ensure_mode(vm.MODE_PROFILE_POSITION)
        self._homing = HomingState.IDLE
        yield from self._write_once((vm.PROFILE_VELOCITY, 0, velocity),
                                    (vm.PROFILE_ACCELERATION, 0, acceleration),
                                    (vm.PROFILE_DECELERATION, 0, deceleration))
        self._target = target
        # the new-set-point handshake of CiA 402 on bits 4 / 12 [CONTROLWORD], [STATUSWORD]
        yield from pp.start(self)

    def set_velocity(self, velocity_steps_s: float, motion: Motion) -> Operation[None]:
        units = self._rps100(velocity_steps_s, vm.PROFILE_VELOCITY, 0, 'velocity')
        jog = self._in_mode(vm.MODE_JOG)
        if units == 0:                        # a stop: never refused, see stop()
            if not jog or cia402.decode_state(self._read_statusword()) != \
                    State.OPERATION_ENABLED:
                self.stop()
                return
            try:
                deceleration = self._rps2x10(motion.deceleration_steps_s2,
                                             vm.PROFILE_DECELERATION, 'profile deceleration')
                yield from self._write_once((vm.PROFILE_DECELERATION, 0, deceleration))
            except DriveError as exc:         # a stop is never refused: the drive's own ramp
                if isinstance(exc, LinkError):
                    raise
                logger.warning('%sJOG stop on the deceleration 0x6084 holds: %s',
                               self._prefix(), exc)
            self._command(CW_ENABLE_OPERATION)           # bit 4 = 0: "0 = Stop"
            return
        acceleration, deceleration = self._profile(motion)
        self._require_enabled('velocity')
        jog_mode = yield from self._ensure_mode(vm.MODE_JOG)
        self._homing = HomingState.IDLE
        yield from self._write_once((vm.PROFILE_ACCELERATION, 0, acceleration),
                                    (vm.PROFILE_DECELERATION, 0, deceleration))
        cw = jog_mode.run_controlword(reverse=velocity_steps_s < 0)
        if self._cw & vm.CW_BIT_JOG_START and jog_mode.stopped(self._read_statusword()):
            # Stopped by the drive (limit switch, STOP, mode change) with bit 4 still high:
            # a low level first, so that "1 = Start" starts again.
            self._command(CW_ENABLE_OPERATION)
        self._command(cw, velocity=units)

    def stop(self, quick: bool = False) -> None:
        """One frame: JOG or interpolation bit 4 low, else the Rcmdwr STOP/ABORT bit (during
        homing and interpolation also bit 4 low, which ends the run); never waits."""
        self._ip_active = False                      # no more interpolation points after this
        sw = self._read_statusword()
        if cia402.decode_state(sw) != State.OPERATION_ENABLED:
            return
        mode = self.modes.get(self._value(vm.MODES_OF_OPERATION_DISPLAY))
        if mode is not None and mode.stops_by_start_bit(self._cw) and not quick:
            # JOG: bit 4 = 0 is the stop, on 0x6084. IP: bit 4 = 0 disables the interpolation
            # (CiA 402; the manual has no IP column); the drive stops from its last segment (the
            # simulator on the 0x605D stop ramp).
            self._command(mode.stop_controlword(self._cw))
        else:
            # No halt bit (CW bit 8 is reserved): the AEC command register, one bit per write.
            self.link.write(vm.RCMDWR, vm.AEC_SUB, vm.RCMDWR_ABORT if quick else vm.RCMDWR_STOP)
            if self._cw & CW_BIT_NEW_SET_POINT:    # bit 4: homing start (a falling edge ends
                self._command(CW_ENABLE_OPERATION)  # the run), JOG start, PP new set-point
        if self._homing == HomingState.RUNNING:
            self._homing = HomingState.IDLE

    @property
    def min_velocity_steps_s(self) -> float:
        """0x6081 Profile velocity is in 0.01 rev/s (vm.rps100_from_hz): one unit."""
        return self.steps_per_rev / 100.0

    # ------------------------------------------------------------------ interpolated position
    @property
    def interpolation_period_s(self) -> float | None:
        """The period trajectories are streamed at: the node's SYNC period when 0x60C2 can
        take it (1..10 ms, whole ms); None: follow trajectories point to point instead."""
        sync_s = self.can.sync_period_s
        low, high = vm.IP_PERIOD_UNITS
        units = round(sync_s * 1000.0)
        if low <= units <= high and abs(units / 1000.0 - sync_s) <= 1e-9:
            return sync_s
        return None

    def start_interpolation(self, period_s: float) -> Operation[int]:
        """Interpolated position mode (7), ready for `interpolation_point` once per SYNC period;
        returns the position it holds. Sub-mode 0x60C0 = 0 (linear), period 0x60C2, mode 7
        (0x6061 confirms), controlword bit 4 and statusword bit 12 (CiA 402 "enable ip mode" /
        "ip mode active": the manual has no IP column), then both elements of the buffer 0x60C1
        = the actual position, so nothing moves. [INTERPOLATION DATA RECORD]: "Il movimento
        interpolato del drive inizia dopo aver abilitato il profilo interpolazione e aver
        scritto entrambi gli elementi del buffer": the second write starts it, and the last
        step, so that the owner's first point follows at once. From then on the drive takes
        one element per SYNC: the first point must come within two SYNC periods (EMCY FF03)."""
        self._ip_active = False
        sync_s = self.can.sync_period_s
        units = round(period_s * 1000.0)            # 0x60C2:02 = 0xFD: units of 10^-3 s
        low, high = vm.IP_PERIOD_UNITS
        if abs(period_s - sync_s) > 1e-9 or not low <= units <= high or \
                abs(units / 1000.0 - period_s) > 1e-9:
            raise DriveError(f'interpolation period {period_s:g} s: can.sync_period_s '
                             f'({sync_s:g} s) must equal it, and it must be {low / 1000.0:g}..'
                             f'{high / 1000.0:g} s in whole ms (0x60C2 interpolation time '
                             f'period: ip_time_units {low}..{high}, ip_time_index 0xFD = ms)')
        self._require_enabled('interpolation')
        yield from self._write_once(
            (vm.INTERPOLATION_SUBMODE_SELECT, 0, vm.IP_SUBMODE_LINEAR),
            (vm.INTERPOLATION_TIME_PERIOD, 2, vm.IP_TIME_INDEX_MS),
            (vm.INTERPOLATION_TIME_PERIOD, 1, units))
        self._homing = HomingState.IDLE
        if self._cw & vm.CW_BIT_IP_ENABLE:       # bit 4 low first: the enable is its rise
            self._command(CW_ENABLE_OPERATION)
            yield 0.0
        ip_mode = yield from self._ensure_mode(vm.MODE_INTERPOLATED)
        sw = self._barrier()                     # the frames before are handled: at rest?
        if sw & vm.SW_BIT_MOTOR_MOVING or cia402.decode_state(sw) != State.OPERATION_ENABLED:
            raise DriveError(f'interpolation: the drive is not enabled at rest '
                             f'({cia402.describe(sw)}, statusword 0x{sw:04X}); stop it first')
        yield 0.0
        position = int(self.link.read(vm.POSITION_ACTUAL_VALUE))
        if self.link.emcy is not None and self.link.emcy.code in vm.IP_EMCY_CODES:
            self.link.emcy = None                # an earlier run's alarm
        # bit 4 up, then bit 12 from TxPDO1 as the receive thread records it (no CW->SW delay
        # first: the start must leave the owner in time for the first point, two SYNCs on)
        self._command(CW_ENABLE_OPERATION | vm.CW_BIT_IP_ENABLE)
        ok = yield from self.link.wait(lambda: ip_mode.active(self._read_statusword()),
                                       IP_START_TIMEOUT_S)
        if not ok:
            sw = self._barrier()
            if not sw & vm.SW_BIT_IP_ACTIVE:
                raise DriveError(f'{self._prefix()}statusword 0x{sw:04X} does not show bit 12 '
                                 f'(ip mode active) {IP_START_TIMEOUT_S:g} s after controlword '
                                 f'0x{self._cw:04X} in mode 7')
        for sub in (1, 2):
            yield 0.0
            self.link.write(vm.INTERPOLATION_DATA_RECORD, sub, position)
        self._ip_active = True
        logger.info('%sinterpolation started at %d steps, period %g s', self._prefix(), position,
                    period_s)
        return position

    def interpolation_point(self, position_steps: int) -> None:
        """The next position: ONE frame (RxPDO4: the controlword, 0x60C1:01), no SDO, no wait.
        The bus owner calls it once per SYNC period, best right after the SYNC: the drive takes
        one element of its two-position buffer at every SYNC (none left: EMCY FF03)."""
        value = self._checked(vm.INTERPOLATION_DATA_RECORD, 1, int(position_steps),
                              'interpolation point [steps]')
        if not self._ip_active:
            raise DriveError(f'{self._prefix()}interpolation point: no interpolation running '
                             '(start_interpolation first; a stop or an error ends it)')
        sw = self._read_statusword()
        if cia402.decode_state(sw) != State.OPERATION_ENABLED or \
                not sw & vm.SW_BIT_IP_ACTIVE or \
                self._value(vm.MODES_OF_OPERATION_DISPLAY) != vm.MODE_INTERPOLATED:
            self._ip_active = False     # (bit 12 is another mode's after a command of its own)
            emcy = self.link.emcy
            why = f'; EMCY 0x{emcy.code:04X}: {emcy.text}' \
                if emcy is not None and emcy.code in vm.IP_EMCY_CODES else ''
            raise DriveError(f'{self._prefix()}interpolation ended by the drive '
                             f'({cia402.describe(sw)}{why})')
        node = self.link.node
        if node is None or not self.link.attached:
            raise LinkError(f'{self._prefix()}not connected')
        pdo = node.rpdo[4]
        pdo[vm.CONTROLWORD].raw = self._cw
        pdo[vm.INTERPOLATION_DATA_RECORD].raw = value        # its sub 1, the only one mapped
        self.can.transactions += 1
        self.can.send(pdo.cob_id, bytes(pdo.data))

    # ------------------------------------------------------------------ homing
    def start_homing(self, homing: Homing) -> Operation[str]:
        method = int(homing.method)
        if method not in vm.HOMING_METHODS:
            raise DriveError(f'homing method {method} is not a Vector Step method '
                             f'({vm.HOMING_METHODS_TEXT})')
        search = self._rps100(homing.speed_search_steps_s, vm.HOMING_SPEEDS, 1,
                              'homing search speed')
        zero = self._rps100(homing.speed_zero_steps_s, vm.HOMING_SPEEDS, 2, 'homing zero speed')
        if method not in ON_THE_SPOT_METHODS and not (search and zero):
            raise DriveError(f'homing method {method} needs search and zero speeds > 0')
        acceleration = self._rps2x10(homing.acceleration_steps_s2, vm.HOMING_ACCELERATION,
                                     'homing acceleration')
        offset = self._checked(vm.HOME_OFFSET, 0, int(homing.offset_steps),
                               'homing offset [steps]')
        self._require_enabled('home')
        note = f'method {method}: {vm.HOMING_METHODS[method]}'
        if method not in ON_THE_SPOT_METHODS and search > zero:
            # "Deve essere una velocita' nel range di start/stop" (Rhvl 0x2055 = 0x6099:02): a
            # faster zero search ramps down after the home point and stops past it.
            end_velocity = int(self.link.read(vm.END_VELOCITY))
            if zero > end_velocity:
                past = homing.speed_zero_steps_s ** 2 / (2 * homing.acceleration_steps_s2)
                warning = (f'zero search speed 0x6099:02 (Rhvl) {zero} x 0.01 rev/s is above '
                           f'the start/stop speed 0x6082 = {end_velocity}: the manual wants it '
                           f'within the start/stop range, so the axis stops about '
                           f'{past:.0f} steps past the home point (it still reads 0x607C '
                           'there); set 0x6082 >= 0x6099:02 or lower homing.speed_zero')
                logger.warning('%shoming: %s', self._prefix(), warning)
                note += f'; warning: {warning}'
            yield 0.0
        homing_mode = yield from self._ensure_mode(vm.MODE_HOMING)
        self.link.write(vm.HOMING_METHOD, 0, method)          # raw AEC number, not the library's
        yield 0.0
        yield from self._write_once((vm.HOMING_SPEEDS, 1, search), (vm.HOMING_SPEEDS, 2, zero),
                                    (vm.HOMING_ACCELERATION, 0, acceleration))
        self.link.write(vm.HOME_OFFSET, 0, offset)             # position forced after homing
        yield 0.0
        if self.link.emcy is not None and self.link.emcy.code in vm.HOME_ERROR_CODES:
            self.link.emcy = None
        yield from homing_mode.start(self)       # bit 4 rising edge starts, then _homing_started
        if offset:
            note += f'; position after homing {offset} steps (0x607C)'
        return note

    def _homing_started(self, mode: HomingMode) -> None:
        """The manual ties no "not started" meaning to bits 13/12/10 (bit 10 during homing is
        not documented): no check; the statusword by SDO returns once the drive has handled the
        start edge."""
        self._homing = HomingState.RUNNING
        self._barrier()

    def _homing_state(self, sw: int, mode: int, standing: bool) -> HomingState:
        """AEC homing bits: 12 "Home eseguito", 13 "Errore in azzeramento" ([STATUSWORD]).

        Unlike the CiA table, attained does not wait for bit 10: the manual ties no meaning to
        bit 10 during homing. It waits for the axis to stand (bit 8 "Motor moving" off) with
        its position read after that statusword (`standing`): the position homing ends on (a
        zero search faster than the start/stop speed stops past the home point).
        """
        if self._homing != HomingState.RUNNING:
            return self._homing
        if mode == vm.MODE_HOMING:
            if sw & vm.SW_BIT_HOMING_ERROR:
                self._homing = HomingState.ERROR
            elif sw & vm.SW_BIT_HOMING_ATTAINED:
                if standing:
                    self._homing = HomingState.ATTAINED
            elif not sw & vm.SW_BIT_MOTOR_MOVING and sw & cia402.SW_BIT_TARGET_REACHED and \
                    not self._cw & CW_BIT_NEW_SET_POINT:
                self._homing = HomingState.IDLE       # interrupted
        elif cia402.decode_state(sw) != State.OPERATION_ENABLED:
            self._homing = HomingState.IDLE
        return self._homing
