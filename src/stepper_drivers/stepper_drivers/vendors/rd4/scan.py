"""`stepperctl scan rd4`: Modbus RTU on a serial line, FC04 of the identity block 0x0C-0x0F per
unit id (§8.1.2), over the baud rates/parities asked for (§4.4.2 dip-switch settings). No rclpy.

Through the driver's own ModbusRtuBus, so what the scanner finds the node can reach the same way.
"""

from __future__ import annotations

import logging
import math
import sys
from typing import Any

from ...contract.drive import DriveError, LinkError
from ...contract.scanning import (
    BusResult,
    Deadline,
    Found,
    Progress,
    ScanError,
    Scanner,
    ScanUsageError,
    parse_ids,
)
from ...protocol.modbus_rtu import ModbusRtuBus
from . import regmap as rm

logger = logging.getLogger(__name__)


def add_options(p) -> tuple[float, float]:
    p.add_argument('--port', required=True, help='serial device or pyserial URL')
    p.add_argument('--ids', default='1-247', help='unit ids, e.g. 1-10,12 (default 1-247)')
    p.add_argument('--baudrate', default='9600,19200', help='baud rates to try, in order '
                   '(default 9600,19200)')
    p.add_argument('--parity', default='E,N,O', help='parities to try, in order (default '
                   'E,N,O; factory setting 9600 8E1)')
    p.add_argument('--all-settings', action='store_true',
                   help='go on with the other settings after one found drives')
    return 0.05, 120.0


def scan(args, deadline: Deadline) -> list[BusResult]:
    ids = parse_ids(args.ids, 1, 247, '--ids')
    bauds, parities = _settings(args)
    results: list[BusResult] = []
    problems: list[str] = []
    for parity in parities:
        for baud in bauds:
            if deadline.over() or (results and not args.all_settings):
                break
            result = _scan_setting(args, ids, deadline, baud, parity, problems)
            if result is not None:
                results.append(result)
    if not results and problems:
        logger.info('rd4 scan problems: %s', problems)
    return results


def _settings(args) -> tuple[list[int], list[str]]:
    """The baud rates and parities to try (--baudrate, --parity), or ScanUsageError."""
    try:
        bauds = [int(b) for b in args.baudrate.split(',')]
    except ValueError:
        raise ScanUsageError(f'--baudrate: {args.baudrate!r} is not a list of baud '
                             'rates (e.g. 9600,19200)') from None
    parities = [p.strip().upper() for p in args.parity.split(',')]
    for b in bauds:
        if b not in (9600, 19200):
            raise ScanUsageError(f'--baudrate: {b} is not an RD4 rate (allowed: 9600, '
                                 '19200; §4.4.2)')
    for p in parities:
        if p not in ('N', 'E', 'O'):
            raise ScanUsageError(f'--parity: {p!r} (allowed: N, E, O)')
    return bauds, parities


def _scan_setting(args, ids: list[int], deadline: Deadline, baud: int, parity: str,
                  problems: list[str]) -> BusResult | None:
    """The units that answer at one baud rate and parity, None when none does; what went wrong
    with the line goes to `problems` (and stderr)."""
    stopbits = 2 if parity == 'N' else 1              # §7.3.1 11-bit characters
    setting = f'{baud} 8{parity}{stopbits}'
    bus = ModbusRtuBus(args.port, baud, parity, stopbits, timeout_s=args.timeout, retries=0)
    try:
        bus.open()
    except LinkError as e:
        if 'parity' not in str(e):     # missing, busy, no permission: no use going on
            raise ScanError(f'scan rd4: {e}') from None
        problems.append(str(e))         # a pty refuses E/O: try the other settings
        print(f'scan rd4: {e}', file=sys.stderr)
        return None
    progress = Progress(f'rd4 {args.port} {setting}', len(ids))
    try:
        found = _probe_units(bus, ids, deadline, progress)
    finally:
        progress.end()
        bus.close()
    if bus.crc_errors or bus.mismatches:
        problems.append(f'{setting}: {bus.crc_errors} CRC errors, {bus.mismatches} '
                        'replies that did not match: units may be set to another baud '
                        'rate/parity, or two units share an id')
        print(f'scan rd4: {problems[-1]}', file=sys.stderr)
    return _result(args.port, baud, parity, found) if found else None


