"""xmind_k_sim: R.T.A. X-MIND K drives on a pseudo-terminal, answering like the manual.

Two layers, neither needs rclpy:

- `XmindKDriveSim`: one drive. Presets and cells 100-227 in a simulated EEPROM (with write
  counters, optionally kept in a JSON file across runs), cells 228-230 in RAM, the stored-program
  engine (chaining by DDD, conditional jump 63, one loop counter 61/62, delays 65, outputs and
  flags 58, cam 57, counter reset 60, current 70, recovery 69, delayed stop 05), every run
  instruction on a `SimAxis` with the Table 5 ramps, the zero search on the PX input (the axis'
  'home' switch), the coordinate modes (§5), the error register (QE). `receive()` takes one host
  string and returns the answer, or None for silence: broadcast, unknown address, busy (only EE
  and ES are heard, §3), the 200 ms after WS,RS.
- `XmindKLine`: the RS-485 line on a `pty_line.PtyLine` (slave kept open, symlinked to `port`),
  one or more drives on it, link faults (`LinkFaults`), and, with `line_timing`, the timing of a
  real 9600 baud line (§3): the host string takes N x 1.04 ms to arrive, the answer starts
  1.5 ms (WN: 12 ms) plus the RD answer delay later and takes its own characters' time.

The device model shares the frame codec and the tables with the driver
(`stepper_drivers.protocol.xmind_k`), never its state logic. Readings of the manual's open points
are parameters (docs/xmind_k.md lists them).

One file: XmindKDriveSim's EEPROM, program engine, motion and zero search share the cells, the
busy flag and the axis; the line needs only receive(), update() and address.
"""

from __future__ import annotations

import heapq
import itertools
import json
import logging
import math
import os
import pathlib
import sys
import time
from typing import Any, Callable, Mapping, Sequence

from stepper_drivers.protocol import xmind_k as xk

from ..core.axis import HOME, TARGET_REACHED, AxisEvent, SimAxis
from ..core.motion import INF
from ..core.pty_line import LINK_FAULTS, PtyLine, PtyLineBackend

logger = logging.getLogger(__name__)

TICK_S = 0.05                 # state refresh of the drives between strings (cam, outputs)
INPUTS = ('ST', 'EE', 'ES', 'I0', 'I1', 'I2', 'PX', 'S0', 'S1', 'S2', 'S3')
NULL_CELL = xk.Instruction(0, (), xk.END_OF_PROGRAM)     # content of a cell never written


def corrupt_ascii(reply: bytes) -> bytes:
    """Line noise on one character: the terminator survives, the answer does not parse."""
    return reply[:2] + b'?' + reply[3:] if len(reply) > 3 else b'?' + reply[1:]


