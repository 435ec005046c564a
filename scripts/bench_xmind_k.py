#!/usr/bin/env python3
"""Position-poll rate of the X-MIND K driver on a 9600 baud line, against the manual's arithmetic.

The simulator runs in its own process with line timing on (§3: 1.04 ms per character, 1.5 ms
turnaround, the RD answer delay); the driver polls idle drives with `read_state()` (one QA each)
as the node's poll loop does. The manual's example 4 (§3) is the limit: '08QA' answered
'08QA,+10854000' holds the line 5 x 1.04 + 1.5 + 15 x 1.04 + 4 ms margin = 26.3 ms, so at most
38.0 polls per second on one drive and 12.7 cycles of three drives. The counters are loaded with
8-digit values first so every answer has that length; RD is set to 0 (as §3 assumes) through the
driver's answer_delay_ms, which writes the preset only because it differs.

    scripts/bench_xmind_k.py [--seconds 5]
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import pathlib
import sys
import tempfile
import time

from stepper_drivers.contract.drive import complete
from stepper_drivers.protocol import xmind_k as xk
from stepper_drivers.vendors import xmind_k as v

MANUAL_QA_S = 0.0263          # §3 example 4
GOAL = 0.90


def serve(link: str, ready, stop) -> None:
    from stepper_sim.xmind_k.sim import build_line
    line = build_line({'port': link, 'line_timing': True},
                      {f'axis{i}': {'address': i} for i in (1, 2, 3)})
    line.start()
    ready.set()
    stop.wait()
    line.stop()


def measure(drives: list, seconds: float) -> float:
    """Cycles per second: one read_state() (one QA) of every drive per cycle."""
    for d in drives:
        complete(d.read_state())
    n = 0
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        for d in drives:
            complete(d.read_state())
        n += 1
    return n / (time.monotonic() - t0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=5.0, help='length of each measurement')
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format='%(name)s: %(message)s', stream=sys.stdout)
    link = str(pathlib.Path(tempfile.mkdtemp(prefix='bench_xmind_k_')) / 'tty')
    ctx = multiprocessing.get_context('fork')
    ready, stop = ctx.Event(), ctx.Event()
    sim = ctx.Process(target=serve, args=(link, ready, stop), name='xmind_k_sim')
    sim.start()
    try:
        if not ready.wait(20.0):
            print('simulator did not start', file=sys.stderr)
            return 1
        bus_params = {'port': link, 'baudrate': 9600, 'parity': 'N', 'stopbits': 1,
                      'timeout_s': 0.02, 'retries': 1, 'local_echo': False}
        bus = v.make_bus(bus_params)
        drive_params = {**bus_params, 'resolution': '', 'current_preset': -1,
                        'answer_delay_ms': 0, 'equalization': -1, 'power_cycle_flag': '',
                        'busy_poll_period_s': 0.25, 'status_poll_period_s': 3600.0,
                        'steps_per_rev': 2000.0, 'homing.method': 3}
        drives = [v.make_drive(bus, f'axis{i}', {**drive_params, 'address': i})
                  for i in (1, 2, 3)]
        bus.open()
        for i, d in enumerate(drives):
            complete(d.connect())
            complete(d.write_register('SA', 'i32', 10854000 + i))   # 8-digit answers (example 4)
        answer = len(xk.encode_answer(xk.Frame(8, 'QA', (10854000,))))
        exact_s = xk.transaction_time_s(5, answer)
        print(f'line: 9600 8N1 on a pty with simulated timing; RD 0; answer {answer} chars')
        print(f'manual §3 example 4: {MANUAL_QA_S * 1000:.1f} ms per QA '
              f'(exact 10-bit characters: {exact_s * 1000:.2f} ms)')
        ok = True
        for count in (1, 3):
            rate = measure(drives[:count], args.seconds)
            limit = 1.0 / (count * MANUAL_QA_S)
            ratio = rate / limit
            ok &= ratio >= GOAL
            print(f'{count} idle drive{"s" if count > 1 else " "}: {rate:6.2f} cycles/s, '
                  f'{1000 / rate / count:5.2f} ms per QA; manual limit {limit:6.2f}/s; '
                  f'ratio {ratio * 100:5.1f} % (goal {GOAL * 100:.0f} %)')
        counters = bus.counters()
        print(f"transactions {counters['transactions']}, errors {counters['errors']}, "
              f"silences {counters['silences']}")
        bus.close()
        return 0 if ok else 1
    finally:
        stop.set()
        sim.join(timeout=10)
        if sim.is_alive():
            sim.terminate()
            sim.join(timeout=5)


if __name__ == '__main__':
    sys.exit(main())
