#!/usr/bin/env python3
"""Benchmark (not a test): XplusMtDrive.read_state() polls per second against xplus_mt_sim.

The simulator runs in a child process (so it does not share the GIL with the measured loop) on
127.0.0.1 and a free port. Prints, for the same drive and the same time budget:
1. read_state() polls/s of XplusMtDrive (and Modbus transactions/s it needs),
2. polls/s of a bare pymodbus ModbusTcpClient loop reading the same registers the same way
   (one FC03 of 1001..1021, or the three reads a strict simulator needs),
and the ratio 1/2, the cost of the driver layer on top of pymodbus.

Run: source scripts/env.sh && python scripts/bench_xplus_mt.py [--seconds 3] [--strict]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

from pymodbus.client import ModbusTcpClient
from stepper_drivers.vendors.xplus_mt import SPLIT_READS, STATE_BLOCK, VENDOR

SIM_CODE = r"""
import sys
from stepper_sim.xplus_mt.sim import XplusMtSim
sim = XplusMtSim(port=0, strict={strict})
sim.start()
print(sim.port, flush=True)
sys.stdin.read()          # runs until the parent closes our stdin
sim.stop()
"""


def start_sim(strict: bool) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen([sys.executable, '-c', SIM_CODE.format(strict=strict)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    if not line.strip().isdigit():
        proc.kill()
        raise SystemExit(f'simulator did not start (got {line!r})')
    return proc, int(line)


def stop_sim(proc: subprocess.Popen) -> None:
    proc.stdin.close()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)


class DriveLoop:
    def __init__(self, port: int):
        self.bus = VENDOR.make_bus({'host': '127.0.0.1', 'port': port, 'timeout_s': 1.0})
        self.bus.open()
        self.drive = VENDOR.make_drive(self.bus, 'axis1', {'unit_id': 1, 'word_order': 'little'})
        self.drive.connect()
        self.drive.read_state()             # learns whether the block read is allowed
        self.transactions = 0

    def run(self, seconds: float) -> float:
        t0, n, tx0 = time.perf_counter(), 0, self.bus.transactions
        while time.perf_counter() - t0 < seconds:
            self.drive.read_state()
            n += 1
        self.transactions += self.bus.transactions - tx0
        return n / (time.perf_counter() - t0)

    def close(self) -> None:
        self.bus.close()


class BareLoop:
    def __init__(self, port: int, strict: bool):
        self.client = ModbusTcpClient('127.0.0.1', port=port, timeout=1.0, retries=0)
        if not self.client.connect():
            raise SystemExit(f'bare client cannot connect to 127.0.0.1:{port}')
        self.reads = SPLIT_READS if strict else (STATE_BLOCK,)

    def run(self, seconds: float) -> float:
        t0, n = time.perf_counter(), 0
        while time.perf_counter() - t0 < seconds:
            for address, count in self.reads:
                rr = self.client.read_holding_registers(address, count=count, device_id=1)
                if rr.isError():
                    raise SystemExit(f'bare read at {address} failed: {rr}')
            n += 1
        return n / (time.perf_counter() - t0)

    def close(self) -> None:
        self.client.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--seconds', type=float, default=3.0, help='time per measurement [s]')
    ap.add_argument('--strict', action='store_true',
                    help='simulator refuses reads over unmapped addresses (3 reads per poll)')
    args = ap.parse_args()
    proc, port = start_sim(args.strict)
    try:
        drive, bare = DriveLoop(port), BareLoop(port, args.strict)
        # Alternate short slices so that load from other processes hits both loops alike.
        slices = max(2, int(args.seconds / 0.25))
        drive_rates, bare_rates = [], []
        for _ in range(slices):
            drive_rates.append(drive.run(args.seconds / slices))
            bare_rates.append(bare.run(args.seconds / slices))
        tx_per_poll = drive.transactions / max(1.0, sum(drive_rates) * args.seconds / slices)
        drive.close()
        bare.close()
    finally:
        stop_sim(proc)
    d, b = statistics.median(drive_rates), statistics.median(bare_rates)
    ratios = sorted(x / y for x, y in zip(drive_rates, bare_rates))
    mode = 'strict (3 FC03 per poll)' if args.strict else 'permissive (1 FC03 1001..1021)'
    print(f'simulator: 127.0.0.1:{port}, {mode}; {slices} alternating slices of '
          f'{args.seconds / slices:.2f} s per loop (medians)')
    print(f'XplusMtDrive.read_state(): {d:8.0f} polls/s ({d * tx_per_poll:.0f} transactions/s)')
    print(f'bare ModbusTcpClient loop: {b:8.0f} polls/s')
    print(f'ratio driver/bare:         {d / b:8.2f} (per-slice range {ratios[0]:.2f}..'
          f'{ratios[-1]:.2f})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
