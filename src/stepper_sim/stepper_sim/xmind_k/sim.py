"""xmind_k_sim: R.T.A. X-MIND K drives on a pseudo-terminal, answering like the manual.

The wire front of the X-MIND K simulator, no rclpy below `main()`:

- `XmindKLine`: the RS-485 line on a `pty_line.PtyLine` (slave kept open, symlinked to `port`),
  one or more drives on it, link faults (`LinkFaults`), and, with `line_timing`, the timing of a
  real 9600 baud line (§3): the host string takes N x 1.04 ms to arrive, the answer starts
  1.5 ms (WN: 12 ms) plus the RD answer delay later and takes its own characters' time.
- `build_line()`, `XmindKSimBackend` and `main()`: the line from the parameters, the backend of
  core/sim_node and the ROS executable.

The drives themselves (`XmindKDriveSim`: EEPROM, host strings, program engine, motion, zero
search) are in xmind_k/device.py and xmind_k/program.py, and importable from here too; the line
needs only receive(), update() and address.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import os
import pathlib
import sys
import time
from typing import Any, Callable, Mapping, Sequence

from stepper_drivers.protocol import xmind_k as xk

from ..core.motion import INF
from ..core.pty_line import LINK_FAULTS, PtyLine, PtyLineBackend
from .device import INPUTS, NULL_CELL, XmindKDriveSim

__all__ = ['INPUTS', 'NULL_CELL', 'TICK_S', 'XmindKDriveSim', 'XmindKLine', 'XmindKSimBackend',
           'build', 'build_line', 'corrupt_ascii', 'main']

logger = logging.getLogger(__name__)

TICK_S = 0.05                 # state refresh of the drives between strings (cam, outputs)


def corrupt_ascii(reply: bytes) -> bytes:
    """Line noise on one character: the terminator survives, the answer does not parse."""
    return reply[:2] + b'?' + reply[3:] if len(reply) > 3 else b'?' + reply[1:]



class XmindKLine(PtyLine):
    """An RS-485 line on a pty with one or more simulated drives."""

    label = 'X-MIND K'
    thread_name = 'xmind-k-line'
    reply_words = ('answer', 'answers')
    tick_s = TICK_S

    def __init__(self, drives: Sequence[XmindKDriveSim], link_path: str | None = None, *,
                 line_timing: bool = False, baudrate: int = xk.BAUDRATE,
                 tolerant: bool = True, rd_mode: str = 'add',
                 tap: Callable[[str, bytes, float], None] | None = None):
        if rd_mode not in ('add', 'max'):
            raise ValueError(f"rd_mode: {rd_mode!r} (allowed: 'add', 'max')")
        seen: dict[int, str] = {}
        for d in drives:
            if d.address in seen:
                raise ValueError(f'drives.{d.name}.address: {d.address:02d} is also '
                                 f"{seen[d.address]}'s (addresses are unique on a line)")
            seen[d.address] = d.name
        super().__init__(link_path or f'/tmp/xmind_k_sim_{os.getpid()}', corrupt=corrupt_ascii,
                         line_timing=line_timing, tap=tap)
        self.drives = list(drives)
        self.by_name = {d.name: d for d in drives}
        self.char_s = xk.char_time_s(baudrate)
        self.tolerant = tolerant
        self.rd_mode = rd_mode
        self.counters.update({'strings': 0, 'answers': 0})
        self._buf = bytearray()            # the string being received
        self._first_rx = 0.0
        self._schedule: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = itertools.count()
        self._line_free_at = 0.0

    # ----------------------------------------------------------------------- framing (§3)
    def _received_bytes(self, data: bytes, now: float) -> None:
        buf = self._buf
        for byte in data:
            if not buf:
                self._first_rx = now
            buf.append(byte)
            if byte == 13:                      # §3 ASCII 13 ends every string
                self._received(bytes(buf), self._first_rx, now)
                buf.clear()
        if len(buf) > 256:
            buf.clear()                         # no string is that long: noise

    def _deadline_s(self) -> float | None:
        return self._schedule[0][0] if self._schedule else None

    def _service(self, now: float) -> None:
        while self._schedule and self._schedule[0][0] <= time.monotonic():
            _, _, action = heapq.heappop(self._schedule)
            action()

    def _tick(self, now: float) -> None:
        with self.lock:
            for d in self.drives:
                d.update(now)

    def _later(self, t: float, action: Callable[[], None]) -> None:
        if t <= time.monotonic():
            action()
        else:
            heapq.heappush(self._schedule, (t, next(self._seq), action))

    def _received(self, frame: bytes, first_rx: float, now: float) -> None:
        """A host string is in: it ends on the wire N characters after it began (§3), then
        each addressed drive acts after the turnaround plus its RD delay (§4.2.2.5 Note)."""
        if self.tap:
            self.tap('rx', frame, now)
        self.counters['strings'] += 1
        if frame[:2] == b'%02d' % xk.BROADCAST:     # one line per broadcast string (the tests)
            logger.info('broadcast %s', frame.decode('ascii', errors='replace').rstrip('\r'))
        if not self.line_timing:
            self._deliver(frame, now, now)
            return
        begin = max(first_rx, self._line_free_at)
        end_rx = begin + len(frame) * self.char_s
        self._line_free_at = end_rx
        turnaround = xk.turnaround_s(frame[2:4].decode('ascii', errors='replace'))
        with self.lock:
            rds = {d.name: float(d.presets['RD']) / 1000.0 for d in self.drives}
        # Every drive hears the string end at end_rx and acts its turnaround plus its RD later
        # (§3, §4.2.2.5 Note): drives with the same delay act in the same instant, which a
        # broadcast (99, §2.2.1) makes visible: they are served together at that instant.
        by_delay: dict[float, list[XmindKDriveSim]] = {}
        for d in self.drives:
            rd = rds[d.name]
            delay = turnaround + rd if self.rd_mode == 'add' else max(turnaround, rd)
            by_delay.setdefault(delay, []).append(d)
        for delay, drives in by_delay.items():
            t = end_rx + delay
            self._later(t, lambda t=t, drives=drives: self._deliver(frame, end_rx, t, drives))

    def _deliver(self, frame: bytes, end_rx: float, now: float | None,
                 drives: Sequence[XmindKDriveSim] | None = None) -> None:
        with self.lock:
            if self._master is None:
                return
            t = time.monotonic() if now is None else now
            answers = [a for a in (d.receive(frame, self.tolerant, t)
                                   for d in (drives or self.drives)) if a is not None]
            if not answers:
                return
            # two drives on one address answer at once: a collision on the wire
            reply, extra = self._apply_link_faults(b''.join(answers))
        if reply is None:
            return
        self.counters['answers'] += 1
        start = t + extra
        if self.line_timing and len(reply) > 1:
            end = start + len(reply) * self.char_s
            self._line_free_at = max(self._line_free_at, end)
            self._later(start, lambda: self._send(reply[:1]))
            self._later(end, lambda: self._send(reply[1:]))
        else:
            self._later(start, lambda: self._send(reply))


# --------------------------------------------------------------------------------- backend
def build_line(params: Mapping[str, Any], drives: Mapping[str, Mapping[str, Any]]) -> XmindKLine:
    """An XmindKLine from the simulator's parameters (also used by the tests and the bench)."""
    storage = str(params.get('storage_dir', ''))
    if storage:
        pathlib.Path(storage).mkdir(parents=True, exist_ok=True)
    sims = []
    for name, p in drives.items():
        address = int(p.get('address', 0))
        if not xk.ADDRESS_MIN <= address <= xk.ADDRESS_MAX:
            raise ValueError(f'parameter drives.{name}.address: {address} (allowed: 0..47)')
        rd = int(p.get('answer_delay_ms', -1))
        sims.append(XmindKDriveSim(
            name, address,
            storage_path=pathlib.Path(storage) / f'xmind_k_{name}.json' if storage else None,
            px_edge_steps=float(p.get('px_edge_steps', 1000.0)),
            px_width_steps=float(p.get('px_width_steps', INF)),
            cyclic_modulus=str(params.get('cyclic_modulus', 'kkk+1')),
            position_steps=float(p.get('position_steps', 0.0)),
            factory={'RD': rd} if rd >= 0 else None))
    return XmindKLine(sims, str(params.get('port', '')) or None,
                      line_timing=bool(params.get('line_timing', False)),
                      tolerant=bool(params.get('tolerate_trailing', True)),
                      rd_mode=str(params.get('rd_mode', 'add')))


