"""The AEC Vector Step's parameters: what the vendor entry and the drive class both need.

The ParamSpecs (PARAMS), the drive defaults, the constants they and the checks name (the 0x1016
consumer time in heartbeat periods, the least SYNC periods of 0x1006), `with_defaults` (what
VENDOR.with_defaults gives, without the Vendor object) and the rules of one drive's parameters
that its constructor and validate apply (`_check_drive`). Not here: the node-ID rules of the
whole configuration, make_bus, make_drive, validate and VENDOR (the entry, `__init__.py`), nor
anything of the drive itself (`drive.py`, `node.py`, `pdo.py`, `modes.py`); this module imports
neither, they import it.
"""

from __future__ import annotations

from typing import Any, Mapping

from ...contract.drive import ParamSpec, param_defaults
from . import regmap as vm

# 0x1016 consumer time: this many periods of the node's own heartbeat ("deve essere settato piu'
# alto del tempo impostato nel generatore" [CONSUMER HEARTBEAT TIME]). 10: 1 s at 100 ms, as the
# node's own heartbeat_timeout_s; 3 (300 ms) tripped on a loaded 2-core machine when the python-can
# periodic task was late. It only lights the LED and sends EMCY 0x8130: SYNC is the safety.
MASTER_HEARTBEAT_PERIODS = 10
SYNC_TIMEOUT_MIN_PERIODS = 2   # 0x1006 must span this many SYNC periods (jitter of the producer)

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

# Vendor.drive_defaults
DRIVE_DEFAULTS = {'steps_per_rev': 3200.0, 'homing.method': 35}


def with_defaults(params: Mapping[str, Any]) -> dict[str, Any]:
    """One drive's `params` over the Vector Step's defaults: VENDOR.with_defaults(params) (the
    Vector Step has no per-drive link parameters, Vendor.drive_bus_params)."""
    return param_defaults(PARAMS, DRIVE_DEFAULTS, (), params)


def _check_drive(name: str, params: Mapping[str, Any], master_heartbeat_ms: int,
                 sync_period_s: float) -> None:
    """The rules of one drive's parameters, or ValueError; `master_heartbeat_ms` and
    `sync_period_s` are those of its bus (a drive made on a bus checks against what that bus
    produces, not against its own copy of the bus parameters)."""
    params = with_defaults(params)
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
