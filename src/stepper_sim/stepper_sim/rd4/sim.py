"""Simulated Lika RD4 ROTADRIVE units on a Modbus RTU line (a pseudo-terminal it creates).

The wire front of the RD4 simulator, no rclpy below `main()`:
- `RtuLine`: the serial line: a `pty_line.PtyLine` (an `os.openpty()` pair, the slave side's
  path handed to the driver through a symlink) whose bytes it frames as RTU itself. Every
  frame's CRC is checked; a bad CRC, a broadcast or a frame for another node id gets silence
  (§7.3.1, §8.2), which pymodbus's server does not do (research/transports.md §B1 item 4). With
  `line_timing` the replies come as late as a real line at the dip-switch baud rate delivers them:
  11 bits per character and t3.5 silences (§7.3.1).
- `build_line()`, `Rd4SimBackend` and `main()`: the line from the parameters, the backend of
  core/sim_node and the ROS executable.

The units themselves (`Rd4DriveSim`, `Rd4Options`: register map, Control Word, motion, alarms,
flash) are in rd4/device.py and importable from here too. RtuLine uses only a unit's node_id,
handle(), update() and frame_received().
"""

from __future__ import annotations

import logging
import os
import pathlib
import sys
import termios
import time
from typing import Callable, Mapping, Sequence

from stepper_drivers.protocol import modbus_rtu as rtu
from stepper_drivers.vendors.rd4 import regmap as rm

from ..core.pty_line import LINK_FAULTS, PtyLine, PtyLineBackend
from .device import (
    CURRENT_ACCEL_MA,
    CURRENT_HOLD_MA,
    CURRENT_RUN_MA,
    STORAGE_VERSION,
    TEMPERATURE_C,
    VELOCITY_REFRESH_S,
    Rd4DriveSim,
    Rd4Options,
)

__all__ = ['CURRENT_ACCEL_MA', 'CURRENT_HOLD_MA', 'CURRENT_RUN_MA', 'STORAGE_VERSION',
           'TEMPERATURE_C', 'TICK_S', 'VELOCITY_REFRESH_S', 'Rd4DriveSim', 'Rd4Options',
           'Rd4SimBackend', 'RtuLine', 'build', 'build_line', 'corrupt_crc', 'main']

logger = logging.getLogger(__name__)

TICK_S = 0.01                 # model update period of the line thread (watchdog, arrival)


def corrupt_crc(reply: bytes) -> bytes:
    """A reply whose CRC is wrong (last byte flipped): framed like a real one."""
    return reply[:-1] + bytes((reply[-1] ^ 0xFF,)) if reply else reply


_BAUD_CONSTANTS = {getattr(termios, f'B{b}'): b for b in
                   (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400)
                   if hasattr(termios, f'B{b}')}


