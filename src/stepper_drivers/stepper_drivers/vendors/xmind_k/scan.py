"""`stepperctl scan xmind_k`: ASCII on RS-485, `AAQS,RS` per address 00-47 (§4.3.2; a busy drive
is silent, §3). No rclpy.

Through the driver's own XmindKBus, so what the scanner finds the node can reach the same way.
"""

from __future__ import annotations

from typing import Any

from ...contract.drive import DriveError, LinkError
from ...contract.scanning import (
    BusResult,
    Deadline,
    Found,
    Progress,
    ScanError,
    Scanner,
    parse_ids,
)
from ...protocol import xmind_k as xk
from ...protocol.xmind_k_bus import XmindKBus


def add_options(p) -> tuple[float, float]:
    p.add_argument('--port', required=True, help='serial device or pyserial URL')
    p.add_argument('--addresses', default='0-47', help='addresses (default 0-47)')
    p.add_argument('--answer-delay-ms', type=float, default=10.0, metavar='MS',
                   help='answer delay preset RD the drives use (§4.2.2.5, factory 10)')
    p.add_argument('--local-echo', action='store_true',
                   help='the RS-485 adapter echoes what it sends')
    return 0.03, 30.0


def scan(args, deadline: Deadline) -> list[BusResult]:
    ids = parse_ids(args.addresses, xk.ADDRESS_MIN, xk.ADDRESS_MAX, '--addresses')
    bus = XmindKBus({'port': args.port, 'baudrate': xk.BAUDRATE, 'parity': 'N', 'stopbits': 1,
                     'local_echo': args.local_echo, 'timeout_s': args.timeout, 'retries': 0})
    try:
        bus.open()
    except LinkError as e:
        raise ScanError(f'scan xmind_k: {e}') from None
    found: list[Found] = []
    progress = Progress(f'xmind_k {args.port}', len(ids))
    try:
        for address in deadline.each(ids):
            try:
                answer = bus.request(xk.Frame(address, 'QS', ('RS',)), rd_ms=args.answer_delay_ms,
                                     tries=1)
            except DriveError as e:          # garbled: something is there
                found.append(Found(address, {'answer': f'garbled: {e}'},
                                   notes=[f'address {address:02d}: garbled answer (wrong baud '
                                          'rate, or two drives at one address?)']))
                progress.step(f'address {address:02d}', len(found))
                continue
            if answer is None:
                progress.step(f'address {address:02d}')
                continue
            if answer.code == 'N':           # §4.4.2: a garbled request, or not an X-MIND K
                found.append(Found(address, {'answer': f'{address:02d}N to QS,RS'},
                                   notes=[f'address {address:02d}: answered N to QS,RS, which '
                                          'every X-MIND K answers (§4.3)']))
                progress.step(f'address {address:02d}', len(found))
                continue
            found.append(_found(bus, address, answer.args[1], args.answer_delay_ms))
            progress.step(f'address {address:02d}', len(found))
    finally:
        progress.end()
        bus.line.close()
    if not found:
        return []
    return [BusResult(
        'xmind_k', f'X-MIND K {args.port} 9600 8N1',
        {'port': args.port, 'baudrate': xk.BAUDRATE, 'parity': 'N', 'stopbits': 1,
         'timeout_s': 0.03, 'retries': 1, 'publish_rate_hz': 5.0, 'command_timeout_s': 0.5,
         'reconnect_period_s': 0.5}, found,
        ['RS-485 line at 9600 8N1 (§3); 5 Hz polls leave line time for commands'])]


def _found(bus, address: int, rs: str, rd_ms: float) -> Found:
    identity = {'RS': rs, 'steps_per_rev': str(xk.RESOLUTIONS.get(rs, '?'))}
    for preset in ('RD', 'IN'):
        try:
            a = bus.request(xk.Frame(address, 'QS', (preset,)), rd_ms=rd_ms, tries=2)
            if a is not None and a.code != 'N':
                identity[preset] = str(a.args[1])
        except DriveError:
            pass
    try:
        a = bus.request(xk.Frame(address, 'QE'), rd_ms=rd_ms, tries=2)
        if a is not None and a.code != 'N':
            identity['QE'] = f'{a.args[0]:02d},{a.args[1]:03d}'
    except DriveError:
        pass
    params: dict[str, Any] = {'address': address}
    notes = []
    if rs in xk.RESOLUTIONS:
        params['steps_per_rev'] = float(xk.RESOLUTIONS[rs])
    notes.append('homing.method 60: the current position is home (no switch needed); set 3/-3 '
                 'for a zero search on PX')
    params['homing'] = {'method': 60, 'timeout_s': 5.0}
    return Found(address, identity, params, notes)


SCANNER = Scanner(
    help='R.T.A. X-MIND K: ASCII addresses 00-47 on RS-485',
    hint='check the port and wiring; a drive running a program does not answer (§3): stop it '
         '(EE) first',
    add_options=add_options,
    scan=scan,
)
