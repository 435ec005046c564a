"""Lika RD4 ROTADRIVE over Modbus RTU (RS-485): the vendor's entry (make_bus, make_drive,
validate and its line check, VENDOR).

Several RD4 units share one serial line (`ModbusRtuBus`), each addressed by its dip-switch node
ID. Register numbers and bit meanings come from the manual `lika_rd4_modbus_rtu.txt` (§8.1.1
machine data and Control Word [0x2A], §8.1.2 input registers). The package: the map in
`regmap.py`, the parameters, their defaults and the per-unit rules in `settings.py` (which the
entry and the drive class both import, never the other way round), the drive class `Rd4Drive`
in `drive.py` on its base `Rd4Unit` (`unit.py`: the line, the Control Word intent, the identity
checks), the bus scanner in `scan.py`. No rclpy.

How the contract maps to the RD4 (docs/rd4.md has the full table):
- connect: identity (HW Version: RD4 with Modbus; Dip-switch node ID = the address; Dip-switch
  baud rate = the line's; Gear ratio 32 or 48; machine data in range unless the unit lists them
  as wrong) or IdentityError; writes nothing.
- state: one FC04 of 0x00-0x07 per poll (Alarms, Status word, Current position, Current velocity,
  Position following error, Current value); the Wrong parameters list only when its alarm is on.
- enable: Target position := Current position, Control Word with Emergency and Stop high (plus
  Watch dog enable and Axis torque as configured), and an Alarm reset edge to leave the power-up
  Emergency (§5.3). disable: Stop low, Emergency high, watchdog and hold torque off.
- move, jog, preset: refused unless enabled, checked on the wire (Alarms register read first);
  values outside the registers' ranges are refused before anything is written.
- move: Target position (FC16) + a clean 0 -> 1 edge of Start; Start is cleared once the target
  is reached, so the move is right whether the firmware starts on the edge or the level.
- velocity: Jog + / Jog - at Jog speed [0x0C]; a new speed re-issues the jog (clear, then set).
- stop: Stop (bit 2) low, restored at standstill; quick stop: Emergency (bit 7) low.
- home: the RD4 has no homing run: Preset [0x16-0x17] := homing.offset and a rising edge of
  Perform counting preset (bit 11), so it is right whether the register write or the edge applies.
"""

from __future__ import annotations

from typing import Any, Mapping

from ...contract import param_rules
from ...contract.drive import Bus, Vendor
from ...protocol.modbus_rtu import ModbusRtuBus
from . import scan as rd4_scan
from . import settings
from .drive import Rd4Drive
from .settings import (
    HOMING_METHOD_PRESET,
    MIN_WATCHDOG_POLL_HZ,
    PARAMS,
    _check_drive,
    _number,
)
from .unit import BAUD_RATES

# The entry's names, and those of settings.py / drive.py / unit.py that code imports from the
# package.
__all__ = ['BAUD_RATES', 'HOMING_METHOD_PRESET', 'MIN_WATCHDOG_POLL_HZ', 'PARAMS', 'VENDOR',
           'Rd4Drive', 'make_bus', 'make_drive', 'validate']


def _line_settings(params: Mapping[str, Any]) -> tuple:
    """(port, baud, parity, stopbits, timeout_s, retries) of the line, or ValueError."""
    params = VENDOR.with_defaults(params)
    port = str(params['port'])
    if not port:
        raise ValueError("parameter port: '' (allowed: a serial device such as /dev/ttyUSB0, "
                         'or a pyserial URL)')
    allowed_bauds = ', '.join(str(b) for b in BAUD_RATES)
    baud = _number(params, 'baudrate', int, allowed_bauds)
    if baud not in BAUD_RATES:
        raise ValueError(f'parameter baudrate: {baud} is not an RD4 baud rate (allowed: '
                         f'{allowed_bauds}; §4.4.2 dip-switch)')
    parity = str(params['parity']).upper()
    if parity not in ('N', 'E', 'O'):
        raise ValueError(f'parameter parity: {parity!r} (allowed: N, E, O)')
    stopbits = _number(params, 'stopbits', int, '0, 1 or 2')
    need = 2 if parity == 'N' else 1
    if stopbits not in (0, need):
        raise ValueError(f'parameter stopbits: {stopbits} with parity {parity} is not the RD4 '
                         f'format (allowed: 0 = auto or {need}; §7.3.1 11-bit characters, '
                         '"the parity bit is replaced by a stop bit")')
    timeout_s = _number(params, 'timeout_s', float, 'seconds > 0', 0.5)
    retries = _number(params, 'retries', int, '0..5')
    if not timeout_s > 0 or not 0 <= retries <= 5:
        raise ValueError(f'parameter timeout_s/retries: {timeout_s:g} s / {retries} (allowed: '
                         'timeout_s > 0, retries 0..5)')
    return port, baud, parity, stopbits or need, timeout_s, retries


def make_bus(params: Mapping[str, Any]) -> ModbusRtuBus:
    port, baud, parity, stopbits, timeout_s, retries = _line_settings(params)
    return ModbusRtuBus(port, baud, parity, stopbits, timeout_s=timeout_s, retries=retries,
                        rs485=bool(VENDOR.with_defaults(params)['rs485']))


def make_drive(bus: Bus, name: str, params: Mapping[str, Any]) -> Rd4Drive:
    _check_drive(name, params)
    return Rd4Drive(bus, name, params)


def validate(params: Mapping[str, Any]) -> list[str]:
    """The RD4's parameter rules on the node's parameters (param_rules), at start-up and for
    every run-time change: the line settings, and per unit homing, node ID and watchdog."""
    return param_rules.check_each(params, _line_settings, _check_drive)


VENDOR = Vendor(
    name='Lika RD4',
    params=PARAMS,
    make_bus=make_bus,
    make_drive=make_drive,
    drive_defaults=settings.DRIVE_DEFAULTS,
    validate=validate,
    scanner=rd4_scan.SCANNER,
)
