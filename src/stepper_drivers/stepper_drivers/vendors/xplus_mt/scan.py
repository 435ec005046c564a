"""`stepperctl scan xplus_mt`: Modbus TCP, FC03 of the identification registers 1152-1159 and
1162 per unit id (§13 T15), on one or more hosts. No rclpy.

Through the driver's own ModbusTcpBus, so what the scanner finds the node can reach the same way.
"""

from __future__ import annotations

from ...contract.drive import DriveError, LinkError
from ...contract.scanning import (
    BusResult,
    Deadline,
    Found,
    Progress,
    Scanner,
    parse_hosts,
    parse_ids,
)
from ...protocol.modbus_tcp import ModbusTcpBus
from . import regmap as xm

DEFAULT_HOST = '192.168.1.10'     # the factory address


def add_options(p) -> tuple[float, float]:
    p.add_argument('--host', action='append', default=None,
                   help='host, range 192.168.1.10-20 or network 192.168.1.0/28; repeatable '
                   f'(default {DEFAULT_HOST}, the factory address)')
    p.add_argument('--port', type=int, default=502, help='TCP port (default 502)')
    p.add_argument('--ids', default='1-247', help='unit ids (default 1-247)')
    return 0.2, 60.0


def scan(args, deadline: Deadline) -> list[BusResult]:
    ids = parse_ids(args.ids, 1, 247, '--ids')
    # --host appends to a list of its own: a default list would be appended to
    hosts = parse_hosts(args.host or [DEFAULT_HOST])
    results: list[BusResult] = []
    progress = Progress(f'xplus_mt port {args.port}', len(hosts) * len(ids))
    try:
        for host in deadline.each(hosts):
            bus = ModbusTcpBus(host, args.port, timeout_s=args.timeout)
            try:
                bus.open()
            except LinkError:
                progress.done += len(ids) - 1
                progress.step(host)
                continue
            found: list[Found] = []
            orders = set()
            try:
                for unit in deadline.each(ids):
                    try:
                        order_value = bus.read_holding_registers(unit, 1162, 1)[0]
                        words = bus.read_holding_registers(unit, 1152, 8)     # T15 identification
                    except DriveError as e:
                        if not isinstance(e, LinkError) and 'GATEWAY' not in str(e):
                            found.append(Found(unit, {'answer': str(e)},
                                               notes=[f'unit {unit} answers with an exception: '
                                                      'not an X-PLUS MT?']))
                        if isinstance(e, LinkError) and not bus.is_open:
                            bus.close()
                            bus.open()
                        progress.step(f'{host} u{unit}', len(found))
                        continue
                    order = xm.WORD_ORDER_BY_1162.get(order_value, 'little')
                    orders.add(order)
                    sw_ver, product, hw_ver, serial = (
                        xm.decode32(words[i:i + 2], order, signed=False) for i in (0, 2, 4, 6))
                    found.append(Found(
                        unit, {'product_code': f'0x{product:08X}', 'serial_number': str(serial),
                               'software_version': str(sw_ver),
                               'hardware_version': str(hw_ver),
                               'word_order': f'{order} (1162 = {order_value})'},
                        {'unit_id': unit, 'steps_per_rev': 12800.0}))
                    progress.step(f'{host} u{unit}', len(found))
            finally:
                bus.close()
            if found:
                header = [f'Modbus TCP {host}:{args.port}']
                if len(orders) > 1:
                    header.append('the drives report different word orders (register 1162): '
                                  'one node per word order')
                results.append(BusResult(
                    'xplus_mt', f'modbus tcp {host}:{args.port}',
                    {'host': host, 'port': args.port,
                     'word_order': sorted(orders)[0] if orders else 'little',
                     'timeout_s': 0.5, 'publish_rate_hz': 50.0, 'command_timeout_s': 0.5,
                     'reconnect_period_s': 0.5}, found, header))
    finally:
        progress.end()
    return results


SCANNER = Scanner(
    help='R.T.A. X-PLUS MT: Modbus TCP hosts and unit ids',
    hint=f'check --host/--port (factory {DEFAULT_HOST}:502) and that the drive is powered',
    add_options=add_options,
    scan=scan,
)
