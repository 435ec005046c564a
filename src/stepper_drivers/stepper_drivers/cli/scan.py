"""stepperctl scan: find the drives that answer on a bus, without a node (no rclpy here).

One probe per address, through the project's own protocol code, so what the scanner finds the node
can reach the same way:
- rd4          Modbus RTU on a serial line: FC04 of the identity block 0x0C-0x0F per unit id
               (§8.1.2), over the baud rates/parities asked for (§4.4.2 dip-switch settings)
- xplus_mt     Modbus TCP: FC03 of the identification registers 1152-1159 and 1162 per unit id
               (§13 T15), on one or more hosts
- xmind_k      ASCII on RS-485: `AAQS,RS` per address 00-47 (§4.3.2; a busy drive is silent, §3)
- vector_step  CANopen: an SDO upload of 0x1000 to every node-ID at once (canopen's NodeScanner),
               then the identity object 0x1018:1-4 (CiA 301), 0x1008, 0x100A and Rstpres by SDO

Every scan is bounded by --max-time; progress goes to stderr. `--write-yaml FILE` writes a params
file that starts the vendor's node for the drives found (one drive block per address).
"""

from __future__ import annotations

import dataclasses
import ipaddress
import logging
import math
import sys
import time
from typing import Any, Callable, Iterable

from .. import vendor_table
from .errors import EXIT_FAILED, EXIT_NOT_FOUND, EXIT_OK, EXIT_USAGE, CliError

logger = logging.getLogger(__name__)

NODE_NAMES = {row.key: row.node for row in vendor_table.ROWS}


# ------------------------------------------------------------------------------------ results
@dataclasses.dataclass
class Found:
    """One drive that answered: its address, identity and what its params file needs."""

    address: int
    identity: dict[str, str]
    drive_params: dict[str, Any] = dataclasses.field(default_factory=dict)
    notes: list[str] = dataclasses.field(default_factory=list)   # comments in the YAML
    raw: dict[str, int] = dataclasses.field(default_factory=dict)  # values read, for the bus


@dataclasses.dataclass
class BusResult:
    """The drives found on one bus (one serial setting, one TCP host, one CAN bus)."""

    vendor: str
    description: str
    bus_params: dict[str, Any]
    drives: list[Found] = dataclasses.field(default_factory=list)
    header: list[str] = dataclasses.field(default_factory=list)  # comments at the top


class Deadline:
    def __init__(self, max_time_s: float):
        self.max_time_s = max_time_s
        self.end = time.monotonic() + max_time_s
        self.hit = False

    def over(self) -> bool:
        if time.monotonic() >= self.end:
            self.hit = True
        return self.hit


class Progress:
    """A redrawn line on a terminal, elsewhere a line per 10 %; on stderr (not mixed with the
    results)."""

    def __init__(self, what: str, total: int, stream=None):
        self.what, self.total = what, max(total, 1)
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.done = 0
        self.found = 0
        self._shown = -1
        self.t0 = time.monotonic()

    def step(self, label: str, found: int | None = None) -> None:
        self.done += 1
        if found is not None:
            self.found = found
        pct = int(100 * self.done / self.total)
        text = (f'scan {self.what}: {label:<14} {self.done}/{self.total} ({pct:3d} %), '
                f'found {self.found}, {time.monotonic() - self.t0:4.1f} s')
        if self.tty:
            self.stream.write('\r' + text)
            self.stream.flush()
        elif pct // 10 != self._shown or self.done == self.total:
            self._shown = pct // 10
            self.stream.write(text + '\n')
            self.stream.flush()

    def end(self) -> None:
        if self.tty:
            self.stream.write('\n')
            self.stream.flush()


def parse_ids(text: str, lo: int, hi: int, what: str) -> list[int]:
    """'1-10,12,0x20' -> [1..10, 12, 32], each within lo..hi."""
    ids: list[int] = []
    try:
        for part in text.split(','):
            part = part.strip()
            if not part:
                continue
            if '-' in part[1:]:
                a, b = part.split('-', 1) if not part.startswith('-') else ('-', part)
                first, last = int(a, 0), int(b, 0)
            else:
                first = last = int(part, 0)
            if first > last:
                first, last = last, first
            ids.extend(range(first, last + 1))
    except ValueError:
        raise CliError(EXIT_USAGE, f'{what}: {text!r} is not a list of numbers and ranges '
                       '(e.g. 1-10,12)') from None
    bad = [i for i in ids if not lo <= i <= hi]
    if bad or not ids:
        raise CliError(EXIT_USAGE, f'{what}: {text!r} (allowed: {lo}..{hi})')
    return sorted(set(ids))


