"""R.T.A. X-PLUS MT (B4/S4) over Modbus TCP: the vendor's entry (make_bus, make_drive, validate
and its link check, VENDOR).

Register numbers, bit meanings and timings come from the manual `rta_xplus_mt_modbus_tcp.txt`
(§12 drive sub-states and T13/T14, §13 registers, App.1). The package: the map in `regmap.py`,
the parameters, their defaults and the per-drive rules in `settings.py` (which the entry and the
drive class both import, never the other way round), the drive class `XplusMtDrive` in
`drive.py` on its base `XplusMtUnit` (`unit.py`: registers, identity, the polled state), the bus
scanner in `scan.py`. The CiA 402 state machine is
`profiles/cia402/state_machine.py`, and enable, disable, the motion preconditions and the fault
reset are `profiles.cia402.drive.Cia402Drive`'s, whose hooks the drive class fills. No rclpy.
"""

from __future__ import annotations

from typing import Any, Mapping

from ...contract import param_rules
from ...contract.drive import Bus, Vendor
from ...protocol.modbus_tcp import ModbusTcpBus
from ...protocol.modbus_tcp import make_bus as make_tcp_bus
from . import scan as xplus_mt_scan
from . import settings
from .drive import XplusMtDrive
from .settings import (
    DRIVE_BUS_PARAMS,
    PARAMS,
    REG,
    WATCHDOG_MIN_MS,
    WATCHDOG_MIN_POLLS,
    WATCHDOG_MS_DEFAULT,
    _check_drive,
)
from .unit import SPLIT_READS, STATE_BLOCK

# The entry's names, and those of settings.py / drive.py / unit.py that code imports from the
# package.
__all__ = ['DRIVE_BUS_PARAMS', 'PARAMS', 'REG', 'SPLIT_READS', 'STATE_BLOCK', 'VENDOR',
           'WATCHDOG_MIN_MS', 'WATCHDOG_MIN_POLLS', 'WATCHDOG_MS_DEFAULT', 'XplusMtDrive',
           'make_bus', 'make_drive', 'validate']


def make_bus(params: Mapping[str, Any]) -> ModbusTcpBus:
    """Bus params 'host', 'port' and the common 'timeout_s'. For a drive with its own host or
    port the node passes the bus params with the drive's non-empty values in their place."""
    return make_tcp_bus(VENDOR.with_defaults(params))


def _check_link(params: Mapping[str, Any]) -> None:
    """What protocol.modbus_tcp.make_bus refuses, without making the bus (same messages)."""
    params = VENDOR.with_defaults(params)
    if not str(params['host']).strip():
        raise ValueError("host: '' (allowed: an IP address or host name of the Modbus server)")
    port = params['port']
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ValueError(f'port: {port!r} (allowed: a TCP port 1..65535)')


def make_drive(bus: Bus, name: str, params: Mapping[str, Any]) -> XplusMtDrive:
    _check_drive(name, params)
    return XplusMtDrive(bus, name, params)


def validate(params: Mapping[str, Any]) -> list[str]:
    """The X-PLUS MT's parameter rules on the node's parameters (param_rules), at start-up and
    for every run-time change: each drive's link, and per drive homing method, unit id, word
    order, resolution, watchdog against the poll rate, input config."""
    return param_rules.check_each(params, _check_link, _check_drive, DRIVE_BUS_PARAMS)


VENDOR = Vendor(
    name='X-PLUS MT',
    params=PARAMS,
    make_bus=make_bus,
    make_drive=make_drive,
    drive_defaults=settings.DRIVE_DEFAULTS,
    drive_bus_params=DRIVE_BUS_PARAMS,
    validate=validate,
    scanner=xplus_mt_scan.SCANNER,
)
