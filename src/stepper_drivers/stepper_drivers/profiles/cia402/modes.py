"""CiA 402 modes of operation as small objects; no transport, no rclpy.

One class per mode, as ros2_canopen's canopen_402_driver has (a mode object per modes of
operation value, registered with the motor): each knows its code (0x6060; X-PLUS MT register
1041, §12 "Mode of Operation"), its name for messages, what controlword bit 4 starts in it, what
the "operation mode specific" statusword bits 12 and 13 mean in it, how a run is started and how
it is stopped. A `drive.Cia402Drive` lists the modes its manual has (`MODES`) and gives the
object access and its quirks through its hooks; a mode that is not CiA 402 (the AEC JOG of the
Vector Step) derives from `Mode` in its vendor module.

Controlword bit 4 and statusword bits 12/13 per mode (CiA 402 0x6040/0x6041; X-PLUS MT T13/T14):

    mode                     CW bit 4                 SW bit 12              SW bit 13
    1 profile position       new set-point            set-point acknowledge  following error
    3 profile velocity       (X-PLUS MT A10: start)   speed (zero speed)     max slippage error
    6 homing                 homing operation start   homing attained        homing error
    7 interpolated position  enable ip mode           ip mode active         (reserved)
"""

from __future__ import annotations

from typing import Protocol

from ...contract.drive import HomingState, Operation, is_operation
from . import state_machine as cia402
from .state_machine import CW_BIT_HALT, CW_BIT_NEW_SET_POINT, CW_ENABLE_OPERATION, CW_MODE_BITS


class ModeDrive(Protocol):
    """What a mode needs of the drive that runs it (drive.Cia402Drive): its state walker, the
    set-point handshake's time-out, the start edge and the homing start check."""

    cia: cia402.Cia402Walker
    HANDSHAKE_TIMEOUT_S: float

    def start_edge(self, base_cw: int, bits: int) -> Operation[None]: ...

    def _homing_started(self, mode: HomingMode) -> None | Operation[None]: ...


class Mode:
    """A mode of operation: its code, name and the meaning of its mode-specific bits."""

    code = cia402.MODE_NONE
    name = ''
    START_BIT = ''          # controlword bit 4 in this mode
    SW_BIT_12 = ''          # statusword bit 12 in this mode
    SW_BIT_13 = ''          # statusword bit 13 in this mode

    def __init__(self, code: int | None = None, name: str | None = None):
        if code is not None:
            self.code = code
        if name is not None:
            self.name = name

    def __repr__(self) -> str:
        return f'{type(self).__name__}({self.code}, {self.name!r})'

    def stops_by_start_bit(self, cw: int) -> bool:
        """A stop in this mode is controlword bit 4 low (the run lasts while bit 4 is high), not
        Halt (bit 8, CiA 402 in profile position, profile velocity and homing); `cw`: the
        controlword last commanded."""
        return False

    def stop_controlword(self, cw: int | None) -> int:
        """The controlword that stops a run in OPERATION ENABLED, from the last one commanded
        (`cw`; None or not an enable operation: 0x000F): Halt (bit 8) set, or with
        `stops_by_start_bit` the mode bits 4-6 and 8 low."""
        if cw is None or cw & 0x000F != CW_ENABLE_OPERATION:
            cw = CW_ENABLE_OPERATION
        if self.stops_by_start_bit(cw):
            return cw & ~CW_MODE_BITS
        return cw | CW_BIT_HALT


class ProfilePositionMode(Mode):
    """Profile position (1): the new-set-point handshake on bits 4/12 starts a move."""

    code = cia402.MODE_PROFILE_POSITION
    name = 'PROFILE POSITION'
    START_BIT = 'new set-point'
    SW_BIT_12 = 'set-point acknowledge'
    SW_BIT_13 = 'following error'

    def start(self, drive: ModeDrive) -> Operation[int]:
        """New set point, absolute (bit 6 = 0), change set immediately (bit 5): bit 4 up, wait
        for statusword bit 12, bit 4 down (Cia402Walker.start_set_point); the statusword."""
        return (yield from drive.cia.start_set_point(
            CW_ENABLE_OPERATION, relative=False, immediate=True,
            timeout_s=drive.HANDSHAKE_TIMEOUT_S))


class EdgeStartMode(Mode):
    """A mode whose run starts on a controlword bit 4 rising edge and lasts while bit 4 is held
    high (the drive's `start_edge` writes the low level first where needed)."""

    START_BITS = CW_BIT_NEW_SET_POINT   # the bits the start sets with bit 4

    def start_edge(self, drive: ModeDrive) -> Operation[None]:
        yield from drive.start_edge(CW_ENABLE_OPERATION, self.START_BITS)


class ProfileVelocityMode(EdgeStartMode):
    """Profile velocity (3): the drive follows the target velocity. CiA 402 gives bit 4 no
    meaning here; the X-PLUS MT starts on its rising edge (manual A10)."""

    code = cia402.MODE_PROFILE_VELOCITY
    name = 'PROFILE VELOCITY'
    START_BIT = 'start (X-PLUS MT A10)'
    SW_BIT_12 = 'speed (zero speed)'
    SW_BIT_13 = 'max slippage error'


class HomingMode(EdgeStartMode):
    """Homing (6): bit 4 rising edge = homing operation start, held high while homing (a falling
    edge interrupts it); bits 13/12/10 tell the homing status (`cia402.HOMING_STATUS`)."""

    code = cia402.MODE_HOMING
    name = 'HOMING'
    START_BIT = 'homing operation start'
    SW_BIT_12 = 'homing attained'
    SW_BIT_13 = 'homing error'

    def state(self, sw: int) -> HomingState:
        return cia402.homing_state(sw)

    def started(self, sw: int) -> bool:
        """The statusword no longer says "not started" (bits 13/12/10 = 0/0/1)."""
        return self.state(sw) != HomingState.IDLE

    def start(self, drive: ModeDrive) -> Operation[None]:
        """The start edge, then the drive's check that homing runs (`_homing_started`)."""
        yield from self.start_edge(drive)
        started = drive._homing_started(self)
        if is_operation(started):
            yield from started


class InterpolatedPositionMode(Mode):
    """Interpolated position (7): bit 4 high enables the interpolation, statusword bit 12 shows
    it active; bit 4 low disables it (the stop)."""

    code = 7
    name = 'INTERPOLATED POSITION'
    START_BIT = 'enable ip mode'
    SW_BIT_12 = 'ip mode active'

    def active(self, sw: int) -> bool:
        return bool(sw & cia402.SW_BIT_SET_POINT_ACKNOWLEDGE)   # bit 12 = "ip mode active"

    def stops_by_start_bit(self, cw: int) -> bool:
        """Bit 4 low stops a run; with bit 4 low already there is no run for it to stop."""
        return bool(cw & CW_BIT_NEW_SET_POINT)