class XmindKSimBackend(PtyLineBackend):
    """xmind_k_sim's `sim_node.SimBackend` (duck-typed: no rclpy in this module)."""

    line: XmindKLine

    def _drive(self, name: str) -> XmindKDriveSim:
        return self.line.device(name)

    def true_position_steps(self, drive: str) -> float:
        with self.line.lock:
            return self._drive(drive).true_position_steps()

    def inject_fault(self, drive: str, kind: str, code: int, value: float) -> tuple[bool, str]:
        """Link faults (code = number of answers affected, 0 = until link_ok); drive faults:
        drive_fault (a protection: FA off), clear_fault (cause gone and power-cycled, as the
        manual requires), power_cycle."""
        try:
            if kind in LINK_FAULTS:
                return True, self.line.set_link_fault(kind, code, value)
            with self.line.lock:
                d = self._drive(drive)
                if kind == 'drive_fault':
                    d.inject_protection()
                    return True, f'{drive}: protection tripped, FA = 0, motor current off'
                if kind in ('clear_fault', 'power_cycle'):
                    d.power_cycle()
                    return True, f'{drive}: power-cycled (counter 0, RAM cells cleared, FA = 1)'
        except ValueError as e:
            return False, str(e)
        return False, (f'unknown fault {kind!r} (allowed: drive_fault, clear_fault, power_cycle, '
                       + ', '.join(LINK_FAULTS) + ')')

    def set_input(self, drive: str, name: str, value: bool, release: bool) -> tuple[bool, str]:
        try:
            with self.line.lock:
                d = self._drive(drive)
                d.set_input(name, value, release)
                key = 'PX' if name.strip().upper() in ('PX', 'HOME') else name.strip().upper()
                return True, f'{drive}: {key} = {d.input(key)}'
        except ValueError as e:
            return False, str(e)


