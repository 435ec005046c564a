#!/usr/bin/env python3
"""Helper processes of scripts/bench_command_path.py (not run by hand).

Each runs in a process of its own, so its timing never waits for the benchmark's GIL (the old
in-process TCP relay answered late enough for the node to declare the link lost), prints `ready`
(or `port N`) once it serves, then one line per event with its time.monotonic() (CLOCK_MONOTONIC,
the same clock in every process of the machine):

    tcp UPSTREAM_PORT                  Modbus TCP relay 127.0.0.1:<port> -> UPSTREAM_PORT
        Q <t> <conn> <unit> <fc> <address> <count>     a request, t = its first byte read
        A <t> <conn>                                   reply bytes written back to the node
    pty LINK UPSTREAM BAUD             serial relay: a pty whose slave is linked at LINK (the
                                       node opens it) <-> the simulator's pty at UPSTREAM
        Q <t> <hex>                    bytes from the node (one write of the driver = one frame)
        A <t> 0                        reply bytes from the simulator, forwarded
    can PORT                           a socketcand client on the broker at 127.0.0.1:PORT
        F <t> <cob-id hex> <data hex>  every frame another client sent, t = the broker's stamp
    canlink UPSTREAM_PORT              socketcand relay 127.0.0.1:<port> -> the broker at
                                       UPSTREAM_PORT, on the node's link as `tcp` is
        F <t> <cob-id hex> <data hex>  a frame the node sent, t = its first byte read
        A <t> <conn>                   bytes from the broker written back to the node
    floor TOPIC                        an rclpy subscriber (SingleThreadedExecutor, the node's
                                       QoS: depth 10, reliable) of std_msgs/Float64
        M <t> <data>
    xsims PORTS UNITS                  PORTS X-PLUS MT simulators (non-strict) in one process,
                                       UNITS drives (unit ids 1..UNITS) each; `port N` per sim
    bare-modbus RATE_HZ UNITS PORT...  a pymodbus loop reading the node's state block of every
                                       unit on every port once per period (CPU reference)
    bare-canopen RATE_HZ PORT IDS      a canopen loop: the node's TxPDO set on drives IDS
                                       (comma-separated), SYNC and heartbeat as the node sends
                                       them, the cached values read once per period
    bare-modbus-threads RATE_HZ UNITS PORT...  the same with a thread per port
    bare-modbus-ros, bare-canopen-ros  the same, publishing what a drive node publishes when
                                       nothing changes: one JointState per period, each
                                       DriveStatus at 1 Hz, /diagnostics at 2 Hz
    driver-xplus RATE_HZ UNITS PORT... the project's XplusMtDrive.read_state() loop, no ROS
"""

from __future__ import annotations

import asyncio
import os
import select
import socket
import struct
import sys
import termios
import threading
import time
import tty
from typing import Callable

# Fast DDS discovery stays on this machine (the floor subscriber and the *-ros loops are nodes)
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

XPLUS_STATE_BLOCK = (1001, 21)       # what XplusMtDrive.read_state() reads (non-strict sim)


def out(line: str) -> None:
    sys.stdout.write(line + '\n')
    sys.stdout.flush()


