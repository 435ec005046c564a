"""The drive skeleton every CiA 402 vendor shares; no transport, no rclpy.

`Cia402Drive` is a `drive.Drive` whose controlword and statusword follow CiA 402: the R.T.A.
X-PLUS MT (Modbus holding registers 1040/1001) and the AEC Vector Step (CANopen 0x6040/0x6041 by
RxPDO/TxPDO). Written once here, on `cia402.Cia402Walker`: the power stage (enable, disable), the
preconditions of a motion command (`_require_enabled`, `_ensure_mode`), the start edge of the
modes that run while controlword bit 4 is high and the fault reset. The modes of operation are
`modes` objects the vendor lists in `MODES` (registered in `self.modes` by code): each
knows its start and stop and its statusword bits. A vendor class gives its object access
(`_read_statusword`, `_write_controlword` and how it reads and writes the mode and the target)
and its quirks through the hook methods below, each named for the step of the skeleton it takes.

A hook typed `X | Operation[X]` may be step-wise (`drive.Operation`) or return at once: the
skeleton runs it either way, so a vendor that needs no transaction there adds no step.
"""

from __future__ import annotations

import abc
from typing import Any, Mapping, TypeVar

from ...contract.drive import Bus, Drive, DriveError, HomingState, Operation, State, is_operation
from . import state_machine as cia402
from .modes import HomingMode, Mode
from .state_machine import CW_BIT_NEW_SET_POINT, FAULT_STATES

T = TypeVar('T')


def _run(result: T | Operation[T]) -> Operation[T]:
    """A hook's result: its steps run here when it is step-wise, else the value as it is."""
    if is_operation(result):
        return (yield from result)
    return result