class RtuLine(PtyLine):
    """A Modbus RTU line on a pty: the units answer the master on the other side.

    `link_path` is a symlink to the pty's slave side (the driver's `port`), replaced atomically
    when the pty is re-created. `tap(direction, frame, t)` sees every frame ('rx' from the
    master, 'tx' to it).
    """

    label = 'RTU'
    thread_name = 'rd4-line'
    tick_s = TICK_S

    def __init__(self, units: Sequence[Rd4DriveSim], link_path: str | os.PathLike | None = None,
                 baud_switch: int = rm.BAUD_SWITCH_DEFAULT, line_timing: bool = False,
                 turnaround_s: float = 0.0, check_baud: bool = True,
                 tap: Callable[[str, bytes, float], None] | None = None):
        if baud_switch not in rm.BAUD_SWITCH:
            raise ValueError(f'baud_switch: {baud_switch} is not in the dip-switch table '
                             '(allowed: 0..5, §4.4.2)')
        by_id: dict[int, Rd4DriveSim] = {}
        for unit in units:
            unit.baud_switch = baud_switch     # every unit on a line has the line's setting
            if unit.node_id in by_id:
                raise ValueError(f'drives.{unit.name}.node_id: {unit.node_id} is also '
                                 f"{by_id[unit.node_id].name}'s (node ids are unique on "
                                 'a line, §7.1)')
            by_id[unit.node_id] = unit
        baud, parity = rm.BAUD_SWITCH[baud_switch]
        super().__init__(link_path or f'/tmp/rd4_sim_{os.getpid()}', corrupt=corrupt_crc,
                         pty_baud=baud, line_timing=line_timing, tap=tap)
        self.units = by_id
        self.by_name = {u.name: u for u in units}
        self.baud, self.parity = baud, parity
        self.turnaround_s = turnaround_s
        self.check_baud = check_baud
        self.t35_s = rtu.t35_s(self.baud)
        self.counters.update({'frames': 0, 'replies': 0, 'crc_errors': 0, 'other_node': 0,
                              'broadcast': 0, 'exceptions': 0, 'baud_mismatch': 0})
        self._line_free_at = 0.0
        self._warned_baud = False
        self._buf = bytearray()            # the frame being received
        self._first_rx = self._last_rx = 0.0
        self._pending: tuple[float, bytes] | None = None    # (due time, reply)

    def _settings(self) -> str:
        return (f'{self.baud} baud {rm.serial_format(self.parity)}, '
                f'line timing {"on" if self.line_timing else "off"}')

    # ------------------------------------------------------------------- framing (§7.3.1)
    def _received_bytes(self, data: bytes, now: float) -> None:
        if not self._buf:
            self._first_rx = now
        self._buf += data
        self._last_rx = now

    def _deadline_s(self) -> float | None:
        due = [self._last_rx + self.t35_s] if self._buf else []
        if self._pending is not None:
            due.append(self._pending[0])
        return min(due, default=None)

    def _service(self, now: float) -> None:
        buf = self._buf
        if buf:
            n = rtu.request_length(buf)
            if n is not None and len(buf) >= n and rtu.crc_ok(bytes(buf[:n])):
                frame = bytes(buf[:n])
                del buf[:n]
                self._pending = self._frame(frame, self._first_rx, now) or self._pending
                self._first_rx = now
            elif now - self._last_rx >= self.t35_s or len(buf) > rtu.MAX_FRAME_BYTES:
                frame = bytes(buf)       # t3.5 of silence ends a frame (§7.3.1)
                buf.clear()
                self._pending = self._frame(frame, self._first_rx, now) or self._pending
        if self._pending is not None and time.monotonic() >= self._pending[0]:
            self._send(self._pending[1])
            self._pending = None

    def _tick(self, now: float) -> None:
        with self.lock:
            for unit in self.units.values():
                unit.update(now)

    def _master_baud(self) -> int | None:
        try:
            attrs = termios.tcgetattr(self._slave)
        except (termios.error, TypeError):
            return None
        return _BAUD_CONSTANTS.get(attrs[5])

    def _frame(self, frame: bytes, start_s: float, now: float) -> tuple[float, bytes] | None:
        """Handle one received frame; return (due time, reply) when the reply must wait."""
        if self.tap:
            self.tap('rx', frame, now)
        with self.lock:
            self.counters['frames'] += 1
            reply = self._answer(frame, now)
            if reply is not None:
                reply, extra = self._apply_link_faults(reply)
            else:
                extra = 0.0
        # Line timing: the request takes its time on the wire (starting when the line is free),
        # then t3.5, the turnaround, and the reply's own characters (§7.3.1).
        begin = max(start_s, self._line_free_at) if self.line_timing else now
        request_s = rtu.frame_time_s(len(frame), self.baud) if self.line_timing else 0.0
        if reply is None:
            self._line_free_at = begin + request_s + self.t35_s
            return None
        due = now + extra
        if self.line_timing:
            due = max(due, begin + request_s + self.t35_s + self.turnaround_s
                      + rtu.frame_time_s(len(reply), self.baud) + extra)
            self._line_free_at = due + self.t35_s
        self.counters['replies'] += 1
        if due <= time.monotonic():
            self._send(reply)
            return None
        return due, reply

    def _answer(self, frame: bytes, now: float) -> bytes | None:
        """The reply to one frame, or None for silence (§7.3.1 receiver, §8.2)."""
        if len(frame) < 4 or not rtu.crc_ok(frame):
            self.counters['crc_errors'] += 1
            return None
        address = frame[0]
        if address == rtu.BROADCAST_ADDRESS:
            self.counters['broadcast'] += 1     # §7.1: broadcast not implemented
            return None
        unit = self.units.get(address)
        if unit is None:
            self.counters['other_node'] += 1
            return None
        if self.check_baud:
            baud = self._master_baud()
            if baud is not None and baud != self.baud:
                # On a real line the characters would be garbage to the unit: no reply.
                self.counters['baud_mismatch'] += 1
                if not self._warned_baud:
                    logger.warning('master opened the line at %d baud, the units are set to %d '
                                   'by the dip-switch (§4.4.2): no reply', baud, self.baud)
                    self._warned_baud = True
                return None
        unit.frame_received(now)
        try:
            request = rtu.parse_request(frame)
            return unit.handle(request, frame)
        except rtu.ModbusExceptionError as exc:
            self.counters['exceptions'] += 1
            return rtu.exception_response(address, frame[1], exc.code)
        except rtu.FrameError:
            return None
        except Exception:   # noqa: BLE001 - a device fault is exception 04, not a dead line
            logger.exception('%s: request %s', unit.name, frame.hex(' '))
            self.counters['exceptions'] += 1
            return rtu.exception_response(address, frame[1], rtu.SERVER_DEVICE_FAILURE)

    # ------------------------------------------------------------------------- access
    def unit(self, name: str) -> Rd4DriveSim:
        return self.device(name)


