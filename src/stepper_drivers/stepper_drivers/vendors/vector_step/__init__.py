"""AEC Vector Step over CANopen (DS-301 V4.01 / DSP-402 V1.1): the drive class and the vendor.

Objects, codes and texts come from `vector_step_map.py` (which cites the sections of the manual
`aec_vector_step_canopen_it.txt`), the CiA 402 tables and walker from `cia402.py`, enable,
disable, the motion preconditions and the fault reset from `cia402_drive.Cia402Drive` (this class
fills its hooks), the bus and node plumbing from `protocol/canopen_link.py`. Every boot (connect)
of a node: SDO ping, identity (0x1000, 0x1018 and the AEC registers the driver needs:
IdentityError otherwise), NMT reset communication with the boot-up latch, heartbeat producer
0x1017, the drive-side watchdogs (0x1006 SYNC timeout, 0x1016 consumer of this node's heartbeat),
the PDO set of DRIVER_RPDOS/DRIVER_TPDOS written with the manual's mapping procedure, values
seeded by SDO, NMT start and a heartbeat that shows OPERATIONAL. After that the state comes from
TxPDOs, so `read_state()` costs no bus traffic but one SDO read of 0x6064 for a statusword that
says the axis stands (see `_standing_position`); the heartbeat consumer and the boot-up latch
turn a silent or rebooted node into a LinkError (the node layer reconnects).

Interpolated position (mode 7) is step-wise like the rest for its start (`start_interpolation`);
the bus owner then sends one point per SYNC period (`interpolation_point`, one RxPDO4 frame).

Every operation that waits or takes more than two transactions is step-wise (`drive.Operation`: one
SDO or PDO exchange per step, `yield POLL_S` while waiting for a TxPDO); stop() is one frame (two
during homing) and never waits.

canopen's BaseNode402 is used for its PDO plumbing (tpdo_values), not for the parts that do not
fit this drive (digest section 10): `op_mode` (its getter has no name for mode -1, its setter
refuses mode 7 because 0x6502 lacks bit 6, and it waits for a "periodic" TxPDO that an
event-driven TxPDO seen twice looks like), its `controlword` setter (it would send RxPDO1 with a
stale mode byte 0), `homing()` (the AEC method numbers are not the library's, bit 10 during homing
is not documented) and `reset_from_fault()` (the manual clears 0x1003 first). No rclpy.

One class: every command rides on an RxPDO that carries the controlword with the mode or the
target (`_write_controlword`), and connect maps those same PDOs, so boot, state machine, motion
and interpolation share one PDO image.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any, Mapping

from ...contract import param_rules
from ...contract.drive import (
    Bus,
    DriveError,
    DriveState,
    Homing,
    HomingState,
    IdentityError,
    InterpolatingDrive,
    LinkError,
    Motion,
    Operation,
    ParamSpec,
    State,
    Vendor,
    register_type,
)
from ...profiles.cia402 import state_machine as cia402
from ...profiles.cia402.drive import Cia402Drive
from ...profiles.cia402.modes import (
    HomingMode,
    InterpolatedPositionMode,
    Mode,
    ProfilePositionMode,
)
from ...profiles.cia402.state_machine import CW_BIT_NEW_SET_POINT, CW_ENABLE_OPERATION
from ...protocol.canopen_link import (
    MASTER,
    POLL_S,
    CanBus,
    RemoteDrive,
    SdoAbortError,
    pack,
    unpack,
)
from . import regmap as vm
from . import scan as vector_step_scan

logger = logging.getLogger(__name__)

IP_START_TIMEOUT_S = 0.5       # statusword bit 12 (ip mode active) after the enable, by TxPDO
SAVE_TIMEOUT_S = 5.0           # Rloadsav 0x81 (EEPROM write) must read 0 again within this
SAVE_POLL_S = 0.02
WARNING_READ_PERIOD_S = 1.0    # Rwarning is read by SDO at most this often while SW bit 7 is set
PING_TIMEOUT_S = 0.2
# unchanged_until vouches for at most this long: the bus' receive thread is looked at again
QUIET_CHECK_S = 0.1
RESCUE_BOOT_WAIT_S = 0.5       # boot-up wait after a reset sent to a node that gave no SDO answer
# A statusword change goes out in every TxPDO back to back; the other drives' bursts, SYNC and
# heartbeats may come in between. The wire time of one such round is the bound of the wait for a
# coherent snapshot: FRAME_BITS per frame (11-bit identifier, 8 data bytes, worst-case stuff
# bits; ISO 11898-1), one frame per TxPDO and drive on the bus, at the bus' bit rate (10 kbit/s:
# 13.5 ms per frame [LAYER FISICO]), plus BURST_SLACK_S for the receive thread.
FRAME_BITS = 135
BURST_SLACK_S = 0.02
# The TxPDOs that tpdo_inhibit_ms spaces out: the two whose values change all through a motion
# (position, velocity); TxPDO1 and TxPDO4 still carry a statusword change at once.
INHIBITED_TPDOS = (2, 3)
POSITION_TPDO = next(n for n, entries in enumerate(vm.DRIVER_TPDOS, 1)
                     if any(index == vm.POSITION_ACTUAL_VALUE for index, _, _ in entries))
# A standing axis' 0x6064 is read by SDO after its statusword came (_standing_position); a
# newer statusword before the answer voids it: at most this many reads in one poll, then the
# snapshot does not show the axis standing (the next poll reads again).
STANDING_READS = 3
# 0x1016 consumer time: this many periods of the node's own heartbeat ("deve essere settato piu'
# alto del tempo impostato nel generatore" [CONSUMER HEARTBEAT TIME]). 10: 1 s at 100 ms, as the
# node's own heartbeat_timeout_s; 3 (300 ms) tripped on a loaded 2-core machine when the python-can
# periodic task was late. It only lights the LED and sends EMCY 0x8130: SYNC is the safety.
MASTER_HEARTBEAT_PERIODS = 10
SYNC_TIMEOUT_MIN_PERIODS = 2   # 0x1006 must span this many SYNC periods (jitter of the producer)
HOLD_CW = {                    # controlword that keeps each state (sent with a mode change)
    State.SWITCH_ON_DISABLED: cia402.CW_DISABLE_VOLTAGE, State.READY_TO_SWITCH_ON:
    cia402.CW_SHUTDOWN, State.SWITCHED_ON: cia402.CW_SWITCH_ON,
    State.OPERATION_ENABLED: CW_ENABLE_OPERATION, State.QUICK_STOP_ACTIVE: cia402.CW_QUICK_STOP,
}
ON_THE_SPOT_METHODS = (0, 35, 37)    # no search, no speed: nothing moves
OBJECTS = {(o.index, o.sub): o for o in vm.DRIVER_OBJECTS}
# AEC registers the driver relies on; a firmware without one is not the drive this driver knows.
REQUIRED_REGISTERS = (vm.RSTPRES, vm.RCMDWR, vm.RSTSFLG, vm.RSTSFLG1, vm.RWARNING, vm.RALARM32)


def parse_address(address: str) -> tuple[int, int]:
    """'0x6041:0', '6041:00', '0x20C2' -> (index, sub); hex as CANopen writes them.

    Without a sub-index: 1 for an AEC register (0x2000-0x5FFF: sub 0 is the number of axes),
    0 otherwise.
    """
    text = address.strip().lower()
    try:
        if ':' in text:
            index_text, sub_text = text.split(':', 1)
            index, sub = int(index_text, 16), int(sub_text, 16)
        else:
            index = int(text, 16)
            sub = vm.AEC_SUB if 0x2000 <= index <= 0x5FFF else 0
    except ValueError:
        raise DriveError(f'address {address!r}: expected "index:subindex" in hex, e.g. '
                         '"0x6041:0" or "0x20C2:1"') from None
    if not (0 <= index <= 0xFFFF and 0 <= sub <= 0xFF):
        raise DriveError(f'address {address!r}: index 0..0xFFFF, sub-index 0..0xFF')
    return index, sub


def _check_drive(name: str, params: Mapping[str, Any], master_heartbeat_ms: int,
                 sync_period_s: float) -> None:
    """The rules of one drive's parameters, or ValueError; `master_heartbeat_ms` and
    `sync_period_s` are those of its bus (a drive made on a bus checks against what that bus
    produces, not against its own copy of the bus parameters)."""
    params = VENDOR.with_defaults(params)
    bitrate = int(params['can.bitrate'])
    if bitrate not in vm.BITRATES:
        raise ValueError(f'can.bitrate: {bitrate} is not a Vector Step bit rate (allowed: '
                         f'{", ".join(str(b) for b in vm.BITRATES)}; Rcanbaud codes 0..7)')
    method = int(params['homing.method'])
    if method not in vm.HOMING_METHODS:
        raise ValueError(f'drives.{name}.homing.method: {method} is not a Vector Step homing '
                         f'method (allowed: {vm.HOMING_METHODS_TEXT}; see 0x6098)')
    heartbeat_ms = int(params['heartbeat_period_ms'])
    heartbeat_timeout_s = float(params['heartbeat_timeout_s'])
    if heartbeat_ms and heartbeat_timeout_s * 1000.0 <= heartbeat_ms:
        raise ValueError(f'drives.{name}.heartbeat_timeout_s: {heartbeat_timeout_s} '
                         f'must exceed the heartbeat period ({heartbeat_ms} ms)')
    sync_timeout_s = float(params['sync_timeout_s'])
    if sync_timeout_s and not sync_period_s:
        raise ValueError(f'drives.{name}.sync_timeout_s: {sync_timeout_s:g} needs the '
                         'SYNC of this node (can.sync_period_s > 0); 0 leaves 0x1006 off')
    if sync_timeout_s and sync_timeout_s < SYNC_TIMEOUT_MIN_PERIODS * sync_period_s:
        raise ValueError(f'drives.{name}.sync_timeout_s: {sync_timeout_s:g} must be at '
                         f'least {SYNC_TIMEOUT_MIN_PERIODS} x can.sync_period_s '
                         f'({sync_period_s:g} s)')
    if MASTER_HEARTBEAT_PERIODS * master_heartbeat_ms > 0xFFFF:
        raise ValueError(f'can.master_heartbeat_ms: {master_heartbeat_ms}: '
                         f'{MASTER_HEARTBEAT_PERIODS} periods must fit the 16-bit 0x1016 '
                         f'time (at most {0xFFFF // MASTER_HEARTBEAT_PERIODS} ms)')


def _node_id_errors(params: Mapping[str, Any], bus: Mapping[str, Any]) -> list[str]:
    """Two drives with one node-ID, or a drive on the node's own heartbeat node-ID: the rules
    CanBus.claim applies when the drives are made (same messages). `bus`: the bus parameters
    with their defaults."""
    taken: dict[int, str] = {}
    if int(bus['can.master_heartbeat_ms']):
        taken[int(bus['can.master_node_id'])] = MASTER
    errors = []
    for name in param_rules.drive_names(params):
        node_id = int(VENDOR.with_defaults(param_rules.drive_params(params, name))['node_id'])
        other = taken.setdefault(node_id, name)
        if other == MASTER:
            errors.append(f'drives.{name}.node_id: {node_id} is can.master_node_id, the '
                          "node-ID of this node's own heartbeat (allowed: 1..127, one per "
                          'device)')
        elif other != name:
            errors.append(f'drives.{name}.node_id: {node_id} is already the node-ID of '
                          f'drive {other!r} on this bus (allowed: 1..127, one per drive)')
    return errors


def validate(params: Mapping[str, Any]) -> list[str]:
    """The Vector Step's parameter rules on the node's parameters (param_rules), at start-up
    and for every run-time change: node-IDs, and per drive bit rate, homing method, heartbeat,
    SYNC watchdog and the node's own heartbeat."""
    bus = VENDOR.with_defaults(param_rules.bus_params(params))
    return _node_id_errors(params, bus) + param_rules.check_each(
        params, None, lambda name, view: _check_drive(
            name, view, int(bus['can.master_heartbeat_ms']), float(bus['can.sync_period_s'])))


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