def _probe_units(bus: ModbusRtuBus, ids: list[int], deadline: Deadline,
                 progress: Progress) -> list[Found]:
    """FC04 of the identity block (§8.1.2) at each unit id until the deadline."""
    found: list[Found] = []
    for unit in deadline.each(ids):
        try:
            baud_reg, node_reg, sw, hw = bus.read_input_registers(unit, *rm.IDENTITY_BLOCK)
        except LinkError:
            progress.step(f'unit {unit}')
            continue
        except DriveError as e:
            found.append(Found(unit, {'answer': f'exception: {e}'},
                               notes=[f'unit {unit} answers FC04 0x0C with an '
                                      'exception: not an RD4?']))
            progress.step(f'unit {unit}', len(found))
            continue
        found.append(_found(bus, unit, baud_reg, node_reg, sw, hw))
        progress.step(f'unit {unit}', len(found))
    return found


def _result(port: str, baud: int, parity: str, found: list[Found]) -> BusResult:
    """The line settings for the params file: what the units' Dip-switch baud rate [0x0C]
    reports when they agree (a pty carries no parity, so the probe setting may differ)."""
    setting = f'{baud} {rm.serial_format(parity)}'
    header = [f'RS-485 line {port}: answers at {setting}']
    reported = {rm.BAUD_SWITCH.get(d.raw.get('baud_reg', -1)) for d in found}
    if len(reported) == 1 and None not in reported:
        r_baud, r_parity = reported.pop()
        if (r_baud, r_parity) != (baud, parity):
            header.append(f'the units report dip-switch {r_baud} {rm.serial_format(r_parity)} '
                          '(§4.4.2): used below')
        baud, parity = r_baud, r_parity
    else:
        header.append('the units do not report one dip-switch setting (Dip-switch baud rate '
                      '[0x0C]): the probe setting is used below')
    header.append('10 Hz polls keep the 1 s watchdog of every unit fed (§8.1.1)')
    return BusResult('rd4', f'modbus rtu {port} {setting}',
                     {'port': port, 'baudrate': baud, 'parity': parity, 'stopbits': 0,
                      'retries': 1, 'timeout_s': 0.1, 'publish_rate_hz': 10.0,
                      'command_timeout_s': 0.5, 'reconnect_period_s': 0.5}, found, header)


def _found(bus, unit: int, baud_reg: int, node_reg: int, sw: int, hw: int) -> Found:
    identity = {'sw_version': rm.describe_sw_version(sw),
                'hw_version': rm.describe_hw_version(hw),
                'dip_switch_baud_rate': rm.describe_baud_register(baud_reg),
                'dip_switch_node_id': str(node_reg)}
    params: dict[str, Any] = {'node_id': unit}
    notes = []
    raw = {'baud_reg': baud_reg}
    try:
        dpr = bus.read_holding_registers(unit, rm.HR['DISTANCE_PER_REVOLUTION'].address, 1)[0]
        gear = bus.read_holding_registers(unit, rm.HR['GEAR_RATIO'].address, 1)[0]
    except (LinkError, DriveError) as e:
        notes.append(f'machine data not readable: {e}')
        return Found(unit, identity, params, notes, raw)
    model = rm.MODEL_BY_GEAR_RATIO.get(gear)
    identity['distance_per_revolution'] = str(dpr)
    identity['gear_ratio'] = str(gear)
    identity['model'] = model.name if model else f'unknown (Gear ratio {gear})'
    params['steps_per_rev'] = float(dpr)
    if model and dpr:
        pps = rm.max_speed_pps(model, dpr)
        # §6.4 Max. speed of the model, in rad/s of the output shaft, rounded down
        params['max_velocity'] = math.floor(pps / dpr * 2 * math.pi * 100) / 100
        notes.append(f'{model.name}: max. speed {pps} PPS at {dpr} pulses/rev (§6.4)')
    return Found(unit, identity, params, notes, raw)


SCANNER = Scanner(
    help='Lika RD4: Modbus RTU unit ids on a serial line',
    hint="check the port, the A/B wiring, and --baudrate/--parity against the units' "
         'dip-switches (factory 9600 8E1)',
    add_options=add_options,
    scan=scan,
)