class Cia402Drive(Drive):
    """Enable, disable, `_require_enabled`, `_ensure_mode` and fault reset of a CiA 402 drive.

    The vendor sets the class attributes where its manual gives other values and implements the
    abstract hooks; the hooks with a body here do nothing unless overridden.
    """

    # Controlword write -> first statusword read that checks its effect
    # (Cia402Walker.min_delay_s).
    CW_SW_DELAY_S = 0.012
    # Statusword poll interval while the walker waits (Cia402Walker.POLL_S).
    STATUSWORD_POLL_S = cia402.Cia402Walker.POLL_S
    ENABLE_TIMEOUT_S = 1.0           # the whole walk to OPERATION ENABLED
    DISABLE_TIMEOUT_S = 1.0          # the whole walk to SWITCH ON DISABLED
    FAULT_RESET_TIMEOUT_S = 1.0      # one fault-reset edge and the wait for FAULT to end
    FAULT_RESET_ATTEMPTS = 1         # edges tried, each after _before_fault_reset(attempt)
    HANDSHAKE_TIMEOUT_S = 0.5        # new set point -> set-point acknowledge (statusword bit 12)
    MODE_SWITCH_TIMEOUT_S = 0.5      # modes of operation written -> its display shows it
    # True: a statusword read is a transaction of its own (an FC03): the skeleton ends the step
    # after it, so that the next transaction goes in a step of its own. False: the statusword
    # comes from a cache (TxPDOs) and costs no transaction.
    STATUSWORD_READ_IS_TRANSACTION = False
    # States disable() leaves as they are, writing nothing.
    DISABLE_LEAVES: tuple[State, ...] = FAULT_STATES
    # _require_enabled's refusal; {what}: the command, {state}: cia402.describe(statusword).
    NOT_ENABLED_TEXT = '{what}: drive is in {state}, not OPERATION ENABLED; enable first'
    # The modes of operation of the manual (modes.py objects), self.modes by code.
    MODES: tuple[Mode, ...] = ()
    # start_edge writes the low level even when bit 4 is low already (False: only when it is
    # high or not known).
    START_EDGE_LOW_ALWAYS = False

    def __init__(self, bus: Bus, name: str, params: Mapping[str, Any]):
        super().__init__(bus, name, params)
        self.cia = cia402.Cia402Walker(self._read_statusword, self._write_controlword,
                                       min_delay_s=self.CW_SW_DELAY_S, name=name)
        self.cia.POLL_S = self.STATUSWORD_POLL_S
        self.modes: dict[int, Mode] = {mode.code: mode for mode in self.MODES}
        # What the statusword last showed of homing (bits 13/12/10) in homing mode before a
        # homing start edge, as the vendor's start_homing read it (None: not read): a result it
        # still shows after the edge may be the previous homing's (_homing_started).
        self._homing_shown_before: HomingState | None = None

    # ------------------------------------------------------------------ object access
    @abc.abstractmethod
    def _read_statusword(self) -> int:
        """The statusword (0x6041; X-PLUS MT register 1001)."""

    @abc.abstractmethod
    def _write_controlword(self, cw: int) -> None:
        """One controlword write (0x6040; X-PLUS MT register 1040)."""

    def _end_read_step(self) -> Operation[None]:
        """End the step after a statusword read that was a transaction (see
        STATUSWORD_READ_IS_TRANSACTION); nothing after a cached one."""
        if self.STATUSWORD_READ_IS_TRANSACTION:
            yield 0.0

    # ------------------------------------------------------------------ power stage
    def enable(self) -> Operation[None]:
        """OPERATION ENABLED without moving. Refused in FAULT (`_enable_refusal` says why);
        otherwise the vendor holds the position (`_hold_position`: target = actual position,
        profile position mode), checks what its manual wants on the way (`_before_switch_on`),
        then the walk of cia402's tables; a walk that sticks is explained by `_enable_failed`."""
        sw = self._read_statusword()
        state = cia402.decode_state(sw)
        if state in FAULT_STATES:
            text = yield from _run(self._enable_refusal(sw))
            raise DriveError(f'{text}; call fault_reset first')
        if state == State.OPERATION_ENABLED:
            self._enabled(switched_on=False)
            return
        yield from self._end_read_step()
        yield from _run(self._hold_position(state))
        yield from _run(self._before_switch_on(state))
        try:
            yield from self.cia.bring_to(State.OPERATION_ENABLED, self.ENABLE_TIMEOUT_S)
        except DriveError as exc:
            yield from self._end_read_step()
            yield from _run(self._enable_failed(exc))
            raise
        self._enabled(switched_on=True)

    @abc.abstractmethod
    def _enable_refusal(self, sw: int) -> str | Operation[str]:
        """What enable() tells about the fault in `sw` (the fault and its code); enable adds
        '; call fault_reset first'."""

    @abc.abstractmethod
    def _hold_position(self, state: State) -> None | Operation[None]:
        """Nothing moves once enabled: target position = actual position, profile position
        mode (`state`: the state enable() starts from)."""

    def _before_switch_on(self, state: State) -> None | Operation[None]:
        """What the vendor checks before the walk to OPERATION ENABLED; raises DriveError."""

    def _enable_failed(self, exc: DriveError) -> None | Operation[None]:
        """The walk to OPERATION ENABLED stuck (`exc`): raise a DriveError that says why, or
        return to let `exc` go up as it is."""

    def _enabled(self, switched_on: bool) -> None:
        """The drive is in OPERATION ENABLED; `switched_on`: enable() brought it there (False:
        it was there already)."""

    def disable(self) -> Operation[None]:
        """SWITCH ON DISABLED (current off), except from DISABLE_LEAVES."""
        state = cia402.decode_state(self._read_statusword())
        self._disabling()
        if state in self.DISABLE_LEAVES:
            return
        yield from self._end_read_step()
        yield from self.cia.bring_to(State.SWITCH_ON_DISABLED, self.DISABLE_TIMEOUT_S)
        self._disabled()

    def _disabling(self) -> None:
        """disable() has read the state; called before anything is written."""

    def _disabled(self) -> None:
        """disable() brought the drive to SWITCH ON DISABLED."""

    # ------------------------------------------------------------------ motion preconditions
    def _require_enabled(self, what: str) -> int | None:
        """DriveError unless the drive is in OPERATION ENABLED, as `_statusword_for_motion`
        reads it; returns the modes of operation display that read gave (None: it gives
        none), for `_ensure_mode`."""
        sw, mode = self._statusword_for_motion()
        if cia402.decode_state(sw) != State.OPERATION_ENABLED:
            raise DriveError(self.NOT_ENABLED_TEXT.format(what=what,
                                                          state=cia402.describe(sw)))
        return mode

    @abc.abstractmethod
    def _statusword_for_motion(self) -> tuple[int, int | None]:
        """(statusword, modes of operation display or None) checked before a motion command."""

    def _ensure_mode(self, code: int, what: str = '', current: int | None = None
                     ) -> Operation[Mode]:
        """Modes of operation = `code`, unless the drive is in it already (`_in_mode`); returns
        the mode object. `what`: the command, for messages; `current`: what `_require_enabled`
        returned just before (the step that read it)."""
        mode = self.modes[code]
        yield from self._end_read_step()
        if not self._in_mode(code, current):
            yield from self._switch_mode(mode, what, current)
        return mode

    @abc.abstractmethod
    def _in_mode(self, mode: int, current: int | None = None) -> bool:
        """The drive is in `mode` (`current`: as in _ensure_mode)."""

    @abc.abstractmethod
    def _switch_mode(self, mode: Mode, what: str, current: int | None) -> Operation[None]:
        """Write modes of operation = `mode.code` and wait until the drive shows it; DriveError
        when it does not."""

    def start_edge(self, base_cw: int, bits: int) -> Operation[None]:
        """Controlword bit 4 rising edge, then held high (`bits` includes bit 4): the homing
        operation start and the start of the modes that run while bit 4 is high
        (modes.EdgeStartMode). The low level `base_cw` first when bit 4 is high or not
        known (always with START_EDGE_LOW_ALWAYS) and the controlword -> statusword delay, so
        the drive sees the edge; then `base_cw | bits`."""
        cw = self.cia.controlword
        if self.START_EDGE_LOW_ALWAYS or cw is None or cw & CW_BIT_NEW_SET_POINT:
            self.cia.write(base_cw)
            yield self.CW_SW_DELAY_S
        self.cia.write(base_cw | bits)

    def _homing_started(self, mode: HomingMode) -> None | Operation[None]:
        """After the homing start edge: wait until the statusword shows this homing (bits
        13/12/10, `mode.state`): running or failed, or attained where the drive did not show
        ATTAINED before the edge (`_homing_shown_before`). The previous homing's ATTAINED,
        which a drive may show for a while after the edge before it runs, is no start: the
        homing would be answered done while the axis still runs it. Still "not started" after
        HANDSHAKE_TIMEOUT_S: DriveError. ATTAINED all that time where it showed ATTAINED before
        (or nothing is known): a homing that ended where it began before the drive could show
        it running (the manual's statusword delay, CW_SW_DELAY_S, is far shorter), taken as
        done."""
        before = self._homing_shown_before

        def this_homing(sw: int) -> bool:
            state = mode.state(sw)
            return state in (HomingState.RUNNING, HomingState.ERROR) or (
                state == HomingState.ATTAINED and before not in (HomingState.ATTAINED, None))
        met, sw = yield from self.cia.wait_for(this_homing, self.HANDSHAKE_TIMEOUT_S)
        if not met and mode.state(sw) != HomingState.ATTAINED:
            raise DriveError(f'home: homing did not start (status word bits 13/12/10 still '
                             f'"not started"): {cia402.describe(sw)}')

    @property
    def motion_sent_t(self) -> float | None:
        """The new set point's write (controlword bit 4 up: the drive starts then)."""
        return self.cia.set_point_sent_t

    # ------------------------------------------------------------------ maintenance
    def fault_reset(self) -> Operation[str]:
        """Up to FAULT_RESET_ATTEMPTS fault-reset edges (Cia402Walker.fault_reset), each after
        `_before_fault_reset`; '' once the drive is out of FAULT (`_fault_cleared`), else what
        `_fault_remains` says."""
        sw = 0
        for attempt in range(self.FAULT_RESET_ATTEMPTS):
            yield from _run(self._before_fault_reset(attempt))
            sw = yield from self.cia.fault_reset(self.FAULT_RESET_TIMEOUT_S)
            if cia402.decode_state(sw) not in FAULT_STATES:
                self._fault_cleared(sw)
                return ''
        return (yield from _run(self._fault_remains(sw)))

    def _before_fault_reset(self, attempt: int) -> None | Operation[None]:
        """What the vendor's manual does before fault-reset edge number `attempt` (from 0)."""

    def _fault_cleared(self, sw: int) -> None:
        """The fault reset worked: `sw` is the statusword out of FAULT."""

    @abc.abstractmethod
    def _fault_remains(self, sw: int) -> str | Operation[str]:
        """fault_reset()'s answer when the drive is still in FAULT after the last edge (`sw`):
        the fault and that its cause is still present."""
