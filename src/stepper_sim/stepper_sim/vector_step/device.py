"""Vector Step simulator, the AEC drive application: the base class of VectorStepNode.

The CiA 402 state machine, statusword state bits and PP handshake are the shared device-side
`cia402.slave` (profile VECTOR_STEP); this adds what the Vector Step does around them: option
codes 0x605A-0x605C read from the object dictionary, Ralarmreact 0x471E as the fault reaction,
STO for transition 2, Rcmdwr STOP/ABORT/DISABLE, drive alarms with EMCY 0x5400, the error
register 0x1001, history 0x1003 (2 entries) and 0x603F, the manual's fault reset procedure
([SEGNALAZIONE DI ERRORE]), and the DSP-402/AEC object values read over SDO/PDO (`_READS`) and
the checks and side effects of their writes (`_WRITES`).

Along the drive's own seams, mixins hold the rest: `modes` (0x6060 changes and `_run_mode`'s
dispatch: 1 PP with one buffered set-point, -1 AEC JOG; the quick stop at a limit switch),
`homing` (6: the manual's methods on a SimAxis: BLS/FLS limit switches, TOP = encoder index;
0x607C forced after homing), `interpolation` (7: the two-position buffer 0x60C1, one linear
segment per SYNC over the period of 0x60C2, EMCY FF03/FF04/FF05) and `storage` (save/load
through Rloadsav 0x20C2). All of them read and write the same object dictionary, CiA 402 state
and SimAxis; NMT, SDO and PDO are apart (nmt.py, sdo.py, pdo.py), parts of VectorStepNode.
"""

from __future__ import annotations

import functools
import logging
import struct
import time
from typing import Any, Callable

from canopen.objectdictionary import ODVariable
from canopen.sdo.exceptions import SdoAbortedError
from stepper_drivers.vendors.vector_step import regmap as vm

from ..cia402 import slave as cia
from ..core.axis import HOME, LIMIT_NEG, LIMIT_POS
from ..core.homing import HomingRun
from .homing import AEC_HOMING_PROCEDURES, DEFAULT_MAX_TRAVEL_STEPS, VectorStepHoming
from .interpolation import (
    IP_SYNC_PHASE_GAIN,
    IP_SYNC_TOLERANCE_PERIODS,
    VectorStepInterpolation,
)
from .modes import VectorStepModes
from .nmt import NMT_OPERATIONAL, NMT_PRE_OPERATIONAL, NMT_STOPPED
from .storage import SAVE_TIME_S, SAVED_REGISTERS, VectorStepStorage

# the drive, its CiA 402 states, and what moved to the mixins' modules (importable here as before)
__all__ = ['AEC_HOMING_PROCEDURES', 'DEFAULT_MAX_TRAVEL_STEPS', 'FAULT', 'FRA',
           'IP_SYNC_PHASE_GAIN', 'IP_SYNC_TOLERANCE_PERIODS', 'NRTSO', 'OE', 'QSA', 'RTSO',
           'SAVED_REGISTERS', 'SAVE_TIME_S', 'SO', 'SOD', 'VectorStepDriveSim']

logger = logging.getLogger(__name__)

# The CiA 402 state machine, statusword state bits and PP handshake: cia402.slave (VECTOR_STEP).
NRTSO, SOD, RTSO, SO, OE = cia.NRTSO, cia.SOD, cia.RTSO, cia.SO, cia.OE
QSA, FRA, FAULT = cia.QSA, cia.FRA, cia.FAULT
SW_WARNING, SW_INTERNAL_LIMIT = cia.SW_WARNING, cia.SW_INTERNAL_LIMIT
SW_TARGET_REACHED, SW_BIT12 = cia.SW_TARGET_REACHED, cia.SW_BIT12


class VectorStepDriveSim(VectorStepModes, VectorStepHoming, VectorStepInterpolation,
                         VectorStepStorage):
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

    # --- Object values on read, checks and side effects on write (the tables _READS, _WRITES) ---
    def _on_read_device(self, index: int, subindex: int, od: ODVariable) -> Any:
        """The value of a DSP-402/AEC object the drive keeps (after SdoServer's checks); None:
        the stored one."""
        if 0x2000 <= index <= 0x5FFF and subindex != vm.AEC_SUB:
            return None                      # sub 0 of an AEC register: the number of axes
        read = _READS.get(index)
        return None if read is None else read(self, subindex)

    def _error_history(self, subindex: int) -> int:
        """0x1003: the number of errors at sub 0, the newest at sub 1."""
        if subindex == 0:
            return len(self.history)
        if subindex > len(self.history):     # "present only if errors occurred"
            raise SdoAbortedError(vm.ABORT_NO_DATA)
        return self.history[subindex - 1]

    def _digital_inputs(self) -> int:
        return self._input(LIMIT_NEG) | self._input(LIMIT_POS) << 1 | self._input(HOME) << 2

    def rstsflg1(self) -> int:
        value = vm.RSTSFLG1_STO if self.power_stage_blocked else 0
        if self.rcmdrd & vm.RCMDWR_STOP:
            value |= 1 << 3              # b3 "STOP in esecuzione"
        if self._input(LIMIT_NEG):
            value |= 1 << 7              # b7 BLS
        if self._input(LIMIT_POS):
            value |= 1 << 8              # b8 FLS
        return value

    def rcansts(self) -> int:
        red = 0b0101 if self.nmt.sync_error else 0b0100 if self.comm_error else 0
        green = {NMT_PRE_OPERATIONAL: 0b0001, NMT_STOPPED: 0b0010,
                 NMT_OPERATIONAL: 0b0101}.get(self.nmt_state, 0)
        return red | green << 4

    def _identity(self, subindex: int) -> int | None:
        """0x1018:01/02/04 from the configuration; the other sub-indexes: stored."""
        return {1: self.cfg.vendor_id, 2: self.cfg.product_code,
                4: self.cfg.serial_number or 10000 + self.id}.get(subindex)

    def _on_write_device(self, index: int, subindex: int, value: Any) -> None:
        """Checks and side effects of a write to a DSP-402 or AEC object (after SdoServer's)."""
        write = _WRITES.get(index)
        if write is not None:
            write(self, index, subindex, value)

    def _check_mode(self, index: int, sub: int, value: int) -> None:
        if value not in vm.MODES:
            raise SdoAbortedError(vm.ABORT_VALUE_RANGE)

    def _write_homing_method(self, index: int, sub: int, value: int) -> None:
        """0x6098, or Rhmode (which writes 0x6098 too)."""
        if value not in vm.HOMING_METHODS:
            raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
        if index == vm.RHMODE:
            self._store(vm.HOMING_METHOD, 0, value)

    def _write_rstsflg(self, index: int, sub: int, value: int) -> None:
        if value == 0:                   # "accetta solo il valore 0": clears "axis homed"
            self.homed = False

    def _write_ralarm(self, index: int, sub: int, value: int) -> None:
        if value == 0:                   # "Per resettare gli allarmi scrivere 0"
            self.alarms &= self.alarm_causes

    def _write_rcmdwr(self, index: int, sub: int, value: int) -> None:
        if value & (value - 1):          # "i bit devono essere alzati uno alla volta"
            raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
        self.sim.after(functools.partial(self._rcmdwr, value))

    # --- Alarms, fault reaction and fault reset -------------------------------------------------
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


