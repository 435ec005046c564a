"""One simulated R.T.A. X-MIND K drive: the device behind the RS-485 line of `xmind_k.sim`.

`XmindKDriveSim`: presets and cells 100-227 in a simulated EEPROM (with write counters,
optionally kept in a JSON file across runs), cells 228-230 in RAM, the coordinate modes (§5), the
error register (QE), the inputs. `receive()` takes one host string and returns the answer, or
None for silence: broadcast, unknown address, busy (only EE and ES are heard, §3), the 200 ms
after WS,RS; each string code has its handler (`_STRINGS`). The stored-program engine, motion and
zero search are the mixin `xmind_k.program.XmindKProgram`.

The device model shares the frame codec and the tables with the driver
(`stepper_drivers.protocol.xmind_k`), never its state logic. Readings of the manual's open points
are parameters (docs/xmind_k.md lists them). Not here: the line, its timing and link faults
(`xmind_k.sim.XmindKLine`), the ROS backend.
"""

from __future__ import annotations

import json
import logging
import os
import pathlib
import time
from typing import Any, Callable, Mapping

from stepper_drivers.protocol import xmind_k as xk

from ..core.axis import HOME, SimAxis
from ..core.motion import INF
from .program import XmindKProgram

logger = logging.getLogger(__name__)

INPUTS = ('ST', 'EE', 'ES', 'I0', 'I1', 'I2', 'PX', 'S0', 'S1', 'S2', 'S3')
NULL_CELL = xk.Instruction(0, (), xk.END_OF_PROGRAM)     # content of a cell never written


class XmindKDriveSim(XmindKProgram):
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

    def _execute_string(self, f: xk.Frame, now: float) -> tuple[str, tuple]:
        """Act on one host string; the answer's code and arguments ('Y' for a command)."""
        handler = _STRINGS.get(f.code)
        answer = handler(self, f, now) if handler is not None else None
        return ('Y', ()) if answer is None else answer

    # --------------------------------------------------------- one host string code each
    def _write_cell(self, f: xk.Frame, now: float) -> None:
        """WN: cells 228-230 in RAM, the others in EEPROM (one write more, saved)."""
        cell, instr = f.args
        if cell in xk.CELL_RAM:
            self.ram[cell] = instr
        else:
            self.eeprom[cell] = instr
            self.eeprom_cell_writes += 1
            self._save()

    def _write_preset(self, f: xk.Frame, now: float) -> None:
        """WS: a preset into EEPROM (CM with its working range kkk); WS,RS then deafens."""
        preset, value, kkk = f.args
        self.presets[preset] = value
        if preset == 'CM' and kkk is not None:
            self.cyclic_range = kkk
        self.eeprom_preset_writes += 1
        self._save()
        if preset == 'RS':
            self.silent_until = now + xk.RS_SILENT_S

    def _motor_current(self, f: xk.Frame, now: float) -> None:
        """CY / CN: motor current on / off."""
        self.current_on = f.code == 'CY'
        logger.info('%s: motor current %s (%s)', self.name, 'ON' if self.current_on
                    else 'OFF', f.code)       # not readable over the line: logged

    def _program_start(self, f: xk.Frame, now: float) -> None:
        """PS: run the program from a cell, unless a protection has tripped (FA 0)."""
        if self.fa:
            self._start_program(f.args[0], now)

    def _set_counter(self, f: xk.Frame, now: float) -> None:
        """RA (to 0) / SA (to a value): the position counter."""
        self.axis.set_position(float(f.args[0]) if f.code == 'SA' else 0.0)
        self._last_counter = self.counter     # a reset is not a motion past the cam

    def _set_output(self, f: xk.Frame, now: float) -> None:
        """SO: an output or flag."""
        self.outputs[f.args[0]] = f.args[1]

    def _set_cam(self, f: xk.Frame, now: float) -> None:
        """SC: the cam on (at a position) or off."""
        a = f.args
        self.cam = (a[0], a[1] if a[0] else None)

    def _query_preset(self, f: xk.Frame, now: float) -> tuple[str, tuple]:
        """QS: a preset (CM in cyclic mode with its working range)."""
        preset = f.args[0]
        kkk = self.cyclic_range if preset == 'CM' and self.presets['CM'] == 2 else None
        return 'QS', (preset, self.presets[preset], kkk)

    def _query_output(self, f: xk.Frame, now: float) -> tuple[str, tuple]:
        """QO: an output or flag, FA, or BS (busy)."""
        name = f.args[0]
        value = self.fa if name == 'FA' else int(self.busy) if name == 'BS' \
            else self.outputs[name]
        return 'QO', (name, value)

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


# The host strings by code: each handler acts and returns the answer, None for 'Y'.
_STRINGS: dict[str, Callable[[XmindKDriveSim, xk.Frame, float], tuple[str, tuple] | None]] = {
    'WN': XmindKDriveSim._write_cell,
    'WS': XmindKDriveSim._write_preset,
    'CY': XmindKDriveSim._motor_current,
    'CN': XmindKDriveSim._motor_current,
    'PS': XmindKDriveSim._program_start,
    'EE': lambda d, f, now: d.emergency_stop(now),
    'ES': lambda d, f, now: d.free_run_stop(now),
    'RA': XmindKDriveSim._set_counter,
    'SA': XmindKDriveSim._set_counter,
    'SO': XmindKDriveSim._set_output,
    'SC': XmindKDriveSim._set_cam,
    'QA': lambda d, f, now: ('QA', (d.counter,)),
    'QS': XmindKDriveSim._query_preset,
    'QI': lambda d, f, now: ('QI', (f.args[0], d.input(f.args[0]))),
    'QO': XmindKDriveSim._query_output,
    'QM': lambda d, f, now: ('QM', (f.args[0], d.cell(f.args[0]))),
    'QC': lambda d, f, now: ('QC', d.cam),
    'QE': lambda d, f, now: ('QE', d.error),
}