# ---------------------------------------------------------------------- TCP relays (node link)
def relay_tcp(upstream_port: int, on_requests: Callable[[float, int, bytes], bytes],
              time_replies: bool = True) -> None:
    """A TCP relay 127.0.0.1:<port> -> upstream: the node's bytes are forwarded first, then
    `on_requests(t, conn, buffer)` prints what they complete and returns the rest; `A` lines
    time the bytes going back to the node (time_replies; not for CAN, where nothing reads them
    and the broker's frames to the node would make hundreds of lines a second)."""
    conns = [0]

    async def client(reader, writer):
        conns[0] += 1
        conn = conns[0]
        up_r, up_w = await asyncio.open_connection('127.0.0.1', upstream_port)
        for w in (writer, up_w):
            w.get_extra_info('socket').setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

        async def requests():
            buf = b''
            while data := await reader.read(4096):
                now = time.monotonic()
                up_w.write(data)               # forward first, then parse
                buf = on_requests(now, conn, buf + data)
            up_w.close()

        async def replies():
            while data := await up_r.read(4096):
                writer.write(data)
                if time_replies:
                    out(f'A {time.monotonic():.6f} {conn}')
            writer.close()
        await asyncio.gather(requests(), replies(), return_exceptions=True)

    async def serve():
        server = await asyncio.start_server(client, '127.0.0.1', 0)
        out(f'port {server.sockets[0].getsockname()[1]}')
        async with server:
            await server.serve_forever()
    asyncio.run(serve())


def modbus_requests(now: float, conn: int, buf: bytes) -> bytes:
    while len(buf) >= 12:          # MBAP (7) + fc + address + count/value
        length = struct.unpack('>H', buf[4:6])[0]
        if len(buf) < 6 + length:
            break
        frame, buf = buf[:6 + length], buf[6 + length:]
        unit, fc = frame[6], frame[7]
        address, count = struct.unpack('>HH', frame[8:12])
        out(f'Q {now:.6f} {conn} {unit} {fc} {address} {count}')
    return buf


def socketcand_sends(now: float, conn: int, buf: bytes) -> bytes:
    """`< send 301 8 1f 0 ... >` from the node: an F line as the broker probe prints, its time
    the relay's read (the node's frame on its link, before the broker's fan-out)."""
    while (end := buf.find(b'>')) >= 0:
        words, buf = buf[buf.find(b'<') + 1:end].split(), buf[end + 1:]
        if len(words) >= 3 and words[0] == b'send':
            n = int(words[2], 16)
            data = bytes(int(b, 16) for b in words[3:3 + n])
            out(f'F {now:.6f} {int(words[1], 16):03X} {data.hex()}')
    return buf


# ----------------------------------------------------------------------------------- serial
def _raw_at(fd: int, baud: int) -> None:
    tty.setraw(fd)
    attrs = termios.tcgetattr(fd)
    attrs[4] = attrs[5] = getattr(termios, f'B{baud}')
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


def run_pty(link: str, upstream: str, baud: int) -> None:
    master, slave = os.openpty()
    _raw_at(slave, baud)                    # slave kept open: no EIO between node opens
    tmp = f'{link}.{os.getpid()}.tmp'
    os.symlink(os.ttyname(slave), tmp)
    os.replace(tmp, link)
    sim = os.open(upstream, os.O_RDWR | os.O_NOCTTY)
    _raw_at(sim, baud)                      # the simulator compares the opener's baud rate
    out('ready')
    while True:
        ready, _, _ = select.select([master, sim], [], [])
        now = time.monotonic()
        if master in ready:
            try:
                data = os.read(master, 4096)
            except OSError:                 # the node closed its side: wait for a reopen
                time.sleep(0.001)
                continue
            os.write(sim, data)
            out(f'Q {now:.6f} {data.hex()}')
        if sim in ready:
            data = os.read(sim, 4096)
            os.write(master, data)
            out(f'A {now:.6f} 0')


# -------------------------------------------------------------------------------------- CAN
def run_can(port: int) -> None:
    import can
    bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel='can0')
    out('ready')
    while True:
        msg = bus.recv(1.0)
        if msg is not None:
            # the broker's time.time() of the frame's arrival (it is the bus), on the
            # monotonic clock: a stall of this process does not move it
            t = msg.timestamp - (time.time() - time.monotonic())
            out(f'F {t:.6f} {msg.arbitration_id:03X} {bytes(msg.data).hex()}')


