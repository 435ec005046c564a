"""The X-PLUS MT's parameters: what the vendor entry and the drive class both need.

The ParamSpecs (PARAMS), the per-drive link parameters (DRIVE_BUS_PARAMS), the drive defaults,
`with_defaults` (what VENDOR.with_defaults gives, without the Vendor object) and the rules of
one drive's parameters that make_drive and validate apply (`_check_drive`). Not here: the link
check, make_bus, make_drive, validate and VENDOR (the entry, `__init__.py`), nor anything of the
drive itself (`unit.py`, `drive.py`); this module imports neither, they import it.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

from ...contract.drive import ParamSpec, param_defaults
from . import regmap as xm

REG = xm.REGISTERS

# Drive-side watchdog (§13 "Register 1097": no Modbus read or write within the timeout -> Fault,
# current off). 1 s: 50 polls at the default 50 Hz, and more than a lost reply (timeout_s 0.5 s)
# plus a quick reconnect or a scheduling stall of a loaded host, so only a master that is really
# gone trips it; a running axis still stops about 1 s after its master died.
WATCHDOG_MS_DEFAULT = 1000
WATCHDOG_MIN_MS = 100          # §13 "Register 1097": 100÷32000 ms (0 = off)
WATCHDOG_MIN_POLLS = 5         # the watchdog must span at least this many poll periods

PARAMS = (
    ParamSpec('host', '127.0.0.1', 'IP address of the drive (Modbus TCP server); the drives '
              'that set no drives.<name>.host of their own', scope='bus'),
    ParamSpec('port', 502, 'TCP port of the drive (§11 "TCP Port": 502); the drives that set '
              'no drives.<name>.port of their own', scope='bus', min_value=1, max_value=65535),
    ParamSpec('word_order', 'little', "32-bit word order, must match register 1162: 'little' "
              "(1162 = 1, default, low word at the lower address) or 'big' (1162 = 0)",
              scope='bus', choices=xm.WORD_ORDERS),
    ParamSpec('unit_id', 1, 'Modbus unit identifier of the drive (the manual does not fix it)',
              scope='drive', min_value=0, max_value=255),
    # Every X-PLUS MT is its own Modbus TCP server: drives on other hosts get a link of their own
    # (Vendor.drive_bus_params); drives with equal host and port share one.
    ParamSpec('host', '', "IP address of this drive when it is not the bus-level host ('' = "
              'the bus-level host)', scope='drive'),
    ParamSpec('port', 0, 'TCP port of this drive when it is not the bus-level port (0 = the '
              'bus-level port)', scope='drive', min_value=0, max_value=65535),
    ParamSpec('watchdog_ms', WATCHDOG_MS_DEFAULT, 'drive-side watchdog, register 1097, written at '
              'connect: with no Modbus request (from any client) for this long the drive goes to '
              'Fault, current off (§13 "Register 1097"); 0 = off, else 100..32000 ms [ms]',
              scope='drive', min_value=0, max_value=32000),
    ParamSpec('input_config', -1, 'Input Config 1088 written at connect (RAM; save_params stores '
              'it): bit 0 = 0 makes I0 the home proximity input, bits 1/2 = 0 make I1/I2 limit '
              'switches, bit 3 = 0 I3 the touch probe (§13 "Register 1088"; factory 15: all '
              'general purpose); -1 = leave the drive as it is', scope='drive', min_value=-1,
              max_value=xm.REGISTERS['INPUT_CONFIG'].max),
)


# Per-drive parameters that give a drive a link of its own (Vendor.drive_bus_params).
DRIVE_BUS_PARAMS = ('host', 'port')

# Vendor.drive_defaults; float: the common parameter steps_per_rev is a double (params.py)
DRIVE_DEFAULTS = {'steps_per_rev': float(xm.STEPS_PER_REV), 'homing.method': 35}


def with_defaults(params: Mapping[str, Any]) -> dict[str, Any]:
    """One drive's `params` over the X-PLUS MT's defaults: VENDOR.with_defaults(params)."""
    return param_defaults(PARAMS, DRIVE_DEFAULTS, DRIVE_BUS_PARAMS, params)


def _check_choice(key: str, value: Any, allowed: Sequence[Any], what: str) -> None:
    if value not in allowed:
        raise ValueError(f'{key}: {value!r} is not {what} (allowed: '
                         f'{", ".join(map(str, allowed))})')


def _check_drive(name: str, params: Mapping[str, Any]) -> None:
    """The rules of one drive's parameters (with the bus-level ones), or ValueError."""
    prefix = f'drives.{name}.'
    params = with_defaults(params)
    method = params['homing.method']
    if method not in xm.HOMING_METHODS:
        raise ValueError(f'{prefix}homing.method: {method} is not a homing method of the '
                         f'X-PLUS MT (allowed: {", ".join(map(str, xm.HOMING_METHODS))})')
    unit_id = params['unit_id']
    if not isinstance(unit_id, int) or not 0 <= unit_id <= 255:
        raise ValueError(f'{prefix}unit_id: {unit_id!r} is not a Modbus unit id '
                         f'(allowed: 0..255)')
    _check_choice('word_order', params['word_order'], xm.WORD_ORDERS,
                  'a word order')
    steps = params['steps_per_rev']
    if float(steps) != xm.STEPS_PER_REV:
        raise ValueError(f'{prefix}steps_per_rev: {steps:g} is not the X-PLUS MT resolution '
                         f'(allowed: {xm.STEPS_PER_REV}, fixed by STEP_REVOLUTION (1081))')
    watchdog_ms = params['watchdog_ms']
    if not isinstance(watchdog_ms, int) or not (
            watchdog_ms == 0 or WATCHDOG_MIN_MS <= watchdog_ms <= REG['COUNTER_WATCHDOG'].max):
        raise ValueError(f'{prefix}watchdog_ms: {watchdog_ms!r} (allowed: 0 = off, or '
                         f'{WATCHDOG_MIN_MS}..{REG["COUNTER_WATCHDOG"].max} ms, §13 "Register '
                         f'1097")')
    rate = float(params.get('publish_rate_hz', 50.0))
    if watchdog_ms and watchdog_ms / 1000.0 < WATCHDOG_MIN_POLLS / rate:
        raise ValueError(f'{prefix}watchdog_ms: {watchdog_ms} ms is less than '
                         f'{WATCHDOG_MIN_POLLS} poll periods at publish_rate_hz {rate:g} (the '
                         f'polls feed the drive watchdog); allowed: >= '
                         f'{math.ceil(WATCHDOG_MIN_POLLS * 1000.0 / rate)} ms, or 0 = off')
    input_config = params['input_config']
    if not isinstance(input_config, int) or not (
            input_config == -1 or REG['INPUT_CONFIG'].accepts(input_config)):
        raise ValueError(f'{prefix}input_config: {input_config!r} (allowed: -1 = leave the drive '
                         f'as it is, or INPUT_CONFIG (1088) {REG["INPUT_CONFIG"].range_text()})')
    if method in xm.HOMING_METHODS_HOME_SWITCH and input_config >= 0 and input_config & 0x01:
        raise ValueError(f'{prefix}homing.method: {method} needs the home switch on I0, but '
                         f'{prefix}input_config {input_config} has bit 0 = 1 (I0 general '
                         f'purpose, §13 "Register 1088"); clear bit 0 (e.g. 14)')
