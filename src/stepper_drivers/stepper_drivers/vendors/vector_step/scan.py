"""`stepperctl scan vector_step`: CANopen, an SDO upload of 0x1000 to every node-ID at once
(canopen's NodeScanner), then the identity object 0x1018:1-4 (CiA 301), 0x1008, 0x100A and
Rstpres by SDO. No rclpy.

Through the driver's own CanBus, so what the scanner finds the node can reach the same way.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

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
from ...protocol.canopen_link import CanBus
from . import regmap as vm


def add_options(p) -> tuple[float, float]:
    p.add_argument('--interface', default='socketcand',
                   help='python-can interface: socketcan (Linux CAN card) or socketcand '
                   '(default, the loopback broker)')
    p.add_argument('--channel', default='can0', help='CAN channel (default can0)')
    p.add_argument('--bitrate', type=int, default=125000, help='bit rate (default 125000)')
    p.add_argument('--can-host', default='127.0.0.1', help='socketcand host')
    p.add_argument('--can-port', type=int, default=29536, help='socketcand port')
    p.add_argument('--ids', default='1-127', help='node-ids (default 1-127)')
    p.add_argument('--listen', type=float, default=0.5, metavar='S',
                   help='how long to collect answers to the broadcast probe [s]')
    return 0.3, 30.0


def scan(args, deadline: Deadline) -> list[BusResult]:
    ids = parse_ids(args.ids, 1, 127, '--ids')
    bus = CanBus(interface=args.interface, channel=args.channel, bitrate=args.bitrate,
                 host=args.can_host, port=args.can_port, timeout_s=args.timeout)
    try:
        bus.open()
    except LinkError as e:
        raise ScanError(f'scan vector_step: {e}') from None
    found: list[Found] = []
    try:
        network = bus.network
        scanner = network.scanner
        scanner.reset()
        # One SDO upload of 0x1000 per node-ID, all sent at once; the answers (and any heartbeat,
        # EMCY or TPDO seen meanwhile) name the nodes present.
        request = b'\x40\x00\x10\x00\x00\x00\x00\x00'      # CiA 301 initiate upload 0x1000:00
        for node_id in ids:
            network.send_message(0x600 + node_id, request)
        print(f'scan vector_step: SDO upload 0x1000 sent to {len(ids)} node-ids on '
              f'{bus.description}; listening {args.listen:g} s', file=sys.stderr, flush=True)
        listen_end = min(time.monotonic() + args.listen, deadline.end)
        while time.monotonic() < listen_end:
            time.sleep(0.02)     # the replies arrive on the network's receive thread
        present = sorted(n for n in scanner.nodes if n in ids)
        progress = Progress('vector_step identity', len(present))
        for node_id in deadline.each(present):
            node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
            node.sdo.RESPONSE_TIMEOUT = args.timeout
            network.add_node(node)
            found.append(_found(node, node_id))
            progress.step(f'node {node_id}', len(found))
        progress.end()
    except (LinkError, DriveError, OSError) as e:
        raise ScanError(f'scan vector_step: {e}') from None
    finally:
        bus.close()
    if not found:
        return []
    params = {'can.interface': args.interface, 'can.channel': args.channel,
              'can.bitrate': args.bitrate, 'can.host': args.can_host, 'can.port': args.can_port,
              'can.eds_file': '', 'timeout_s': 0.5, 'publish_rate_hz': 50.0,
              'command_timeout_s': 0.5, 'reconnect_period_s': 0.5}
    return [BusResult('vector_step', bus.description, params, found,
                      [f'CANopen {bus.description}'])]


def _found(node, node_id: int) -> Found:
    def u32(index: int, sub: int) -> int | None:
        try:
            return int.from_bytes(node.sdo.upload(index, sub)[:4], 'little')
        except (SdoAbortedError, SdoCommunicationError):
            return None

    def text(index: int) -> str | None:
        try:
            return node.sdo.upload(index, 0).decode('latin-1').strip('\0 ')
        except (SdoAbortedError, SdoCommunicationError):
            return None
    identity: dict[str, str] = {}
    device_type = u32(vm.DEVICE_TYPE, 0)
    if device_type is not None:
        identity['device_type'] = f'0x{device_type:08X}'
    vendor, product = u32(vm.IDENTITY_OBJECT, 1), u32(vm.IDENTITY_OBJECT, 2)
    revision, serial = u32(vm.IDENTITY_OBJECT, 3), u32(vm.IDENTITY_OBJECT, 4)
    if vendor is not None:
        aec = ' (AEC)' if vendor == vm.VENDOR_ID_AEC else ''
        identity['vendor_id'] = f'0x{vendor:08X}{aec}'
    if product is not None:
        identity['product_code'] = (f'0x{product:08X} '
                                    f'({vm.PRODUCT_CODES.get(product, "unknown")})')
    if revision is not None:
        identity['revision'] = f'0x{revision:08X}'
    if serial is not None:
        identity['serial'] = str(serial)
    for key, index in (('device_name', vm.MANUFACTURER_DEVICE_NAME),
                       ('software', vm.MANUFACTURER_SOFTWARE_VERSION)):
        value = text(index)
        if value:
            identity[key] = value
    params: dict[str, Any] = {'node_id': node_id}
    notes = []
    if vendor is not None and vendor != vm.VENDOR_ID_AEC:
        notes.append(f'vendor ID 0x{vendor:08X} is not AEC (0x000000BC): not a Vector Step?')
    try:
        stpres = int.from_bytes(node.sdo.upload(vm.RSTPRES, vm.AEC_SUB)[:2], 'little')
    except (SdoAbortedError, SdoCommunicationError):
        stpres = None
    if stpres:
        identity['Rstpres'] = str(stpres)
        # The manual gives no steps per revolution: 200 full steps x Rstpres is an assumption
        # (spec aec_vector_step.md §5); check one revolution before trusting positions.
        params['steps_per_rev'] = 200.0 * stpres
        notes.append(f'steps_per_rev = 200 full steps x Rstpres {stpres} (assumed: the manual '
                     'gives no steps per revolution; check one revolution)')
    return Found(node_id, identity, params, notes)


SCANNER = Scanner(
    help='AEC Vector Step: CANopen node-ids (0x1018)',
    hint='check the CAN interface, the bit rate (Rcanbaud) and the bus termination',
    add_options=add_options,
    scan=scan,
)
