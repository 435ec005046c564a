"""The X-MIND K's parameters: what the vendor entry and the drive class both need.

The ParamSpecs (PARAMS), the drive defaults, the homing methods, `with_defaults` (what
VENDOR.with_defaults gives, without the Vendor object) and the rules of one drive's parameters
that its constructor and validate apply (`_check_address`, `_check_drive`). Not here: make_bus,
make_drive, validate and VENDOR (the entry, `__init__.py`), nor anything of the drive itself
(`link.py`, `drive.py` ...); this module imports neither, they import it.
"""

from __future__ import annotations

from typing import Any, Mapping

from ...contract.drive import ParamSpec, param_defaults
from ...protocol import serial_port
from ...protocol import xmind_k as xk

HOMING_METHODS = {3: 'zero search (instruction 03) in + direction, then counter reset',
                  -3: 'zero search (instruction 03) in - direction, then counter reset',
                  60: 'counter reset at the current position (RA)'}

PS = ParamSpec
PARAMS = (
    PS('port', '/dev/ttyUSB0', 'serial port of the RS-485 line (or a pyserial URL; the '
       "simulator's link path)", scope='bus'),
    PS('baudrate', 9600, 'the drive talks 9600 baud only (§3)', scope='bus',
       min_value=1200, max_value=115200),
    PS('parity', 'N', 'N (the drive has no parity bit, §3; ptys refuse E and O)',
       scope='bus', choices=('N', 'E', 'O')),
    PS('stopbits', 1, 'stop bits (1, §3)', scope='bus', min_value=1, max_value=2),
    PS('retries', 1, 'repeats of a string an idle drive left unanswered or answered '
       'garbled (never for PS)', scope='bus', min_value=0, max_value=5),
    PS('local_echo', False, 'the RS-485 adapter echoes what it sends: read and drop it',
       scope='bus'),
    PS('rs485', False, serial_port.RS485_DESCRIPTION, scope='bus'),
    PS('broadcast_start', False, 'start the trajectory segments of the drives of this line '
       'in one instant by the broadcast stored instruction execution 99PS (§2.2.1, '
       '§4.2.5). A broadcast is executed by EVERY X-MIND K on the line, driven by this node '
       'or not: true only where the line carries no X-MIND K but the drives of this node. '
       'The node then probes the other addresses once the line is open and falls back to '
       'per-drive starts until then, when one answers, or when any check fails '
       '(docs/xmind_k.md)', scope='bus'),
    PS('broadcast_probe_wait_ms', 255, 'how long the line probe of broadcast_start waits '
       'for an answer at each address: the largest answer delay RD of any drive on the '
       'line (§4.2.2.5; 255 = the largest possible, about 15 s for the probe)',
       scope='bus', min_value=1, max_value=255),
    PS('address', 0, 'drive address (§2.2.1, WS,AD)', min_value=0, max_value=47),
    PS('resolution', '', 'operation mode preset RS written at connect when it differs '
       "('' = leave as is); must match steps_per_rev", choices=('',) + tuple(xk.RESOLUTIONS)),
    PS('current_preset', -1, 'drive current preset IN: 0..3 = 55/70/85/100 % (-1 = leave)',
       min_value=-1, max_value=3),
    PS('answer_delay_ms', -1, 'answer delay preset RD in ms, also delays EE (§4.2.2.5; '
       '-1 = leave)', min_value=-1, max_value=255),
    PS('equalization', -1, 'equalization preset EQ 0/1 (-1 = leave)', min_value=-1,
       max_value=1),
    PS('power_cycle_flag', 'F7', "dummy output set to 1 at connect; read back 0 means the "
       "drive was power-cycled and lost its position ('' = off)",
       choices=('',) + tuple(f'F{i}' for i in range(8))),
    PS('busy_poll_period_s', 0.25, 'how often a busy (silent) drive is asked QA',
       min_value=0.01, max_value=10.0),
    PS('status_poll_period_s', 1.0, 'how often an idle drive is asked for FA and the '
       'power-cycle flag', min_value=0.05, max_value=60.0),
)

# Vendor.drive_defaults
DRIVE_DEFAULTS = {'steps_per_rev': 2000.0, 'homing.method': 3}   # RS D2 factory default


def with_defaults(params: Mapping[str, Any]) -> dict[str, Any]:
    """One drive's `params` over the X-MIND K's defaults: VENDOR.with_defaults(params) (the
    X-MIND K has no per-drive link parameters, Vendor.drive_bus_params)."""
    return param_defaults(PARAMS, DRIVE_DEFAULTS, (), params)


def _check_address(name: str, number: int, taken: Mapping[str, int], url: str) -> None:
    """Address `number` of drive `name` is not one of `taken` (drive -> address), or
    ValueError."""
    for other, used in taken.items():
        if other != name and used == number:
            raise ValueError(f'parameter drives.{name}.address: {number:02d} is already used by '
                             f'drive {other} on {url} (allowed: a free address 0..47)')


def _check_drive(name: str, params: Mapping[str, Any]) -> None:
    """The rules of one drive's own parameters, or ValueError."""
    p = f'drives.{name}.'
    method = int(params['homing.method'])
    if method not in HOMING_METHODS:
        raise ValueError(f'parameter {p}homing.method: {method} is not an X-MIND K method '
                         '(allowed: ' + '; '.join(f'{k} = {v}' for k, v in
                                                  HOMING_METHODS.items()) + ')')
    resolution = str(params['resolution'])
    spr = float(params['steps_per_rev'])
    if resolution and spr != xk.RESOLUTIONS[resolution]:
        raise ValueError(f'parameter {p}steps_per_rev: {spr:g} does not match resolution '
                         f'{resolution} (allowed: {xk.RESOLUTIONS[resolution]}, §4.2.2.3)')
