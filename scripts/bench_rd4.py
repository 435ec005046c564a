#!/usr/bin/env python3
"""Lika RD4 state-poll benchmark: cycles per second on an emulated 19200 8E1 line vs its limit.

The simulator (stepper_sim.rd4.sim, in a child process, no ROS) emulates the line: a reply comes
when a real line at the dip-switch baud rate would deliver it (11-bit characters, t3.5 silences).
The driver side is the real Rd4Drive + ModbusRtuBus doing what the node does every cycle: one
read_state() per unit (one FC04 of 8 input registers). The theoretical limit for the same frames:

    per poll = (request bytes + reply bytes) * 11 / baud + 2 * t3.5        (manual §7.3.1)

(the reply follows the request after t3.5, the next request follows the reply after t3.5).
The pty itself runs at parity N (a pty refuses E; timing is the same 11 bits per character).
Also measured for comparison: pymodbus 3.16's AsyncModbusSerialClient doing the same reads.

Run: source scripts/env.sh && python scripts/bench_rd4.py [--seconds 5] [--units 1 4]
Exit code 1 when the driver stays below --goal (default 90 %) of the limit.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import os
import shutil
import statistics
import sys
import tempfile
import time

from stepper_drivers.contract.drive import complete
from stepper_drivers.protocol import modbus_rtu as rtu
from stepper_drivers.vendors import rd4
from stepper_drivers.vendors.rd4 import regmap as rm

BAUD_SWITCH = 0x04                      # §4.4.2: 19200 baud, Even parity (8E1)
BAUD = rm.BAUD_SWITCH[BAUD_SWITCH][0]
POLL_REGISTERS = rm.STATE_BLOCK[1]      # what Rd4Drive.read_state() reads per unit


def run_sim(path: str, units: int, line_timing: bool, conn) -> None:
    from stepper_sim.rd4.sim import build_line
    line = build_line({'port': path, 'baud_switch': BAUD_SWITCH, 'line_timing': line_timing},
                      {f'axis{i + 1}': {'node_id': i + 1} for i in range(units)})
    line.start()
    conn.send(line.counters['pty_opened'])
    conn.recv()                          # until the parent says stop
    line.stop()


class Sim:
    """The simulated line in its own process (the driver and the sim share 2 cores)."""

    def __init__(self, units: int, line_timing: bool = True):
        self.path = os.path.join(tempfile.mkdtemp(prefix='bench_rd4_'), 'rd4.pty')
        ctx = multiprocessing.get_context('spawn')
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=run_sim, args=(self.path, units, line_timing, child),
                                daemon=True)
        self.proc.start()
        if not self.conn.poll(20.0):
            raise RuntimeError('simulator did not start')
        self.conn.recv()

    def stop(self) -> None:
        self.conn.send('stop')
        self.proc.join(timeout=10.0)
        if self.proc.is_alive():
            self.proc.kill()
        shutil.rmtree(os.path.dirname(self.path), ignore_errors=True)


def theoretical_poll_s() -> float:
    request = rtu.read_request(1, rtu.FC_READ_INPUT_REGISTERS, 0, POLL_REGISTERS)
    return (rtu.frame_time_s(len(rtu.encode(request)) + rtu.reply_length(request), BAUD)
            + 2 * rtu.t35_s(BAUD))


def bench_driver(units: int, seconds: float, line_timing: bool = True) -> dict:
    sim = Sim(units, line_timing)
    bus = rd4.make_bus({'port': sim.path, 'baudrate': BAUD, 'parity': 'N', 'timeout_s': 0.2})
    try:
        bus.open()
        drives = [rd4.make_drive(bus, f'axis{i + 1}', {'node_id': i + 1}) for i in range(units)]
        for d in drives:
            complete(d.connect())
        for _ in range(3):
            for d in drives:
                complete(d.read_state())
        cycle_s = []
        errors_before = bus.errors
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            t0 = time.monotonic()
            for d in drives:
                complete(d.read_state())
            cycle_s.append(time.monotonic() - t0)
        return {'cycles_s': len(cycle_s) / sum(cycle_s), 'p99_ms': 1000 * sorted(
            cycle_s)[int(0.99 * (len(cycle_s) - 1))], 'mean_ms': 1000 * statistics.mean(cycle_s),
            'errors': bus.errors - errors_before, 'n': len(cycle_s)}
    finally:
        bus.close()
        sim.stop()


def bench_pymodbus(units: int, seconds: float) -> dict:
    from pymodbus.client import AsyncModbusSerialClient
    sim = Sim(units)

    async def run() -> dict:
        client = AsyncModbusSerialClient(sim.path, baudrate=BAUD, parity='N', stopbits=2,
                                         timeout=0.2, retries=0)
        assert await client.connect(), 'pymodbus could not open the pty'
        try:
            cycles = 0
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds:
                for unit in range(1, units + 1):
                    r = await client.read_input_registers(0, count=POLL_REGISTERS,
                                                          device_id=unit)
                    assert not r.isError(), r
                cycles += 1
            return {'cycles_s': cycles / (time.monotonic() - t0)}
        finally:
            client.close()
    try:
        return asyncio.run(run())
    finally:
        sim.stop()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=5.0, help='measuring time per case')
    ap.add_argument('--units', type=int, nargs='+', default=[1, 4])
    ap.add_argument('--goal', type=float, default=0.90, help='required fraction of the limit')
    ap.add_argument('--no-pymodbus', action='store_true', help='skip the pymodbus comparison')
    args = ap.parse_args()
    poll_s = theoretical_poll_s()
    request_bytes = 8
    reply_bytes = 5 + 2 * POLL_REGISTERS
    print(f'RD4 state poll: FC04 of {POLL_REGISTERS} registers = {request_bytes} + {reply_bytes} '
          f'bytes; line {BAUD} 8E1 emulated (dip-switch {BAUD_SWITCH:02X}h), 11 bits/char, '
          f't3.5 = {1000 * rtu.t35_s(BAUD):.3f} ms')
    print(f'limit per poll = {request_bytes + reply_bytes} x 11 / {BAUD} + 2 x t3.5 = '
          f'{1000 * poll_s:.3f} ms')
    print(f'{"units":>5} {"limit/s":>9} {"driver/s":>9} {"ratio":>7} {"mean ms":>8} '
          f'{"p99 ms":>7} {"errors":>6} {"pymodbus/s":>10} {"ratio":>6}')
    ok = True
    for units in args.units:
        limit = 1.0 / (units * poll_s)
        res = bench_driver(units, args.seconds)
        ratio = res['cycles_s'] / limit
        ok &= ratio >= args.goal and res['errors'] == 0
        pm = '' if args.no_pymodbus else bench_pymodbus(units, args.seconds)
        pm_text = '' if not pm else (f'{pm["cycles_s"]:10.2f} {pm["cycles_s"] / limit:6.1%}')
        print(f'{units:5d} {limit:9.2f} {res["cycles_s"]:9.2f} {ratio:7.1%} '
              f'{res["mean_ms"]:8.2f} {res["p99_ms"]:7.2f} {res["errors"]:6d} {pm_text}',
              flush=True)
    raw = bench_driver(1, min(args.seconds, 2.0), line_timing=False)
    print(f'without line timing (pty speed, master keeps t3.5): {raw["cycles_s"]:.1f} polls/s '
          f'for 1 unit')
    print(f'goal {args.goal:.0%} of the limit: ' + ('met' if ok else 'NOT met'))
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
