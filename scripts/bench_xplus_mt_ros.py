#!/usr/bin/env python3
"""Benchmark (not a test): X-PLUS MT node against xplus_mt_sim, measured on the wire.

A sniffing TCP relay sits between node and simulator and timestamps every Modbus request. Prints:
1. state-poll transactions per second the node achieves (publish_rate_hz set far above what it
   can do, so the poll loop runs flat out), and the same for a bare pymodbus loop reading the same
   register block from the same simulator: the ratio is the figure;
2. ROS-command-to-wire latency: time from publishing position_command to the FC16 write of
   Target Position (1042) arriving at the relay, p50/p99 over N commands.

Run: source scripts/env.sh && python scripts/bench_xplus_mt_ros.py [--seconds 5] [--commands 200]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import pathlib
import statistics
import struct
import sys
import tempfile
import threading
import time

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from std_msgs.msg import Float64
from std_srvs.srv import SetBool
from stepper_drivers.cli.ros_client import RosClient
from stepper_drivers_msgs.msg import DriveStatus
from stepper_sim.harness import CONFIG, Proc, executable, free_port

STATE_BLOCK = (1001, 21)      # the block the node reads per drive per cycle (1001..1021)
TARGET_POSITION = 1042
# Commands this far apart: each one finds the bus free (a move holds it for the handshake).
COMMAND_GAP_S = 0.06


class SniffingRelay:
    """127.0.0.1:listen -> 127.0.0.1:upstream; records (time, function code, address) per request.

    Run in a process of its own (`--relay PORT`, see RelayProcess): in the benchmark process its
    asyncio thread would share the GIL with rclpy's executor threads and answer late.
    """

    def __init__(self, upstream_port: int, on_target=None):
        self.upstream_port = upstream_port
        self.on_target = on_target
        self.port = free_port()
        self.requests: list[tuple[float, int, int]] = []
        self.loop = asyncio.new_event_loop()
        self.ready = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()
        self.ready.wait(5)

    def _run(self):
        asyncio.set_event_loop(self.loop)
        self.loop.run_until_complete(self._serve())

    async def _serve(self):
        server = await asyncio.start_server(self._client, '127.0.0.1', self.port)
        self.ready.set()
        async with server:
            await server.serve_forever()

    async def _client(self, reader, writer):
        up_r, up_w = await asyncio.open_connection('127.0.0.1', self.upstream_port)

        async def requests():
            buf = b''
            while data := await reader.read(4096):
                now = time.monotonic()
                buf += data
                while len(buf) >= 7:                      # MBAP: tid, pid, length, unit
                    length = struct.unpack('>H', buf[4:6])[0]
                    if len(buf) < 6 + length:
                        break
                    frame, buf = buf[:6 + length], buf[6 + length:]
                    fc, addr = frame[7], struct.unpack('>H', frame[8:10])[0]
                    self.requests.append((now, fc, addr))
                    if fc == 16 and addr == TARGET_POSITION and self.on_target:
                        self.on_target(now)
                up_w.write(data)
            up_w.close()

        async def replies():
            while data := await up_r.read(4096):
                writer.write(data)
            writer.close()
        await asyncio.gather(requests(), replies(), return_exceptions=True)


class RelayProcess:
    """The relay as a child process; it prints the time.monotonic() (system-wide on Linux) of
    every Target Position write, which this process turns into an event."""

    def __init__(self, upstream_port: int):
        import subprocess
        self.proc = subprocess.Popen([sys.executable, __file__, '--relay', str(upstream_port)],
                                     stdout=subprocess.PIPE, text=True)
        self.port = int(self.proc.stdout.readline().split()[1])
        self.target_written = threading.Event()
        self.target_written_at = 0.0
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stdout:
            self.target_written_at = float(line.split()[1])
            self.target_written.set()

    def stop(self):
        self.proc.terminate()
        self.proc.wait(5)


def run_relay(upstream_port: int) -> int:
    relay = SniffingRelay(upstream_port, on_target=lambda t: print(f'T {t:.6f}', flush=True))
    print(f'port {relay.port}', flush=True)
    threading.Event().wait()     # until terminated
    return 0


def bare_pymodbus_tps(port: int, seconds: float) -> tuple[float, float]:
    """Transactions/s and median round trip (ms) of a plain sync pymodbus loop."""
    from pymodbus.client import ModbusTcpClient
    c = ModbusTcpClient('127.0.0.1', port=port, timeout=1)
    assert c.connect()
    rtts, t_end = [], time.monotonic() + seconds
    t0 = time.monotonic()
    while time.monotonic() < t_end:
        t = time.perf_counter()
        r = c.read_holding_registers(STATE_BLOCK[0], count=STATE_BLOCK[1], device_id=1)
        rtts.append(time.perf_counter() - t)
        assert not r.isError(), r
    c.close()
    return len(rtts) / (time.monotonic() - t0), statistics.median(rtts) * 1000


def start_node(log_dir, name, port, rate_hz):
    return Proc([executable('stepper_drivers', 'xplus_mt_node'), '--ros-args', '--params-file',
                 str(CONFIG / 'xplus_mt.yaml'), '-p', f'port:={port}',
                 '-p', f'publish_rate_hz:={rate_hz}', '-p', 'drives:=[axis1]'], log_dir, name)


def node_tps(ros: RosClient, seconds: float) -> float:
    """The node's own transaction counter (DriveStatus.link_transactions) over a time window."""
    status = '/xplus_mt_node/axis1/status'
    ros.wait_msg(status, lambda m: m.connected, 30)
    time.sleep(1.0)  # warm-up before the window (discovery, first cycles)
    a = ros.latest[status]
    time.sleep(seconds)  # measurement window
    b = ros.latest[status]
    dt = ((b.header.stamp.sec - a.header.stamp.sec)
          + (b.header.stamp.nanosec - a.header.stamp.nanosec) * 1e-9)
    return (b.link_transactions - a.link_transactions) / dt


