"""The Lika RD4's parameters: what the vendor entry and the drive class both need.

The ParamSpecs (PARAMS), the drive defaults and the preset homing method they name,
`with_defaults` (what VENDOR.with_defaults gives, without the Vendor object) and the rules of
one unit's parameters that make_drive and validate apply (`_check_drive`, with `_number`, which
the entry's line check shares). Not here: the line check, make_bus, make_drive, validate and
VENDOR (the entry, `__init__.py`), nor anything of the drive itself (`unit.py`, `drive.py`);
this module imports neither, they import it.
"""

from __future__ import annotations

from typing import Any, Mapping

from ...contract.drive import ParamSpec, param_defaults
from ...protocol import serial_port

HOMING_METHOD_PRESET = 35      # CiA 402 method 35 "current position is home": what a preset is
MIN_WATCHDOG_POLL_HZ = 5.0     # spec §9B: poll period <= 200 ms keeps the 1 s watchdog fed

PARAMS = (
    ParamSpec('port', '/dev/ttyUSB0', 'serial port of the RS-485 line (a device path or a '
              'pyserial URL); the simulator gives a symlink to its pty', scope='bus'),
    ParamSpec('baudrate', 9600, 'baud rate, as the dip-switch of every unit on the line: 9600 '
              'or 19200 (§4.4.2; factory 9600)', scope='bus', min_value=9600, max_value=19200),
    ParamSpec('parity', 'E', 'parity as the dip-switch: E (factory), O or N; a pty accepts N '
              'only', scope='bus', choices=('N', 'E', 'O')),
    ParamSpec('stopbits', 0, 'stop bits: 0 = the RD4 format (§7.3.1: 11-bit characters, 1 stop '
              'bit with parity, 2 without)', scope='bus', min_value=0, max_value=2),
    ParamSpec('retries', 1, 'resends after a timeout, a CRC error or a reply that does not '
              'match; then the link counts as lost', scope='bus', min_value=0, max_value=5),
    ParamSpec('rs485', False, serial_port.RS485_DESCRIPTION, scope='bus'),
    ParamSpec('node_id', 1, 'node ID on the dip-switch (1..247, §4.4.1)', min_value=1,
              max_value=247),
    ParamSpec('watchdog', True, 'set Watch dog enable (Control Word bit 8) while enabled: the '
              'unit stops with an alarm when no frame reaches it for 1 s (§8.1.1)'),
    ParamSpec('hold_torque', True, 'set Axis torque (Control Word bit 12) while enabled: PWM '
              'stays on in position'),
    ParamSpec('velocity_source', 'register', "joint velocity from 'register' (Current velocity "
              "[0x04], refreshed once per second, §8.1.2; 0 when Axis running = 0) or "
              "'position' (Current position differentiated between polls)",
              choices=('register', 'position')),
)

# Vendor.drive_defaults
DRIVE_DEFAULTS = {'steps_per_rev': 1024.0, 'homing.method': HOMING_METHOD_PRESET}


def with_defaults(params: Mapping[str, Any]) -> dict[str, Any]:
    """One unit's `params` over the RD4's defaults: VENDOR.with_defaults(params) (the RD4 has
    no per-drive link parameters, Vendor.drive_bus_params)."""
    return param_defaults(PARAMS, DRIVE_DEFAULTS, (), params)


def _number(params: Mapping[str, Any], name: str, kind: type, allowed: str,
            default: Any = None) -> Any:
    """A numeric parameter, or ValueError naming it in one line (`default` only for the
    node's common parameters: the RD4's own come from with_defaults)."""
    value = params.get(name, default)
    try:
        if isinstance(value, bool) or (kind is int and float(value) != int(float(value))):
            raise ValueError
        return kind(value)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f'parameter {name}: {value!r} is not a number (allowed: {allowed})') \
            from None


def _check_drive(name: str, params: Mapping[str, Any]) -> None:
    """The rules of one unit's parameters (with the bus-level ones), or ValueError."""
    prefix = f'parameter drives.{name}.'
    params = with_defaults(params)
    method = params['homing.method']
    if method != HOMING_METHOD_PRESET:
        raise ValueError(f'{prefix}homing.method: {method} is not possible on the RD4 (allowed: '
                         f'{HOMING_METHOD_PRESET} = preset at the current position; the RD4 has '
                         'no homing run)')
    node_id = params['node_id']
    if isinstance(node_id, bool) or not isinstance(node_id, int) or not 1 <= node_id <= 247:
        raise ValueError(f'{prefix}node_id: {node_id!r} (allowed: 1..247, §4.4.1)')
    rate = _number(params, 'publish_rate_hz', float, 'Hz > 0', 50.0)
    if params['watchdog'] and rate < MIN_WATCHDOG_POLL_HZ:
        raise ValueError(f'{prefix}watchdog: true needs publish_rate_hz >= '
                         f'{MIN_WATCHDOG_POLL_HZ:g} to keep the 1 s watchdog fed (now {rate:g})')