def parse_hosts(specs: Iterable[str]) -> list[str]:
    """'192.168.1.10', '192.168.1.10-20', '10.0.0.0/30', 'localhost' -> host list."""
    hosts: list[str] = []
    for spec in specs:
        for part in spec.split(','):
            part = part.strip()
            if not part:
                continue
            try:
                if '/' in part:
                    net = ipaddress.ip_network(part, strict=False)
                    hosts.extend(str(h) for h in (net.hosts() if net.num_addresses > 2 else net))
                elif '-' in part and part.count('.') == 3:
                    base, last = part.rsplit('-', 1)
                    first_ip = ipaddress.ip_address(base)
                    prefix = base.rsplit('.', 1)[0]
                    for n in range(int(str(first_ip).rsplit('.', 1)[1]), int(last) + 1):
                        hosts.append(f'{prefix}.{n}')
                else:
                    hosts.append(part)
            except ValueError:
                raise CliError(EXIT_USAGE, f'--host: {part!r} is not a host, a range '
                               '(192.168.1.10-20) or a network (192.168.1.0/28)') from None
    if len(hosts) > 1024:
        raise CliError(EXIT_USAGE, f'--host: {len(hosts)} hosts; scan at most 1024 at once')
    return hosts


# --------------------------------------------------------------------------------- RD4 (RTU)
def scan_rd4(args, deadline: Deadline) -> list[BusResult]:
    from ..drive import DriveError, LinkError
    from ..protocol.modbus_rtu import ModbusRtuBus
    from ..vendors import rd4_map as rm

    ids = parse_ids(args.ids, 1, 247, '--ids')
    try:
        bauds = [int(b) for b in args.baudrate.split(',')]
    except ValueError:
        raise CliError(EXIT_USAGE, f'--baudrate: {args.baudrate!r} is not a list of baud '
                       'rates (e.g. 9600,19200)') from None
    parities = [p.strip().upper() for p in args.parity.split(',')]
    for b in bauds:
        if b not in (9600, 19200):
            raise CliError(EXIT_USAGE, f'--baudrate: {b} is not an RD4 rate (allowed: 9600, '
                           '19200; §4.4.2)')
    for p in parities:
        if p not in ('N', 'E', 'O'):
            raise CliError(EXIT_USAGE, f'--parity: {p!r} (allowed: N, E, O)')
    results: list[BusResult] = []
    problems: list[str] = []
    for parity in parities:
        for baud in bauds:
            if deadline.over() or (results and not args.all_settings):
                break
            stopbits = 2 if parity == 'N' else 1              # §7.3.1 11-bit characters
            setting = f'{baud} 8{parity}{stopbits}'
            bus = ModbusRtuBus(args.port, baud, parity, stopbits, timeout_s=args.timeout,
                               retries=0)
            try:
                bus.open()
            except LinkError as e:
                if 'parity' not in str(e):     # missing, busy, no permission: no use going on
                    raise CliError(EXIT_FAILED, f'scan rd4: {e}') from None
                problems.append(str(e))         # a pty refuses E/O: try the other settings
                print(f'scan rd4: {e}', file=sys.stderr)
                continue
            found: list[Found] = []
            progress = Progress(f'rd4 {args.port} {setting}', len(ids))
            try:
                for unit in ids:
                    if deadline.over():
                        break
                    try:
                        baud_reg, node_reg, sw, hw = bus.read_input_registers(
                            unit, *rm.IDENTITY_BLOCK)
                    except LinkError:
                        progress.step(f'unit {unit}')
                        continue
                    except DriveError as e:
                        found.append(Found(unit, {'answer': f'exception: {e}'},
                                           notes=[f'unit {unit} answers FC04 0x0C with an '
                                                  'exception: not an RD4?']))
                        progress.step(f'unit {unit}', len(found))
                        continue
                    found.append(_rd4_found(bus, unit, baud_reg, node_reg, sw, hw, rm))
                    progress.step(f'unit {unit}', len(found))
            finally:
                progress.end()
                bus.close()
            if bus.crc_errors or bus.mismatches:
                problems.append(f'{setting}: {bus.crc_errors} CRC errors, {bus.mismatches} '
                                'replies that did not match: units may be set to another baud '
                                'rate/parity, or two units share an id')
                print(f'scan rd4: {problems[-1]}', file=sys.stderr)
            if found:
                results.append(_rd4_result(args.port, baud, parity, found, rm))
    if not results and problems:
        logger.info('rd4 scan problems: %s', problems)
    return results


