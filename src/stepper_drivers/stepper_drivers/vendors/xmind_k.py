"""R.T.A. X-MIND K on its ASCII RS-485 line: `XmindKBus`, `XmindKDrive` and `VENDOR`.

How the common contract maps onto the drive (docs/xmind_k.md has the full table):

- moves and free runs are written to the RAM cells 228-230 (`WN`) and started with `PS`; the
  EEPROM cells 100-227 are never written at run time, presets (`WS`) only when they differ;
- the drive answers nothing while it executes a program (§3), so while busy the position is
  estimated from the commanded profile (DriveState.position_estimated) and corrected by `QA` as
  soon as the drive answers again; velocity cannot be read at all (velocity_valid = False);
- a velocity change while running is stop (`ES`), wait until the drive answers, rewrite, restart;
- stop = `ES` for a free run (the only thing ES stops, §4.2.7), `EE` otherwise; quick stop = `EE`;
  a bus closed with drives in motion gets a broadcast `99EE`;
- enable = `CY`, disable = `CN` (not readable back, so tracked); homing = zero search (03) plus
  counter reset (60); fault reset does not exist (RefusedError); every preset is already stored.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Any, Mapping

from .. import drive
from ..drive import (DriveError, DriveState, HomingState, LinkError, Motion, RefusedError,
                     State)
from ..protocol import xmind_k as xk
from ..protocol.ascii_line import AsciiLine, LineError

logger = logging.getLogger(__name__)

MOVE_CELL = 228          # RAM (§4.1): indexed runs, and the zero search of a homing
RUN_CELL = 229           # RAM: free runs, and the counter reset after the zero search
HOMING_METHODS = {3: 'zero search (instruction 03) in + direction, then counter reset',
                  -3: 'zero search (instruction 03) in - direction, then counter reset',
                  60: 'counter reset at the current position (RA)'}
RAMPED_MIN_HZ = min(xk.TABLE2_HZ.values())          # 3000 Hz: below, only unramped runs (§4.1.6)
RAMPED_MAX_HZ = max(xk.HR_RAMPED_X100) * 100        # 24000 Hz (§4.1.2)
FAULT_TEXT = ('FA output OFF: drive blocked by a protection (§2.2.4); X-MIND K has no fault '
              'reset command: clear the cause and power-cycle')
NO_FAULT_RESET = 'X-MIND K has no fault reset command; clear the cause and power-cycle'
STOP_WAIT_S = 3.0        # bound on waiting for a stopping drive to answer again
STOP_POLL_S = 0.02       # rate limit of that wait (nothing to wait on but the drive's answer)
GARBLED_LINK_LOST = 3    # transactions in a row without a valid answer: the link is unusable
RETRY_SLACK_FACTOR = 4   # a repeat waits timeout_s x (1 + 4 k) beyond the manual's timing
BUSY_POLL_SLACK_S = 0.03  # a drive that may be busy: a late answer is taken at the next poll


class GarbledAnswer(DriveError):
    """Something answered, but not a valid answer to the request (after the retries): the
    drive is there, this transaction failed."""


# ----------------------------------------------------------------------------------------- bus
class XmindKBus(drive.Bus):
    """One RS-485 line, 9600 8N1 (§3), strictly one transaction at a time."""

    def __init__(self, params: Mapping[str, Any]):
        self.url = str(params['port'])
        self.line = AsciiLine(self.url, baudrate=int(params['baudrate']),
                              parity=str(params['parity']), stopbits=int(params['stopbits']),
                              margin_s=xk.MARGIN_S, local_echo=bool(params['local_echo']))
        self.char_s = self.line.char_time_s
        self.slack_s = float(params['timeout_s'])
        self.retries = int(params['retries'])
        self.description = f'X-MIND K RS-485 {self.line.description}'
        self.addresses: dict[str, int] = {}          # drive name -> address, for checks
        self.drives: dict[str, 'XmindKDrive'] = {}   # connected drives (99EE on close)
        self.silences = 0
        self.garbled = 0
        self.broadcasts = 0
        self.failed_in_a_row = 0

    def open(self) -> None:
        try:
            self.line.open()
        except LineError as e:
            raise LinkError(str(e)) from None

    def close(self) -> None:
        if self.line.is_open and any(d.in_motion for d in self.drives.values()):
            try:
                self.broadcast(xk.Frame(xk.BROADCAST, 'EE'))     # §4.2.6 every drive stops
                logger.warning('%s closed with drives in motion: sent 99EE', self.url)
            except LinkError as e:
                logger.warning('%s: 99EE on close failed: %s', self.url, e)
        self.line.close()

    @property
    def is_open(self) -> bool:
        return self.line.is_open

    def counters(self) -> dict[str, int]:
        return {**super().counters(), 'silences': self.silences, 'garbled': self.garbled,
                'broadcasts': self.broadcasts}

    def broadcast(self, frame: xk.Frame) -> None:
        """A 99 string: executed by every drive, answered by none (§2.2.1)."""
        try:
            self.line.send(xk.encode_request(frame))
        except LineError as e:
            raise LinkError(str(e)) from None
        self.broadcasts += 1

    def request(self, frame: xk.Frame, rd_ms: float | None, tries: int | None = None,
                retry_silence: bool = True, slack_s: float | None = None
                ) -> xk.Frame | None:
        """One string and its answer (None: silence). Timeouts from §3 plus timeout_s: the
        first character must come within N_tx t_char + turnaround + RD. A garbled answer is
        repeated up to `tries`; silence only when retry_silence (a busy drive is silent).
        Each repeat allows RETRY_SLACK_FACTOR times more slack (a hiccup of the adapter or
        of the host is not a lost line)."""
        raw = xk.encode_request(frame)
        tries = 1 + self.retries if tries is None else tries
        rd_s = (xk.RD_MAX_MS if rd_ms is None else rd_ms) / 1000.0
        line_s = len(raw) * self.char_s + xk.turnaround_s(frame.code) + rd_s
        prefix = raw[:2]
        garbled = None
        base_s = self.slack_s if slack_s is None else slack_s
        for attempt in range(tries):
            wait_s = base_s * (1 + RETRY_SLACK_FACTOR * attempt)
            first_s = line_s + wait_s
            reply_s = xk.max_answer_chars(frame) * self.char_s + wait_s
            self.transactions += 1
            try:
                answer = self.line.transact(raw, first_byte_timeout_s=first_s,
                                            reply_timeout_s=reply_s,
                                            accept=lambda b: b[:2] == prefix)
            except LineError as e:
                self.errors += 1
                raise LinkError(str(e)) from None
            if answer is None:
                self.silences += 1
                if not retry_silence:
                    break
                continue
            try:
                parsed = xk.parse_answer(answer, frame)
                self.failed_in_a_row = 0
                return parsed
            except xk.ProtocolError as e:
                self.garbled += 1
                self.errors += 1
                garbled = f'{raw!r} got {answer!r}: {e}'
                logger.debug('%s: garbled answer: %s', self.url, garbled)
        if garbled:
            self.failed_in_a_row += 1
            if self.failed_in_a_row >= GARBLED_LINK_LOST:
                self.failed_in_a_row = 0
                raise LinkError(f'{self.url}: {GARBLED_LINK_LOST} transactions in a row without '
                                f'a valid answer, last: {garbled}')
            raise GarbledAnswer(f'{self.url}: no valid answer: {garbled}')
        return None


# ------------------------------------------------------------------------------- estimation
@dataclasses.dataclass
class Estimate:
    """Position over time of the motion a drive was told to make (the drive cannot be asked).

    Pieces (t0_s, x0_steps, v0_hz, a_hz_s, t1_s) with constant acceleration; the last may
    be open-ended (t1_s = inf, a free run). Same ramp model as §6.2: linear, 24 kHz in T."""

    pieces: list[tuple[float, float, float, float, float]]

    @classmethod
    def at_rest(cls, t: float, x: float) -> 'Estimate':
        return cls([(t, x, 0.0, 0.0, math.inf)])

    @classmethod
    def index(cls, t: float, x: float, distance: float, f_hz: float, a_hz_s: float
              ) -> 'Estimate':
        s = math.copysign(1.0, distance)
        d = abs(distance)
        if d == 0:
            return cls.at_rest(t, x)
        if math.isinf(a_hz_s):
            t1 = t + d / f_hz
            return cls([(t, x, s * f_hz, 0.0, t1), (t1, x + s * d, 0.0, 0.0, math.inf)])
        fp = min(f_hz, math.sqrt(a_hz_s * d))          # triangle when short (§6.2 model)
        t_ramp = fp / a_hz_s
        cruise = (d - fp * fp / a_hz_s) / fp
        t1, t2 = t + t_ramp, t + t_ramp + cruise
        t3 = t2 + t_ramp
        x1 = x + s * fp * t_ramp / 2
        x2 = x1 + s * fp * cruise
        return cls([(t, x, 0.0, s * a_hz_s, t1), (t1, x1, s * fp, 0.0, t2),
                    (t2, x2, s * fp, -s * a_hz_s, t3), (t3, x + s * d, 0.0, 0.0, math.inf)])

    @classmethod
    def run(cls, t: float, x: float, v_hz: float, a_hz_s: float) -> 'Estimate':
        if math.isinf(a_hz_s):
            return cls([(t, x, v_hz, 0.0, math.inf)])
        t1 = t + abs(v_hz) / a_hz_s
        x1 = x + v_hz * (t1 - t) / 2
        return cls([(t, x, 0.0, math.copysign(a_hz_s, v_hz), t1), (t1, x1, v_hz, 0.0, math.inf)])

    def state(self, t: float) -> tuple[float, float]:
        for t0, x0, v0, a, t1 in self.pieces:
            if t < t1 or math.isinf(t1):
                tau = max(t - t0, 0.0)
                return x0 + v0 * tau + 0.5 * a * tau * tau, v0 + a * tau
        t0, x0, v0, a, t1 = self.pieces[-1]
        return x0, 0.0

    @property
    def end_s(self) -> float:
        """When the motion is at rest (inf for a free run that was not stopped)."""
        last = self.pieces[-1]
        return last[0] if last[2] == 0.0 and last[3] == 0.0 else math.inf

    def stop(self, t: float, a_hz_s: float) -> None:
        """Decelerate from now with a (inf: at once), unless already ending sooner."""
        x, v = self.state(t)
        if v == 0.0:
            self.pieces = [(t, x, 0.0, 0.0, math.inf)]
            return
        if math.isinf(a_hz_s):
            self.pieces = [(t, x, 0.0, 0.0, math.inf)]
            return
        t_stop = t + abs(v) / a_hz_s
        if t_stop >= self.end_s:
            return
        x_stop = x + v * (t_stop - t) / 2
        self.pieces = [(t, x, v, -math.copysign(a_hz_s, v), t_stop),
                       (t_stop, x_stop, 0.0, 0.0, math.inf)]


@dataclasses.dataclass
class Job:
    """The program the drive runs for us (it is silent until it ends)."""

    kind: str                      # 'move', 'velocity', 'homing', 'program' (raw PS)
    instruction: xk.Instruction | None
    estimate: Estimate
    accel_hz_s: float              # of the ramp (inf: unramped), for the stop estimate
    next_poll_s: float             # do not ask before (the drive is silent while busy)
    target_steps: int | None = None         # move: end of this index; homing: the offset
    final_target_steps: int | None = None   # a move longer than one index (+-8388607) continues
    motion: Motion | None = None
    stopping: bool = False
    pinged_s: float = 0.0

    @property
    def goal(self) -> int | None:
        return self.final_target_steps if self.final_target_steps is not None \
            else self.target_steps


# ------------------------------------------------------------------------------------ drive
class XmindKDrive(drive.Drive):
    def __init__(self, bus: XmindKBus, name: str, params: Mapping[str, Any]):
        super().__init__(bus, name, params)
        self.number = int(params['address'])       # the drive address AA (§2.2.1)
        p = f'drives.{name}.'
        for other, number in bus.addresses.items():
            if other != name and number == self.number:
                raise ValueError(f'parameter {p}address: {self.number:02d} is already used by '
                                 f'drive {other} on {bus.url} (allowed: a free address 0..47)')
        method = int(params['homing.method'])
        if method not in HOMING_METHODS:
            raise ValueError(f'parameter {p}homing.method: {method} is not an X-MIND K method '
                             '(allowed: ' + '; '.join(f'{k} = {v}' for k, v in
                                                      HOMING_METHODS.items()) + ')')
        self.resolution = str(params['resolution'])
        spr = float(params['steps_per_rev'])
        if self.resolution and spr != xk.RESOLUTIONS[self.resolution]:
            raise ValueError(f'parameter {p}steps_per_rev: {spr:g} does not match resolution '
                             f'{self.resolution} (allowed: {xk.RESOLUTIONS[self.resolution]}, '
                             '§4.2.2.3)')
        self.steps_per_rev = spr
        self.presets_wanted = {k: v for k, v in (
            ('IN', int(params['current_preset'])), ('RD', int(params['answer_delay_ms'])),
            ('EQ', int(params['equalization']))) if v >= 0}
        self.flag = str(params['power_cycle_flag'])
        self.busy_poll_s = float(params['busy_poll_period_s'])
        self.status_poll_s = float(params['status_poll_period_s'])
        self.rd_ms: int | None = None          # answer delay, read at connect (§4.2.2.5)
        self.enabled = False
        self.homed = False
        self.homing = HomingState.IDLE
        self.position_steps = 0
        self.fault = False
        self.error = (xk.ERROR_NONE, 0)        # QE at connect (a last-error register, §4.3.7)
        self.alarms: list[str] = []
        self.job: Job | None = None
        self.pending: tuple | None = None      # ('move', target, Motion) | ('velocity', v, Motion)
        self.last_target: int | None = None
        self.next_status_s = 0.0
        bus.addresses[name] = self.number     # (the node also builds drives only to check)

    # ---------------------------------------------------------------------------- transactions
    def _ask(self, code: str, *args, tries: int | None = None, retry_silence: bool = True,
             slack_s: float | None = None) -> xk.Frame | None:
        return self.bus.request(xk.Frame(self.number, code, args), self.rd_ms, tries,
                                retry_silence, slack_s)

    def _poll_busy(self) -> xk.Frame | None:
        """QA to a drive that may be busy: silence is an answer (busy), garbage is repeated."""
        return self._ask('QA', retry_silence=False,
                         slack_s=min(self.bus.slack_s, BUSY_POLL_SLACK_S))

    def _need(self, code: str, *args) -> xk.Frame:
        """A string an idle drive must answer; N and silence raise."""
        answer = self._ask(code, *args)
        if answer is None:
            raise LinkError(f'drive {self.number:02d} did not answer {code} on {self.bus.url} '
                            f'({1 + self.bus.retries} tries)')
        if answer.code == 'N':
            raise DriveError(f'drive {self.number:02d} answered N to '
                             f'{xk.encode_request(xk.Frame(self.number, code, args))!r} '
                             '(syntax or range, §4.4.2)')
        return answer

    def _command(self, code: str, *args) -> None:
        answer = self._need(code, *args)
        if answer.code != 'Y':
            raise DriveError(f'drive {self.number:02d} answered {answer} to {code}')

    def _start(self, cell: int) -> None:
        """PS: never repeated (a lost Y would make the repeat land on a busy drive)."""
        try:
            answer = self._ask('PS', cell, tries=1)
        except GarbledAnswer:
            return        # something answered: the drive only refuses PS for syntax (§4.4.2)
        if answer is None:
            raise LinkError(f'drive {self.number:02d} did not answer PS,{cell} on '
                            f'{self.bus.url}')
        if answer.code != 'Y':
            raise DriveError(f'drive {self.number:02d} refused PS,{cell}')

    @property
    def address(self) -> str:
        return f'{self.number:02d}'       # as the manual writes it (status 'address')

    @property
    def in_motion(self) -> bool:
        return self.job is not None

    # ------------------------------------------------------------------------------ life cycle
    def connect(self) -> dict[str, str]:
        self.bus.drives[self.name] = self
        self.job, self.pending = None, None
        self.rd_ms = None
        answer = self._ask('QS', 'RS')
        if answer is None:
            self._stop_unknown_program()
            answer = self._need('QS', 'RS')
        rs = answer.args[1]
        if self.resolution and rs != self.resolution:
            logger.warning('%s: drive %02d runs RS %s, writing %s (current off >= 200 ms, '
                           '§4.2.2.3)', self.name, self.number, rs, self.resolution)
            self._command('WS', 'RS', self.resolution)
            self._wait_answering(xk.RS_SILENT_S + STOP_WAIT_S)
            rs = self.resolution
        if xk.RESOLUTIONS[rs] != self.steps_per_rev:
            raise DriveError(f'drive {self.number:02d} runs resolution {rs} = '
                             f'{xk.RESOLUTIONS[rs]} step/rev but drives.{self.name}.steps_per_rev'
                             f' is {self.steps_per_rev:g}; set one of them')
        presets = {'RS': rs}
        for preset in ('RD', 'CM', *[k for k in self.presets_wanted if k != 'RD']):
            value = self._need('QS', preset).args[1]
            want = 0 if preset == 'CM' else self.presets_wanted.get(preset)
            if want is not None and value != want:
                # EEPROM: written only when it differs (§4.2.2: every preset is stored)
                logger.warning('%s: drive %02d preset %s is %s, writing %s', self.name,
                               self.number, preset, value, want)
                self._command('WS', preset, want)
                value = want
            presets[preset] = value
            if preset == 'RD':
                self.rd_ms = int(value)
        qe = self._need('QE').args
        self.error = (qe[0], qe[1])
        self.fault = self._need('QO', 'FA').args[1] == 0
        if self.flag and self._need('QO', self.flag).args[1] == 0:
            # Flags are 0 at power-on (§8 A17 reading): new drive or power cycle; current is ON
            # (§4.2.3) but not enabled by this node, and the counter restarted at 0.
            self.enabled, self.homed, self.homing = False, False, HomingState.IDLE
            self._command('SO', self.flag, 1)
        self.position_steps = self._need('QA').args[0]
        self.next_status_s = time.monotonic() + self.status_poll_s
        self.alarms = [] if qe[0] == xk.ERROR_NONE else [
            f'last program error {qe[0]:02d} {xk.ERROR_TEXT.get(qe[0], "")} at cell {qe[1]:03d}']
        return {'address': f'{self.number:02d}',
                **{k: str(v) for k, v in presets.items()},
                'steps_per_rev': str(xk.RESOLUTIONS[rs]),
                'FA': '0 (protection)' if self.fault else '1',
                'QE': f'{qe[0]:02d},{qe[1]:03d}',
                'current': 'ON' if self.enabled else 'not enabled by this node (not readable)'}

    def _stop_unknown_program(self) -> None:
        """Silent at connect: busy with something we did not start, or absent. EE is answered
        even by a busy drive (§3); after a reconnect nothing may go on moving by itself."""
        answer = self._ask('EE')
        if answer is None:
            raise LinkError(f'drive {self.number:02d} does not answer on {self.bus.url} '
                            '(QS,RS and EE unanswered)')
        logger.warning('%s: drive %02d was busy at connect: sent EE', self.name, self.number)
        self._wait_answering(STOP_WAIT_S)

    def _wait_answering(self, timeout_s: float) -> xk.Frame:
        """Poll QA until the drive answers again (it is silent while busy or after WS,RS)."""
        deadline = time.monotonic() + timeout_s
        while True:
            answer = self._poll_busy()
            if answer is not None and answer.code == 'QA':
                return answer
            if time.monotonic() > deadline:
                raise LinkError(f'drive {self.number:02d} still silent after {timeout_s:g} s')
            time.sleep(STOP_POLL_S)

    # ------------------------------------------------------------------------------ read state
    def read_state(self) -> DriveState:
        now = time.monotonic()
        job = self.job
        if job is not None:
            if now < job.next_poll_s:
                return self._state(now)
            answer = self._poll_busy()
            if answer is None or answer.code != 'QA':
                job.next_poll_s = now + self.busy_poll_s        # silent: still busy (§3)
                self._check_alive(job, now)
                return self._state(time.monotonic())
            self._job_ended(answer.args[0])
        else:
            self.position_steps = self._need('QA').args[0]
        if now >= self.next_status_s:
            self._read_status()
        if self.job is None and self.pending is not None:
            self._start_pending()
        return self._state(time.monotonic())

    def _check_alive(self, job: Job, now: float) -> None:
        """A move long overdue: busy or gone? ES is answered even when busy and does nothing
        to an indexed run (§4.2.7), so it tells the two apart (not for free runs or homing)."""
        if job.kind != 'move' or job.stopping or now < job.estimate.end_s + 1.0 \
                or now < job.pinged_s + 1.0:
            return
        job.pinged_s = now
        if self._ask('ES') is None:
            raise LinkError(f'drive {self.number:02d} answers neither QA nor ES on '
                            f'{self.bus.url} ({now - job.estimate.end_s:.1f} s after the '
                            'estimated end of its move)')

    def _job_ended(self, position: int) -> None:
        job, self.job = self.job, None
        self.position_steps = position
        self.next_status_s = 0.0           # a protection may have ended it: read FA now
        if job.kind == 'homing':
            if position == 0 and not job.stopping:
                if job.target_steps:                 # homing.offset
                    self._command('SA', job.target_steps)
                    self.position_steps = job.target_steps
                self._homed()
            else:
                self.homing = HomingState.ERROR
        elif job.kind == 'move' and job.final_target_steps is not None and not job.stopping \
                and self.pending is None and position != job.final_target_steps:
            self.pending = ('move', job.final_target_steps, job.motion)     # next index

    def _homed(self) -> None:
        self.homed, self.homing = True, HomingState.ATTAINED
        self.alarms = [a for a in self.alarms if not a.startswith('power cycle')]

    def _read_status(self) -> None:
        self.next_status_s = time.monotonic() + self.status_poll_s
        self.fault = self._need('QO', 'FA').args[1] == 0
        if self.flag and self._need('QO', self.flag).args[1] == 0:
            # Flags are 0 at power-on: the drive was power-cycled, its counter restarted at 0.
            logger.warning('%s: drive %02d lost flag %s: power cycle; position reference lost, '
                           'current ON by default (§4.2.3)', self.name, self.number, self.flag)
            self.homed, self.enabled = False, False
            self.alarms = [f'power cycle detected (flag {self.flag} was 0): home again']
            self._command('SO', self.flag, 1)

    def _state(self, now: float) -> DriveState:
        job = self.job
        moving = job is not None or self.pending is not None
        position, velocity = float(self.position_steps), 0.0
        if job is not None:
            position, velocity = job.estimate.state(now)
        if self.fault:
            state = State.FAULT
        else:
            state = State.OPERATION_ENABLED if self.enabled else State.SWITCH_ON_DISABLED
        mode = job.instruction.type.name if job is not None and job.instruction else ''
        if job is not None and job.kind == 'program':
            mode = 'STORED INSTRUCTION EXECUTION'
        return DriveState(
            state=state, enabled=self.enabled and not self.fault, moving=moving,
            target_reached=not moving and (self.last_target is None
                                           or self.last_target == self.position_steps),
            homed=self.homed, homing=self.homing, fault=self.fault,
            fault_code=1 if self.fault else 0, fault_text=FAULT_TEXT if self.fault else '',
            alarms=tuple(self.alarms), mode=mode, status_word=0,
            position_steps=int(round(position)), velocity_steps_s=velocity,
            velocity_valid=False, position_estimated=job is not None)

    # -------------------------------------------------------------------------------- power
    def enable(self) -> None:
        if self.job is not None:
            raise DriveError(f'drive {self.number:02d} is busy ({self.job.kind}); it answers '
                             'only EE and ES until the program ends (§3)')
        self._command('CY')                  # §4.2.3; nothing moves
        self.enabled = True

    def disable(self) -> None:
        self.pending = None
        if self.job is not None:             # CN is not heard by a busy drive (§3)
            self._stop_job(quick=True)
            self._job_ended(self._wait_answering(STOP_WAIT_S).args[0])
        self._command('CN')                  # §4.2.4
        self.enabled = False

    # ------------------------------------------------------------------------------- motion
    @staticmethod
    def ramp_code(acceleration_hz_s: float) -> int:
        """The Table 5 code with the largest acceleration not above the one asked for (the
        gentlest code, 42, when even that is too steep)."""
        fitting = [c for c in xk.TABLE5 if xk.ramp_acceleration_hz_s(c) <= acceleration_hz_s]
        return min(fitting) if fitting else max(xk.TABLE5)

    def run_instruction(self, kind: str, v_hz: float, motion: Motion, steps: int = 0
                        ) -> tuple[xk.Instruction, float, float]:
        """The RAM-cell instruction for a move ('move': steps) or a free run ('velocity': the
        sign of v_hz); returns it with its real frequency and acceleration."""
        f = abs(v_hz)
        if f > RAMPED_MAX_HZ:
            raise DriveError(f'{f:.0f} Hz exceeds the X-MIND K maximum of {RAMPED_MAX_HZ} Hz '
                             '(§4.1.2)')
        if f < 1.0:
            raise DriveError(f'{f:.3g} Hz is below the X-MIND K minimum of 1 Hz (Table 4)')
        direction = '+' if v_hz >= 0 else '-'
        if f >= RAMPED_MIN_HZ:
            rr = self.ramp_code(min(motion.acceleration_steps_s2, motion.deceleration_steps_s2))
            fff = int(f // 100)
            if kind == 'move':
                instr = xk.Instruction.make(31, frequency_x100=fff, ramp_code=rr, steps=steps,
                                            multiplier='x1')
            else:
                instr = xk.Instruction.make(32, frequency_x100=fff, ramp_code=rr,
                                            direction=direction, multiplier='x1')
            return instr, fff * 100.0, xk.ramp_acceleration_hz_s(rr)
        hz = xk.table4_floor(min(int(f), xk.HR_UNRAMPED_MAX_HZ))
        if kind == 'move':
            instr = xk.Instruction.make(21, frequency_hz=hz, steps=steps, multiplier='x1')
        else:
            instr = xk.Instruction.make(22, frequency_hz=hz, direction=direction,
                                        multiplier='x1')
        return instr, float(hz), math.inf

    def move_to(self, target_steps: int, motion: Motion) -> None:
        self._refuse_in_fault('move')
        target_steps = int(target_steps)
        job = self.job
        if self.pending == ('move', target_steps, motion) or (
                job is not None and job.kind == 'move' and not job.stopping
                and job.goal == target_steps and self.pending is None):
            return           # the same target again (a streaming command): nothing to send
        self.last_target = target_steps
        if self.job is not None or self.pending is not None:
            self.pending = ('move', int(target_steps), motion)
            if self.job is not None and not self.job.stopping:
                self._stop_job(quick=False)
            return
        self._start_move(int(target_steps), motion)

    def _start_move(self, target: int, motion: Motion) -> None:
        delta = target - self.position_steps
        if delta == 0:
            return
        chunk = max(-xk.STEPS_MAX, min(xk.STEPS_MAX, delta))     # §4.1.2 +-8388607 per index
        instr, f, a = self.run_instruction('move', motion.velocity_steps_s, motion, chunk)
        self._command('WN', MOVE_CELL, instr)
        self._start(MOVE_CELL)
        estimate = Estimate.index(time.monotonic(), self.position_steps, chunk, f, a)
        self.job = Job('move', instr, estimate, a, estimate.end_s,
                       target_steps=self.position_steps + chunk,
                       final_target_steps=target if chunk != delta else None, motion=motion)

    def set_velocity(self, velocity_steps_s: float, motion: Motion) -> None:
        self._refuse_in_fault('velocity')
        if abs(velocity_steps_s) < 1.0:
            self.pending = None
            if self.job is not None and not self.job.stopping:
                self._stop_job(quick=False)
            return
        instr = self.run_instruction('velocity', velocity_steps_s, motion)[0]
        job = self.job
        if job is not None and job.kind == 'velocity' and job.instruction == instr \
                and not job.stopping:
            self.pending = None
            return           # already running just so: nothing to send
        self.last_target = None
        if job is not None or self.pending is not None:
            self.pending = ('velocity', velocity_steps_s, motion)
            if job is not None and not job.stopping:
                self._stop_job(quick=False)          # stop, then rewrite and restart
            return
        self._start_run(velocity_steps_s, motion)

    def _start_run(self, v: float, motion: Motion) -> None:
        instr, f, a = self.run_instruction('velocity', v, motion)
        self._command('WN', RUN_CELL, instr)
        self._start(RUN_CELL)
        now = time.monotonic()
        self.job = Job('velocity', instr,
                       Estimate.run(now, self.position_steps, math.copysign(f, v), a), a,
                       now + self.busy_poll_s)

    def _start_pending(self) -> None:
        kind, value, motion = self.pending
        self.pending = None
        if kind == 'move':
            self._start_move(value, motion)
        else:
            self._start_run(value, motion)

    def stop(self, quick: bool = False) -> None:
        self.pending = None
        if self.job is not None:
            self._stop_job(quick)

    def _stop_job(self, quick: bool) -> None:
        """ES stops free runs only (§4.2.7); EE stops anything, ramped runs on their ramp
        (§4.1.1-4.1.4, §4.2.6)."""
        job = self.job
        code = 'ES' if job.kind == 'velocity' and not quick else 'EE'
        answer = self._ask(code)
        if answer is None:
            raise LinkError(f'drive {self.number:02d} did not answer {code} (answered even '
                            f'when busy, §3) on {self.bus.url}')
        job.stopping = True
        now = time.monotonic()
        job.estimate.stop(now, job.accel_hz_s)
        job.next_poll_s = min(job.estimate.end_s, now + self.busy_poll_s)
        if job.kind == 'homing':
            self.homing = HomingState.ERROR

    def _refuse_in_fault(self, what: str) -> None:
        if self.fault:
            raise DriveError(f'{what}: {FAULT_TEXT}')

    # -------------------------------------------------------------------------------- homing
    def start_homing(self, homing: drive.Homing) -> str:
        if self.job is not None:
            raise DriveError(f'drive {self.number:02d} is busy ({self.job.kind}); stop it '
                             'before homing')
        self.pending = None
        self.last_target = None
        if homing.method == 60:
            if homing.offset_steps:
                self._command('SA', homing.offset_steps)
            else:
                self._command('RA')
            self.position_steps = homing.offset_steps
            self._homed()
            return f'{HOMING_METHODS[60]}' + (f', then SA {homing.offset_steps}'
                                              if homing.offset_steps else '')
        p = f'drives.{self.name}.homing.'
        ff = int(homing.speed_search_steps_s // 1000)
        if ff not in xk.TABLE2_HZ:
            raise DriveError(f'{p}speed_search = {homing.speed_search_steps_s:.0f} Hz is outside '
                             'the zero search fast speeds 3000..24000 Hz (Table 2)')
        ll = int(homing.speed_zero_steps_s // 100)
        if ll not in xk.TABLE3_HZ:
            raise DriveError(f'{p}speed_zero = {homing.speed_zero_steps_s:.0f} Hz is outside the '
                             'zero search approach speeds 200..3000 Hz (Table 3)')
        rr = self.ramp_code(homing.acceleration_steps_s2)
        direction = '+' if homing.method > 0 else '-'
        search = xk.Instruction.make(3, RUN_CELL, frequency_code=ff, ramp_code=rr,
                                     direction=direction, slow_code=ll)
        reset = xk.Instruction.make(60, xk.END_OF_PROGRAM)
        self._command('WN', MOVE_CELL, search)        # §7.6: zero search, then counter reset
        self._command('WN', RUN_CELL, reset)
        self._start(MOVE_CELL)
        a = xk.ramp_acceleration_hz_s(rr)
        v = xk.TABLE2_HZ[ff] * (1 if direction == '+' else -1)
        now = time.monotonic()
        self.job = Job('homing', search, Estimate.run(now, self.position_steps, v, a), a,
                       now + self.busy_poll_s, target_steps=homing.offset_steps)
        self.homed, self.homing = False, HomingState.RUNNING
        return (f'zero search {direction} at {xk.TABLE2_HZ[ff]} Hz (ramp {rr}), approach '
                f'{xk.TABLE3_HZ[ll]} Hz, then counter reset'
                + (f' and SA {homing.offset_steps}' if homing.offset_steps else ''))

    # --------------------------------------------------------------------------- maintenance
    def fault_reset(self) -> str:
        if self.job is None:
            self.fault = self._need('QO', 'FA').args[1] == 0
        if self.fault:
            raise RefusedError(NO_FAULT_RESET)
        return ''

    def save_params(self) -> str:
        if self.job is not None:
            raise DriveError(f'drive {self.number:02d} is busy; presets cannot be read back')
        values = []
        for preset in xk.PRESETS:
            _, value, kkk = self._need('QS', preset).args
            values.append(f'{preset} {value}' + ('' if kkk is None else f',{kkk}'))
        return ('X-MIND K has no save command: every preset is stored in EEPROM when WS writes '
                'it (§4.2.2) and this node writes only cells 228-230 (RAM); read back: '
                + ', '.join(values))

    def _parse_address(self, address: str) -> tuple[str, tuple[str, ...]]:
        parts = address.strip().upper().split(',')
        return parts[0], tuple(parts[1:])

    def read_register(self, address: str, data_type: str) -> int | str:
        """`address` is a data request: QA, QE, QC, QS,<VV>, QI,<in>, QO,<out>, QM,<cell>."""
        code, args = self._parse_address(address)
        if code not in xk.REQUEST_CODES:
            raise DriveError(f'{address!r} is not an X-MIND K data request '
                             f'({", ".join(xk.REQUEST_CODES)}, with their parameter)')
        if self.job is not None:
            raise DriveError(f'drive {self.number:02d} is busy: it answers no data request '
                             'until its program ends (§3, §4.4.3)')
        try:
            values = tuple(int(a) if a.isdigit() else a for a in args)
            frame = xk.Frame(self.number, code, values)
            xk.encode_request(frame)
        except (xk.ProtocolError, IndexError, TypeError) as e:
            raise DriveError(f'{address!r}: {e}') from None
        answer = self._need(code, *frame.args)
        if data_type.lower() == 'string':
            return xk.encode_answer(answer).decode().rstrip('\r')
        value = {'QA': lambda a: a[0], 'QS': lambda a: a[1], 'QI': lambda a: a[1],
                 'QO': lambda a: a[1], 'QC': lambda a: a[0], 'QE': lambda a: a[0]}.get(code)
        if value is None or not isinstance(value(answer.args), int):
            raise DriveError(f'{address} answers text: read it with data_type string')
        return drive.register_type(data_type).check(value(answer.args))

    def write_register(self, address: str, data_type: str, value: int | str) -> None:
        """`address` is a command: SA, PS, SO,<out>, WS,<VV> with the value; CY, CN, RA, EE, ES
        without; or any code with data_type string and the parameters as text."""
        code = self._parse_address(address)[0]
        if code not in xk.COMMAND_CODES + ('WN',):
            raise DriveError(f'{address!r} is not an X-MIND K command or WN')
        if data_type.lower() == 'string':
            text = f'{self.number:02d}{code}' + (f',{value}' if str(value) else '')
        else:
            drive.register_type(data_type).check(int(value))
            extra = '' if code in ('CY', 'CN', 'RA', 'EE', 'ES') else f',{int(value)}'
            text = f'{self.number:02d}{address.strip().upper()}{extra}'
        try:
            frame = xk.parse_request(text, tolerant=False)
        except xk.ProtocolError as e:
            raise DriveError(f'{text!r}: {e} (the drive would answer N)') from None
        if self.job is not None and code not in xk.BUSY_CODES:
            raise DriveError(f'drive {self.number:02d} is busy: only EE and ES are heard (§3)')
        if code == 'PS':
            self._start(frame.args[0])
            now = time.monotonic()           # a stored program: busy until it answers again
            self.job = Job('program', None, Estimate.at_rest(now, self.position_steps),
                           math.inf, now + self.busy_poll_s)
            self.last_target = None
            return
        answer = self._need(frame.code, *frame.args)
        if answer.code != 'Y':
            raise DriveError(f'{text!r} answered {answer.code}')
        if code in xk.BUSY_CODES and self.job is not None:
            self.job.stopping = True
            self.job.estimate.stop(time.monotonic(), self.job.accel_hz_s)


# ---------------------------------------------------------------------------------- vendor
def make_bus(params: Mapping[str, Any]) -> XmindKBus:
    return XmindKBus(params)


def make_drive(bus: XmindKBus, name: str, params: Mapping[str, Any]) -> XmindKDrive:
    return XmindKDrive(bus, name, params)


PS = drive.ParamSpec
VENDOR = drive.Vendor(
    name='X-MIND K',
    params=(
        PS('port', '/dev/ttyUSB0', 'serial port of the RS-485 line (or a pyserial URL; the '
           "simulator's link path)", scope='bus'),
        PS('baudrate', 9600, 'the drive talks 9600 baud only (§3)', scope='bus',
           min_value=1200, max_value=115200),
        PS('parity', 'N', 'N (the drive has no parity bit, §3; ptys refuse E and O)',
           scope='bus', choices=('N', 'E', 'O')),
        PS('stopbits', 1, 'stop bits (1, §3)', scope='bus', min_value=1, max_value=2),
        PS('retries', 1, 'repeats of a string an idle drive left unanswered or answered '
           'garbled (never for PS)', scope='bus', min_value=0, max_value=5),
        PS('local_echo', False, 'the RS-485 adapter echoes what it sends: read and drop it',
           scope='bus'),
        PS('address', 0, 'drive address (§2.2.1, WS,AD)', min_value=0, max_value=47),
        PS('resolution', '', 'operation mode preset RS written at connect when it differs '
           "('' = leave as is); must match steps_per_rev", choices=('',) + tuple(xk.RESOLUTIONS)),
        PS('current_preset', -1, 'drive current preset IN: 0..3 = 55/70/85/100 % (-1 = leave)',
           min_value=-1, max_value=3),
        PS('answer_delay_ms', -1, 'answer delay preset RD in ms, also delays EE (§4.2.2.5; '
           '-1 = leave)', min_value=-1, max_value=255),
        PS('equalization', -1, 'equalization preset EQ 0/1 (-1 = leave)', min_value=-1,
           max_value=1),
        PS('power_cycle_flag', 'F7', "dummy output set to 1 at connect; read back 0 means the "
           "drive was power-cycled and lost its position ('' = off)",
           choices=('',) + tuple(f'F{i}' for i in range(8))),
        PS('busy_poll_period_s', 0.25, 'how often a busy (silent) drive is asked QA',
           min_value=0.01, max_value=10.0),
        PS('status_poll_period_s', 1.0, 'how often an idle drive is asked for FA and the '
           'power-cycle flag', min_value=0.05, max_value=60.0),
    ),
    make_bus=make_bus,
    make_drive=make_drive,
    drive_defaults={'steps_per_rev': 2000.0, 'homing.method': 3},   # RS D2 factory default
)