# The values the drive keeps, by index: (drive, sub-index) -> value, None for the stored one.
_READS: dict[int, Callable[[VectorStepDriveSim, int], Any]] = {
    vm.STATUSWORD: lambda d, sub: d.statusword(),
    vm.MODES_OF_OPERATION_DISPLAY: lambda d, sub: d.mode,
    vm.POSITION_ACTUAL_VALUE: lambda d, sub: int(round(d.axis.position_steps)),
    vm.RPOSACT: lambda d, sub: int(round(d.axis.position_steps)),
    vm.RPOSACTREQ: lambda d, sub: int(round(d.axis.motion.target_position_steps
                                            if d.axis.moving else d.axis.position_steps)),
    vm.VELOCITY_ACTUAL_VALUE: lambda d, sub: vm.rps100_from_hz(d.axis.velocity_hz,
                                                               d.steps_per_rev),
    vm.RVELACT: lambda d, sub: vm.rps100_from_hz(d.axis.velocity_hz, d.steps_per_rev),
    vm.ERROR_REGISTER: lambda d, sub: d.error_register(),
    vm.INTERPOLATION_DATA_CONFIGURATION:
        lambda d, sub: len(d.ip_buffer) if sub == 2 else None,      # 2: actual_size
    vm.PRE_DEFINED_ERROR_FIELD: VectorStepDriveSim._error_history,
    vm.ERROR_CODE: lambda d, sub: d.error_code,
    vm.DIGITAL_INPUTS: lambda d, sub: d._digital_inputs(),
    vm.RSTSFLG: lambda d, sub: d.rstsflg(),
    vm.RSTSFLG1: lambda d, sub: d.rstsflg1(),
    vm.RHSTS: lambda d, sub: d.rhsts,
    vm.RALARM: lambda d, sub: d.alarms & 0xFFFF,
    vm.RALARM32: lambda d, sub: d.alarms,
    vm.RWARNING: lambda d, sub: d.warnings & 0xFFFF,
    vm.RWARNING32: lambda d, sub: d.warnings,
    vm.REEPSTS: lambda d, sub: d.reepsts,
    vm.RLOADSAV: lambda d, sub: d.loadsav_busy[0] if d.loadsav_busy else 0,
    vm.RCMDRD: lambda d, sub: d.rcmdrd,
    vm.RCANMODEOFOPERATION: lambda d, sub: d.mode & 0xFFFF,
    vm.RHMODE: lambda d, sub: d._stored(vm.HOMING_METHOD),
    vm.RHPOS: lambda d, sub: d._stored(vm.HOME_OFFSET),
    vm.RROTSW: lambda d, sub: d.id % 100,
    vm.RCANSTS: lambda d, sub: d.rcansts(),
    vm.IDENTITY_OBJECT: VectorStepDriveSim._identity,
    vm.MANUFACTURER_DEVICE_NAME: lambda d, sub: d.cfg.device_name,
}

# What a write does, by index: (drive, index, sub-index, value); an SdoAbortedError refuses it.
_WRITES: dict[int, Callable[[VectorStepDriveSim, int, int, Any], None]] = {
    vm.MODES_OF_OPERATION: VectorStepDriveSim._check_mode,
    vm.HOMING_METHOD: VectorStepDriveSim._write_homing_method,
    vm.RHMODE: VectorStepDriveSim._write_homing_method,
    vm.RHPOS: lambda d, index, sub, value: d._store(vm.HOME_OFFSET, 0, value),
    vm.RSTSFLG: VectorStepDriveSim._write_rstsflg,
    vm.RALARM: VectorStepDriveSim._write_ralarm,
    vm.RALARM32: VectorStepDriveSim._write_ralarm,
    vm.INTERPOLATION_DATA_RECORD: lambda d, index, sub, value: d._ip_write(sub, value),
    vm.INTERPOLATION_DATA_CONFIGURATION:
        lambda d, index, sub, value: d._ip_configure(sub, value),
    vm.RCMDWR: VectorStepDriveSim._write_rcmdwr,
    vm.RLOADSAV: VectorStepDriveSim._write_rloadsav,
}
