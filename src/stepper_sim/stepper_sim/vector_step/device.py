"""Vector Step simulator, the AEC drive application: the base class of VectorStepNode.

The CiA 402 state machine, statusword state bits and PP handshake are the shared device-side
`cia402_device` (profile VECTOR_STEP); this adds what the Vector Step does around them: option
codes 0x605A-0x605C read from the object dictionary, Ralarmreact 0x471E as the fault reaction,
STO for transition 2, the modes (profile position with one buffered set-point, AEC JOG -1,
homing with the manual's methods on a SimAxis: BLS/FLS limit switches, TOP = encoder index;
0x607C forced after homing), Rcmdwr STOP/ABORT/DISABLE, drive alarms with EMCY 0x5400, the
error register 0x1001, history 0x1003 (2 entries) and 0x603F, the manual's fault reset procedure
([SEGNALAZIONE DI ERRORE]), save/load through Rloadsav 0x20C2, and the DSP-402/AEC object values
read over SDO/PDO.

Operating modes: `_run_mode` dispatches on 0x6060 (1 PP, 6 homing, -1 JOG, 7 interpolated
position). Mode 7 [INTERPOLATION SUBMODE SELECT] .. [INTERPOLATION DATA CONFIGURATION]: the
two-position buffer 0x60C1 (filled by SDO or RxPDO), the start once IP is enabled and both
elements are written, one linear segment per SYNC (`ip_on_sync`, called by vector_step_pdo's
`on_sync`) over the period of 0x60C2, and the EMCYs FF03 (underflow), FF04/FF05 (SYNC early/late).

One file: one drive application; modes, alarms and storage all read and write the same object
dictionary, CiA 402 state and SimAxis (NMT, SDO and PDO are apart in vector_step_nmt/_sdo/_pdo).
"""

from __future__ import annotations

import collections
import functools
import json
import logging
import math
import pathlib
import struct
import time
from typing import Any, Generator

from canopen.objectdictionary import ODVariable
from canopen.sdo.exceptions import SdoAbortedError
from stepper_drivers.vendors.vector_step import regmap as vm

from ..cia402 import slave as cia
from ..core.axis import HOME, INDEX, LIMIT_NEG, LIMIT_POS, AxisEvent, HomingRun, SwitchMethod
from .nmt import NMT_OPERATIONAL, NMT_PRE_OPERATIONAL, NMT_STOPPED

logger = logging.getLogger(__name__)

SAVE_TIME_S = 0.15                   # Rloadsav 0x81 busy time (EEPROM write)
DEFAULT_MAX_TRAVEL_STEPS = 50 * 3200
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

# The CiA 402 state machine, statusword state bits and PP handshake: cia402_device (VECTOR_STEP).
NRTSO, SOD, RTSO, SO, OE = cia.NRTSO, cia.SOD, cia.RTSO, cia.SO, cia.OE
QSA, FRA, FAULT = cia.QSA, cia.FRA, cia.FAULT
SW_WARNING, SW_INTERNAL_LIMIT = cia.SW_WARNING, cia.SW_INTERNAL_LIMIT
SW_TARGET_REACHED, SW_BIT12 = cia.SW_TARGET_REACHED, cia.SW_BIT12

# Registers stored by Rloadsav 0x81 (the SAVE note) that this simulator keeps.
SAVED_REGISTERS = (vm.RHMAXSPC, vm.RHPOS, 0x2051, vm.RCANBAUD, vm.RCANADDR, vm.RSTRTMODE,
                   vm.RSTPRES, vm.RSTRMODEOFOPERATION, vm.RALARMREACT, vm.RALMBUFFRES, 0x4801)


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