def build(node) -> XmindKSimBackend:
    from ..core.sim_node import declare, declare_drives
    params = {
        'port': declare(node, 'port', '', "symlink the simulator creates to its pty (the "
                        "driver's port); '' = /tmp/xmind_k_sim_<pid>"),
        'line_timing': declare(node, 'line_timing', False, 'answer as late as a real 9600 baud '
                               'line (§3: 1.04 ms per character, 1.5/12 ms turnaround, + RD)'),
        'storage_dir': declare(node, 'storage_dir', '', "folder for the drives' EEPROM "
                               "(presets, cells 100-227); '' = memory only"),
        'tolerate_trailing': declare(node, 'tolerate_trailing', True, "accept one '.' or ',' "
                                     'before the terminator, as the manual prints them'),
        'rd_mode': declare(node, 'rd_mode', 'add', "answer delay RD: 'add' to the turnaround "
                           "or 'max' of both"),
        'cyclic_modulus': declare(node, 'cyclic_modulus', 'kkk+1', "cyclic mode positions "
                                  "0..kkk ('kkk+1') or 0..kkk-1 ('kkk')"),
    }
    drives = declare_drives(node, ['axis1'], {
        'address': (0, 'drive address 0..47 at first power-on (WS,AD changes it)'),
        'px_edge_steps': (1000.0, 'raw position where the proximity input PX comes on'),
        'px_width_steps': (INF, 'PX active over this many steps from its edge (inf: the whole '
                           'side beyond it)'),
        'position_steps': (0.0, 'raw shaft position at start'),
        'answer_delay_ms': (-1, 'RD of a new unit (-1: the factory 10 ms)'),
    })
    return XmindKSimBackend(build_line(params, drives))


def main(args=None) -> None:
    from ..core.sim_node import run_sim
    sys.exit(run_sim('xmind_k_sim', build, args))


if __name__ == '__main__':
    main()