# ------------------------------------------------------------------------------ ROS backend
def _storage_path(storage_dir: str, name: str, node_id: int) -> pathlib.Path | None:
    if not storage_dir:
        return None
    path = pathlib.Path(storage_dir)
    path.mkdir(parents=True, exist_ok=True)
    return path / f'rd4_{name}_node{node_id}.json'


def build_line(params: Mapping, drives: Mapping[str, Mapping]) -> RtuLine:
    """An RtuLine from the simulator's parameters (also used by scripts/bench_rd4.py)."""
    options = Rd4Options(preset_on_write=bool(params.get('preset_on_write', False)),
                         emergency_with_alarms=bool(params.get('emergency_with_alarms', True)),
                         hole_policy=str(params.get('hole_policy', 'zero')),
                         ro_write_policy=str(params.get('ro_write_policy', 'ignore')),
                         baud_register=str(params.get('baud_register', 'switch')))
    for key, allowed in (('hole_policy', ('zero', 'exception')),
                         ('ro_write_policy', ('ignore', 'exception')),
                         ('baud_register', ('switch', 'baud'))):
        if getattr(options, key) not in allowed:
            raise ValueError(f'parameter {key}: {getattr(options, key)!r} (allowed: '
                             f'{", ".join(allowed)})')
    baud_switch = int(params.get('baud_switch', rm.BAUD_SWITCH_DEFAULT))
    units = []
    for name, p in drives.items():
        node_id = int(p.get('node_id', 1))
        units.append(Rd4DriveSim(
            name, node_id, str(p.get('model', 'T32')), options=options, baud_switch=baud_switch,
            sw_version=int(p.get('sw_version', 0x0102)),
            hw_version=int(p.get('hw_version', 0x0001)),
            storage_path=_storage_path(str(params.get('storage_dir', '')), name, node_id),
            position_steps=float(p.get('position_steps', 0.0))))
    return RtuLine(units, str(params.get('port', '')) or None, baud_switch=baud_switch,
                   line_timing=bool(params.get('line_timing', False)),
                   turnaround_s=float(params.get('turnaround_s', 0.0)),
                   check_baud=bool(params.get('check_baud', True)))