def command_latencies(ros: RosClient, relay: 'RelayProcess', n: int) -> list[float]:
    resp = ros.call(SetBool, '/xplus_mt_node/axis1/enable', SetBool.Request(data=True))
    assert resp.success, resp.message
    latencies = []
    topic = '/xplus_mt_node/axis1/position_command'
    ros.publish(Float64, topic, Float64(data=0.0))   # first set point after enable waits settling
    time.sleep(0.5)
    for i in range(n):
        target = 0.5 if i % 2 == 0 else -0.5
        relay.target_written.clear()
        t_pub = time.monotonic()
        ros.publish(Float64, topic, Float64(data=target))
        if relay.target_written.wait(2.0):
            latencies.append((relay.target_written_at - t_pub) * 1000)
        time.sleep(COMMAND_GAP_S)  # let the set-point handshake (>= 2 x 12 ms) finish
    ros.call(SetBool, '/xplus_mt_node/axis1/enable', SetBool.Request(data=False))
    return sorted(latencies)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=5.0)
    ap.add_argument('--commands', type=int, default=200)
    ap.add_argument('--relay', type=int, metavar='UPSTREAM_PORT', help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.relay:
        return run_relay(args.relay)
    log_dir = pathlib.Path(tempfile.mkdtemp(prefix='bench_xplus_'))
    sim_port = free_port()
    procs, ros, relay = [], None, None
    try:
        sim = Proc([executable('stepper_sim', 'xplus_mt_sim'), '--ros-args', '--params-file',
                    str(CONFIG / 'xplus_mt_sim.yaml'), '-p', f'port:={sim_port}',
                    '-p', 'strict:=false'],    # strict refuses reading across the 1003 hole
                   log_dir, 'sim')
        procs.append(sim)
        sim.wait_line('ready', 30)
        bare, bare_rtt = bare_pymodbus_tps(sim_port, args.seconds)
        ros = RosClient('bench')
        ros.subscribe(DriveStatus, '/xplus_mt_node/axis1/status')
        node = start_node(log_dir, 'node_fast', sim_port, 1000.0)
        procs.append(node)
        fast = node_tps(ros, args.seconds)
        node.stop()
        procs.remove(node)
        ros.latest.clear()
        relay = RelayProcess(sim_port)
        relay_tps, relay_rtt = bare_pymodbus_tps(relay.port, 1.0)
        node = start_node(log_dir, 'node_50hz', relay.port, 50.0)
        procs.append(node)
        ros.wait_msg('/xplus_mt_node/axis1/status', lambda m: m.connected, 30)
        lat = command_latencies(ros, relay, args.commands)
    finally:
        if ros:
            ros.close()
        for p in reversed(procs):
            p.stop()
        if relay:
            relay.stop()

    p50 = statistics.median(lat)
    p99 = lat[min(len(lat) - 1, int(0.99 * len(lat)))]
    print(f'X-PLUS MT benchmark ({os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; '
          'sim, node and this script on 127.0.0.1)')
    print(f'  state read: one FC03 of {STATE_BLOCK[1]} registers from {STATE_BLOCK[0]} '
          'per drive per cycle')
    print(f'  bare pymodbus sync loop:        {bare:8.0f} transactions/s '
          f'(round trip {bare_rtt:.2f} ms)')
    print(f'  node poll loop, 1 drive:        {fast:8.0f} transactions/s '
          '(publish_rate_hz 1000: joint_states + status published every cycle)')
    print(f'  ratio node / bare:              {fast / bare:8.1%}')
    print(f'  command -> wire latency:        p50 {p50:.2f} ms, p99 {p99:.2f} ms '
          f'over {len(lat)} of '
          f'{args.commands} position_command messages (node at 50 Hz; measured at a relay whose '
          f'own round trip is {relay_rtt:.2f} ms)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
