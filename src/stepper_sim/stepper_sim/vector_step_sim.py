"""Simulated AEC Vector Step drives on a real CAN stack: canopen.LocalNode + what it lacks.

One `VectorStepSim` is one CAN bus (python-can; the loopback socketcand broker in tests) with one
or more `VectorStepNode`s. Each node is a `canopen.LocalNode` built from config/vector_step.eds
(the same file the driver loads), plus the parts LocalNode does not have (transports.md A5.3):
  - NMT slave: boot-up after power-on and after NMT reset node/communication (with a reboot
    delay and 10 ms between boot-up and the first heartbeat), heartbeat producer (0x1017),
    node guarding (a 0-byte frame on 0x700+ID counts as the RTR socketcand cannot carry), life
    guarding and consumer heartbeat (0x1016) with EMCY 0x8130 (and no other reaction: the
    manual ties none to them but the LED); SDO refused in STOPPED,
  - the SYNC watchdog: with 0x1006 (communication cycle period, us) not 0, no SYNC for that long
    (counted from the write of 0x1006 or the last SYNC) is the drive alarm "Mancanza Sync"
    (Ralarm32 bit 18, Rcansts "Sync error") with the alarm reaction of Ralarmreact 0x471E; the
    cause is gone with the next SYNC (or 0x1006 = 0, an NMT reset communication),
  - a PDO engine: the master's (re)mapping honoured after every SDO write, TxPDOs on change,
    on their event timer (re-armed at every event), spaced by the inhibit time, on SYNC (types
    0..240) or on request (252/253), RxPDOs into the object dictionary, applied at once (254/255)
    or at the next SYNC (0..240), EMCY 0x8210/0x8220 on a length error,
  - SDO checks LocalNode leaves out: value ranges from the EDS, sub-index existence, the
    manual's abort codes (0x1005/0x1014 bits 29/30, 0x1016 duplicates, PDO mapping),
  - the application: a CiA 402 state machine of its own (the shared cia402 module only gives
    the controlword command masks), profile position (absolute/relative, change set
    immediately, one buffered set-point), AEC JOG velocity mode (-1), homing with the manual's
    methods on a SimAxis (BLS/FLS limit switches, TOP = encoder index), 0x607C as the position
    forced after homing, Rcmdwr STOP/ABORT, drive alarms with EMCY 0x5400 and the reaction of
    Ralarmreact, the error register 0x1001, history 0x1003 (2 entries) and 0x603F, fault reset
    as the manual's procedure ([SEGNALAZIONE DI ERRORE]), save/load through Rloadsav 0x20C2.
The simulator does not interpolate (mode 7 is accepted and shown, nothing moves) and ignores
S-curve profiles (0x6086): moves are trapezoidal. `main()` wraps it in the common ROS simulator
node (sim_node.run_sim). Nothing here imports the driver's state logic.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import pathlib
import struct
import sys
import threading
import time
from typing import Any, Callable, Generator, Sequence

import can
import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.sdo.exceptions import SdoAbortedError
from stepper_drivers import cia402
from stepper_drivers.drive import State
from stepper_drivers.vendors import vector_step_map as vm

from .axis import (HOME, INDEX, LIMIT_NEG, LIMIT_POS, AxisEvent, HomingRun, SimAxis,
                   SwitchMethod)

logger = logging.getLogger(__name__)
logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)
logging.getLogger('canopen').setLevel(logging.WARNING)    # one line per SDO otherwise

# NMT states (heartbeat byte values, CiA 301)
NMT_INITIALISING = 0x00
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F
NMT_NAMES = {NMT_INITIALISING: 'INITIALISING', NMT_STOPPED: 'STOPPED',
             NMT_OPERATIONAL: 'OPERATIONAL', NMT_PRE_OPERATIONAL: 'PRE-OPERATIONAL'}
# transports.md A5.3.6: a heartbeat right behind the boot-up hides it from
# NmtMaster.wait_for_bootup()
BOOTUP_TO_HEARTBEAT_S = 0.010
SAVE_TIME_S = 0.15                   # Rloadsav 0x81 busy time (EEPROM write)
# A missing SYNC is confirmed this much later: a simulator process the machine starved for a
# while would otherwise see its own lateness (SYNCs still queued in its socket) as a lost SYNC.
SYNC_CONFIRM_S = 0.02
RALARM_MISSING_SYNC = 1 << 18        # Ralarm32 bit 18 "Mancanza Sync (CANopen o EtherCAT)"
DEFAULT_MAX_TRAVEL_STEPS = 50 * 3200

# State bits the statusword shows per state [STATUSWORD] (bits 0-3, 5, 6).
STATE_BITS = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000, State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021, State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027, State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F, State.FAULT: 0x0008,
}
SW_VOLTAGE_ENABLED = 1 << 4          # [STATUSWORD] "Voltage disabled": polarity not stated
SW_QUICK_STOP = 1 << 5
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_BIT12 = 1 << 12
SW_BIT13 = 1 << 13

# The simulator's own transition table, read "backwards": (state, controlword command) -> (next
# state, DSP-402 transition number) [MACCHINA A STATI DSP-402 V1.1 -> Definizioni transizioni].
SOD, RTSO, SO, OE = (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                     State.OPERATION_ENABLED)
QSA, FRA, FAULT = State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE, State.FAULT
NEXT_STATE: dict[tuple[State, str], tuple[State, int]] = {
    (SOD, 'SHUTDOWN'): (RTSO, 2),
    (RTSO, 'SWITCH ON'): (SO, 3),
    (SO, 'ENABLE OPERATION'): (OE, 4),
    (OE, 'DISABLE OPERATION'): (SO, 5),
    (SO, 'SHUTDOWN'): (RTSO, 6),
    (RTSO, 'DISABLE VOLTAGE'): (SOD, 7),
    (RTSO, 'QUICK STOP'): (SOD, 7),           # CiA 402 (the manual lists 0x2 for 11 only)
    (OE, 'SHUTDOWN'): (RTSO, 8),
    (OE, 'DISABLE VOLTAGE'): (SOD, 9),
    (SO, 'DISABLE VOLTAGE'): (SOD, 10),
    (SO, 'QUICK STOP'): (SOD, 10),
    (OE, 'QUICK STOP'): (QSA, 11),
    (QSA, 'DISABLE VOLTAGE'): (SOD, 12),
    (QSA, 'ENABLE OPERATION'): (OE, 16),      # only with 0x605A = 5 or 6
}

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
    yield   # noqa: unreachable - makes this a generator


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


@dataclasses.dataclass
class NodeConfig:
    """One simulated drive; positions are raw (physical) steps."""

    name: str
    node_id: int
    full_steps_per_rev: int = 200
    step_resolution: int = 16            # Rstpres power-on value (micro-steps per full step)
    limit_neg_steps: float | None = None
    limit_pos_steps: float | None = None
    home_switch_steps: float | None = None
    index_phase_steps: float = 0.0
    position_steps: float = 0.0
    product_code: int = 0x138E           # another value plays a device that is no Vector Step
    vendor_id: int = vm.VENDOR_ID_AEC
    device_name: str = 'SMD50.06LIC'
    serial_number: int = 0
    power_stage_blocked: bool = False
    homing_error_faults: bool = False
    strict_fault_reset: bool = True
    # indexes answered "object does not exist" (another firmware), e.g. Ralarm32 0x222F; not
    # those the simulation itself keeps (Rstpres 0x210E, the DS-301 and DSP-402 objects)
    missing_objects: tuple[int, ...] = ()

    def __post_init__(self):
        if not 1 <= self.node_id <= 127:
            raise ValueError(f'drives.{self.name}.node_id: {self.node_id} is not a node-ID '
                             '(allowed: 1..127)')
        kept = [hex(i) for i in self.missing_objects
                if i == vm.RSTPRES or not 0x2000 <= i <= 0x5FFF]
        if kept:
            raise ValueError(f'drives.{self.name}.missing_objects: {", ".join(kept)} cannot be '
                             'missing (the simulation uses them)')
        for name in ('product_code', 'vendor_id'):
            if not 0 <= getattr(self, name) <= 0xFFFFFFFF:
                raise ValueError(f'drives.{self.name}.{name}: {getattr(self, name)} is not an '
                                 'UNSIGNED32 (0x1018)')


@dataclasses.dataclass
class _Pdo:
    number: int
    direction: str                        # 'rx' or 'tx'
    cob_id: int = 0
    valid: bool = False
    rtr_allowed: bool = True
    trans_type: int = 0xFE
    inhibit_100us: int = 0
    event_timer_ms: int = 0
    entries: tuple[tuple[int, int, int], ...] = ()
    last_data: bytes | None = None
    last_sent: float = -1e9
    due: float | None = None              # a change waiting for the inhibit time
    sync_count: int = 0
    sampled: bytes | None = None           # type 252: data sampled at SYNC
    pending: bytes | None = None           # synchronous RxPDO waiting for SYNC
    handler: Callable | None = None

    @property
    def length(self) -> int:
        return sum(bits for _, _, bits in self.entries) // 8


class VectorStepNode:
    """One simulated Vector Step on the bus."""

    def __init__(self, sim: 'VectorStepSim', cfg: NodeConfig, eds: str):
        self.sim = sim
        self.cfg = cfg
        self.id = cfg.node_id
        self.name = cfg.name
        self.od = canopen.import_od(eds, self.id)
        for index in cfg.missing_objects:         # another firmware: SDO abort 0x06020000
            del self.od[index]
        self.local = canopen.LocalNode(self.id, self.od)
        # LocalNode's NmtSlave runs the heartbeat as a python-can periodic task and never boots:
        # this class does NMT itself.
        self.local._write_callbacks.remove(self.local.nmt.on_write)
        self.local.add_read_callback(self._on_read)
        self.local.add_write_callback(self._on_write)
        self.axis = SimAxis(limit_neg_steps=cfg.limit_neg_steps,
                            limit_pos_steps=cfg.limit_pos_steps,
                            home_switch_steps=cfg.home_switch_steps,
                            steps_per_rev=cfg.full_steps_per_rev * cfg.step_resolution,
                            index_phase_steps=cfg.index_phase_steps,
                            position_steps=cfg.position_steps)
        self.axis.add_listener(self._on_axis_event)
        self.eeprom: dict[str, int] = {}
        self.link_cut = False
        self.nvram_fault = False
        self.power_stage_blocked = cfg.power_stage_blocked
        self.alarm_causes = 0            # Ralarm32 bits whose cause is present
        self.sync_at: float | None = None   # last SYNC (or 0x1006 write) the watchdog counts from
        self._subscriptions: list[tuple[int, Callable]] = []
        self.rx: list[_Pdo] = []
        self.tx: list[_Pdo] = []
        self._load_eeprom()
        self._power_on_state()
        self.nmt_state = NMT_INITIALISING
        self.boot_at: float | None = None
        self.heartbeat_due: float | None = None

    # ================================================================= power and NMT
    def _power_on_state(self) -> None:
        """Application state after power-on or NMT reset node."""
        self.local.data_store.clear()
        for key, value in self.eeprom.items():
            index = int(key, 16)
            self._store(index, vm.AEC_SUB, value)
        self.axis.motion.stop_immediately()
        self.axis.set_position(0.0)       # the position counter restarts at 0 (not homed)
        self.state = State.NOT_READY_TO_SWITCH_ON
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
        self.setpoint_ack = False
        self.setpoint_queued: float | None = None
        self.pp_target: float | None = None
        self.jog_running = False
        self.jog_inhibit = False
        self.jog_velocity_hz = 0.0
        self.pending: tuple[State, int] | None = None   # state entered at standstill
        self.fault_reaction_done_at: float | None = None
        self.rcmdrd = 0
        self.loadsav_busy: tuple[int, float] | None = None
        self.loadsav_last = 0
        self.reepsts = 0
        self.last_emcy_at = -1e9
        self.emcy_queue: list[bytes] = []
        self.guard_toggle = 0
        self.guard_seen: float | None = None
        self.consumer_seen: dict[int, float] = {}
        self.sdo_rx_cob = 0x600 + self.id
        self.sdo_tx_cob = 0x580 + self.id
        self._sync_watch(None)
        self.state = SOD                  # transition 1 (automatic)

    def _reset_communication(self) -> None:
        for index in [i for i in self.local.data_store if 0x1000 <= i <= 0x1FFF]:
            del self.local.data_store[index]
        self.guard_toggle = 0
        self.guard_seen = None
        self.consumer_seen.clear()
        self._sync_watch(None)            # 0x1006 is back to 0: not watched

    # ================================================================= SYNC watchdog
    def _sync_watch(self, since: float | None) -> None:
        """(Re)start the SYNC watchdog from `since` (a SYNC, a write of 0x1006); None: off. A
        SYNC or a new 0x1006 removes the alarm's cause (it stays latched in Ralarm32)."""
        self.sync_at = since
        self.sync_suspect_at: float | None = None
        self.sync_error = False
        self.alarm_causes &= ~RALARM_MISSING_SYNC

    def _sync_timeout_s(self) -> float:
        return self._stored(vm.COMMUNICATION_CYCLE_PERIOD) / 1e6

    def _sync_deadline(self) -> float | None:
        timeout_s = self._sync_timeout_s()
        if not timeout_s or self.sync_at is None:
            return None
        if self.sync_suspect_at is not None:
            return self.sync_suspect_at + SYNC_CONFIRM_S
        return self.sync_at + timeout_s

    def _check_sync(self, now: float) -> None:
        deadline = self._sync_deadline()
        if deadline is None or now < deadline:
            return
        if self.sync_suspect_at is None:
            self.sync_suspect_at = now       # confirmed at the next cycle (SYNC_CONFIRM_S)
            return
        logger.info('%s: no SYNC for %.3f s (0x1006 = %d us): alarm "missing SYNC"', self.name,
                    now - self.sync_at, self._stored(vm.COMMUNICATION_CYCLE_PERIOD))
        self.sync_at = self.sync_suspect_at = None        # one alarm per loss
        self.sync_error = True                            # Rcansts / LED "Sync error"
        self.raise_alarm(RALARM_MISSING_SYNC)

    def attach(self) -> None:
        network = self.sim.network
        self.local.network = network
        self.local.sdo.network = network
        self._subscribe(0x000, self._on_nmt)
        self._subscribe(0x700 + self.id, self._on_guard)

    def detach(self) -> None:
        for cob, handler in self._subscriptions:
            try:
                self.sim.network.unsubscribe(cob, handler)
            except (KeyError, ValueError):
                pass
        self._subscriptions.clear()

    def _subscribe(self, cob: int, handler: Callable) -> None:
        self.sim.network.subscribe(cob, handler)
        self._subscriptions.append((cob, handler))

    def _unsubscribe(self, cob: int, handler: Callable) -> None:
        if (cob, handler) in self._subscriptions:
            self._subscriptions.remove((cob, handler))
            try:
                self.sim.network.unsubscribe(cob, handler)
            except (KeyError, ValueError):
                pass

    def boot(self, delay_s: float) -> None:
        """Go silent, then boot after delay_s (power-on / reset)."""
        self.nmt_state = NMT_INITIALISING
        self.heartbeat_due = None
        self.boot_at = time.monotonic() + delay_s
        self.sim.wake()

    def _finish_boot(self, now: float) -> None:
        self.boot_at = None
        for cob, handler in [s for s in self._subscriptions if s[1] == self._on_sdo]:
            self._unsubscribe(cob, handler)
        self.sdo_rx_cob, self.sdo_tx_cob = 0x600 + self.id, 0x580 + self.id
        self.local.sdo.rx_cobid, self.local.sdo.tx_cobid = self.sdo_rx_cob, self.sdo_tx_cob
        self._subscribe(self.sdo_rx_cob, self._on_sdo)
        self._load_pdos()
        self._load_consumers()
        self._send(0x700 + self.id, b'\x00')            # boot-up
        self.nmt_state = NMT_PRE_OPERATIONAL
        self.heartbeat_due = now + BOOTUP_TO_HEARTBEAT_S
        logger.info('%s (node %d): boot-up, PRE-OPERATIONAL', self.name, self.id)

    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.id):
            return
        with self.sim.lock:
            if self.link_cut or self.nmt_state == NMT_INITIALISING:
                return
            command = data[0]
            if command == 0x01:
                self._enter_nmt(NMT_OPERATIONAL)
            elif command == 0x02:
                self._enter_nmt(NMT_STOPPED)
            elif command == 0x80:
                self._enter_nmt(NMT_PRE_OPERATIONAL)
            elif command == 0x81:
                logger.info('%s: NMT reset node', self.name)
                self._power_on_state()
                self.boot(self.sim.reboot_delay_s)
            elif command == 0x82:
                logger.info('%s: NMT reset communication', self.name)
                self._reset_communication()
                self.boot(self.sim.reboot_delay_s)

    def _enter_nmt(self, state: int) -> None:
        old, self.nmt_state = self.nmt_state, state
        if state != old:
            logger.info('%s: NMT %s', self.name, NMT_NAMES[state])
        if state == NMT_OPERATIONAL and old != NMT_OPERATIONAL:
            for pdo in self.tx:                 # current values once on entering OPERATIONAL
                if pdo.valid and pdo.trans_type >= 0xFE:
                    self._send_tpdo(pdo, time.monotonic())

    def _on_guard(self, can_id: int, data: bytes, timestamp: float) -> None:
        """Node guarding: an RTR (a 0-byte frame over socketcand) on 0x700+ID."""
        if len(data) != 0:
            return
        with self.sim.lock:
            if self.link_cut or self.nmt_state == NMT_INITIALISING:
                return
            self.guard_seen = time.monotonic()
            self._send(0x700 + self.id, bytes([self.guard_toggle | self.nmt_state]))
            self.guard_toggle ^= 0x80

    def _load_consumers(self) -> None:
        for cob, handler in [s for s in self._subscriptions if s[1] == self._on_consumer]:
            self._unsubscribe(cob, handler)
        self.consumers: dict[int, float] = {}
        for sub in (1, 2):
            entry = self._stored(vm.CONSUMER_HEARTBEAT_TIME, sub)
            node, time_ms = (entry >> 16) & 0xFF, entry & 0xFFFF
            if node and time_ms:
                self.consumers[node] = time_ms / 1000.0
                self._subscribe(0x700 + node, self._on_consumer)

    def _on_consumer(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self.sim.lock:
            self.consumer_seen[can_id - 0x700] = time.monotonic()

    # ================================================================= object dictionary access
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

    @property
    def steps_per_rev(self) -> float:
        return float(self.cfg.full_steps_per_rev * self._stored(vm.RSTPRES, vm.AEC_SUB))

    def _hz(self, rps100: int) -> float:
        return vm.hz_from_rps100(rps100, self.steps_per_rev)

    def _hz_s(self, rps2x10: int) -> float:
        return vm.hz_s_from_rps2x10(rps2x10, self.steps_per_rev)

    @staticmethod
    def _check_sub(subindex: int, od: ODVariable) -> None:
        """LocalNode answers any sub-index of a VAR and invents ARRAY members: refuse them."""
        if isinstance(od.parent, (ODArray, ODRecord)):
            if subindex not in od.parent.subindices:
                raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)
        elif subindex != 0:
            raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)

    def _on_read(self, index: int, subindex: int, od: ODVariable) -> Any:
        self._check_sub(subindex, od)
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
            red = 0b0101 if self.sync_error else 0b0100 if self.comm_error else 0
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

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """Validate an SDO/RPDO write (raise an abort) and apply side effects of its value."""
        self._check_sub(subindex, od)
        if od.data_type == canopen.objectdictionary.VISIBLE_STRING:
            return
        value = od.decode_raw(data)
        if (od.min is not None and value < od.min) or (od.max is not None and value > od.max):
            raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
        if index in (vm.COB_ID_SYNC, vm.COB_ID_EMCY):
            if (value ^ self._stored(index)) & (0b11 << 29):   # bits 29/30 not modifiable
                raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
        elif index == vm.CONSUMER_HEARTBEAT_TIME:
            other = self._stored(index, 3 - subindex)
            if value & 0xFFFF and other & 0xFFFF and (value >> 16) & 0xFF == (other >> 16) & 0xFF:
                raise SdoAbortedError(vm.ABORT_PARAMETER_INCOMPATIBLE)
            self.sim.after(self._load_consumers)
        elif index == vm.PRE_DEFINED_ERROR_FIELD:
            if value != 0:
                raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
            self.history.clear()             # "Scrivendo 0 in 0x1003:0 viene resettato lo storico"
            self.comm_error = False
            self.home_error_latched = False
        elif index == vm.PRODUCER_HEARTBEAT_TIME:
            self.heartbeat_due = time.monotonic() if value else None
        elif index == vm.COMMUNICATION_CYCLE_PERIOD:
            self._sync_watch(time.monotonic() if value else None)
            self.sim.wake()
        elif vm.RPDO_MAPPING <= index <= vm.RPDO_MAPPING + 3 or \
                vm.TPDO_MAPPING <= index <= vm.TPDO_MAPPING + 3:
            self._check_mapping(index, subindex, value)
            self.sim.after(self._load_pdos)
        elif vm.RPDO_COMMUNICATION <= index <= vm.RPDO_COMMUNICATION + 3 or \
                vm.TPDO_COMMUNICATION <= index <= vm.TPDO_COMMUNICATION + 3:
            self.sim.after(self._load_pdos)
        elif index == vm.SDO1_PARAMETER:
            self.sim.after(self._apply_sdo_cob_ids)
        elif index == vm.MODES_OF_OPERATION and value not in vm.MODES:
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
        elif index == vm.RCMDWR:
            if value & (value - 1):          # "i bit devono essere alzati uno alla volta"
                raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
            self.sim.after(functools.partial(self._rcmdwr, value))
        elif index == vm.RLOADSAV:
            if self.loadsav_busy:
                raise SdoAbortedError(vm.ABORT_DEVICE_STATE)
            self.sim.after(functools.partial(self._rloadsav, value))

    def _check_mapping(self, index: int, sub: int, value: int) -> None:
        rx = index < vm.TPDO_MAPPING
        if sub == 0:
            total = 0
            for k in range(1, value + 1):
                entry = self._stored(index, k)
                self._check_entry(entry, rx)
                total += entry & 0xFF
            if total > 64:
                raise SdoAbortedError(vm.ABORT_PDO_TOO_LONG)
        elif value:
            self._check_entry(value, rx)

    def _check_entry(self, entry: int, rx: bool) -> None:
        index, sub, bits = vm.split_mapping_entry(entry)
        try:
            obj = self._obj(index, sub)
        except (KeyError, SdoAbortedError):
            raise SdoAbortedError(vm.ABORT_NO_OBJECT) from None
        usable = obj.writable if rx else obj.readable
        if not obj.pdo_mappable or not usable or bits != len(obj):
            raise SdoAbortedError(vm.ABORT_NOT_MAPPABLE)

    def _apply_sdo_cob_ids(self) -> None:
        rx = self._stored(vm.SDO1_PARAMETER, 1) & 0x7FF
        tx = self._stored(vm.SDO1_PARAMETER, 2) & 0x7FF
        if rx != self.sdo_rx_cob:
            self._unsubscribe(self.sdo_rx_cob, self._on_sdo)
            self.sdo_rx_cob = rx
            self._subscribe(rx, self._on_sdo)
        self.sdo_tx_cob = self.local.sdo.tx_cobid = tx
        self.local.sdo.rx_cobid = rx

    # ================================================================= SDO server
    def _on_sdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self.sim.lock:
            if self.link_cut or self.nmt_state in (NMT_INITIALISING, NMT_STOPPED):
                return                       # CiA 301: no SDO in STOPPED
            self.local.sdo.on_request(can_id, data, timestamp)
            self.sim.run_after()
            self.process()
            self.sim.wake()                  # timers may have changed

    # ================================================================= PDO engine
    def _load_pdos(self) -> None:
        for pdo in self.rx + self.tx:
            if pdo.handler is not None:
                self._unsubscribe(pdo.cob_id, pdo.handler)
        self.rx, self.tx = [], []
        for n in range(4):
            for direction, comm, mapping, out in (
                    ('rx', vm.RPDO_COMMUNICATION, vm.RPDO_MAPPING, self.rx),
                    ('tx', vm.TPDO_COMMUNICATION, vm.TPDO_MAPPING, self.tx)):
                cob = self._stored(comm + n, 1)
                count = self._stored(mapping + n, 0)
                pdo = _Pdo(n + 1, direction, cob_id=cob & 0x7FF,
                           valid=not cob & vm.PDO_INVALID and count > 0,
                           rtr_allowed=not cob & vm.PDO_RTR_NOT_ALLOWED,
                           trans_type=self._stored(comm + n, 2),
                           entries=tuple(vm.split_mapping_entry(self._stored(mapping + n, k))
                                         for k in range(1, count + 1)))
                if direction == 'tx':
                    pdo.inhibit_100us = self._stored(comm + n, 3)
                    pdo.event_timer_ms = self._stored(comm + n, 5)
                if pdo.valid:
                    handler = functools.partial(self._on_rpdo if direction == 'rx'
                                                else self._on_tpdo_request, pdo)
                    pdo.handler = handler
                    self._subscribe(pdo.cob_id, handler)
                out.append(pdo)

    def _encode(self, pdo: _Pdo) -> bytes:
        data = b''
        for index, sub, bits in pdo.entries:
            data += self.local.get_data(index, sub)[:bits // 8]
        return data

    def _send_tpdo(self, pdo: _Pdo, now: float, data: bytes | None = None) -> None:
        data = self._encode(pdo) if data is None else data
        pdo.last_data, pdo.last_sent, pdo.due = data, now, None
        self._send(pdo.cob_id, data)

    def _on_tpdo_request(self, pdo: _Pdo, can_id: int, data: bytes, timestamp: float) -> None:
        """RTR for a TxPDO (socketcand carries it as a 0-byte data frame)."""
        if len(data) != 0:
            return
        with self.sim.lock:
            if self.link_cut or self.nmt_state != NMT_OPERATIONAL or not pdo.rtr_allowed:
                return
            self.process()
            self._send_tpdo(pdo, time.monotonic(),
                            pdo.sampled if pdo.trans_type == 252 and pdo.sampled else None)

    def _on_rpdo(self, pdo: _Pdo, can_id: int, data: bytes, timestamp: float) -> None:
        with self.sim.lock:
            if self.link_cut or self.nmt_state != NMT_OPERATIONAL:
                return
            if len(data) > pdo.length:
                self.emcy(vm.EMCY_PDO_TOO_LONG, comm=True)     # the manual's assignment
                return
            if len(data) < pdo.length:
                self.emcy(vm.EMCY_PDO_TOO_SHORT, comm=True)
                return
            if pdo.trans_type <= 240:
                pdo.pending = bytes(data)                      # applied at the next SYNC
                return
            self._apply_rpdo(pdo, bytes(data))

    def _apply_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        offset = 0
        for index, sub, bits in pdo.entries:
            chunk = data[offset:offset + bits // 8]
            offset += bits // 8
            try:
                self.local.set_data(index, sub, chunk)
            except SdoAbortedError as exc:
                logger.info('%s: RxPDO%d 0x%04X:%02X = %s refused: %s', self.name, pdo.number,
                            index, sub, chunk.hex(), vm.abort_text(exc.code))
        self.sim.run_after()
        self.process()
        self.sim.wake()

    def on_sync(self, now: float) -> None:
        if self.link_cut or self.nmt_state == NMT_INITIALISING:
            return
        if self._sync_timeout_s():
            self._sync_watch(now)
        if self.nmt_state != NMT_OPERATIONAL:
            return
        for pdo in self.rx:
            if pdo.valid and pdo.pending is not None:
                data, pdo.pending = pdo.pending, None
                self._apply_rpdo(pdo, data)
        self.process()
        for pdo in self.tx:
            if not pdo.valid:
                continue
            if pdo.trans_type == 252:
                pdo.sampled = self._encode(pdo)
            elif pdo.trans_type == 0:
                data = self._encode(pdo)
                if data != pdo.last_data:
                    self._send_tpdo(pdo, now, data)
            elif pdo.trans_type <= 240:
                pdo.sync_count += 1
                if pdo.sync_count >= pdo.trans_type:
                    pdo.sync_count = 0
                    self._send_tpdo(pdo, now)

    def _tpdo_check(self, now: float) -> None:
        """Event-driven TxPDOs (254/255): on change, spaced by the inhibit time; event timer."""
        if self.link_cut or self.nmt_state != NMT_OPERATIONAL:
            return
        for pdo in self.tx:
            if not pdo.valid or pdo.trans_type < 0xFE:
                continue
            inhibit_s = pdo.inhibit_100us * 1e-4
            data = self._encode(pdo)
            if data != pdo.last_data:
                if now >= pdo.last_sent + inhibit_s:
                    self._send_tpdo(pdo, now, data)
                else:
                    pdo.due = pdo.last_sent + inhibit_s
            elif pdo.event_timer_ms and now >= pdo.last_sent + pdo.event_timer_ms / 1000.0:
                period_s = pdo.event_timer_ms / 1000.0
                due = pdo.last_sent + period_s
                self._send_tpdo(pdo, now, data)
                if now - due < period_s:
                    pdo.last_sent = due       # a late wake-up does not shift the timer's phase

    # ================================================================= EMCY and errors
    def error_register(self) -> int:
        value = 0
        if self.state in (FAULT, FRA) or self.home_error_latched or self.history:
            value |= vm.ERROR_REGISTER_GENERIC
        if self.comm_error:
            value |= vm.ERROR_REGISTER_COMMUNICATION
        return value

    def emcy(self, code: int, vendor: bytes = b'', comm: bool = False) -> None:
        """Send an EMCY [PRE-DEFINED ERROR FIELD]; record it in 0x1003/0x603F unless a reset."""
        if code != vm.EMCY_NO_ERROR:
            self.comm_error = self.comm_error or comm
            extra = int.from_bytes(vendor[:2].ljust(2, b'\0'), 'little')
            self.history.insert(0, code | extra << 16)     # newest at sub 1
            del self.history[vm.ERROR_HISTORY_DEPTH:]
            self.error_code = code
        frame = struct.pack('<HB', code, self.error_register()) + vendor[:5].ljust(5, b'\0')
        cob = self._stored(vm.COB_ID_EMCY)
        if cob & vm.PDO_INVALID:
            return
        inhibit_s = self._stored(vm.INHIBIT_TIME_EMCY) * 1e-4
        now = time.monotonic()
        if self.emcy_queue or now < self.last_emcy_at + inhibit_s:
            self.emcy_queue.append(frame)
            self.sim.wake()
        else:
            self.last_emcy_at = now
            self._send(cob & 0x7FF, frame)
        logger.info('%s: EMCY 0x%04X %s', self.name, code, vm.emcy_text(code, vendor))

    def raise_alarm(self, bits: int) -> None:
        """A drive alarm (Ralarm32 bits): EMCY 0x5400, fault reaction, FAULT."""
        self.alarm_causes |= bits
        self.alarms |= bits
        self.emcy(vm.EMCY_POWER_STAGE, struct.pack('<I', self.alarms))
        self._enter_fault()

    def _enter_fault(self) -> None:
        if self.state in (FAULT, FRA):
            return
        self.homing_abort(interrupted=False)
        self.jog_running = False
        self.pending = None
        was_on = self.state in (OE, QSA)
        self.state = FRA
        react = self._stored(vm.RALARMREACT, vm.AEC_SUB)
        immediate = react in (-1, 0) or (react == -4 and any(
            self.alarms & (1 << b) for b in vm.RALARM_IMMEDIATE_BITS))
        if not was_on or immediate or not self.axis.moving:
            self.axis.motion.stop_immediately()           # current off: uncontrolled stop
        elif react in (-2, 1):
            self.axis.motion.stop(self._hz_s(self._stored(vm.PROFILE_DECELERATION)))
        else:                                              # -4, -3, 2: emergency ramp
            self.axis.motion.quick_stop(self._hz_s(self._stored(vm.QUICK_STOP_DECELERATION)))

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
        self.state = SOD
        self.emcy(vm.EMCY_NO_ERROR)
        logger.info('%s: fault reset -> SWITCH ON DISABLED', self.name)

    # ================================================================= statusword
    def statusword(self) -> int:
        sw = STATE_BITS[self.state] | SW_REMOTE
        if self.state != QSA:
            sw |= SW_QUICK_STOP
        if not self.power_stage_blocked:
            sw |= SW_VOLTAGE_ENABLED
        if self.warnings:
            sw |= SW_WARNING
        if self.axis.moving:
            sw |= vm.SW_BIT_MOTOR_MOVING
        if self._input(LIMIT_NEG) or self._input(LIMIT_POS):
            sw |= SW_INTERNAL_LIMIT
        at_rest = not self.axis.moving
        if self.mode == vm.MODE_PROFILE_POSITION:
            if at_rest and self.setpoint_queued is None:
                sw |= SW_TARGET_REACHED
            if self.setpoint_ack:
                sw |= SW_BIT12
        elif self.mode == vm.MODE_HOMING:
            if self.homing_result == 'attained':
                sw |= SW_BIT12
            elif self.homing_result == 'error':
                sw |= SW_BIT13
            if at_rest and self.homing is None:
                sw |= SW_TARGET_REACHED
        elif self.mode == vm.MODE_JOG:
            if self.axis.velocity_hz == 0.0:
                sw |= SW_BIT12                # "1 = Motore fermo"
            if not self.axis.motion.in_ramp:
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

    # ================================================================= the application cycle
    def process(self) -> None:
        """One application cycle: motion time, controlword, modes, pending transitions."""
        now = time.monotonic()
        self.axis.update(now)
        mode = self._stored(vm.MODES_OF_OPERATION)
        if mode != self.mode:
            self._change_mode(mode)
        cw = self._stored(vm.CONTROLWORD)
        prev, self.cw_prev = self.cw_prev, cw
        if self.state == FAULT and cw & cia402.CW_BIT_FAULT_RESET \
                and not prev & cia402.CW_BIT_FAULT_RESET:
            self._try_fault_reset()
        for _ in range(3):
            if not self._transition(cw):
                break
        if self.state == OE:
            self._run_mode(cw, prev)
        self._settle(now)
        self._tpdo_check(now)

    def _transition(self, cw: int) -> bool:
        if self.pending is not None or self.state in (FAULT, FRA):
            return False
        for command in cia402.decode_commands(cw):
            found = NEXT_STATE.get((self.state, command))
            if found is None:
                continue
            target, number = found
            if number == 16 and self._stored(vm.QUICK_STOP_OPTION_CODE) not in (5, 6):
                continue
            if number == 2 and self.power_stage_blocked:
                return False                 # no power stage: stays SWITCH ON DISABLED
            self._enter(target, number)
            return True
        return False

    def _enter(self, target: State, number: int) -> None:
        """Enter `target` by transition `number`, with the option code's stop where it has one."""
        motion = self.axis.motion
        dec = self._hz_s(self._stored(vm.PROFILE_DECELERATION))
        qdec = self._hz_s(self._stored(vm.QUICK_STOP_DECELERATION))
        logger.info('%s: transition %d %s -> %s', self.name, number, self.state.value,
                    target.value)
        if number == 4 or number == 16:
            self.state = OE
            self.jog_running = False
            self.jog_inhibit = False
            self.setpoint_ack = False
            self.setpoint_queued = None
            if number == 4:
                motion.stop_immediately()
            return
        self.homing_abort(interrupted=True)
        self.jog_running = False
        self.setpoint_queued = None
        if number == 11:
            option = self._stored(vm.QUICK_STOP_OPTION_CODE)
            self.state = QSA
            if option == 0 or not self.axis.moving:
                motion.stop_immediately()
                if option in (0, 1, 2):
                    self.state = SOD
            else:
                motion.quick_stop(qdec if option in (2, 6) else dec)
                if option in (1, 2):
                    self.pending = (SOD, 12)
            return
        ramp = ((number == 8 and self._stored(vm.SHUTDOWN_OPTION_CODE) == 1)
                or (number == 5 and self._stored(vm.DISABLE_OPERATION_OPTION_CODE) == 1))
        if ramp and self.axis.moving:
            motion.stop(dec)
            self.pending = (target, number)
            return
        if self.state in (OE, QSA):
            motion.stop_immediately()        # current off
        self.state = target

    def _settle(self, now: float) -> None:
        moving = self.axis.moving
        if self.pending is not None and not moving:
            target, number = self.pending
            self.pending = None
            logger.info('%s: transition %d completed at standstill', self.name, number)
            self.state = target
        if self.state == FRA and not moving:
            self.state = FAULT
        if self.rcmdrd and not moving:
            self.rcmdrd = 0
        if self.mode == vm.MODE_PROFILE_POSITION and self.state == OE and not moving \
                and self.setpoint_queued is not None:
            target, self.setpoint_queued = self.setpoint_queued, None
            self._start_move(target)

    def _change_mode(self, mode: int) -> None:
        """A new 0x6060: moving -> Abort on the emergency ramp, state unchanged [MODES OF...]."""
        logger.info('%s: mode %s -> %s', self.name, vm.MODE_NAMES.get(self.mode),
                    vm.MODE_NAMES.get(mode))
        if self.axis.moving:
            self.axis.motion.quick_stop(self._hz_s(self._stored(vm.QUICK_STOP_DECELERATION)))
        self.homing_abort(interrupted=True)
        self.jog_running = False
        self.jog_inhibit = True
        self.setpoint_ack = False
        self.setpoint_queued = None
        self.homing_result = ''
        self.mode = mode

    def _run_mode(self, cw: int, prev: int) -> None:
        rising = cw & cia402.CW_BIT_NEW_SET_POINT and not prev & cia402.CW_BIT_NEW_SET_POINT
        falling = prev & cia402.CW_BIT_NEW_SET_POINT and not cw & cia402.CW_BIT_NEW_SET_POINT
        if self.mode == vm.MODE_PROFILE_POSITION:
            if rising:
                self._new_setpoint(cw)
            elif falling:
                self.setpoint_ack = False
        elif self.mode == vm.MODE_JOG:
            self._jog(cw, prev)
        elif self.mode == vm.MODE_HOMING:
            if rising:
                self._start_homing()
            elif falling and self.homing is not None:
                self.homing_abort(interrupted=True)

    # --- profile position
    def _profile(self) -> tuple[float, float, float]:
        return (self._hz(self._stored(vm.PROFILE_VELOCITY)),
                self._hz_s(self._stored(vm.PROFILE_ACCELERATION)),
                self._hz_s(self._stored(vm.PROFILE_DECELERATION)))

    def _new_setpoint(self, cw: int) -> None:
        target = float(self._stored(vm.TARGET_POSITION))
        if cw & cia402.CW_BIT_RELATIVE:
            base = self.pp_target if self.pp_target is not None and self.axis.moving \
                else self.axis.position_steps
            target += base
        self.setpoint_ack = True
        if cw & cia402.CW_BIT_CHANGE_SET_IMMEDIATELY or not self.axis.moving:
            self.setpoint_queued = None
            self._start_move(target)
        else:
            self.setpoint_queued = target

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

    # --- JOG (AEC velocity mode)
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

    # --- homing
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
        self.emcy(vm.EMCY_HOME_ERROR, bytes([rhsts & 0xFF]))
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
            self.setpoint_queued = None

    # --- AEC command and save registers
    def _rcmdwr(self, value: int) -> None:
        if value == vm.RCMDWR_STOP:
            self.homing_abort(interrupted=True, deceleration_hz_s=self._stop_deceleration())
            self.jog_running = False
            self.jog_inhibit = True
            self.setpoint_queued = None
            if self.axis.moving:
                self.axis.motion.stop(self._stop_deceleration())
                self.rcmdrd = vm.RCMDWR_STOP
        elif value == vm.RCMDWR_ABORT:
            qdec = self._hz_s(self._stored(vm.QUICK_STOP_DECELERATION))
            self.homing_abort(interrupted=True, deceleration_hz_s=qdec)
            self.jog_running = False
            self.jog_inhibit = True
            self.setpoint_queued = None
            if self.axis.moving:
                self.axis.motion.quick_stop(qdec)
                self.rcmdrd = vm.RCMDWR_ABORT
        elif value == 1 and self.state in (OE, QSA, SO, RTSO):   # DISABLE DRIVE
            self.axis.motion.stop_immediately()
            self.state = SOD
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
            self._reset_communication()
            self.boot(self.sim.reboot_delay_s)
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
            self.emcy(vm.EMCY_NVRAM, struct.pack('<H', self.reepsts))
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

    # ================================================================= time
    def next_deadline(self, now: float) -> float:
        times = [math.inf]
        if self.boot_at is not None:
            times.append(self.boot_at)
        if self.nmt_state == NMT_INITIALISING:
            return min(times)
        sync = self._sync_deadline()        # a cut cable loses the SYNC too
        if sync is not None:
            times.append(sync)
        if self.active:
            times.append(now + self.sim.cycle_s)
        if self.link_cut:
            return min(times)
        period_ms = self._stored(vm.PRODUCER_HEARTBEAT_TIME)
        if period_ms and self.heartbeat_due is not None:
            times.append(self.heartbeat_due)
        if self.loadsav_busy:
            times.append(self.loadsav_busy[1])
        if self.emcy_queue:
            inhibit_s = self._stored(vm.INHIBIT_TIME_EMCY) * 1e-4
            times.append(self.last_emcy_at + inhibit_s)
        if self.nmt_state == NMT_OPERATIONAL:
            for pdo in self.tx:
                if pdo.valid and pdo.trans_type >= 0xFE:
                    if pdo.due is not None:
                        times.append(pdo.due)
                    if pdo.event_timer_ms:
                        times.append(pdo.last_sent + pdo.event_timer_ms / 1000.0)
        life = self._life_time_s()
        if life and self.guard_seen is not None:
            times.append(self.guard_seen + life)
        for node, timeout in getattr(self, 'consumers', {}).items():
            seen = self.consumer_seen.get(node)
            if seen is not None:
                times.append(seen + timeout)
        return min(times)

    @property
    def active(self) -> bool:
        return (self.axis.moving or self.homing is not None or self.pending is not None
                or self.state == FRA)

    def _life_time_s(self) -> float:
        return self._stored(vm.GUARD_TIME) * self._stored(vm.LIFE_TIME_FACTOR) / 1000.0

    def tick(self, now: float) -> None:
        if self.boot_at is not None and now >= self.boot_at:
            self._finish_boot(now)
        if self.nmt_state == NMT_INITIALISING:
            return
        self._check_sync(now)
        if self.link_cut:
            self.process()                  # the alarm's stop ramp runs without the bus
            return
        period_ms = self._stored(vm.PRODUCER_HEARTBEAT_TIME)
        if period_ms and self.heartbeat_due is not None and now >= self.heartbeat_due:
            self._send(0x700 + self.id, bytes([self.nmt_state]))
            self.heartbeat_due += period_ms / 1000.0
            if self.heartbeat_due <= now:          # late (or just switched on): re-phase
                self.heartbeat_due = now + period_ms / 1000.0
        if self.loadsav_busy and now >= self.loadsav_busy[1]:
            self._finish_save()
        if self.emcy_queue and now >= self.last_emcy_at + \
                self._stored(vm.INHIBIT_TIME_EMCY) * 1e-4:
            cob = self._stored(vm.COB_ID_EMCY) & 0x7FF
            self.last_emcy_at = now
            self._send(cob, self.emcy_queue.pop(0))
        life = self._life_time_s()
        if life and self.guard_seen is not None and now > self.guard_seen + life:
            self.guard_seen = None               # one event per loss
            logger.info('%s: life guarding: no guard request within %.3f s', self.name, life)
            self.emcy(vm.EMCY_ERROR_CONTROL, comm=True)
        for node, timeout in getattr(self, 'consumers', {}).items():
            seen = self.consumer_seen.get(node)
            if seen is not None and now > seen + timeout:
                del self.consumer_seen[node]
                logger.info('%s: heartbeat of node %d lost', self.name, node)
                self.emcy(vm.EMCY_ERROR_CONTROL, bytes([node]), comm=True)
        self.process()

    def _send(self, cob: int, data: bytes) -> None:
        if self.link_cut:
            return
        self.sim.send(cob, data)

    # ================================================================= fault injection
    def inject(self, kind: str, code: int, value: float) -> str:
        if kind == 'drive_fault':
            bits = code or 1 << 6
            self.raise_alarm(bits)
            return (f'alarm Ralarm32 0x{bits:08X} ({vm.bit_texts(bits, vm.RALARM_BITS)}): '
                    f'EMCY 0x5400, state {self.state.value}')
        if kind == 'clear_fault':
            self.alarm_causes = 0
            return 'alarm causes removed (a fault reset can now succeed)'
        if kind == 'power_stage_blocked':
            self.power_stage_blocked = True
            if self.state in (RTSO, SO, OE, QSA):
                self.axis.motion.stop_immediately()
                self.homing_abort(interrupted=True)
                self.state = SOD
            return 'power stage blocked (Rstsflg1 STO): enabling stays in SWITCH ON DISABLED'
        if kind == 'power_stage_ok':
            self.power_stage_blocked = False
            return 'power stage available'
        if kind == 'warning':
            self.warnings = code
            return f'Rwarning = 0x{code:04X}'
        if kind == 'emcy':
            self.emcy(code, comm=0x8100 <= code <= 0x82FF)
            return f'EMCY 0x{code:04X} sent'
        if kind == 'nvram_fault':
            self.nvram_fault = True
            return 'Rloadsav saves fail (Reepsts bit 3, EMCY 0xFF01) until nvram_ok'
        if kind == 'nvram_ok':
            self.nvram_fault = False
            return 'EEPROM works again'
        if kind in ('cut', 'no_reply'):
            self.link_cut = True
            return 'node silent (no heartbeat, no SDO, no PDO) until link_ok'
        if kind == 'link_ok':
            self.link_cut = False
            if self._stored(vm.PRODUCER_HEARTBEAT_TIME):
                self.heartbeat_due = time.monotonic()
            return 'node answers again'
        if kind == 'reboot':
            self._power_on_state()
            self._reset_communication()
            self.boot(self.sim.reboot_delay_s)
            return 'power cycle: boot-up follows'
        raise ValueError(f'unknown fault kind {kind!r}; kinds: drive_fault, clear_fault, '
                         'power_stage_blocked, power_stage_ok, warning, emcy, nvram_fault, '
                         'nvram_ok, cut, no_reply, link_ok, reboot')


class VectorStepSim:
    """One CAN bus with simulated Vector Steps (a stepper_sim.sim_node.SimBackend)."""

    def __init__(self, nodes: Sequence[NodeConfig], *, interface: str = 'socketcand',
                 channel: str = 'can0', host: str = '127.0.0.1', port: int = 29536,
                 eds: str | None = None, reboot_delay_s: float = 0.05, cycle_s: float = 0.002,
                 storage_dir: str = ''):
        if not nodes:
            raise ValueError('parameter drives: at least one simulated drive is needed')
        ids = [n.node_id for n in nodes]
        if len(set(ids)) != len(ids):
            raise ValueError(f'drives.*.node_id: {ids} has a node-ID twice (one per drive)')
        if interface == 'socketcand' and host not in ('127.0.0.1', 'localhost'):
            raise ValueError(f'can.host: {host!r}: the simulator stays on 127.0.0.1')
        self.bus_kwargs: dict[str, Any] = (
            dict(interface='socketcand', channel=channel, host=host, port=port, tcp_tune=True)
            if interface == 'socketcand' else dict(interface=interface, channel=channel))
        self.address = (f'socketcand {host}:{port} {channel}' if interface == 'socketcand'
                        else f'{interface} {channel}')
        self.reboot_delay_s = reboot_delay_s
        self.cycle_s = cycle_s
        self.storage_dir = storage_dir
        self.lock = threading.RLock()
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.1          # shutdown waits one receive timeout
        eds = eds or str(vm.eds_path())
        self.nodes = {cfg.name: VectorStepNode(self, cfg, eds) for cfg in nodes}
        self._after: list[Callable[[], None]] = []
        self._wakeup = threading.Event()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self.sent = 0

    # SimBackend --------------------------------------------------------------------------------
    @property
    def drive_names(self) -> Sequence[str]:
        return list(self.nodes)

    def start(self) -> str:
        try:
            self.network.connect(**self.bus_kwargs)
        except (can.CanError, OSError, TimeoutError) as exc:
            raise OSError(f'{self.address}: {exc}') from None
        self.network.subscribe(0x80, self._on_sync)
        with self.lock:
            for node in self.nodes.values():
                node.attach()
                node.boot(self.reboot_delay_s)
        self._thread = threading.Thread(target=self._run, name='vector-step-sim', daemon=True)
        self._thread.start()
        ids = ', '.join(str(n.id) for n in self.nodes.values())
        return f'{self.address} (node-IDs {ids})'

    def stop(self) -> None:
        self._stopping = True
        self._wakeup.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        with self.lock:
            for node in self.nodes.values():
                node.detach()
        try:
            self.network.disconnect()
        except Exception as exc:  # noqa: BLE001 - the bus may already be gone
            logger.debug('disconnect: %s', exc)

    def true_position_steps(self, drive: str) -> float:
        with self.lock:
            node = self._node(drive)
            node.axis.update()
            return node.axis.position_steps

    def inject_fault(self, drive: str, kind: str, code: int, value: float) -> tuple[bool, str]:
        with self.lock:
            node = self._node(drive)
            try:
                message = node.inject(kind, code, value)
            except ValueError as exc:
                return False, str(exc)
            node.process()
            self.wake()
            return True, f'{drive}: {message}'

    def set_input(self, drive: str, name: str, value: bool, release: bool) -> tuple[bool, str]:
        aliases = {'bls': LIMIT_NEG, 'fls': LIMIT_POS, 'top': HOME}
        with self.lock:
            node = self._node(drive)
            name = aliases.get(name.lower(), name)
            node.axis.update()
            if release:
                node.axis.release(name)
            else:
                node.axis.set_input(name, value)
            node.process()
            self.wake()
            return True, f'{drive}: input {name} = {node._input(name)}'

    def _node(self, drive: str) -> VectorStepNode:
        try:
            return self.nodes[drive]
        except KeyError:
            raise ValueError(f'unknown drive {drive!r}; drives: {", ".join(self.nodes)}') \
                from None

    # Machinery ---------------------------------------------------------------------------------
    def send(self, cob: int, data: bytes) -> None:
        try:
            self.network.send_message(cob, data)
            self.sent += 1
        except (can.CanError, OSError, RuntimeError) as exc:
            logger.warning('send 0x%03X failed: %s', cob, exc)

    def after(self, fn: Callable[[], None]) -> None:
        """Run fn once the current SDO/PDO access has been stored (write callbacks run first)."""
        self._after.append(fn)

    def run_after(self) -> None:
        pending, self._after = self._after, []
        for fn in pending:
            fn()

    def wake(self) -> None:
        self._wakeup.set()

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self.lock:
            now = time.monotonic()
            for node in self.nodes.values():
                if node._stored(vm.COB_ID_SYNC) & 0x7FF == can_id:
                    node.on_sync(now)

    def _run(self) -> None:
        while not self._stopping:
            with self.lock:
                now = time.monotonic()
                deadline = min(node.next_deadline(now) for node in self.nodes.values())
            wait_s = deadline - time.monotonic()
            if wait_s > 0:
                self._wakeup.wait(min(wait_s, 0.5))
            self._wakeup.clear()
            if self._stopping:
                break
            with self.lock:
                now = time.monotonic()
                for node in self.nodes.values():
                    try:
                        node.tick(now)
                    except Exception:  # noqa: BLE001 - one broken cycle must not stop the bus
                        logger.exception('%s: cycle failed', node.name)


# ============================================================================ ROS wrapper
def build(node) -> VectorStepSim:
    """Declare the simulator's parameters on the ROS node and build the backend."""
    from .sim_node import declare, declare_drives
    nan = math.nan
    interface = declare(node, 'can.interface', 'socketcand', 'python-can interface')
    channel = declare(node, 'can.channel', 'can0', 'CAN channel')
    host = declare(node, 'can.host', '127.0.0.1', 'socketcand server host (loopback only)')
    port = declare(node, 'can.port', 29536, 'socketcand server port')
    reboot = declare(node, 'reboot_delay_s', 0.05, 'silence between an NMT reset and boot-up')
    cycle = declare(node, 'cycle_s', 0.002, 'application cycle while something moves [s]')
    storage = declare(node, 'storage_dir', '', 'folder for the simulated EEPROM (Rloadsav)')
    drives = declare_drives(node, ['axis1'], {
        'node_id': (0, 'CANopen node-ID (1..127)'),
        'full_steps_per_rev': (200, 'motor full steps per revolution'),
        'step_resolution': (16, 'Rstpres at power-on: micro-steps per full step'),
        'limit_neg_steps': (nan, 'BLS (backward limit switch) active below this raw position; '
                                 'NaN = none'),
        'limit_pos_steps': (nan, 'FLS (forward limit switch) active from this raw position; '
                                 'NaN = none'),
        'home_switch_steps': (nan, '0x60FD bit 2 home input from this raw position; NaN = none'),
        'position_steps': (0.0, 'raw position at power-on'),
        'product_code': (0x138E, '0x1018:02 (0x138E SMD5006, 0xBBE SMD3006; another value '
                                 'plays a device that is not a Vector Step)'),
        'vendor_id': (vm.VENDOR_ID_AEC, '0x1018:01 (0xBC AEC; another value plays another '
                                        "maker's device)"),
        'serial_number': (0, '0x1018:04 (0 = 10000 + node-ID)'),
        'power_stage_blocked': (False, 'start with the power stage blocked (STO)'),
        'homing_error_faults': (False, 'a homing error also puts the drive in FAULT'),
        'strict_fault_reset': (True, 'fault reset needs 0x1003:00 = 0 first (manual procedure)'),
    })

    def opt(value: float) -> float | None:
        return None if math.isnan(value) else float(value)

    configs = []
    for name, p in drives.items():
        configs.append(NodeConfig(
            name=name, node_id=int(p['node_id']), full_steps_per_rev=int(p['full_steps_per_rev']),
            step_resolution=int(p['step_resolution']), limit_neg_steps=opt(p['limit_neg_steps']),
            limit_pos_steps=opt(p['limit_pos_steps']),
            home_switch_steps=opt(p['home_switch_steps']),
            position_steps=float(p['position_steps']), product_code=int(p['product_code']),
            vendor_id=int(p['vendor_id']),
            serial_number=int(p['serial_number']),
            power_stage_blocked=bool(p['power_stage_blocked']),
            homing_error_faults=bool(p['homing_error_faults']),
            strict_fault_reset=bool(p['strict_fault_reset'])))
    return VectorStepSim(configs, interface=interface, channel=channel, host=host, port=int(port),
                         reboot_delay_s=float(reboot), cycle_s=float(cycle), storage_dir=storage)


def main(args: list[str] | None = None) -> None:
    import faulthandler
    import signal
    faulthandler.register(signal.SIGUSR1)          # kill -USR1 <pid>: thread dump in the log
    from .sim_node import run_sim
    sys.exit(run_sim('vector_step_sim', build, args))