# ---------------------------------------------------------------------------- rclpy floor
def run_floor(topic: str) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Float64
    rclpy.init()
    node = rclpy.create_node('bench_cp_floor')
    # the QoS the drive nodes give position_command: depth 10, reliable, volatile
    node.create_subscription(Float64, topic,
                             lambda m: out(f'M {time.monotonic():.6f} {m.data:.0f}'), 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    out('ready')
    try:
        executor.spin()
    except KeyboardInterrupt:
        pass


# ------------------------------------------------------------------------------ X-PLUS MT
def run_xsims(ports: int, units: int) -> None:
    from stepper_sim.xplus_mt.sim import XplusMtDriveConfig, XplusMtSim
    sims = []
    for p in range(ports):
        # serial numbers differ: the node refuses two drives that answer with one identity
        drives = [XplusMtDriveConfig(f'axis{u}', unit_id=u, serial_number=200000 + 100 * p + u,
                                     home_switch_steps=None, limit_neg_steps=None,
                                     limit_pos_steps=None) for u in range(1, units + 1)]
        sim = XplusMtSim(port=0, drives=drives, strict=False)
        sim.start()
        sims.append(sim)
        out(f'port {sim.port}')
    out('ready')
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        for sim in sims:
            sim.stop()


def ros_publisher(n: int, status_rate_hz: float = 1.0, diagnostics_rate_hz: float = 2.0):
    """publish(values): what a drive node publishes, for n drives, done the cheapest way we
    know: one JointState per poll cycle (CDR bytes published raw, as the node does; the system
    clock), each drive's DriveStatus at status_rate_hz and one DiagnosticArray (a status of 12
    values per drive, built once, stamped anew) at diagnostics_rate_hz, as the node does when
    nothing changes (rclpy, the node's QoS); values: (position, statusword). The floor of an
    rclpy node that offers the interface at this rate (the CPU goal's reference)."""
    import array

    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from stepper_drivers_msgs.msg import DriveStatus
    rclpy.init()
    node = rclpy.create_node('bench_cp_bare')
    js_pub = node.create_publisher(JointState, '~/joint_states',
                                   QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    st_pubs = [node.create_publisher(DriveStatus, f'~/axis{i}/status', 10)
               for i in range(1, n + 1)]
    diag_pub = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
    names = [f'bench_joint{i}' for i in range(1, n + 1)]
    try:                        # the node's way: CDR bytes published raw (joint_state_cdr.py)
        from stepper_drivers.ros.joint_state_cdr import JointStateCdr
        cdr, js = JointStateCdr(names), None
    except ImportError:         # a tree from before it
        cdr, js = None, JointState(name=names)
    diag = DiagnosticArray(status=[DiagnosticStatus(
        name=f'bench_cp_bare: axis{i}', message='OK', hardware_id=f'unit {i}',
        values=[KeyValue(key=f'key{k}', value=str(k)) for k in range(12)])
        for i in range(1, n + 1)])
    due = {'status': 0.0, 'diag': 0.0}

    def publish(values: list[tuple[int, int]]) -> None:
        ns = time.time_ns()
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if cdr is not None:
            js_pub.publish(cdr.encode(stamp.sec, stamp.nanosec,
                                      [float(p) / 12800.0 for p, _ in values], [0.0] * n))
        else:
            js.header.stamp = stamp
            js.position = array.array('d', [float(p) / 12800.0 for p, _ in values])
            js.velocity = array.array('d', [0.0] * n)
            js_pub.publish(js)
        now = time.monotonic()
        if now >= due['status']:
            due['status'] = now + 1.0 / status_rate_hz
            for i, (pub, (position, sw)) in enumerate(zip(st_pubs, values)):
                m = DriveStatus()
                m.header.stamp = stamp
                m.drive, m.joint_name, m.state, m.connected = f'axis{i + 1}', names[i], 'X', True
                m.status_word, m.position_steps = sw, position
                m.position = float(position) / 12800.0
                pub.publish(m)
        if now >= due['diag']:
            due['diag'] = now + 1.0 / diagnostics_rate_hz
            diag.header.stamp = stamp
            diag_pub.publish(diag)
    return publish


def modbus_clients(ports: list[int]):
    """A connected pymodbus client per port on 127.0.0.1."""
    from pymodbus.client import ModbusTcpClient
    clients = []
    for port in ports:
        c = ModbusTcpClient('127.0.0.1', port=port, timeout=1)
        assert c.connect(), f'no connection to 127.0.0.1:{port}'
        clients.append(c)
    return clients


def poll_units(client, units: int) -> list[tuple[int, int]]:
    """One FC03 of the state block per unit id 1..units: (position, statusword) each."""
    values = []
    for unit in range(1, units + 1):
        r = client.read_holding_registers(XPLUS_STATE_BLOCK[0], count=XPLUS_STATE_BLOCK[1],
                                          device_id=unit)
        assert not r.isError(), r
        w = r.registers
        values.append((w[3] | w[4] << 16, w[0]))     # position 1004-1005 (little)
    return values


def run_bare_modbus(rate_hz: float, units: int, ports: list[int], ros: bool) -> None:
    clients = modbus_clients(ports)
    publish = ros_publisher(units * len(ports)) if ros else None
    out('ready')
    period_s, t_next = 1.0 / rate_hz, time.monotonic()
    while True:
        values = [v for c in clients for v in poll_units(c, units)]
        if publish:
            publish(values)
        t_next = max(t_next + period_s, time.monotonic())
        time.sleep(max(0.0, t_next - time.monotonic()))


def run_bare_modbus_threads(rate_hz: float, units: int, ports: list[int]) -> None:
    """bare-modbus with a thread per port, all on one grid of periods: the bare loop of a
    design that gives every link a thread of its own (as the node does: a dead host stalls
    only its own link's polls and watchdog)."""
    clients = modbus_clients(ports)
    period_s, t0 = 1.0 / rate_hz, time.monotonic()

    def loop(c) -> None:
        t_next = t0
        while True:
            poll_units(c, units)
            t_next = max(t_next + period_s, time.monotonic())
            time.sleep(max(0.0, t_next - time.monotonic()))
    threads = [threading.Thread(target=loop, args=(c,), daemon=True) for c in clients]
    for t in threads:
        t.start()
    out('ready')
    threads[0].join()


def run_driver_xplus(rate_hz: float, units: int, ports: list[int]) -> None:
    """The project's X-PLUS MT driver without ROS: connect, then read_state() of every drive
    once per period (what the node's owner threads do between publishing)."""
    from stepper_drivers.vendors import xplus_mt as xp
    try:
        from stepper_drivers.contract.drive import complete
    except ImportError:                  # a tree from before the step-wise contract
        def complete(result):
            return result
    drives = []
    for port in ports:
        bus = xp.make_bus({'host': '127.0.0.1', 'port': port, 'timeout_s': 0.5})
        bus.open()
        for unit in range(1, units + 1):
            d = xp.make_drive(bus, f'p{port}u{unit}', {'unit_id': unit, 'watchdog_ms': 1000,
                                                       'input_config': -1,
                                                       'word_order': 'little'})
            complete(d.connect())
            drives.append(d)
    out('ready')
    period_s, t_next = 1.0 / rate_hz, time.monotonic()
    while True:
        for d in drives:
            complete(d.read_state())
        t_next = max(t_next + period_s, time.monotonic())
        time.sleep(max(0.0, t_next - time.monotonic()))


def run_bare_canopen(rate_hz: float, port: int, ids: list[int], ros: bool) -> None:
    import canopen
    from stepper_drivers.vendors.vector_step import regmap as vm
    network = canopen.Network()
    network.connect(interface='socketcand', host='127.0.0.1', port=port, channel='can0')
    nodes = []
    for node_id in ids:
        node = canopen.RemoteNode(node_id, canopen.objectdictionary.ObjectDictionary())
        network.add_node(node)
        nodes.append(node)
    network.nmt.send_command(0x82)           # reset communication: a clean PDO set, boot-ups
    time.sleep(0.5)
    for node in nodes:
        # the node's set: heartbeat 100 ms, TxPDO1..4 as DRIVER_TPDOS, only TxPDO2 timed
        node.sdo.download(0x1017, 0, (100).to_bytes(2, 'little'))
        for number, entries in enumerate(vm.DRIVER_TPDOS, 1):
            comm, mapping = 0x1800 + number - 1, 0x1A00 + number - 1
            cob_id = vm.PDO_COB_BASES_TX[number - 1] + node.id
            timer = 100 if number == 2 else 0
            writes = [(comm, 1, cob_id | vm.PDO_INVALID, 4), (comm, 2, 0xFE, 1),
                      (comm, 3, 0, 2), (comm, 5, timer, 2), (mapping, 0, 0, 1)]
            writes += [(mapping, k, vm.mapping_entry(*e), 4) for k, e in enumerate(entries, 1)]
            writes += [(mapping, 0, len(entries), 1), (comm, 1, cob_id, 4)]
            for index, sub, value, size in writes:
                node.sdo.download(index, sub, value.to_bytes(size, 'little'))
    latest: dict[int, bytes] = {}

    def on_frame(can_id, data, _timestamp):
        latest[can_id] = bytes(data)
    for node in nodes:
        for number in range(len(vm.DRIVER_TPDOS)):
            network.subscribe(vm.PDO_COB_BASES_TX[number] + node.id, on_frame)
    network.sync.start(0.1)
    network.send_periodic(0x77F, [0x05], 0.1)    # the node's own heartbeat (node-ID 127)
    network.nmt.send_command(0x01)               # all drives OPERATIONAL
    publish = ros_publisher(len(nodes)) if ros else None
    out('ready')
    period_s, t_next = 1.0 / rate_hz, time.monotonic()
    while True:
        values = []
        for node in nodes:                       # what a poll reads: statusword + position
            data = latest.get(0x280 + node.id, b'\0' * 6)
            values.append((int.from_bytes(data[2:6], 'little', signed=True),
                           int.from_bytes(data[:2], 'little')))
        if publish:
            publish(values)
        t_next = max(t_next + period_s, time.monotonic())
        time.sleep(max(0.0, t_next - time.monotonic()))


def main(argv: list[str]) -> int:
    kind, args = argv[0], argv[1:]
    if kind == 'tcp':
        relay_tcp(int(args[0]), modbus_requests)
    elif kind == 'canlink':
        relay_tcp(int(args[0]), socketcand_sends, time_replies=False)
    elif kind == 'pty':
        run_pty(args[0], args[1], int(args[2]))
    elif kind == 'can':
        run_can(int(args[0]))
    elif kind == 'floor':
        run_floor(args[0])
    elif kind == 'xsims':
        run_xsims(int(args[0]), int(args[1]))
    elif kind in ('bare-modbus', 'bare-modbus-ros'):
        run_bare_modbus(float(args[0]), int(args[1]), [int(p) for p in args[2:]],
                        kind.endswith('-ros'))
    elif kind == 'bare-modbus-threads':
        run_bare_modbus_threads(float(args[0]), int(args[1]), [int(p) for p in args[2:]])
    elif kind == 'driver-xplus':
        run_driver_xplus(float(args[0]), int(args[1]), [int(p) for p in args[2:]])
    elif kind in ('bare-canopen', 'bare-canopen-ros'):
        run_bare_canopen(float(args[0]), int(args[1]), [int(i) for i in args[2].split(',')],
                         kind.endswith('-ros'))
    else:
        raise SystemExit(f'unknown helper {kind!r}')
    return 0


if __name__ == '__main__':
    try:
        sys.exit(main(sys.argv[1:]))
    except KeyboardInterrupt:
        sys.exit(0)