class VectorStepDrive(Cia402Drive, InterpolatingDrive):
    """One Vector Step on a CAN bus (node-ID = parameter `node_id`)."""

    # read_state: the TxPDO values (SDO only for faults, warnings and a standing axis' position)
    state_from_cache = True
    # every PP move sets bit 5, "1 = Cambia setpoint immediatamente" ([CONTROLWORD])
    retargets_on_the_way = True
    CW_SW_DELAY_S = 0.002        # first statusword check after a controlword (TxPDO on change)
    STATUSWORD_POLL_S = POLL_S   # the statusword comes by TxPDO: the receive thread records it
    ENABLE_TIMEOUT_S = 1.0
    FAULT_RESET_TIMEOUT_S = 0.4
    FAULT_RESET_ATTEMPTS = 2     # the second after Ralarm32 := 0 (_before_fault_reset)
    # disable() writes nothing where the power stage is off already (or the drive leaves the
    # state by itself)
    DISABLE_LEAVES = (State.SWITCH_ON_DISABLED, State.FAULT, State.FAULT_REACTION_ACTIVE,
                      State.NOT_READY_TO_SWITCH_ON)
    NOT_ENABLED_TEXT = '{what}: the drive is not enabled ({state}); call enable first'
    # [MODES OF OPERATION]: PP, homing, interpolated position and the AEC JOG; no PV (0x6502)
    MODES = (ProfilePositionMode(), HomingMode(), InterpolatedPositionMode(), JogMode())

    def __init__(self, bus: Bus, name: str, params: Mapping[str, Any]):
        params = VENDOR.with_defaults(params)
        super().__init__(bus, name, params)
        if not isinstance(bus, CanBus):
            raise TypeError(f'{name}: Vector Step needs a CanBus, got {type(bus).__name__}')
        self.can: CanBus = bus
        self.node_id = int(params['node_id'])
        bus.claim(self.node_id, name)
        self.address = self.node_id
        _check_drive(name, params, self.can.master_heartbeat_ms, self.can.sync_period_s)
        self.steps_per_rev = float(params['steps_per_rev'])
        self.heartbeat_ms = int(params['heartbeat_period_ms'])
        self.heartbeat_timeout_s = float(params['heartbeat_timeout_s'])
        self.sync_timeout_s = float(params['sync_timeout_s'])
        # 0x1016:01 = node-ID << 16 | time [ms] [CONSUMER HEARTBEAT TIME]; 0 = not watched
        consumer_ms = MASTER_HEARTBEAT_PERIODS * self.can.master_heartbeat_ms
        self.consumer_heartbeat = self.can.master_node_id << 16 | consumer_ms \
            if consumer_ms else 0
        self.event_timer_ms = int(params['tpdo_event_timer_ms'])
        self.inhibit_100us = int(round(float(params['tpdo_inhibit_ms']) * 10))
        self.boot_timeout_s = float(params['boot_timeout_s'])
        self.boot_retries = int(params['boot_retries'])
        eds = str(params.get('can.eds_file') or '') or str(vm.eds_path())
        self.link = RemoteDrive(bus, self.node_id, eds, name, emcy_text=vm.emcy_text)
        self._extra: tuple[int | None, int | None] = (None, None)   # (mode, velocity) to send
        self._mode_cmd: int | None = None  # 0x6060 last sent
        self._target = 0                   # 0x607A sent with every RxPDO2
        self._written: dict[tuple[int, int], int] = {}   # profile objects written this boot
        self._bootups_at_connect = 0
        self._connected_at = 0.0
        self._configured = False           # this driver armed the node (connect completed)
        self._homing = HomingState.IDLE
        self._fault_cache: tuple[int, int, str, tuple[str, ...]] | None = None
        self._reset_code = 0               # the fault code a fault_reset started from
        self._warnings: tuple[float, tuple[str, ...]] = (0.0, ())
        self._pdo_statusword: dict[int, int] = {}    # COB-ID -> statusword of its last TxPDO
        # (newest TxPDO1 statusword, when it came, its number): every change of TxPDO1's
        # statusword gets the next number, never reset, so a number names one of them even
        # where the drive comes back to an earlier value (the end of a move is the standstill
        # before it again)
        self._statusword_seen = (0, 0.0, 0)
        # what the receive thread writes (_on_tpdo) and a snapshot reads as one (the statusword
        # and its number, the cache, the standing position)
        self._rx_lock = threading.Lock()
        # (statusword number, 0x6064): the position of a standing axis, read by SDO after that
        # statusword came (_standing_position); None: not read since the last change
        self._standing: tuple[int, int] | None = None
        self._position_cob = vm.PDO_COB_BASES_TX[POSITION_TPDO - 1] + self.node_id
        self._state_cob = vm.PDO_COB_BASES_TX[0] + self.node_id      # TxPDO1
        # (reception, position): the last TxPDO2, or the SDO read of a late one
        self._position_rx: tuple[float, int] | None = None
        self._tpdo_entries: dict[int, tuple] = {}     # COB-ID: what that TxPDO maps
        self._tpdo_layouts: dict[int, tuple] = {}     # COB-ID: (struct, indexes) to store it
        self._sdo_read: set[int] = set()  # TxPDOs whose objects _wait_for_burst read by SDO
        self._snapshot: tuple[tuple | None, DriveState | None] = (None, None)  # (key, state)
        # (link.changes, controlword, homing, the snapshot) under which read_state gives the
        # snapshot again without a look at the cache, until _alive_until (unchanged_until); None:
        # look
        self._quiet: tuple[int, int | None, HomingState, DriveState] | None = None
        self._alive_until = 0.0
        self._burst_given_up: int | None = None   # number of the statusword whose wait gave up
        self._ip_active = False            # start_interpolation done; no stop or error since

    def _prefix(self) -> str:
        return f'{self.name} (node {self.node_id}): '

    # ------------------------------------------------------------------ controlword / PDO access
    @property
    def _cw(self) -> int:
        """The controlword last commanded (the driver's intent; never read back)."""
        return self.cia.controlword or 0

    def _values(self) -> dict[int, Any]:
        node = self.link.node
        if node is None:
            raise LinkError(f'{self._prefix()}not connected')
        return node.tpdo_values

    def _read_statusword(self) -> int:
        """The newest statusword: TxPDO1's (see _on_tpdo)."""
        self.can.check()
        sw = self._pdo_statusword.get(self._state_cob)
        return int(self._values().get(vm.STATUSWORD, 0)) if sw is None else sw

    def _write_controlword(self, cw: int) -> None:
        """Send the controlword by RxPDO: RxPDO1 with a mode, RxPDO3 with a JOG speed, else
        RxPDO2 with the target position (the controlword is first in all three)."""
        node = self.link.node
        if node is None or not self.link.attached:
            raise LinkError(f'{self._prefix()}not connected')
        mode, velocity = self._extra
        if mode is not None:
            pdo = node.rpdo[1]
            pdo[vm.MODES_OF_OPERATION].raw = mode
            self._mode_cmd = mode
        elif velocity is not None:
            pdo = node.rpdo[3]
            pdo[vm.PROFILE_VELOCITY].raw = velocity
            self._written[(vm.PROFILE_VELOCITY, 0)] = velocity
        else:
            pdo = node.rpdo[2]
            pdo[vm.TARGET_POSITION].raw = self._target
        if cw & CW_BIT_NEW_SET_POINT:
            # bit 4 starts every mode's run [CONTROLWORD]: homing on the spot forces 0x607C and
            # may end in the statusword it started from; the position is read again
            self._standing = None
        pdo[vm.CONTROLWORD].raw = cw
        self.can.transactions += 1
        self.can.send(pdo.cob_id, bytes(pdo.data))

    def _command(self, cw: int, *, mode: int | None = None, velocity: int | None = None) -> None:
        self._extra = (mode, velocity)
        try:
            self.cia.write(cw)
        finally:
            self._extra = (None, None)

    def _barrier(self) -> int:
        """Statusword by SDO: the drive answers after it has handled the PDOs sent before."""
        return int(self.link.read(vm.STATUSWORD))

    def _value(self, index: int, default: int = 0) -> int:
        return int(self._values().get(index, default))

    def _write_once(self, *writes: tuple[int, int, int]) -> Operation[None]:
        """SDO writes of profile objects, each skipped when this boot already wrote the value;
        one per step."""
        for index, sub, value in writes:
            if self._written.get((index, sub)) != value:
                self.link.write(index, sub, value)
                self._written[(index, sub)] = value
                yield 0.0

    def _checked(self, index: int, sub: int, value: int, what: str) -> int:
        """`value` if the object can hold it (its type and the EDS limits), else DriveError
        naming the object: checked before anything of a command is sent."""
        obj = OBJECTS[(index, sub)]
        rtype = register_type(obj.data_type)
        low, high = (-(1 << (rtype.bits - 1)), (1 << (rtype.bits - 1)) - 1) if rtype.signed \
            else (0, (1 << rtype.bits) - 1)
        eds_low, eds_high = self.link.limits(index, sub)
        low = low if eds_low is None else max(low, eds_low)
        high = high if eds_high is None else min(high, eds_high)
        if not low <= value <= high:
            raise DriveError(f'{what}: {value} is outside {obj} ({low}..{high})')
        return value

    # ------------------------------------------------------------------ life cycle
    def connect(self) -> Operation[dict[str, str]]:
        self._configured = False
        self._quiet = None
        self.link.attach()
        self.link.emcy = None
        self._written.clear()
        self._fault_cache = None
        self._homing = HomingState.IDLE
        self._ip_active = False
        try:
            yield from self._ping()
            rebooted = False
        except LinkError:
            # A node in NMT STOPPED does not answer SDO (CiA 301), an NMT reset reaches it.
            ok = yield from self.link.reset_and_wait_bootup(
                'RESET COMMUNICATION', min(self.boot_timeout_s, RESCUE_BOOT_WAIT_S))
            if not ok:
                raise
            rebooted = True
        identity = yield from self._identity()   # before any write: is it the drive we know?
        # A defined start: communication objects back to the manual's defaults, then boot-up.
        if not rebooted:
            ok = yield from self.link.reset_and_wait_bootup('RESET COMMUNICATION',
                                                            self.boot_timeout_s)
            if not ok:
                yield from self._ping()   # CiA 301 wants a boot-up here; go on if it answers
                logger.warning('%sno boot-up frame within %g s after NMT reset communication; '
                               'the node answers SDO, continuing', self._prefix(),
                               self.boot_timeout_s)
        # Error control and the drive-side watchdogs, lost at every boot (DS-301 objects are
        # not saved [GESTIONE MEMORIA NON VOLATILE]): a missing SYNC for 0x1006 us is alarm
        # Ralarm32 bit 18 and its reaction (Ralarmreact 0x471E); a missing heartbeat of ours
        # (0x1016) only lights the LED [STATO DEL LED FLD].
        for index, sub, value in (
                (vm.PRODUCER_HEARTBEAT_TIME, 0, self.heartbeat_ms),
                (vm.COMMUNICATION_CYCLE_PERIOD, 0, round(self.sync_timeout_s * 1e6)),
                (vm.CONSUMER_HEARTBEAT_TIME, 1, self.consumer_heartbeat)):
            yield 0.0
            self.link.write(index, sub, value)
        yield from self._configure_pdos()
        yield from self._seed()
        self._bootups_at_connect = self.link.bootups
        self._connected_at = time.monotonic()
        self.link.nmt('OPERATIONAL')
        if self.heartbeat_ms:
            ok = yield from self.link.wait_heartbeat_state(
                0x05, self._connected_at, self.heartbeat_timeout_s + self.heartbeat_ms / 1000.0)
            if not ok:
                raise LinkError(f'{self._prefix()}no heartbeat showing OPERATIONAL after NMT '
                                f'start (producer {self.heartbeat_ms} ms)')
        state = cia402.decode_state(self._read_statusword())
        self.cia.controlword = HOLD_CW.get(state, cia402.CW_DISABLE_VOLTAGE)
        self._mode_cmd = self._value(vm.MODES_OF_OPERATION_DISPLAY)
        self._target = self._value(vm.POSITION_ACTUAL_VALUE)
        if state == State.OPERATION_ENABLED and \
                self._read_statusword() & vm.SW_BIT_MOTOR_MOVING:
            logger.warning('%sstill moving after (re)connecting: stopping it', self._prefix())
            self.stop()
        self._configured = True
        return identity

    def _ping(self) -> Operation[None]:
        """SDO read of 0x1000 with retries: a missing node fails fast, before any NMT."""
        last: LinkError | None = None
        sdo = self.link.node.sdo
        timeout, sdo.RESPONSE_TIMEOUT = sdo.RESPONSE_TIMEOUT, min(PING_TIMEOUT_S,
                                                                  self.can.timeout_s)
        try:
            for attempt in range(max(self.boot_retries, 1)):
                if attempt:
                    yield 0.0
                try:
                    self.link.read(vm.DEVICE_TYPE)
                    return
                except LinkError as exc:
                    last = exc
        finally:
            sdo.RESPONSE_TIMEOUT = timeout
        raise LinkError(f'{self._prefix()}no answer on {self.can.description} after '
                        f'{self.boot_retries} tries ({last})')

    def _identity(self) -> Operation[dict[str, str]]:
        """Identity [DEVICE TYPE], [IDENTITY OBJECT]; IdentityError when the node is not a
        Vector Step or lacks an AEC register the driver needs."""
        device_type = int(self.link.read(vm.DEVICE_TYPE))
        if device_type & 0xFFFF != vm.DEVICE_PROFILE_DS402:
            raise IdentityError(f'{self._prefix()}0x1000 device type reads 0x{device_type:08X}: '
                                f'not a DSP-402 drive (a Vector Step reads '
                                f'0x{vm.DEVICE_TYPE_VALUE:08X})')
        yield 0.0
        vendor = int(self.link.read(vm.IDENTITY_OBJECT, 1))
        if vendor != vm.VENDOR_ID_AEC:
            raise IdentityError(f'{self._prefix()}0x1018:01 vendor-ID reads 0x{vendor:08X}, '
                                f'not AEC (0x{vm.VENDOR_ID_AEC:08X}): not a Vector Step')
        yield 0.0
        product = int(self.link.read(vm.IDENTITY_OBJECT, 2))
        if product not in vm.PRODUCT_CODES:
            known = ', '.join(f'0x{c:08X} ({n})' for c, n in vm.PRODUCT_CODES.items())
            raise IdentityError(f'{self._prefix()}0x1018:02 product code reads 0x{product:08X}, '
                                f'not a Vector Step of the manual ({known})')
        texts: dict[str, str] = {}
        for key, index, sub in (('device_name', vm.MANUFACTURER_DEVICE_NAME, 0),
                                ('software', vm.MANUFACTURER_SOFTWARE_VERSION, 0),
                                ('revision', vm.IDENTITY_OBJECT, 3),
                                ('serial', vm.IDENTITY_OBJECT, 4)):
            yield 0.0
            value = self.link.read(index, sub)
            texts[key] = f'0x{value:08X}' if key == 'revision' else str(value).strip('\0 ')
        registers: dict[int, int] = {}
        for index in REQUIRED_REGISTERS:
            yield 0.0
            registers[index] = self._probe(index)
        return {
            'node_id': str(self.node_id), 'device_name': texts['device_name'],
            'software': texts['software'], 'vendor_id': f'0x{vendor:08X}',
            'product_code': f'0x{product:08X} ({vm.PRODUCT_CODES[product]})',
            'revision': texts['revision'], 'serial': texts['serial'],
            'Rstpres': str(registers[vm.RSTPRES]), 'heartbeat_ms': str(self.heartbeat_ms),
            'sync_timeout_s': f'{self.sync_timeout_s:g}',
        }

    def _probe(self, index: int) -> int:
        """Read an AEC register (sub 1) that must exist: -1 for a write-only one that does."""
        obj = OBJECTS[(index, vm.AEC_SUB)]
        try:
            return int(self.link.read(index, vm.AEC_SUB, expected_aborts=(
                vm.ABORT_NOT_READABLE, vm.ABORT_NO_OBJECT, vm.ABORT_NO_SUBINDEX)))
        except SdoAbortError as exc:
            if exc.code == vm.ABORT_NOT_READABLE:         # write only (Rcmdwr): it exists
                return -1
            if exc.code in (vm.ABORT_NO_OBJECT, vm.ABORT_NO_SUBINDEX):
                raise IdentityError(f'{self._prefix()}{obj} is missing ({exc}): not the Vector '
                                    'Step firmware this driver knows (it needs that register)'
                                    ) from None
            raise

    def _configure_pdos(self) -> Operation[None]:
        for number, entries in enumerate(vm.DRIVER_RPDOS, 1):
            yield from self.link.configure_pdo('rx', number, entries)
            yield 0.0
        for number in range(len(vm.DRIVER_RPDOS) + 1, 5):      # the others off
            yield from self.link.configure_pdo('rx', number, ())
            yield 0.0
        for number, entries in enumerate(vm.DRIVER_TPDOS, 1):
            yield 0.0
            timer = self.event_timer_ms if number == 2 else 0
            yield from self.link.configure_pdo(
                'tx', number, entries, 0xFE, event_timer_ms=timer,
                inhibit_time_100us=self.inhibit_100us if number in INHIBITED_TPDOS else 0)
        node = self.link.node
        node.setup_pdos(upload=False)
        self._tpdo_entries, self._tpdo_layouts = {}, {}
        for number in range(1, len(vm.DRIVER_TPDOS) + 1):
            pdo = node.tpdo[number]
            entries = vm.DRIVER_TPDOS[number - 1]
            self._tpdo_entries[pdo.cob_id] = entries
            self._tpdo_layouts[pdo.cob_id] = (self.link.pdo_struct(entries),
                                              tuple(index for index, _, _ in entries))
        self.link.watch_tpdos(self._on_tpdo)

    def _on_tpdo(self, cob: int, data: bytearray) -> None:
        """(receive thread) Store what a TxPDO carries in the cache (tpdo_values).

        Every DRIVER_TPDOS mapping starts with the statusword, and a change of it sends all
        four, TxPDO1 first: TxPDO1 has the node's lowest COB-ID, so it also overtakes the
        TxPDO2..4 of the state before when they still wait for the bus (a slow or busy bus; a
        drive with several transmit buffers). So the statusword of TxPDO1 is the newest: the
        cache keeps it, and the others' only tells whether their burst is complete. A TxPDO2..4
        of an older state is still newer than the cache, except after _wait_for_burst read its
        objects by SDO for the newest state: then it is dropped until its own TxPDO of that
        state comes.

        Not so the position of a standing axis: a TxPDO2 with the newest statusword may still
        be older than it (the standstill before a move shorter than the bus' delay has the
        statusword of its end). Once _standing_position has read it by SDO for that statusword,
        a TxPDO2 leaves it as read; one that shows another position with that statusword has
        it read again at the next poll (it is older, or the axis was moved: an encoder)."""
        layout, indexes = self._tpdo_layouts[cob]
        fields = layout.unpack_from(data)     # (the bus checked the frame's length)
        sw = fields[0]
        now = time.monotonic()
        with self._rx_lock:
            self._pdo_statusword[cob] = sw
            newest = self._pdo_statusword.get(self._state_cob, sw)
            if cob == self._state_cob:
                if sw != self._statusword_seen[0]:
                    self._statusword_seen = (sw, now, self._statusword_seen[2] + 1)
                    self._sdo_read.clear()
            elif cob in self._sdo_read:
                if sw != newest:
                    return
                self._sdo_read.discard(cob)
            values = self._values()
            standing = self._standing
            if cob == self._position_cob and standing is not None and \
                    standing[0] == self._statusword_seen[2]:
                if sw == newest and fields[1] != standing[1]:
                    self._standing = None
                fields = (sw, standing[1])        # statusword, then the position (i32)
            elif cob == self._position_cob:
                self._position_rx = (now, fields[1])
            for index, value in zip(indexes, fields):
                values[index] = value
            values[vm.STATUSWORD] = newest

    def _coherent(self) -> bool:
        return len(set(self._pdo_statusword.values())) <= 1

    def _wait_for_burst(self) -> Operation[None]:
        """A statusword change goes out in every TxPDO, back to back. Until the last of those
        frames is in, the others hold values from before the change (velocity, Rstsflg's homed
        bit, the position after homing): wait for them, as long as the bus needs to carry them
        at its bit rate, so one snapshot is coherent."""
        newest, since, number = self._statusword_seen
        if self._coherent() or number == self._burst_given_up:
            return
        bound_s = len(vm.DRIVER_TPDOS) * max(self.can.drive_count, 1) * FRAME_BITS \
            / self.can.bitrate + BURST_SLACK_S + self.inhibit_100us * 1e-4
        if not (yield from self.link.wait(self._coherent, since + bound_s - time.monotonic())):
            # A frame of the burst is late (a slow or busy bus: other drives' lower COB-IDs go
            # first) or lost: what the late TxPDOs carry is read by SDO instead, so this
            # snapshot holds nothing older than its statusword (a position from before a
            # "target reached" would end a move_to at the wrong place). Then no poll waits
            # again until the next change.
            self._burst_given_up = number
            late = sorted(c for c, sw in self._pdo_statusword.items() if sw != newest)
            logger.info('%sTxPDO burst of statusword 0x%04X incomplete after %.3f s (late: %s):'
                        ' reading their objects by SDO', self._prefix(), newest, bound_s,
                        ', '.join(f'0x{c:03X}' for c in late))
            values = self._values()
            for cob in late:
                for index, sub, _bits in self._tpdo_entries.get(cob, ()):
                    if index == vm.STATUSWORD or (index == vm.POSITION_ACTUAL_VALUE and
                                                  self._standing_for(number)):
                        continue
                    yield 0.0
                    value = self.link.read(index, sub)
                    with self._rx_lock:
                        if index == vm.POSITION_ACTUAL_VALUE and \
                                not newest & vm.SW_BIT_MOTOR_MOVING and \
                                self._stand(number, int(value)):
                            continue            # read after the statusword of a standstill
                        # the late TxPDO itself came during the upload: its values are as new
                        # (an older upload written over them would stay until the next change)
                        if self._pdo_statusword.get(cob) != newest:
                            values[index] = value
                            if index == vm.POSITION_ACTUAL_VALUE:
                                # true when its answer came, not at every later poll
                                self._position_rx = (time.monotonic(), int(value))
                with self._rx_lock:
                    if self._statusword_seen[2] == number and \
                            self._pdo_statusword.get(cob) != newest:
                        self._sdo_read.add(cob)   # its frames of older states are older

    def _standing_for(self, number: int) -> bool:
        """The position of statusword `number` (a standstill) was read after it came."""
        standing = self._standing
        return standing is not None and standing[0] == number

    def _stand(self, number: int, position: int) -> bool:
        """(_rx_lock held) 0x6064 read by SDO after statusword `number` came, which says the
        axis stands: its position while it stands, unless a newer statusword came meanwhile
        (the answer may be of that one, moving again)."""
        if self._statusword_seen[2] != number:
            return False
        self._standing = (number, position)
        self._values()[vm.POSITION_ACTUAL_VALUE] = position
        self._position_rx = (time.monotonic(), position)
        return True

    def _standing_position(self) -> Operation[None]:
        """The position of a standing axis (statusword bit 8 "Motor moving" off, [STATUSWORD]),
        read by SDO after the statusword came, once per statusword (and command, see
        _write_controlword): the position a move_to, a homing or a trajectory ends on.

        No TxPDO can tell it: a standing drive repeats one statusword, so the TxPDO2 of the
        standstill before a move that is shorter than the bus' delay (a slow or busy bus:
        TxPDO2..4 come after TxPDO1) carries the statusword of the move's end with the
        position the move started from, and the order in which frames come in tells nothing
        of when they were sampled. An SDO answer does: the drive sends it after the TxPDO1 of
        the statusword it has then (TxPDO1 is sent at the change, and its COB-ID wins the
        arbitration against the answer's), so while no newer TxPDO1 came before the answer,
        the answer is of that statusword (`_stand`)."""
        sw, _, number = self._statusword_seen
        if sw & vm.SW_BIT_MOTOR_MOVING or self._standing_for(number):
            return
        yield 0.0
        value = int(self.link.read(vm.POSITION_ACTUAL_VALUE, 0))
        with self._rx_lock:
            self._stand(number, value)

    def _seed(self) -> Operation[None]:
        """Current values by SDO, so the cache is right before the first TxPDO arrives (the
        position 0x6064 after the statusword 0x6041: a standing axis' position is known)."""
        values = self._values()
        for index, sub, _bits in sorted({e for pdo in vm.DRIVER_TPDOS for e in pdo}):
            yield 0.0
            values[index] = self.link.read(index, sub)
        sw = int(values[vm.STATUSWORD])
        with self._rx_lock:
            self._pdo_statusword = {pdo.cob_id: sw for pdo in self.link.node.tpdo.values()
                                    if pdo.enabled}
            number = self._statusword_seen[2] + 1
            self._statusword_seen = (sw, time.monotonic(), number)
            self._burst_given_up = None
            self._sdo_read.clear()
            self._position_rx = None
            self._standing = None if sw & vm.SW_BIT_MOTOR_MOVING else \
                (number, int(values[vm.POSITION_ACTUAL_VALUE]))

    def close(self) -> None:
        """Orderly end (the node shuts down): disarm the drive-side watchdogs, so that a drive
        left standing does not fault when the SYNC stops with the bus. Nothing is written to a
        drive that is not answering (it then stops by itself, which is the point)."""
        self._homing = HomingState.IDLE
        if not self._configured or not self.link.attached:
            return                           # never armed, or not ours (IdentityError)
        try:
            self._check_alive()
            for index, sub in ((vm.COMMUNICATION_CYCLE_PERIOD, 0),
                               (vm.CONSUMER_HEARTBEAT_TIME, 1)):
                self.link.write(index, sub, 0)
        except DriveError as exc:
            logger.info('%swatchdogs left armed at close: %s', self._prefix(), exc)
        self._configured = False

    # ------------------------------------------------------------------ state
    def _check_alive(self) -> None:
        if not self.link.attached:
            raise LinkError(f'{self._prefix()}not connected')
        self.can.check()
        if self.link.bootups > self._bootups_at_connect:
            raise LinkError(f'{self._prefix()}boot-up seen: the drive restarted; reconnecting '
                            'to configure it again')
        if not self.heartbeat_ms:
            return
        age = self.link.heartbeat_age_s()
        if age is None:
            age = time.monotonic() - self._connected_at
        if age > self.heartbeat_timeout_s:
            raise LinkError(f'{self._prefix()}heartbeat lost: nothing for {age:.2f} s (producer '
                            f'{self.heartbeat_ms} ms, heartbeat_timeout_s '
                            f'{self.heartbeat_timeout_s:g})')
        nmt = self.link.heartbeat_state
        if nmt is not None and nmt != 0x05:
            raise LinkError(f'{self._prefix()}heartbeat reports NMT state 0x{nmt:02X}, not '
                            'OPERATIONAL: reconnecting')

    def read_state(self) -> DriveState | Operation[DriveState]:
        """The state from the TxPDO cache. The last snapshot again while nothing it was made of
        changed: an idle drive's TxPDO2 event timer repeats the same bytes, which the link does
        not count as a change (RemoteDrive.changes). While the link counted no change, this
        driver commanded nothing (controlword, homing) and the heartbeat's deadline is ahead,
        the poll is that look (`unchanged_until`); else the liveness checks and the snapshot key.
        Step-wise only while a burst is incomplete, a fault is read, a warning is due, or the
        position of an axis that stands is read (_standing_position)."""
        state = self._snapshot[1]
        if state is not None and self.unchanged_until(state):
            return state
        self._quiet = None
        changes = self.link.changes              # before what it vouches for
        self._check_alive()
        with self._rx_lock:
            key = self._snapshot_key()
        if key == self._snapshot[0]:
            self._quiet = (changes, self.cia.controlword, self._homing, self._snapshot[1])
            self._alive_until = self._heartbeat_deadline()
            return self._snapshot[1]
        return self._read_state_steps()

    def unchanged_until(self, state: DriveState) -> float:
        """While the link counted no change, the controlword and homing are as the snapshot
        had them, and the bus receives: until the heartbeat's deadline, and at most
        QUIET_CHECK_S ahead (a dead receive thread shows only here when the heartbeat is off)."""
        if self._quiet != (self.link.changes, self.cia.controlword, self._homing, state) \
                or not self.can.receiving:       # the bus open, its receive thread alive
            return 0.0
        now = time.monotonic()
        if now >= self._alive_until:
            self._alive_until = self._heartbeat_deadline()    # from the last heartbeat
            if now >= self._alive_until:
                return 0.0
        return min(self._alive_until, now + QUIET_CHECK_S)

    def _heartbeat_deadline(self) -> float:
        """When _check_alive fails for the heartbeat, unless another one comes before."""
        if not self.heartbeat_ms:
            return math.inf
        at = self.link.heartbeat_at
        return (self._connected_at if at is None else at) + self.heartbeat_timeout_s

    def _snapshot_key(self) -> tuple:
        """(_rx_lock held) What a snapshot is made of, read before it (so a change meanwhile
        makes the next key differ): the statusword and its number (an equal value is not the
        same statusword: the end of a move is the standstill before it again), the standing
        position, the cached objects, EMCY, homing and the controlword; the position's
        reception time only while moving (measured_at_s)."""
        values = self._values()
        sw, _, number = self._statusword_seen
        return (sw, number, self._standing, values.get(vm.MODES_OF_OPERATION_DISPLAY),
                values.get(vm.RSTSFLG), values.get(vm.POSITION_ACTUAL_VALUE),
                values.get(vm.VELOCITY_ACTUAL_VALUE), values.get(vm.ERROR_REGISTER),
                self.link.emcy_count, self.link.emcy, self._homing, self._cw,
                self._position_rx if sw & vm.SW_BIT_MOTOR_MOVING else None)

    def _read_state_steps(self) -> Operation[DriveState]:
        yield from self._wait_for_burst()
        for _ in range(STANDING_READS):
            yield from self._standing_position()
            changes = self.link.changes
            with self._rx_lock:           # one statusword with the values of its snapshot
                key = self._snapshot_key()
                sw, _, number = self._statusword_seen
                values = dict(self._values())
                standing = self._standing if self._standing_for(number) else None
                # a statusword that came after _wait_for_burst: its burst is waited for at
                # the next poll
                waited = self._coherent() or number == self._burst_given_up
            if standing is not None or sw & vm.SW_BIT_MOTOR_MOVING:
                break
        mode = int(values.get(vm.MODES_OF_OPERATION_DISPLAY, 0))
        rstsflg = int(values.get(vm.RSTSFLG, 0))
        position = int(values.get(vm.POSITION_ACTUAL_VALUE, 0))
        velocity = int(values.get(vm.VELOCITY_ACTUAL_VALUE, 0))
        error_register = int(values.get(vm.ERROR_REGISTER, 0))
        if standing is not None:
            position = standing[1]
        state = cia402.decode_state(sw)
        fault = state in (State.FAULT, State.FAULT_REACTION_ACTIVE)
        code, text, alarms = (yield from self._fault()) if fault else (0, '', ())
        if not fault:
            self._fault_cache = None
        homing = self._homing_state(sw, mode, standing is not None)
        extra: list[str] = list(alarms)
        if sw & cia402.SW_BIT_WARNING:
            extra += self._read_warnings()
        emcy = self.link.emcy
        if homing == HomingState.ERROR and emcy is not None and emcy.code in vm.HOME_ERROR_CODES:
            extra.append(f'EMCY 0x{emcy.code:04X}: {emcy.text}')
        if error_register & vm.ERROR_REGISTER_COMMUNICATION and \
                emcy is not None and 0x8100 <= emcy.code <= 0x82FF:
            extra.append(f'EMCY 0x{emcy.code:04X}: {emcy.text}')
        if not fault and emcy is not None and emcy.code in vm.IP_EMCY_CODES:
            extra.append(f'EMCY 0x{emcy.code:04X}: {emcy.text}')   # the manual names no reaction
        mode_text = vm.MODE_NAMES.get(mode, f'mode {mode}')
        if mode == vm.MODE_INTERPOLATED and sw & vm.SW_BIT_IP_ACTIVE:
            mode_text += ' (IP active)'
        # Bit 8 ("Motor moving", theoretical) off means the profile velocity is zero; TxPDO3
        # may still hold the last speed of a stop whose burst was given up.
        velocity_hz = vm.hz_from_rps100(velocity, self.steps_per_rev) \
            if sw & vm.SW_BIT_MOTOR_MOVING else 0.0
        # Standing only with the position read after the statusword that says so
        # (_standing_position): what a move_to, a homing and a trajectory end on. A newer
        # statusword came during each of its reads: not shown standing until the next poll.
        moving = standing is None
        snapshot = DriveState(
            state=state, enabled=state == State.OPERATION_ENABLED,
            moving=moving,
            target_reached=bool(sw & cia402.SW_BIT_TARGET_REACHED),
            homed=bool(rstsflg & vm.RSTSFLG_HOMED), homing=homing, fault=fault,
            fault_code=code, fault_text=text, alarms=tuple(extra),
            mode=mode_text, status_word=sw, position_steps=position, velocity_steps_s=velocity_hz,
            measured_at_s=self._position_measured_at_s(position, moving))
        # a fault or a warning is read again (SDO) at its own pace, a standstill not yet shown
        # and a burst not yet waited for at the next poll: never from the last snapshot
        keyed = waited and not fault and not sw & cia402.SW_BIT_WARNING and \
            (standing is not None or bool(sw & vm.SW_BIT_MOTOR_MOVING))
        self._snapshot = (key if keyed else None), snapshot
        self._quiet = (changes, self.cia.controlword, self._homing, snapshot) if keyed else None
        self._alive_until = self._heartbeat_deadline()
        return snapshot

    def _position_measured_at_s(self, position: int, moving: bool) -> float | None:
        """When the cached position was true. A moving axis' position TxPDO goes out at most
        once per inhibit time (tpdo_inhibit_ms, [0x1800+(No.PDO-1):03] "Inibisce la trasmissione
        dei PDO per il tempo impostato"), and later still when the bus or this process is slow:
        while the axis moves, its time is the last frame's reception, however long ago. A
        standing axis sends a change at once: its position is current, None (the poll's time).
        A frame that came between the caller's read of `position` and this is not it: None."""
        rx = self._position_rx
        if not moving or rx is None or rx[1] != position:
            return None
        return rx[0]

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

    def _fault(self) -> Operation[tuple[int, str, tuple[str, ...]]]:
        """(code, text, alarms) of the current fault; SDO reads once per fault (and EMCY)."""
        count = self.link.emcy_count
        if self._fault_cache is not None and self._fault_cache[0] == count:
            return self._fault_cache[1:]
        emcy = self.link.emcy
        if emcy is not None and emcy.time_s >= self._connected_at:
            code, text = emcy.code, emcy.text
        else:
            code = int(self.link.read(vm.ERROR_CODE))
            text = vm.emcy_text(code)
            yield 0.0
        ralarm = int(self.link.read(vm.RALARM32, vm.AEC_SUB))
        alarms = tuple(vm.RALARM_BITS.get(b, f'alarm bit {b}') for b in range(32)
                       if ralarm & (1 << b))
        if ralarm:
            text = f'{text}: {", ".join(alarms)} (Ralarm32 0x{ralarm:08X})'
        self._fault_cache = (count, code, text, alarms)
        return code, text, alarms

    def _read_warnings(self) -> tuple[str, ...]:
        at, texts = self._warnings
        if time.monotonic() - at >= WARNING_READ_PERIOD_S:
            try:
                value = int(self.link.read(vm.RWARNING, vm.AEC_SUB))
                texts = tuple(f'warning: {vm.RWARNING_BITS.get(b, f"bit {b}")}'
                              for b in range(16) if value & (1 << b))
            except SdoAbortError:
                texts = ('warning (statusword bit 7)',)
            self._warnings = (time.monotonic(), texts)
        return texts

    # ------------------------------------------------------------------ power stage
    # enable() and disable() are Cia402Drive's; the Vector Step's parts of them:
    def _enable_refusal(self, sw: int) -> Operation[str]:
        code, text, _ = yield from self._fault()
        return f'{self._prefix()}in FAULT 0x{code:04X} ({text})'

    def _hold_position(self, state: State) -> None:
        self._target = self._value(vm.POSITION_ACTUAL_VALUE)     # nothing moves on enable
        self._homing = HomingState.IDLE
        if not self._in_mode(vm.MODE_PROFILE_POSITION):
            self._command(HOLD_CW.get(state, cia402.CW_DISABLE_VOLTAGE),
                          mode=vm.MODE_PROFILE_POSITION)

    def _enable_failed(self, exc: DriveError) -> Operation[None]:
        why = yield from self._why_not_enabled()
        raise DriveError(f'cannot enable: {exc}{why}') from None

    def _why_not_enabled(self) -> Operation[str]:
        """The manual's registers that explain a power stage that does not come on."""
        reasons = []
        try:
            sts1 = int(self.link.read(vm.RSTSFLG1, vm.AEC_SUB))
            if sts1 & vm.RSTSFLG1_STO:
                reasons.append('STO active (Rstsflg1 bit 15)')
            if sts1 & vm.RSTSFLG1_POWER_OFF:
                reasons.append('Power_OFF signal (Rstsflg1 bit 2)')
            yield 0.0
            ralarm = int(self.link.read(vm.RALARM32, vm.AEC_SUB))
            if ralarm:
                reasons.append(f'alarms {vm.bit_texts(ralarm, vm.RALARM_BITS)} '
                               f'(Ralarm32 0x{ralarm:08X})')
        except DriveError as exc:
            reasons.append(f'({exc})')
        if not self._read_statusword() & cia402.SW_BIT_VOLTAGE_ENABLED:
            reasons.append('statusword bit 4 shows no power stage voltage')
        if not reasons:
            return ''
        return '; the power stage is blocked: ' + '; '.join(reasons) + \
            ' (check the motor supply and the STO inputs)'

    def _disabling(self) -> None:
        self._homing = HomingState.IDLE

    def _statusword_for_motion(self) -> tuple[int, None]:
        """OPERATION ENABLED as the drive says: its last TxPDO when the event timer of TxPDO2
        keeps them fresh, else the statusword by SDO."""
        self._check_alive()
        sw = self._read_statusword()
        at = self.link.tpdo_at
        if not self.event_timer_ms or at is None or \
                time.monotonic() - at > 2 * self.event_timer_ms / 1000.0:
            sw = self._barrier()
        return sw, None

    def _in_mode(self, mode: int, current: int | None = None) -> bool:
        """The mode this driver sent last (0x6060) and the drive shows (0x6061, TxPDO1)."""
        return self._mode_cmd == mode and self._value(vm.MODES_OF_OPERATION_DISPLAY) == mode

    def _switch_mode(self, mode: Mode, what: str, current: int | None) -> Operation[None]:
        """0x6060 by RxPDO1 (with the controlword that holds OPERATION ENABLED, bits 4-6 low),
        then wait until 0x6061 (TxPDO1) shows it."""
        self._command(CW_ENABLE_OPERATION, mode=mode.code)
        ok = yield from self.link.wait(
            lambda: self._value(vm.MODES_OF_OPERATION_DISPLAY) == mode.code,
            self.MODE_SWITCH_TIMEOUT_S)
        if not ok:                           # no TxPDO1 on the change: ask once by SDO
            display = int(self.link.read(vm.MODES_OF_OPERATION_DISPLAY))
            self._values()[vm.MODES_OF_OPERATION_DISPLAY] = display
            ok = display == mode.code
        if not ok:
            raise DriveError(f'{self._prefix()}modes of operation display 0x6061 shows '
                             f'{self._value(vm.MODES_OF_OPERATION_DISPLAY)} after writing 0x6060 '
                             f'= {mode.code} ({mode.name})')

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

    # ------------------------------------------------------------------ maintenance
    def fault_reset(self) -> Operation[str]:
        """The manual's procedure [SEGNALAZIONE DI ERRORE]: (1) the cause is gone, (2) 0x1003:00
        = 0, (3) back to operation enable, which starts with transition 15 (bit 7 rising edge):
        Cia402Drive.fault_reset, FAULT_RESET_ATTEMPTS edges with the hooks below."""
        state = cia402.decode_state(self._read_statusword())
        if state not in cia402.FAULT_STATES:
            self.link.write(vm.PRE_DEFINED_ERROR_FIELD, 0, 0)
            self.link.emcy = None
            return ''
        self._reset_code, _, _ = yield from self._fault()
        return (yield from super().fault_reset())

    def _before_fault_reset(self, attempt: int) -> Operation[None]:
        yield 0.0
        if attempt:
            # "Per resettare gli allarmi scrivere 0 in questo registro" (Ralarm32).
            self.link.write(vm.RALARM32, vm.AEC_SUB, 0)
            yield 0.0
        self.link.write(vm.PRE_DEFINED_ERROR_FIELD, 0, 0)

    def _fault_cleared(self, sw: int) -> None:
        self.link.emcy = None
        self._fault_cache = None
        self._homing = HomingState.IDLE
        logger.info('%sfault 0x%04X cleared: %s', self._prefix(), self._reset_code,
                    cia402.describe(sw))

    def _fault_remains(self, sw: int) -> Operation[str]:
        self._fault_cache = None
        yield 0.0
        code, text, _ = yield from self._fault()
        return (f'0x{code:04X} {text}: still in {cia402.describe(sw)} after 0x1003:00 = 0 and '
                f'the controlword bit 7 edge; remove the cause first')

    def save_params(self) -> Operation[str]:
        start = time.monotonic()
        self.link.write(vm.RLOADSAV, vm.AEC_SUB, vm.RLOADSAV_SAVE_REGISTERS)
        while True:
            yield SAVE_POLL_S              # poll rate of a register that has no event
            value = int(self.link.read(vm.RLOADSAV, vm.AEC_SUB))
            if value == 0:                  # "Il registro viene azzerato quando il comando e'
                break                       # stato eseguito"
            if time.monotonic() - start > SAVE_TIMEOUT_S:
                raise DriveError(f'save: Rloadsav 0x20C2:01 still reads 0x{value:02X} after '
                                 f'{SAVE_TIMEOUT_S:g} s')
        elapsed = time.monotonic() - start
        yield 0.0
        reepsts = int(self.link.read(vm.REEPSTS, vm.AEC_SUB))
        if reepsts:
            raise DriveError(f'save failed: Reepsts 0x{reepsts:04X} '
                             f'({vm.bit_texts(reepsts, vm.REEPSTS_BITS)})')
        return (f'Rloadsav 0x81 (save registers to EEPROM) done in {elapsed:.2f} s, Reepsts 0; '
                'PDO mapping, heartbeat and watchdogs are not stored (written at every boot)')

    def read_register(self, address: str, data_type: str) -> int | str:
        index, sub = parse_address(address)
        data = self.link.upload(index, sub)
        if data_type.lower() == 'string':
            return data.split(b'\0', 1)[0].decode('latin-1')
        rtype = register_type(data_type)
        if len(data) != rtype.bits // 8:
            raise DriveError(f'0x{index:04X}:{sub:02X} answered {len(data)} byte(s); '
                             f'{rtype.name} is {rtype.bits // 8}')
        return unpack(rtype.name, data)

    def write_register(self, address: str, data_type: str, value: int | str) -> None:
        index, sub = parse_address(address)
        if data_type.lower() == 'string':
            data = str(value).encode('latin-1')
        else:
            rtype = register_type(data_type)
            data = pack(rtype.name, rtype.check(int(value)))
        self.link.download(index, sub, data)
        self._written.pop((index, sub), None)
        self._standing = None      # a register may set the position: read again at the next poll