class Rd4SimBackend(PtyLineBackend):
    """rd4_sim's `sim_node.SimBackend` (duck-typed, so this module imports no rclpy)."""

    line: RtuLine

    def true_position_steps(self, drive: str) -> float:
        with self.line.lock:
            unit = self.line.unit(drive)
            unit.update()
            return unit.position

    def inject_fault(self, drive: str, kind: str, code: int, value: float) -> tuple[bool, str]:
        if kind in LINK_FAULTS:
            return True, self.line.set_link_fault(kind, code, value)
        with self.line.lock:
            try:
                return True, self.line.unit(drive).inject(kind, code, value)
            except ValueError as exc:
                return False, str(exc)

    def set_input(self, drive: str, name: str, value: bool, release: bool) -> tuple[bool, str]:
        key = name.strip().lower().replace(' ', '')
        if key not in rm.INPUT_BITS:
            return False, f'unknown input {name!r} (RD4 inputs: IN 1, IN 2, IN 3)'
        with self.line.lock:
            unit = self.line.unit(drive)
            mask = rm.INPUT_BITS[key]
            unit.inputs = (unit.inputs | mask) if value and not release else unit.inputs & ~mask
            return True, f'{name} = {int(bool(unit.inputs & mask))}'


def build(node) -> Rd4SimBackend:
    from ..core.sim_node import declare, declare_drives
    params = {
        'port': declare(node, 'port', '', 'symlink the simulator creates to its pty (the '
                        "driver's port); '' = /tmp/rd4_sim_<pid>"),
        'baud_switch': declare(node, 'baud_switch', rm.BAUD_SWITCH_DEFAULT,
                               'baud/parity dip-switch code 0..5 (§4.4.2): 1 = 9600 8E1, '
                               '3 = 19200 8N2, 4 = 19200 8E1'),
        'line_timing': declare(node, 'line_timing', False, 'delay replies as a real line at '
                               'the baud rate (11-bit characters, t3.5 silences)'),
        'turnaround_s': declare(node, 'turnaround_s', 0.0, 'unit processing time before a '
                                'reply when line_timing is on [s]'),
        'check_baud': declare(node, 'check_baud', True, 'no reply when the master opened the '
                              'pty at another baud rate than the dip-switch'),
        'storage_dir': declare(node, 'storage_dir', '', "folder for the units' saved "
                               "parameters ('' = kept in memory only)"),
        'preset_on_write': declare(node, 'preset_on_write', False, 'apply Preset on the '
                                   'register write too, not only on CW bit 11'),
        'emergency_with_alarms': declare(node, 'emergency_with_alarms', True, 'set alarm bit 6 '
                                         'Emergency with every other alarm'),
        'hole_policy': declare(node, 'hole_policy', 'zero', "holding 0x1A-0x28: 'zero' or "
                               "'exception'"),
        'ro_write_policy': declare(node, 'ro_write_policy', 'ignore', "writes to Offset/Gear "
                                   "ratio: 'ignore' or 'exception'"),
        'baud_register': declare(node, 'baud_register', 'switch', "Dip-switch baud rate "
                                 "[0x0C] holds the 'switch' code or the 'baud' number"),
    }
    drives = declare_drives(node, ['axis1'], {
        'node_id': (1, 'node ID on the dip-switch (1..247; above 247 the unit uses 247)'),
        'model': ('T32', 'RD4 model: T32 (1600 PPS, gear 32) or T48 (1066 PPS, gear 48)'),
        'sw_version': (0x0102, 'SW Version [0x0E] (major << 8 | minor)'),
        'hw_version': (0x0001, 'HW Version [0x0F]'),
        'position_steps': (0.0, 'position at power-up [pulses]'),
    })
    return Rd4SimBackend(build_line(params, drives))


def main(args=None) -> None:
    from ..core.sim_node import run_sim
    sys.exit(run_sim('rd4_sim', build, args))


if __name__ == '__main__':
    main()