class VectorStepDriveSim:
    """The AEC drive application of one node, the base class of VectorStepNode.

    VectorStepNode creates what this works on (`od`, `local`, `axis`, `cfg`, `sim`, `eeprom`,
    the fault-injection flags) and the CANopen parts it reports through: `nmt` (EMCY, boot-up,
    the SYNC watchdog), `sdo` (its COB-IDs), `pdo` (the TxPDOs of each cycle).
    """

    # --- Object dictionary: LocalNode's stored values, else the EDS defaults -------------------
    def _obj(self, index: int, sub: int) -> ODVariable:
        obj = self.od[index]
        if isinstance(obj, ODVariable):
            if sub != 0:
                raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)
            return obj
        if sub not in obj.subindices:
            raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)
        return obj.subindices[sub]

    def _stored(self, index: int, sub: int = 0) -> Any:
        obj = self._obj(index, sub)
        raw = self.local.data_store.get(index, {}).get(sub)
        if raw is None:
            return obj.value if obj.value is not None else obj.default
        return obj.decode_raw(raw)

    def _store(self, index: int, sub: int, value: Any) -> None:
        obj = self._obj(index, sub)
        self.local.data_store.setdefault(index, {})[sub] = obj.encode_raw(value)

    def _power_on_state(self) -> None:
        """Application state after power-on or NMT reset node."""
        self.local.data_store.clear()
        for key, value in self.eeprom.items():
            index = int(key, 16)
            self._store(index, vm.AEC_SUB, value)
        self.axis.motion.stop_immediately()
        self.axis.set_position(0.0)       # the position counter restarts at 0 (not homed)
        self.cia = cia.PowerStateMachine(cia.VECTOR_STEP, self, self.name, NRTSO)
        start_mode = self._stored(vm.RSTRMODEOFOPERATION, vm.AEC_SUB)
        self.mode = start_mode if start_mode in vm.MODES else vm.MODE_PROFILE_POSITION
        self._store(vm.MODES_OF_OPERATION, 0, self.mode)
        self.cw_prev = 0
        self.alarms = 0                   # Ralarm32 latched
        self.warnings = 0
        self.history: list[int] = []
        self.error_code = 0
        self.comm_error = False
        self.homing: HomingRun | None = None
        self.homing_result = ''           # '', 'attained', 'error', 'interrupted'
        self.rhsts = 0
        self.homed = False
        self.home_error_latched = False
        self.set_point = cia.SetPointHandshake(cia.VECTOR_STEP.set_point_buffer)
        self.pp_target: float | None = None
        self.jog_running = False
        self.jog_inhibit = False
        self.jog_velocity_hz = 0.0
        self._ip_reset()
        self.ip_access = True             # 0x60C4:06: buffer access enabled (simulator's choice)
        self.rcmdrd = 0
        self.loadsav_busy: tuple[int, float] | None = None
        self.loadsav_last = 0
        self.reepsts = 0
        self.nmt.power_on()
        self.sdo.power_on()
        self.cia.force(SOD)               # transition 1 (automatic)

    @property
    def steps_per_rev(self) -> float:
        return float(self.cfg.full_steps_per_rev * self._stored(vm.RSTPRES, vm.AEC_SUB))

    def _hz(self, rps100: int) -> float:
        return vm.hz_from_rps100(rps100, self.steps_per_rev)

    def _hz_s(self, rps2x10: int) -> float:
        return vm.hz_s_from_rps2x10(rps2x10, self.steps_per_rev)

    def _on_read_device(self, index: int, subindex: int, od: ODVariable) -> Any:
        """The value of a DSP-402/AEC object the drive keeps (after SdoServer's checks); None:
        the stored one."""
        if 0x2000 <= index <= 0x5FFF and subindex != vm.AEC_SUB:
            return None                      # sub 0 of an AEC register: the number of axes
        if index == vm.STATUSWORD:
            return self.statusword()
        if index == vm.MODES_OF_OPERATION_DISPLAY:
            return self.mode
        if index in (vm.POSITION_ACTUAL_VALUE, vm.RPOSACT):
            return int(round(self.axis.position_steps))
        if index == vm.RPOSACTREQ:
            return int(round(self.axis.motion.target_position_steps
                             if self.axis.moving else self.axis.position_steps))
        if index in (vm.VELOCITY_ACTUAL_VALUE, vm.RVELACT):
            return vm.rps100_from_hz(self.axis.velocity_hz, self.steps_per_rev)
        if index == vm.ERROR_REGISTER:
            return self.error_register()
        if index == vm.INTERPOLATION_DATA_CONFIGURATION and subindex == 2:
            return len(self.ip_buffer)       # actual_size
        if index == vm.PRE_DEFINED_ERROR_FIELD:
            if subindex == 0:
                return len(self.history)
            if subindex > len(self.history):     # "present only if errors occurred"
                raise SdoAbortedError(vm.ABORT_NO_DATA)
            return self.history[subindex - 1]
        if index == vm.ERROR_CODE:
            return self.error_code
        if index == vm.DIGITAL_INPUTS:
            return (self._input(LIMIT_NEG) | self._input(LIMIT_POS) << 1
                    | self._input(HOME) << 2)
        if index == vm.RSTSFLG:
            return self.rstsflg()
        if index == vm.RSTSFLG1:
            value = vm.RSTSFLG1_STO if self.power_stage_blocked else 0
            if self.rcmdrd & vm.RCMDWR_STOP:
                value |= 1 << 3              # b3 "STOP in esecuzione"
            if self._input(LIMIT_NEG):
                value |= 1 << 7              # b7 BLS
            if self._input(LIMIT_POS):
                value |= 1 << 8              # b8 FLS
            return value
        if index == vm.RHSTS:
            return self.rhsts
        if index == vm.RALARM:
            return self.alarms & 0xFFFF
        if index == vm.RALARM32:
            return self.alarms
        if index == vm.RWARNING:
            return self.warnings & 0xFFFF
        if index == vm.RWARNING32:
            return self.warnings
        if index == vm.REEPSTS:
            return self.reepsts
        if index == vm.RLOADSAV:
            return self.loadsav_busy[0] if self.loadsav_busy else 0
        if index == vm.RCMDRD:
            return self.rcmdrd
        if index == vm.RCANMODEOFOPERATION:
            return self.mode & 0xFFFF
        if index == vm.RHMODE:
            return self._stored(vm.HOMING_METHOD)
        if index == vm.RHPOS:
            return self._stored(vm.HOME_OFFSET)
        if index == vm.RROTSW:
            return self.id % 100
        if index == vm.RCANSTS:
            red = 0b0101 if self.nmt.sync_error else 0b0100 if self.comm_error else 0
            green = {NMT_PRE_OPERATIONAL: 0b0001, NMT_STOPPED: 0b0010,
                     NMT_OPERATIONAL: 0b0101}.get(self.nmt_state, 0)
            return red | green << 4
        if index == vm.IDENTITY_OBJECT and subindex == 1:
            return self.cfg.vendor_id
        if index == vm.IDENTITY_OBJECT and subindex == 2:
            return self.cfg.product_code
        if index == vm.IDENTITY_OBJECT and subindex == 4:
            return self.cfg.serial_number or 10000 + self.id
        if index == vm.MANUFACTURER_DEVICE_NAME:
            return self.cfg.device_name
        return None

    def error_register(self) -> int:
        value = 0
        if self.state in (FAULT, FRA) or self.home_error_latched or self.history:
            value |= vm.ERROR_REGISTER_GENERIC
        if self.comm_error:
            value |= vm.ERROR_REGISTER_COMMUNICATION
        return value

    def raise_alarm(self, bits: int) -> None:
        """A drive alarm (Ralarm32 bits): EMCY 0x5400, fault reaction, FAULT."""
        self.alarm_causes |= bits
        self.alarms |= bits
        self.nmt.emcy(vm.EMCY_POWER_STAGE, struct.pack('<I', self.alarms))
        self._enter_fault()

    def _enter_fault(self) -> None:
        """Transition 13 with the reaction of Ralarmreact 0x471E (spec §12 A2)."""
        if self.state in (FAULT, FRA):
            return
        self.homing_abort(interrupted=False)
        self.jog_running = False
        self._ip_reset()
        react = self._stored(vm.RALARMREACT, vm.AEC_SUB)
        immediate = react in (-1, 0) or (react == -4 and any(
            self.alarms & (1 << b) for b in vm.RALARM_IMMEDIATE_BITS))
        if immediate:
            ramp = cia.CURRENT_OFF                         # current off: uncontrolled stop
        elif react in (-2, 1):
            ramp = cia.SLOW_DOWN_RAMP
        else:                                              # -4, -3, 2: emergency ramp
            ramp = cia.QUICK_STOP_RAMP
        self.cia.fault(ramp)

    def _try_fault_reset(self) -> None:
        """Transition 15 on a bit-7 rising edge, as the manual's procedure allows it."""
        if self.alarm_causes:
            logger.info('%s: fault reset refused: cause still present (Ralarm32 0x%08X)',
                        self.name, self.alarm_causes)
            return
        if self.cfg.strict_fault_reset and self.history:
            logger.info('%s: fault reset refused: 0x1003:00 = %d, the manual writes 0 first',
                        self.name, len(self.history))
            return
        self.alarms = 0
        self.cia.fault_reset()
        self.nmt.emcy(vm.EMCY_NO_ERROR)
        logger.info('%s: fault reset -> SWITCH ON DISABLED', self.name)

    def statusword(self) -> int:
        sw = self.cia.state_word(voltage_enabled=not self.power_stage_blocked)
        if self.warnings:
            sw |= SW_WARNING
        if self.axis.moving:
            sw |= vm.SW_BIT_MOTOR_MOVING
        if self._input(LIMIT_NEG) or self._input(LIMIT_POS):
            sw |= SW_INTERNAL_LIMIT
        at_rest = not self.axis.moving
        if self.mode == vm.MODE_PROFILE_POSITION:
            if self.set_point.target_reached(self.axis.moving):
                sw |= SW_TARGET_REACHED
            if self.set_point.acknowledged:
                sw |= SW_BIT12
        elif self.mode == vm.MODE_HOMING:
            sw |= cia.homing_bits(attained=self.homing_result == 'attained',
                                  error=self.homing_result == 'error',
                                  running=self.homing is not None, moving=self.axis.moving)
        elif self.mode == vm.MODE_JOG:
            if self.axis.velocity_hz == 0.0:
                sw |= SW_BIT12                # "1 = Motore fermo"
            if not self.axis.motion.in_ramp:
                sw |= SW_TARGET_REACHED
        elif self.mode == vm.MODE_INTERPOLATED:
            # The manual's [STATUSWORD] has no IP column: CiA 402's bit 12 "ip mode active" and
            # bit 10 target reached (at rest on the last point)
            if self.ip_enabled:
                sw |= vm.SW_BIT_IP_ACTIVE
            if at_rest:
                sw |= SW_TARGET_REACHED
        else:
            if at_rest:
                sw |= SW_TARGET_REACHED
        return sw

    def rstsflg(self) -> int:
        value = 0
        if self.state == OE:
            value |= vm.RSTSFLG_ENABLED | vm.RSTSFLG_CURRENT_ON
        if self.state in (FAULT, FRA):
            value |= vm.RSTSFLG_ALARM
        if self.homed:
            value |= vm.RSTSFLG_HOMED
        if self.axis.moving:
            value |= vm.RSTSFLG_MOVING
        elif self.state == OE:
            value |= vm.RSTSFLG_IN_POSITION
        if self.home_error_latched:
            value |= vm.RSTSFLG_HOME_ERROR
        if self.homing is not None:
            value |= vm.RSTSFLG_HOME_IN_PROGRESS
        if self.axis.velocity_hz < 0:
            value |= 1 << 13
        return value

    def _input(self, name: str) -> bool:
        try:
            return self.axis.input(name)
        except KeyError:
            return False

    def process(self) -> None:
        """One application cycle: motion time, controlword, modes, pending transitions."""
        now = time.monotonic()
        self.axis.update(now)
        mode = self._stored(vm.MODES_OF_OPERATION)
        if mode != self.mode:
            self._change_mode(mode)
        cw = self._stored(vm.CONTROLWORD)
        prev, self.cw_prev = self.cw_prev, cw
        if self.cia.fault_reset_edge(cw, prev):
            self._try_fault_reset()
        self.cia.apply(cw)
        if self.state == OE:
            self._run_mode(cw, prev)
        self._settle(now)
        self.pdo.tpdo_check(now)

    @property
    def state(self) -> str:
        return self.cia.state

    @property
    def setpoint_ack(self) -> bool:
        return self.set_point.acknowledged

    def cia_allows(self, number: int) -> bool:
        if number == 2 and self.power_stage_blocked:
            return False                 # no power stage: stays SWITCH ON DISABLED
        return True

    def cia_moving(self) -> bool:
        return self.axis.moving

    def cia_option_code(self, transition: int) -> int:
        index = {5: vm.DISABLE_OPERATION_OPTION_CODE, 8: vm.SHUTDOWN_OPTION_CODE,
                 11: vm.QUICK_STOP_OPTION_CODE}[transition]
        return self._stored(index)

    def cia_stop(self, ramp: str, transition: int) -> None:
        motion = self.axis.motion
        if ramp == cia.CURRENT_OFF:
            motion.stop_immediately()            # current off
            return
        dec = self._hz_s(self._stored(vm.PROFILE_DECELERATION))
        qdec = self._hz_s(self._stored(vm.QUICK_STOP_DECELERATION))
        if transition == 11:
            motion.quick_stop(qdec if ramp == cia.QUICK_STOP_RAMP else dec)
        elif ramp == cia.QUICK_STOP_RAMP:
            motion.quick_stop(qdec)
        else:
            motion.stop(dec)

    def cia_leaving(self, number: int, source: str, target: str) -> None:
        if number in (4, 16):
            self.jog_running = False
            self.jog_inhibit = False
            self.set_point.reset()
            self._ip_reset()
            if number == 4:
                self.axis.motion.stop_immediately()
            return
        self.homing_abort(interrupted=True)
        self.jog_running = False
        self.set_point.queued = None
        self._ip_reset()

    def cia_left(self, number: int, source: str, target: str) -> None:
        pass

    def _settle(self, now: float) -> None:
        moving = self.axis.moving
        self.cia.settle()
        if self.rcmdrd and not moving:
            self.rcmdrd = 0
        if self.mode == vm.MODE_PROFILE_POSITION and self.state == OE and not moving \
                and self.set_point.queued is not None:
            self._start_move(self.set_point.take_queued())

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

    # --- Interpolated position (7) -------------------------------------------------------------
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

    def _rcmdwr(self, value: int) -> None:
        if value == vm.RCMDWR_STOP:
            self.homing_abort(interrupted=True, deceleration_hz_s=self._stop_deceleration())
            self.jog_running = False
            self.jog_inhibit = True
            self.set_point.queued = None
            self._ip_reset()
            if self.axis.moving:
                self.axis.motion.stop(self._stop_deceleration())
                self.rcmdrd = vm.RCMDWR_STOP
        elif value == vm.RCMDWR_ABORT:
            qdec = self._hz_s(self._stored(vm.QUICK_STOP_DECELERATION))
            self.homing_abort(interrupted=True, deceleration_hz_s=qdec)
            self.jog_running = False
            self.jog_inhibit = True
            self.set_point.queued = None
            self._ip_reset()
            if self.axis.moving:
                self.axis.motion.quick_stop(qdec)
                self.rcmdrd = vm.RCMDWR_ABORT
        elif value == 1 and self.state in (OE, QSA, SO, RTSO):   # DISABLE DRIVE
            self.axis.motion.stop_immediately()
            self.cia.force(SOD)
        elif value:
            logger.info('%s: Rcmdwr %s not simulated', self.name,
                        vm.bit_texts(value, vm.RCMDWR_BITS))

    def _rloadsav(self, code: int) -> None:
        now = time.monotonic()
        if code == 0:
            return
        if code == vm.RLOADSAV_RESTART[1] and self.loadsav_last == vm.RLOADSAV_RESTART[0]:
            logger.info('%s: Rloadsav 142-143: restart', self.name)
            self._power_on_state()
            self.nmt.reset_communication()
            self.nmt.boot(self.sim.reboot_delay_s)
            return
        self.loadsav_last = code
        if code == vm.RLOADSAV_SAVE_REGISTERS:
            self.loadsav_busy = (code, now + SAVE_TIME_S)
            self.reepsts = vm.REEPSTS_BUSY
            self.sim.wake()
        elif code == vm.RLOADSAV_LOAD_REGISTERS:
            for key, value in self.eeprom.items():
                self._store(int(key, 16), vm.AEC_SUB, value)
            self.reepsts = 0
        elif code == vm.RLOADSAV_RESET_REGISTERS:
            for index in SAVED_REGISTERS:
                self.local.data_store.pop(index, None)
            self.reepsts = 0
        elif 0x01 <= code <= 0x0C or 0x82 <= code <= 0x9A:
            logger.info('%s: Rloadsav %d accepted (not simulated)', self.name, code)
            self.reepsts = 0
        else:
            self.reepsts = vm.REEPSTS_INVALID_COMMAND

    def _finish_save(self) -> None:
        self.loadsav_busy = None
        if self.nvram_fault:
            self.reepsts = 1 << 3                # "Errore in scrittura registri"
            self.nmt.emcy(vm.EMCY_NVRAM, struct.pack('<H', self.reepsts))
            return
        self.eeprom = {f'0x{index:04X}': self._stored(index, vm.AEC_SUB)
                       for index in SAVED_REGISTERS}
        path = self._eeprom_path()
        if path is not None:
            path.write_text(json.dumps({'node_id': self.id, 'registers': self.eeprom},
                                       indent=1))
        self.reepsts = 0
        logger.info('%s: registers saved to EEPROM%s', self.name,
                    f' ({path})' if path else '')

    def _eeprom_path(self) -> pathlib.Path | None:
        if not self.sim.storage_dir:
            return None
        return pathlib.Path(self.sim.storage_dir) / f'vector_step_node{self.id}.json'

    def _load_eeprom(self) -> None:
        path = self._eeprom_path()
        self.eeprom = {f'0x{vm.RSTPRES:04X}': self.cfg.step_resolution}
        if path is not None and path.exists():
            self.eeprom.update(json.loads(path.read_text())['registers'])

    def _on_write_device(self, index: int, subindex: int, value: Any) -> None:
        """Checks and side effects of a write to a DSP-402 or AEC object (after SdoServer's)."""
        if index == vm.MODES_OF_OPERATION and value not in vm.MODES:
            raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
        elif index in (vm.HOMING_METHOD, vm.RHMODE):
            if value not in vm.HOMING_METHODS:
                raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
            if index == vm.RHMODE:
                self._store(vm.HOMING_METHOD, 0, value)
        elif index == vm.RHPOS:
            self._store(vm.HOME_OFFSET, 0, value)
        elif index == vm.RSTSFLG:
            if value == 0:                   # "accetta solo il valore 0": clears "axis homed"
                self.homed = False
        elif index in (vm.RALARM, vm.RALARM32):
            if value == 0:                   # "Per resettare gli allarmi scrivere 0"
                self.alarms &= self.alarm_causes
        elif index == vm.INTERPOLATION_DATA_RECORD:
            self._ip_write(subindex, value)
        elif index == vm.INTERPOLATION_DATA_CONFIGURATION and subindex == 6:
            self.ip_access = value == vm.IP_BUFFER_ENABLE
            if not self.ip_access:    # "Cancello il buffer (accesso al buffer disabilitato)"
                self.ip_buffer.clear()
                self.ip_written.clear()
        elif index == vm.RCMDWR:
            if value & (value - 1):          # "i bit devono essere alzati uno alla volta"
                raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
            self.sim.after(functools.partial(self._rcmdwr, value))
        elif index == vm.RLOADSAV:
            if self.loadsav_busy:
                raise SdoAbortedError(vm.ABORT_DEVICE_STATE)
            self.sim.after(functools.partial(self._rloadsav, value))