def _rd4_result(port: str, baud: int, parity: str, found: list[Found], rm) -> BusResult:
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


def _rd4_found(bus, unit: int, baud_reg: int, node_reg: int, sw: int, hw: int, rm) -> Found:
    from ..drive import DriveError, LinkError
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


# ---------------------------------------------------------------------------- X-PLUS MT (TCP)
def scan_xplus_mt(args, deadline: Deadline) -> list[BusResult]:
    from ..drive import DriveError, LinkError
    from ..protocol.modbus_tcp import ModbusTcpBus
    from ..vendors import xplus_mt_map as xm

    ids = parse_ids(args.ids, 1, 247, '--ids')
    hosts = parse_hosts(args.host)
    results: list[BusResult] = []
    progress = Progress(f'xplus_mt port {args.port}', len(hosts) * len(ids))
    try:
        for host in hosts:
            if deadline.over():
                break
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
                for unit in ids:
                    if deadline.over():
                        break
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


# ----------------------------------------------------------------------------- X-MIND K (ASCII)
def scan_xmind_k(args, deadline: Deadline) -> list[BusResult]:
    from ..drive import DriveError, LinkError
    from ..protocol import xmind_k as xk
    from ..protocol.xmind_k_bus import XmindKBus

    ids = parse_ids(args.addresses, xk.ADDRESS_MIN, xk.ADDRESS_MAX, '--addresses')
    bus = XmindKBus({'port': args.port, 'baudrate': xk.BAUDRATE, 'parity': 'N', 'stopbits': 1,
                     'local_echo': args.local_echo, 'timeout_s': args.timeout, 'retries': 0})
    try:
        bus.open()
    except LinkError as e:
        raise CliError(EXIT_FAILED, f'scan xmind_k: {e}') from None
    found: list[Found] = []
    progress = Progress(f'xmind_k {args.port}', len(ids))
    try:
        for address in ids:
            if deadline.over():
                break
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
            found.append(_xmind_found(bus, address, answer.args[1], xk, args.answer_delay_ms))
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


def _xmind_found(bus, address: int, rs: str, xk, rd_ms: float) -> Found:
    from ..drive import DriveError
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


# -------------------------------------------------------------------------- Vector Step (CAN)
def scan_vector_step(args, deadline: Deadline) -> list[BusResult]:
    import canopen

    from ..drive import DriveError, LinkError
    from ..protocol.canopen_link import CanBus
    from ..vendors import vector_step_map as vm

    ids = parse_ids(args.ids, 1, 127, '--ids')
    bus = CanBus(interface=args.interface, channel=args.channel, bitrate=args.bitrate,
                 host=args.can_host, port=args.can_port, timeout_s=args.timeout)
    try:
        bus.open()
    except LinkError as e:
        raise CliError(EXIT_FAILED, f'scan vector_step: {e}') from None
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
        for node_id in present:
            if deadline.over():
                break
            node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
            node.sdo.RESPONSE_TIMEOUT = args.timeout
            network.add_node(node)
            found.append(_vector_found(node, node_id, vm))
            progress.step(f'node {node_id}', len(found))
        progress.end()
    except (LinkError, DriveError, OSError) as e:
        raise CliError(EXIT_FAILED, f'scan vector_step: {e}') from None
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


def _vector_found(node, node_id: int, vm) -> Found:
    from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

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


# scan_<key> for every vendor of the table with a scanner (scan_help).
SCANNERS: dict[str, Callable[[Any, Deadline], list[BusResult]]] = {
    row.key: globals()[f'scan_{row.key}'] for row in vendor_table.ROWS if row.scan_help}
ADDRESS_NAMES = {row.key: row.address_param for row in vendor_table.ROWS}