class XmindKDriveSim:
    """One simulated X-MIND K (device model, no I/O). Not thread-safe: the line locks it."""

    def __init__(self, name: str, address: int = 0, *, clock: Callable[[], float] = time.monotonic,
                 storage_path: str | os.PathLike | None = None, px_edge_steps: float = 1000.0,
                 px_width_steps: float = INF, cyclic_modulus: str = 'kkk+1',
                 position_steps: float = 0.0, factory: Mapping[str, Any] | None = None):
        if cyclic_modulus not in ('kkk+1', 'kkk'):
            raise ValueError(f"cyclic_modulus: {cyclic_modulus!r} (allowed: 'kkk+1', 'kkk')")
        self.name = name
        self.clock = clock
        self.storage_path = pathlib.Path(storage_path) if storage_path else None
        self.cyclic_modulus = cyclic_modulus
        self.axis = SimAxis(home_switch_steps=px_edge_steps,
                            home_switch_width_steps=px_width_steps, steps_per_rev=0,
                            position_steps=position_steps, clock=clock)
        self.axis.add_listener(self._on_axis_event)
        # EEPROM (§4.1, §4.2.2: cells 100-227 and every preset)
        self.presets: dict[str, Any] = {**xk.PRESET_DEFAULTS, **(factory or {}),
                                        'AD': int(address)}
        self.cyclic_range = 1000
        self.eeprom: dict[int, xk.Instruction] = {}
        self.eeprom_cell_writes = 0
        self.eeprom_preset_writes = 0
        self._load()
        self.counters = {'strings': 0, 'answers': 0, 'N': 0, 'ignored_busy': 0, 'broadcasts': 0}
        # (time, instruction code) of every run the axis began: the truth a test compares
        # with what the host believes (when a broadcast started two drives, for one)
        self.motion_starts: list[tuple[float, int]] = []
        self.power_on()

    # ----------------------------------------------------------------------- EEPROM and power
    @property
    def address(self) -> int:
        return int(self.presets['AD'])

    @property
    def eeprom_writes(self) -> int:
        return self.eeprom_cell_writes + self.eeprom_preset_writes

    def _load(self) -> None:
        if self.storage_path is None or not self.storage_path.exists():
            return
        data = json.loads(self.storage_path.read_text())
        self.presets.update(data.get('presets', {}))
        self.cyclic_range = int(data.get('cyclic_range', self.cyclic_range))
        self.eeprom = {int(c): xk.Instruction.parse(text.split(','))
                       for c, text in data.get('cells', {}).items()}
        self.eeprom_cell_writes = int(data.get('eeprom_cell_writes', 0))
        self.eeprom_preset_writes = int(data.get('eeprom_preset_writes', 0))

    def _save(self) -> None:
        if self.storage_path is None:
            return
        data = {'presets': self.presets, 'cyclic_range': self.cyclic_range,
                'cells': {str(c): i.encode() for c, i in sorted(self.eeprom.items())},
                'eeprom_cell_writes': self.eeprom_cell_writes,
                'eeprom_preset_writes': self.eeprom_preset_writes}
        tmp = self.storage_path.with_suffix('.tmp')
        tmp.write_text(json.dumps(data, indent=1))
        tmp.replace(self.storage_path)

    def power_on(self) -> None:
        """Power-on state (§4.2.3 current ON, §4.3.1 counter from 0; the rest per the digest's
        §6.2 assumptions): RAM cells null, outputs and flags 0, FA 1, no error, cam off."""
        now = self.clock()
        self.axis.update(now)
        self.axis.motion.stop_immediately()
        self.axis.set_position(0.0)
        self.ram = {c: NULL_CELL for c in xk.CELL_RAM}
        self.outputs = {name: 0 for name in xk.SETTABLE_OUTPUTS}
        self.fa = 1
        self.current_on = True
        self.cam: tuple[int, int | None] = (0, None)
        self.error = (xk.ERROR_NONE, 0)
        self.recovery: tuple | None = None
        self.loop_counter = 0
        self.silent_until = 0.0
        self.pc: int | None = None          # cell being executed
        self.current: xk.Instruction | None = None
        self.phase = 'idle'
        self.delay_end = 0.0
        self.resume_next: int | None = None
        self.index_target: float | None = None
        self.dstop_armed = False
        self._last_counter = self.counter

    def power_cycle(self) -> None:
        self.power_on()

    # ---------------------------------------------------------------------------------- state
    @property
    def modulus(self) -> int:
        return self.cyclic_range + (1 if self.cyclic_modulus == 'kkk+1' else 0)

    @property
    def counter(self) -> int:
        """§4.3.1 absolute position counter (modulo the working range in cyclic mode, §5.3)."""
        value = int(round(self.axis.position_steps))
        if self.presets['CM'] == xk.CM_CYCLIC:
            return value % self.modulus
        return (value - xk.COUNTER_MIN) % 2**32 + xk.COUNTER_MIN     # 32-bit counter

    @property
    def busy(self) -> bool:
        """BS output (§2.2.4): a program runs, or the motor still stops after EE."""
        return self.phase != 'idle' or self.axis.moving

    def cell(self, cell: int) -> xk.Instruction:
        if cell in xk.CELL_RAM:
            return self.ram[cell]
        return self.eeprom.get(cell, NULL_CELL)

    def input(self, name: str) -> int:
        if name == 'PX':
            name = HOME
        if name.startswith('F'):
            return self.outputs[name]            # flags can be tested by 63 (§4.1.14)
        return int(name in self.axis.input_names and self.axis.input(name))

    def true_position_steps(self) -> float:
        self.update()
        if self.presets['CM'] == xk.CM_CYCLIC:
            return self.axis.position_steps % self.modulus
        return self.axis.position_steps

    # ------------------------------------------------------------------------------ strings
    def receive(self, text: str | bytes, tolerant: bool = True,
                now: float | None = None) -> bytes | None:
        """One host string (terminator optional); the answer bytes, or None for silence."""
        now = self.clock() if now is None else now
        self.update(now)
        raw = text.decode('ascii', errors='replace') if isinstance(text, bytes) else text
        raw = raw.rstrip('\r')
        try:
            address = xk._address(raw)
        except xk.AddressError:
            return None
        if address not in (self.address, xk.BROADCAST):
            return None
        if now < self.silent_until:
            return None                     # §4.2.2.3 Note 2: deaf after WS,RS
        code = raw[2:4]
        self.counters['strings'] += 1
        if self.busy and code not in xk.BUSY_CODES:
            self.counters['ignored_busy'] += 1
            return None                     # §3, §4.4.3: a busy drive hears only EE and ES
        broadcast = address == xk.BROADCAST
        try:
            frame = xk.parse_request(raw, tolerant)
        except xk.AddressError:
            return None
        except xk.ProtocolError as e:
            logger.info('%s: N to %r: %s', self.name, raw, e)
            self.counters['N'] += 1
            return None if broadcast else xk.encode_answer(xk.Frame(self.address, 'N'))
        if broadcast and frame.code not in xk.BROADCAST_CODES:
            return None                     # not allowed as broadcast: not executed either
        if broadcast:
            self.counters['broadcasts'] += 1    # executed, never answered (§2.2.1, §4.4.3)
        reply_address = self.address        # WS,AD answers with the old address (§4.2.2.1)
        answer = self._execute_string(frame, now)
        self.update(now)
        if broadcast or answer is None:
            return None
        self.counters['answers'] += 1
        return xk.encode_answer(xk.Frame(reply_address, answer[0], answer[1]))

    def _execute_string(self, f: xk.Frame, now: float) -> tuple[str, tuple] | None:
        code, a = f.code, f.args
        if code == 'WN':
            cell, instr = a
            if cell in xk.CELL_RAM:
                self.ram[cell] = instr
            else:
                self.eeprom[cell] = instr
                self.eeprom_cell_writes += 1
                self._save()
        elif code == 'WS':
            preset, value, kkk = a
            self.presets[preset] = value
            if preset == 'CM' and kkk is not None:
                self.cyclic_range = kkk
            self.eeprom_preset_writes += 1
            self._save()
            if preset == 'RS':
                self.silent_until = now + xk.RS_SILENT_S
        elif code in ('CY', 'CN'):
            self.current_on = code == 'CY'
            logger.info('%s: motor current %s (%s)', self.name, 'ON' if self.current_on
                        else 'OFF', code)       # not readable over the line: logged
        elif code == 'PS':
            if self.fa:
                self._start_program(a[0], now)
        elif code == 'EE':
            self.emergency_stop(now)
        elif code == 'ES':
            self.free_run_stop(now)
        elif code == 'RA':
            self.axis.set_position(0.0)
            self._last_counter = self.counter     # a reset is not a motion past the cam
        elif code == 'SA':
            self.axis.set_position(float(a[0]))
            self._last_counter = self.counter
        elif code == 'SO':
            self.outputs[a[0]] = a[1]
        elif code == 'SC':
            self.cam = (a[0], a[1] if a[0] else None)
        elif code == 'QA':
            return 'QA', (self.counter,)
        elif code == 'QS':
            preset = a[0]
            kkk = self.cyclic_range if preset == 'CM' and self.presets['CM'] == 2 else None
            return 'QS', (preset, self.presets[preset], kkk)
        elif code == 'QI':
            return 'QI', (a[0], self.input(a[0]))
        elif code == 'QO':
            name = a[0]
            value = self.fa if name == 'FA' else int(self.busy) if name == 'BS' \
                else self.outputs[name]
            return 'QO', (name, value)
        elif code == 'QM':
            return 'QM', (a[0], self.cell(a[0]))
        elif code == 'QC':
            return 'QC', self.cam
        elif code == 'QE':
            return 'QE', self.error
        return 'Y', ()

    # ------------------------------------------------------------------------------ inputs
    def set_input(self, name: str, value: bool, release: bool = False) -> None:
        name = name.strip().upper()
        key = HOME if name in ('PX', 'HOME') else name
        if name not in INPUTS and name != 'HOME':
            raise ValueError(f'unknown input {name!r} (X-MIND K inputs: {", ".join(INPUTS)})')
        self.update()
        if release:
            self.axis.release(key)
        else:
            self.axis.set_input(key, bool(value))
        self.update()

    def inject_protection(self) -> None:
        """A protection trips: FA off (§2.2.4), the motor is no longer driven, program over."""
        self.update()
        self.fa = 0
        self.current_on = False
        self.axis.motion.stop_immediately()
        self._end_program()

    # ------------------------------------------------------------------------------- engine
    def update(self, now: float | None = None) -> None:
        """Advance program and motion to now, exactly at every motion event and delay end."""
        now = self.clock() if now is None else now
        for _ in range(100000):
            m = self.axis.motion
            t = now
            if self.phase == 'delay':
                t = min(t, self.delay_end)
            if m.finish_time_s > m.time_s:
                t = min(t, m.finish_time_s)
            t = max(t, m.time_s)
            self.axis.update(t)
            self._check_cam()
            if self.phase == 'delay' and self.delay_end <= m.time_s:
                self._finish_instruction(m.time_s)
                continue
            if t >= now:
                break
        else:
            logger.warning('%s: program makes no progress in time (100000 steps)', self.name)

    def _check_cam(self) -> None:
        """§4.1.10: O3 is complemented when the counter reaches the cam position."""
        c = self.counter
        enabled, position = self.cam
        if enabled and min(self._last_counter, c) <= position <= max(self._last_counter, c):
            self.outputs['O3'] ^= 1
            self.cam = (0, None)
        self._last_counter = c

    def _start_program(self, cell: int, t: float) -> None:
        self.resume_next = None
        self._goto(cell, t)

    def _goto(self, cell: int, t: float) -> None:
        """Run from `cell` until an instruction takes time or the program ends."""
        seen = set()
        while cell != xk.END_OF_PROGRAM:
            key = (cell, self.loop_counter)
            if key in seen:             # a jump loop waiting for an input (§4.1.14 Note)
                self.pc, self.phase = cell, 'spin'
                return
            seen.add(key)
            instr = self.cell(cell)
            self.pc, self.current = cell, instr
            nxt = self._execute_instruction(instr, t)
            if nxt is None:
                return                  # takes time: _finish_instruction continues
            cell = nxt
        self._end_program()

    def _end_program(self) -> None:
        self.pc, self.current, self.phase = None, None, 'idle'
        self.resume_next = None

    def _finish_instruction(self, t: float) -> None:
        instr = self.current
        nxt = instr.next_cell if instr is not None else xk.END_OF_PROGRAM
        if self.resume_next is not None:
            nxt, self.resume_next = self.resume_next, None      # after a 69 recovery
        self.phase = 'running'
        self._goto(nxt, t)

    def _execute_instruction(self, instr: xk.Instruction, t: float) -> int | None:
        """Execute one instruction at t; the next cell, or None while it takes time."""
        c = instr.code
        nxt = instr.next_cell
        if c == 0:
            return nxt
        if c == 60:
            self.axis.set_position(0.0)
            self._last_counter = self.counter
            return nxt
        if c == 58:
            self.outputs[instr.get('output')] = instr.get('value')
            return nxt
        if c == 57:
            self.cam = (instr.get('enable'), instr.get('position'))
            return nxt
        if c == 70:
            self.current_on = bool(instr.get('on'))
            return nxt
        if c == 61:
            self.loop_counter = instr.get('repetitions')
            return nxt
        if c == 62:
            self.loop_counter = (self.loop_counter - 1) & 0xFFFF     # decrement, then test
            return nxt if self.loop_counter == 0 else instr.get('loop_cell')
        if c == 63:
            hit = self.input(instr.get('input')) == instr.get('value')
            return instr.get('jump_cell') if hit else nxt
        if c == 65:
            self.phase, self.delay_end = 'delay', t + instr.get('delay_ms') / 1000.0
            return None
        if c == 69:
            if self.recovery is None:
                return xk.END_OF_PROGRAM        # §4.1.15: null action with next 000
            stored, self.recovery = self.recovery, None
            self.resume_next = nxt
            self.current = stored[0]
            return self._resume(stored, t)
        if c in xk.MOTION_CODES:
            if not self.fa:
                return xk.END_OF_PROGRAM
            return None if self._start_motion(instr, t) else xk.END_OF_PROGRAM
        raise AssertionError(f'instruction {c} not handled')   # pragma: no cover

    # -------------------------------------------------------------------------------- motion
    def _scale(self, instr: xk.Instruction) -> int:
        """x4 (§4.1.1) works only in RS D2, D3, B2, B3 (§4.2.2.3 Note 1); else taken as x1."""
        names = instr.type.field_names
        if 'multiplier' in names and instr.get('multiplier') == 'x4' \
                and self.presets['RS'] in xk.X4_RESOLUTIONS:
            return 4
        return 1

    def _accel(self, instr: xk.Instruction, k: int = 1) -> float:
        if instr.code in xk.UNRAMPED_RUNS:
            return INF
        return xk.ramp_acceleration_hz_s(instr.get('ramp_code')) * k

    def _start_motion(self, instr: xk.Instruction, t: float) -> bool:
        c = instr.code
        k = self._scale(instr)
        m = self.axis.motion
        if c == 3:
            return self._start_zero_search(instr)
        f = instr.frequency_hz * k
        a = self._accel(instr, k)
        if c in xk.INDEXED_RUNS:
            target = self._index_target(instr, k)
            if target is None:
                self.error = (xk.ERROR_FIELD_OVERFLOW, self.pc or 0)    # §4.3.7, §5.2
                return False
            self.index_target = target
            m.move_to(target, f, a, a)
            self.motion_starts.append((m.time_s, c))
            self.phase = 'index'
            return True
        sign = 1 if instr.get('direction') == '+' else -1
        m.run_velocity(sign * f, a, a)
        self.motion_starts.append((m.time_s, c))
        self.phase = 'dstop' if c == 5 else 'free'
        self.dstop_armed = math.isinf(a)
        return True

    def _index_target(self, instr: xk.Instruction, k: int) -> float | None:
        """Referenced target of an indexed run by coordinate mode (§5)."""
        n = instr.get('steps')
        position = self.axis.position_steps
        cm = self.presets['CM']
        if cm == xk.CM_RELATIVE:
            return position + n * k                         # §5.1 steps and x4 both scale
        if cm == xk.CM_ABSOLUTE:
            shift = n - self.counter                        # §5.2 target as given
            return None if abs(shift) > xk.STEPS_MAX else position + shift
        mod = self.modulus                                  # §5.3 shortest way round
        if n < 0 or n >= mod:
            return None
        d = (n - self.counter) % mod
        if d > mod / 2:
            d -= mod
        return position + d

    def _start_zero_search(self, instr: xk.Instruction) -> bool:
        """§4.1.9 / Fig. 2 (not in the text, §8 A15 reading): ramped free run at FF until PX
        comes on, decelerate on the ramp, then back at LL until PX goes off, stop there."""
        self.dstop_armed = False
        if self.input('PX'):
            self._zero_approach()
            return True
        sign = 1 if instr.get('direction') == '+' else -1
        self.axis.motion.run_velocity(sign * xk.TABLE2_HZ[instr.get('frequency_code')],
                                      self._accel(instr), self._accel(instr))
        self.phase = 'search'
        return True

    def _zero_approach(self) -> None:
        instr = self.current
        sign = 1 if instr.get('direction') == '+' else -1
        self.axis.motion.run_velocity(-sign * xk.TABLE3_HZ[instr.get('slow_code')], INF, INF)
        self.phase = 'approach'

    def _resume(self, stored: tuple, t: float) -> int | None:
        """§4.1.15: finish the interrupted instruction from where it stopped."""
        instr, target, remaining_s = stored
        m = self.axis.motion
        self.current = instr
        if instr.code == 65:
            self.phase, self.delay_end = 'delay', t + remaining_s
            return None
        if instr.code in xk.INDEXED_RUNS:
            k = self._scale(instr)
            m.move_to(target, instr.frequency_hz * k, self._accel(instr, k),
                      self._accel(instr, k))
            self.index_target, self.phase = target, 'index'
            return None
        return None if self._start_motion(instr, t) else xk.END_OF_PROGRAM

    def _on_axis_event(self, ev: AxisEvent) -> None:
        t = ev.time_s
        m = self.axis.motion
        if ev.name == HOME:
            if self.phase == 'search' and ev.active:
                m.stop(self._accel(self.current))
                self.phase = 'search_stop'
            elif self.phase == 'approach' and not ev.active:
                m.stop_immediately()
                self._finish_instruction(t)
            elif self.phase == 'spin':
                self._goto(self.pc, t)
        elif ev.name == TARGET_REACHED:
            at_rest = not m.moving
            if self.phase == 'index' and at_rest:
                self._finish_instruction(t)
            elif self.phase == 'search_stop' and at_rest:
                if self.input('PX'):
                    self._zero_approach()
                else:
                    self._finish_instruction(t)
            elif self.phase in ('free_stop', 'dstop_brake') and at_rest:
                self._finish_instruction(t)
            elif self.phase == 'dstop' and not at_rest:
                self.dstop_armed = True          # at speed: ES is heard from now (05 Note 4)
            elif self.phase == 'abort' and at_rest:
                self._end_program()
        elif ev.forced:
            if ev.name == 'EE' and ev.active:
                self.emergency_stop(t)
            elif ev.name == 'ES' and ev.active:
                self.free_run_stop(t)
            elif ev.name == 'ST' and ev.active:
                self._hardware_start(t)
            elif self.phase == 'spin':
                self._goto(self.pc, t)

    def _hardware_start(self, t: float) -> None:
        """§2.2.2 ST: start cell 100 + SEL (Table 1) unless busy, EE on, or ES on with ES 0."""
        if self.busy or self.input('EE') or (self.input('ES') and self.presets['ES'] == 0):
            return
        cell = 100 + sum(self.input(f'S{i}') << i for i in range(4))
        self._start_program(cell, t)

    def emergency_stop(self, t: float) -> None:
        """§4.2.6 / §2.2.2 EE: abort the program; ramped runs decelerate on their ramp,
        unramped ones stop at once; the interrupted instruction is kept for 69 (§4.1.15)."""
        instr, m = self.current, self.axis.motion
        if self.phase in ('idle', 'abort'):
            return
        if instr is not None and instr.code in xk.MOTION_CODES | {65} and instr.code != 5:
            target = self.index_target if self.phase == 'index' else None
            self.recovery = (instr, target, max(self.delay_end - t, 0.0))
        self.pc = None
        if m.moving:
            accel = INF if self.phase == 'approach' or instr is None \
                else self._accel(instr, self._scale(instr))
            if accel == INF:
                m.stop_immediately()
                self._end_program()
            else:
                m.stop(accel)
                self.phase = 'abort'
        else:
            self._end_program()

    def free_run_stop(self, t: float) -> None:
        """§4.2.7 ES: stops free runs (then the program goes on at DDD); triggers the braking
        of a delayed stop once it is at speed (§4.1.16); nothing else."""
        m = self.axis.motion
        if self.phase == 'free':
            a = self._accel(self.current, self._scale(self.current))
            if a == INF:
                m.stop_immediately()
                self._finish_instruction(t)
            else:
                m.stop(a)
                self.phase = 'free_stop'
        elif self.phase == 'dstop' and self.dstop_armed:
            instr = self.current
            k = self._scale(instr)
            a = self._accel(instr, k)
            v = m.velocity_hz
            n = max(instr.get('stop_steps') * k, 1)           # Note 2: 0 is one step
            if v * v / (2 * a) > n:                            # Note 1, Fig. 3b: slower first
                v = math.copysign(math.sqrt(2 * a * n), v)
                m.run_velocity(v, INF, INF)
            m.move_to(m.position_steps + math.copysign(n, v), abs(v), a, a)
            self.phase = 'dstop_brake'


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
