"""The program engine of a simulated X-MIND K: a mixin of `xmind_k.device.XmindKDriveSim`.

The stored-program engine (chaining by DDD, conditional jump 63, one loop counter 61/62, delays
65, outputs and flags 58, cam 57, counter reset 60, current 70, recovery 69, delayed stop 05),
every run instruction on a `SimAxis` with the Table 5 ramps, the zero search on the PX input (the
axis' 'home' switch), the stops EE and ES, the hardware start ST. The cells, presets, inputs and
busy flag it works on are XmindKDriveSim's; not here: the host strings, the EEPROM.
"""

from __future__ import annotations

import logging
import math

from stepper_drivers.protocol import xmind_k as xk

from ..core.axis import HOME, TARGET_REACHED, AxisEvent
from ..core.motion import INF

logger = logging.getLogger(__name__)


class XmindKProgram:
    """The program engine and motion of one X-MIND K (state: XmindKDriveSim)."""

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
        if ev.name == HOME:
            self._on_px(ev)
        elif ev.name == TARGET_REACHED:
            self._on_motion_done(ev)
        elif ev.forced:
            self._on_forced_input(ev)

    def _on_px(self, ev: AxisEvent) -> None:
        """PX (the axis' home switch) in a zero search, or a jump loop waiting for it."""
        t = ev.time_s
        m = self.axis.motion
        if self.phase == 'search' and ev.active:
            m.stop(self._accel(self.current))
            self.phase = 'search_stop'
        elif self.phase == 'approach' and not ev.active:
            m.stop_immediately()
            self._finish_instruction(t)
        elif self.phase == 'spin':
            self._goto(self.pc, t)

    def _on_motion_done(self, ev: AxisEvent) -> None:
        """The axis at rest at the end of a run or stop, or at speed: the phase goes on."""
        t = ev.time_s
        at_rest = not self.axis.motion.moving
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

    def _on_forced_input(self, ev: AxisEvent) -> None:
        """An input set from outside: EE, ES and ST act when they come on; any input may end a
        jump loop waiting for it."""
        actions = {'EE': self.emergency_stop, 'ES': self.free_run_stop,
                   'ST': self._hardware_start}
        action = actions.get(ev.name) if ev.active else None
        if action is not None:
            action(ev.time_s)
        elif self.phase == 'spin':
            self._goto(self.pc, ev.time_s)

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