# --------------------------------------------------------------------------------- YAML out
YAML_WORDS = ('N', 'Y', 'YES', 'NO', 'ON', 'OFF', 'TRUE', 'FALSE', 'NULL', '~')


def _yaml_scalar(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        return str(value)
    text = str(value)
    # Quote what YAML would read as something else: N (false!), numbers, '', special starts.
    if text == '' or text.upper() in YAML_WORDS or _looks_numeric(text) or ': ' in text \
            or text.endswith(':') or text[0] in '#*&![]{}|>\'"%@`,?-':
        return "'" + text.replace("'", "''") + "'"
    return text


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def drive_name(vendor: str, address: int) -> str:
    return f'axis{address}'


def render_yaml(result: BusResult, node_name: str | None = None, command: str = '') -> str:
    """A params file for one bus: node name key, ros__parameters, drives and drives.<name>."""
    node_name = node_name or NODE_NAMES[result.vendor]
    lines = [f'# Written by stepperctl scan {result.vendor} on {time.strftime("%Y-%m-%d %H:%M")}'
             + (f' ({command})' if command else '') + '.']
    lines += [f'# {h}' for h in result.header]
    lines += ['# Limits and profiles are the defaults: set min/max_position, max_velocity and the',
              '# profile for the machine before moving it (docs/interface.md lists every '
              'parameter).',
              f'{node_name}:', '  ros__parameters:']
    for key, value in result.bus_params.items():
        lines.append(f'    {key}: {_yaml_scalar(value)}')
    names = [drive_name(result.vendor, d.address) for d in result.drives]
    lines.append(f'    drives: [{", ".join(names)}]')
    for name, d in zip(names, result.drives):
        lines.append(f'    drives.{name}:')
        for k, v in d.identity.items():
            lines.append(f'      # {k}: {v}')
        for note in d.notes:
            lines.append(f'      # {note}')
        params = {ADDRESS_NAMES[result.vendor]: d.address, 'joint_name': f'joint{d.address}',
                  **d.drive_params}
        for key, value in params.items():
            if isinstance(value, dict):
                lines.append(f'      {key}:')
                for k2, v2 in value.items():
                    lines.append(f'        {k2}: {_yaml_scalar(v2)}')
            else:
                lines.append(f'      {key}: {_yaml_scalar(value)}')
    return '\n'.join(lines) + '\n'


def yaml_paths(path: str, results: list[BusResult]) -> list[str]:
    """One file per bus: FILE for the first, FILE with _2, _3 ... before the suffix after."""
    out = []
    for i, _ in enumerate(results):
        if i == 0:
            out.append(path)
        else:
            stem, dot, ext = path.rpartition('.')
            out.append(f'{stem}_{i + 1}.{ext}' if dot else f'{path}_{i + 1}')
    return out


# ----------------------------------------------------------------------------------- output
def print_results(results: list[BusResult]) -> None:
    for r in results:
        print(f'{r.description}: {len(r.drives)} drive(s)')
        for d in r.drives:
            ident = ', '.join(f'{k}={v}' for k, v in d.identity.items())
            print(f'  {ADDRESS_NAMES[r.vendor]} {d.address:>3}: {ident}')
            for note in d.notes:
                print(f'      note: {note}')
    sys.stdout.flush()


def run(args) -> int:
    deadline = Deadline(args.max_time)
    results = SCANNERS[args.vendor](args, deadline)
    if deadline.hit:
        print(f'scan {args.vendor}: stopped after --max-time {args.max_time:g} s; not every '
              'address was probed', file=sys.stderr)
    if not results:
        raise CliError(EXIT_NOT_FOUND, f'scan {args.vendor}: no drive answered; '
                       + vendor_table.BY_KEY[args.vendor].scan_hint)
    print_results(results)
    if args.write_yaml:
        command = ' '.join(sys.argv[1:]) if sys.argv else ''
        for path, r in zip(yaml_paths(args.write_yaml, results), results):
            with open(path, 'w', encoding='utf-8') as f:
                f.write(render_yaml(r, args.node_name, command))
            print(f'wrote {path}: start the node with  ros2 run stepper_drivers '
                  f'{NODE_NAMES[r.vendor]} --ros-args --params-file {path}'
                  + (f' -r __node:={args.node_name}' if args.node_name else ''))
    return EXIT_OK