# ---------------------------------------------------------------------------- vendor
PARAMS = (
    ParamSpec('can.interface', 'socketcand',
              "python-can interface: 'socketcand' (the loopback broker of the tests and the "
              "demo), 'socketcan' for a Linux CAN interface, 'pcan', 'kvaser', 'slcan' or any "
              'other python-can interface (docs/vector_step.md, CAN adapters)', scope='bus'),
    ParamSpec('can.channel', 'can0', "CAN channel: 'can0' (socketcan), 'PCAN_USBBUS1' (pcan), "
              "'0' (kvaser), '/dev/ttyACM0' (slcan)", scope='bus'),
    ParamSpec('can.bitrate', 125000, 'bit rate [bit/s]: 10k, 20k, 50k, 125k, 250k, 500k, 800k, '
              '1M (Rcanbaud 0..7; 125k with the rotary switches at 00); pcan, kvaser and slcan '
              'set it, socketcan takes it from ip link, socketcand ignores it',
              scope='bus', min_value=10000, max_value=1000000),
    ParamSpec('can.host', '127.0.0.1', 'socketcand server host', scope='bus'),
    ParamSpec('can.port', 29536, 'socketcand server port', scope='bus', min_value=1,
              max_value=65535),
    ParamSpec('can.eds_file', '', "EDS of the drives ('' = config/vector_step.eds of the package)",
              scope='bus'),
    ParamSpec('can.sync_period_s', 0.1, 'SYNC (COB-ID 0x080) sent by this node while the bus is '
              'open, every this many seconds: the drives watch it (sync_timeout_s) and stop when '
              'the node or the bus dies [s]; 0 = no SYNC', scope='bus', min_value=0.0,
              max_value=10.0),
    ParamSpec('can.master_node_id', 127, "node-ID of this node's own heartbeat (no drive may "
              'have it)', scope='bus', min_value=1, max_value=127),
    ParamSpec('can.master_heartbeat_ms', 100, "this node's heartbeat (0x700 + "
              'can.master_node_id, OPERATIONAL) every this many ms; each drive watches it '
              f'(0x1016, {MASTER_HEARTBEAT_PERIODS} periods) for its LED and EMCY 0x8130 only '
              '[ms]; 0 = none', scope='bus', min_value=0,
              max_value=0xFFFF // MASTER_HEARTBEAT_PERIODS),
    ParamSpec('node_id', 1, 'CANopen node-ID (rotary switches + Rcanaddr; 125 with switches 00)',
              min_value=1, max_value=127),
    ParamSpec('heartbeat_period_ms', 100, 'producer heartbeat time 0x1017 written at every boot '
              '[ms]; 0 = none (then no heartbeat-loss detection)', min_value=0,
              max_value=65535),
    ParamSpec('heartbeat_timeout_s', 1.0, 'no heartbeat for this long: link lost, reconnect [s]',
              min_value=0.01, max_value=60.0),
    ParamSpec('sync_timeout_s', 0.5, 'drive-side watchdog, written to 0x1006 at every boot: no '
              'SYNC for this long is the drive alarm "missing SYNC" (Ralarm32 bit 18), which '
              f'stops the axis on its emergency ramp [s]; at least {SYNC_TIMEOUT_MIN_PERIODS} x '
              'can.sync_period_s; 0 = off', min_value=0.0, max_value=60.0),
    ParamSpec('tpdo_event_timer_ms', 100, 'event timer of TxPDO2 (statusword + position): sent '
              'at least this often besides on change [ms]; 0 = on change only (then a motion '
              'command first reads the statusword by SDO)', min_value=0, max_value=65535),
    ParamSpec('tpdo_inhibit_ms', 10.0, 'inhibit time of TxPDO2 (statusword + position) and '
              'TxPDO3 (statusword + velocity), 0x1801/0x1802:03: while the axis moves they go '
              'out at most this often instead of at every change, which would fill a 125 kbit/s '
              'bus with one moving axis [ms]; 0 = at every change (the DS-301 default)',
              min_value=0.0, max_value=6553.5),
    ParamSpec('boot_timeout_s', 2.0, 'wait for the boot-up after NMT reset communication [s]',
              min_value=0.05, max_value=60.0),
    ParamSpec('boot_retries', 3, 'SDO pings before a connect attempt gives up', min_value=1,
              max_value=100),
)


def make_bus(params: Mapping[str, Any]) -> CanBus:
    params = VENDOR.with_defaults(params)
    return CanBus(interface=str(params['can.interface']), channel=str(params['can.channel']),
                  bitrate=int(params['can.bitrate']), host=str(params['can.host']),
                  port=int(params['can.port']), timeout_s=float(params['timeout_s']),
                  sync_period_s=float(params['can.sync_period_s']),
                  master_node_id=int(params['can.master_node_id']),
                  master_heartbeat_ms=int(params['can.master_heartbeat_ms']),
                  owner_thread_priority=int(params.get('owner_thread_priority', 0)))


def make_drive(bus: Bus, name: str, params: Mapping[str, Any]) -> VectorStepDrive:
    return VectorStepDrive(bus, name, params)


VENDOR = Vendor(name='AEC Vector Step', params=PARAMS, make_bus=make_bus, make_drive=make_drive,
                drive_defaults={'steps_per_rev': 3200.0, 'homing.method': 35},
                validate=validate, share_files={'can.eds_file': vm.EDS_FILE},
                scanner=vector_step_scan.SCANNER)
