"""The AEC Vector Step drive class: the CiA 402 drive on its node and its process image.

`VectorStepDrive` is `Cia402Drive` (profiles/cia402/drive.py: enable, disable, the motion
preconditions and the fault reset; this class fills its hooks) with three bases of its own,
split from it for size (one record, one class made): `ProcessImage` (pdo.py: the PDO set, the
TxPDO cache, burst coherence, snapshot vouching), `CanopenNode` (node.py: boot, identity,
liveness, SDO access) and `ModeCommands` (modes.py: profile position, JOG, homing, interpolated
position, stop). Here: the drive's record (`__init__`: its parameters, link and state), the
controlword by RxPDO, connect (the node's boot, then the state machine from the image), the
DriveState a poll decodes from the image (`_read_state_steps`: faults, warnings, homing), the
power stage hooks and the mode switch, the fault reset and save.

Every command rides on an RxPDO that carries the controlword with the mode or the target
(`_write_controlword`), and connect maps those same PDOs, so boot, state machine, motion and
interpolation share one PDO image. Every operation that waits or takes more than two
transactions is step-wise (`drive.Operation`: one SDO or PDO exchange per step, `yield POLL_S`
while waiting for a TxPDO); stop() is one frame (two during homing) and never waits.

canopen's BaseNode402 is used for its PDO plumbing (tpdo_values), not for the parts that do not
fit this drive (digest section 10): `op_mode` (its getter has no name for mode -1, its setter
refuses mode 7 because 0x6502 lacks bit 6, and it waits for a "periodic" TxPDO that an
event-driven TxPDO seen twice looks like), its `controlword` setter (it would send RxPDO1 with a
stale mode byte 0), `homing()` (the AEC method numbers are not the library's, bit 10 during homing
is not documented) and `reset_from_fault()` (the manual clears 0x1003 first). No rclpy.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Mapping

from ...contract.capabilities import CachedState, Interpolating, Retargeting
from ...contract.drive import (
    Bus,
    DriveError,
    DriveState,
    HomingState,
    LinkError,
    Operation,
    State,
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
from ...protocol.canopen_link import POLL_S, CanBus, RemoteDrive, SdoAbortError
from . import regmap as vm
from . import settings
from .modes import JogMode, ModeCommands
from .node import CanopenNode
from .pdo import ProcessImage
from .settings import MASTER_HEARTBEAT_PERIODS

# the vendor's one logger (the package's name, as before the package was split into modules)
logger = logging.getLogger(__package__)

SAVE_TIMEOUT_S = 5.0           # Rloadsav 0x81 (EEPROM write) must read 0 again within this
SAVE_POLL_S = 0.02
WARNING_READ_PERIOD_S = 1.0    # Rwarning is read by SDO at most this often while SW bit 7 is set
# A standing axis' 0x6064 is read by SDO after its statusword came (_standing_position); a
# newer statusword before the answer voids it: at most this many reads in one poll, then the
# snapshot does not show the axis standing (the next poll reads again).
STANDING_READS = 3
HOLD_CW = {                    # controlword that keeps each state (sent with a mode change)
    State.SWITCH_ON_DISABLED: cia402.CW_DISABLE_VOLTAGE, State.READY_TO_SWITCH_ON:
    cia402.CW_SHUTDOWN, State.SWITCHED_ON: cia402.CW_SWITCH_ON,
    State.OPERATION_ENABLED: CW_ENABLE_OPERATION, State.QUICK_STOP_ACTIVE: cia402.CW_QUICK_STOP,
}


class VectorStepDrive(ModeCommands, CanopenNode, ProcessImage, Cia402Drive, CachedState,
                      Retargeting, Interpolating):
    """One Vector Step on a CAN bus (node-ID = parameter `node_id`).

    CachedState: read_state gives the TxPDO values (SDO only for faults, warnings and a standing
    axis' position; pdo.ProcessImage). Retargeting: every PP move sets bit 5, "1 = Cambia
    setpoint immediatamente" ([CONTROLWORD]). Interpolating: interpolated position on SYNC
    (modes.ModeCommands)."""

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
        params = settings.with_defaults(params)
        super().__init__(bus, name, params)
        if not isinstance(bus, CanBus):
            raise TypeError(f'{name}: Vector Step needs a CanBus, got {type(bus).__name__}')
        self.can: CanBus = bus
        self.node_id = int(params['node_id'])
        bus.claim(self.node_id, name)
        self.address = self.node_id
        settings._check_drive(name, params, self.can.master_heartbeat_ms,
                              self.can.sync_period_s)
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
        self._ip_active = False            # start_interpolation done; no stop or error since
        self._init_image()                 # the TxPDO cache and its snapshots (pdo.py)

    def _prefix(self) -> str:
        return f'{self.name} (node {self.node_id}): '

    # ------------------------------------------------------------------ controlword / PDO access
    @property
    def _cw(self) -> int:
        """The controlword last commanded (the driver's intent; never read back)."""
        return self.cia.controlword or 0

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

    # ------------------------------------------------------------------ life cycle
    def connect(self) -> Operation[dict[str, str]]:
        """The node's boot (`_boot`), then the controlword, mode and target of the state machine
        from the image; a drive still moving is stopped."""
        self._configured = False
        self._quiet = None
        self.link.attach()
        self.link.emcy = None
        self._written.clear()
        self._fault_cache = None
        self._homing = HomingState.IDLE
        self._ip_active = False
        identity = yield from self._boot()   # node.py: NMT, identity, watchdogs, PDOs, seed
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

    # ------------------------------------------------------------------ state
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
