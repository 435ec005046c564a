"""R.T.A. X-MIND K on its ASCII RS-485 line: `XmindKDrive` and `VENDOR` (the line itself is
`protocol.xmind_k_bus.XmindKBus`).

How the common contract maps onto the drive (docs/xmind_k.md has the full table):

- moves and free runs are written to the RAM cells 228-230 (`WN`) and started with `PS`; the
  EEPROM cells 100-227 are never written at run time, presets (`WS`) only when they differ;
- the drive answers nothing while it executes a program (§3), so while busy the position is
  estimated from the commanded profile (DriveState.position_estimated) and corrected by `QA` as
  soon as the drive answers again; velocity cannot be read at all (velocity_valid = False);
- a velocity change while running is stop (`ES`), wait until the drive answers, rewrite, restart;
- stop = `ES` for a free run (the only thing ES stops, §4.2.7), `EE` otherwise; quick stop = `EE`;
  a bus closed with drives in motion gets a broadcast `99EE`;
- enable = `CY`, disable = `CN` (not readable back, so tracked); what is checked on the wire
  before every start is FA (no protection) and the power-cycle flag (the drive still runs the
  power-on session in which it got CY); homing = zero search (03) plus counter reset (60);
  fault reset does not exist (RefusedError); every preset is already stored;
- every operation of more than one string is step-wise (drive.py): 0.0 is yielded between
  strings, waits are yields; `stop()` is one string. A 9600 baud string takes 20-50 ms.
- the drives of one line start together with `start_together` (a job for the bus owner): each
  run stored, then one broadcast `99PS` where every drive that hears it is known to hold what
  was stored for it (`broadcast_refusal`), else one `PS` per drive; `probe_line` asks the
  addresses no drive of the node has.

One file: the drive is silent while it runs a program (§3), so read_state, stop, a velocity
change and homing all work on the same running DriveProgram, its Estimate and the epoch.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Any, Callable, Mapping

from ...contract import drive, param_rules
from ...contract.drive import (
    DriveError,
    DriveState,
    HomingState,
    LinkError,
    Motion,
    RefusedError,
    State,
)
from ...protocol import serial_port
from ...protocol import xmind_k as xk
from ...protocol.xmind_k_bus import GarbledAnswer, XmindKBus
from . import scan as xmind_k_scan

logger = logging.getLogger(__name__)

MOVE_CELL = 228          # RAM (§4.1): indexed runs, and the zero search of a homing
RUN_CELL = 229           # RAM: free runs, and the counter reset after the zero search
HOMING_METHODS = {3: 'zero search (instruction 03) in + direction, then counter reset',
                  -3: 'zero search (instruction 03) in - direction, then counter reset',
                  60: 'counter reset at the current position (RA)'}
# A move on the line (move_time_s): the FA and power-cycle-flag check, WN 228 and PS 228, about 20
# characters a string and its answer, each answered after the turnaround and RD (§3).
MOVE_STRINGS = 4
MOVE_CHARS_PER_STRING = 20
RAMPED_MIN_HZ = min(xk.TABLE2_HZ.values())          # 3000 Hz: below, only unramped runs (§4.1.6)
RAMPED_MAX_HZ = max(xk.HR_RAMPED_X100) * 100        # 24000 Hz (§4.1.2)
FAULT_TEXT = ('FA output OFF: drive blocked by a protection (§2.2.4); X-MIND K has no fault '
              'reset command: clear the cause and power-cycle')
NO_FAULT_RESET = 'X-MIND K has no fault reset command; clear the cause and power-cycle'
STOP_WAIT_S = 3.0        # bound on waiting for a stopping drive to answer again
STOP_POLL_S = 0.02       # rate limit of that wait (nothing to wait on but the drive's answer)
# A new target for an index run that ends within this waits for its end (a trajectory's next
# segment), instead of stopping it and starting again: the drive takes no command while busy (§3).
QUEUE_BEHIND_S = 0.5
BUSY_POLL_SLACK_S = 0.03  # a drive that may be busy: a late answer is taken at the next poll


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
class DriveProgram:
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
def _check_address(name: str, number: int, taken: Mapping[str, int], url: str) -> None:
    """Address `number` of drive `name` is not one of `taken` (drive -> address), or
    ValueError."""
    for other, used in taken.items():
        if other != name and used == number:
            raise ValueError(f'parameter drives.{name}.address: {number:02d} is already used by '
                             f'drive {other} on {url} (allowed: a free address 0..47)')


def _check_drive(name: str, params: Mapping[str, Any]) -> None:
    """The rules of one drive's own parameters, or ValueError."""
    p = f'drives.{name}.'
    method = int(params['homing.method'])
    if method not in HOMING_METHODS:
        raise ValueError(f'parameter {p}homing.method: {method} is not an X-MIND K method '
                         '(allowed: ' + '; '.join(f'{k} = {v}' for k, v in
                                                  HOMING_METHODS.items()) + ')')
    resolution = str(params['resolution'])
    spr = float(params['steps_per_rev'])
    if resolution and spr != xk.RESOLUTIONS[resolution]:
        raise ValueError(f'parameter {p}steps_per_rev: {spr:g} does not match resolution '
                         f'{resolution} (allowed: {xk.RESOLUTIONS[resolution]}, §4.2.2.3)')


def validate(params: Mapping[str, Any]) -> list[str]:
    """The X-MIND K's parameter rules on the node's parameters (param_rules), at start-up and for
    every run-time change: one address per drive on the line, and per drive homing method and
    resolution. Pure: it never builds a drive (a drive records its address in bus.addresses)."""
    taken: dict[str, int] = {}
    url = str(params.get('port', ''))
    errors = []
    for name in param_rules.drive_names(params):
        number = int(param_rules.drive_params(params, name).get('address', 0))
        errors += param_rules.first_error(_check_address, name, number, taken, url)
        taken.setdefault(name, number)
    return errors + param_rules.check_each(params, None, _check_drive)


class XmindKDrive(drive.Drive):
    """One X-MIND K. Step-wise (drive.py): every operation of more than one string yields 0.0
    between its strings, and its waits yield; stop() is one string.

    `epoch` counts stops and motion commands: a step-wise start checks it before each string it
    writes, so a stop or a newer command that ran between its steps cancels the older start
    (nothing written to the drive after a stop that nobody commanded again)."""

    def __init__(self, bus: XmindKBus, name: str, params: Mapping[str, Any]):
        params = VENDOR.with_defaults(params)
        super().__init__(bus, name, params)
        self.number = int(params['address'])       # the drive address AA (§2.2.1)
        _check_address(name, self.number, bus.addresses, bus.url)
        _check_drive(name, params)
        self.resolution = str(params['resolution'])
        self.steps_per_rev = float(params['steps_per_rev'])
        self.presets_wanted = {k: v for k, v in (
            ('IN', int(params['current_preset'])), ('RD', int(params['answer_delay_ms'])),
            ('EQ', int(params['equalization']))) if v >= 0}
        self.flag = str(params['power_cycle_flag'])
        self.busy_poll_s = float(params['busy_poll_period_s'])
        self.status_poll_s = float(params['status_poll_period_s'])
        self.rd_ms: int | None = None          # answer delay, read at connect (§4.2.2.5)
        self.enabled = False                   # CY sent (current on/off is not readable)
        self.homed = False
        self.homing = HomingState.IDLE
        self.position_steps = 0
        self.fault = False
        self.error = (xk.ERROR_NONE, 0)        # QE at connect (a last-error register, §4.3.7)
        self.program_alarm = ''                # QE at connect, in words
        self.power_alarm = ''                  # a power cycle was seen: until the next homing
        self.job: DriveProgram | None = None
        self.pending: tuple | None = None      # ('move', target, Motion) | ('velocity', v, Motion)
        self.last_target: int | None = None
        self.next_status_s = 0.0
        self.epoch = 0                         # stops and motion commands so far (see above)
        self.stops = 0                         # stops and disables so far (GroupMove.stops)
        self.connects = 0                      # successful connects of this object
        self.may_end_at_zero = False           # a job lost with the link could end at 0
        # RAM cells whose content the drive confirmed (Y to WN) since it connected: what a
        # stored instruction execution (PS, and its broadcast) would run; a cell not here is
        # unknown (never written, a WN without its Y, a power cycle: §4.1 RAM)
        self.cells: dict[int, xk.Instruction] = {}
        bus.addresses[name] = self.number     # (the node also builds drives only to check)

    min_velocity_steps_s = 1.0            # Table 4: 0001..4800 Hz

    def move_time_s(self) -> float:
        rd_ms = self.rd_ms if self.rd_ms is not None else int(self.params['answer_delay_ms'])
        rd_s = (rd_ms if rd_ms >= 0 else xk.RD_DEFAULT_MS) / 1000.0
        return (MOVE_STRINGS * (MOVE_CHARS_PER_STRING * self.bus.char_s + xk.TURNAROUND_S + rd_s)
                + xk.TURNAROUND_WN_S)

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
                             f'{self._text(code, *args)!r} (syntax or range, §4.4.2)')
        return answer

    def _text(self, code: str, *args) -> str:
        return xk.encode_request(xk.Frame(self.number, code, args)).decode().rstrip('\r')

    def _identify(self, code: str, *args, expected: str, silence_ok: bool = False
                  ) -> xk.Frame | None:
        """A data request at connect: its §4.3 answer, or LinkError naming the request and the
        bytes read (the node reconnects with its normal back-off). An answer that breaks the
        §4.3 format (a character outside it, a wrong field count, Y, an echo of the request)
        is a garbled line, not another device; so is N: every idle X-MIND K answers these
        requests, and a request garbled on its way draws N (§4.4.2). Silence raises LinkError
        too, or gives None with silence_ok (a busy drive is silent, §3). IdentityError is
        for well-formed answers that name another device (connect: AD, RS)."""
        nn = f'{self.number:02d}'
        request = self._text(code, *args)
        try:
            answer = self._ask(code, *args, tries=max(2, 1 + self.bus.retries))
        except GarbledAnswer as e:
            read = ', '.join(repr(a) for a in e.answers)
            echo = (' (the request itself: an adapter that echoes what it sends needs '
                    'local_echo: true)' if any(a.rstrip(xk.TERMINATOR) == request.encode()
                                               for a in e.answers) else '')
            raise LinkError(f'drive {nn}: {request!r} was answered {read}, not the §4.3 answer '
                            f'{expected!r}: a garbled answer on {self.bus.url}{echo}') from None
        if answer is None:
            if silence_ok:
                return None
            raise LinkError(f'drive {nn} did not answer {code} on {self.bus.url}')
        if answer.code == 'N':
            raise LinkError(
                f'drive {nn}: {request!r} was answered N (§4.4.2), expected {expected!r}: every '
                'X-MIND K answers this data request (§4.3), so the request was garbled on '
                f'{self.bus.url}, or the device at address {nn} is not an X-MIND K')
        return answer

    def _command(self, code: str, *args) -> None:
        answer = self._need(code, *args)
        if answer.code != 'Y':
            raise DriveError(f'drive {self.number:02d} answered {answer} to {code}')

    def _store(self, cell: int, instr: xk.Instruction) -> None:
        """WN: `instr` into `cell`. The cell counts as known (`cells`) only once the drive
        confirmed it with Y (§4.4.1); while the string is out, and after N, silence or a garbled
        answer (a lost reply may have reached the drive), its content is unknown."""
        self.cells.pop(cell, None)
        self._command('WN', cell, instr)
        self.cells[cell] = instr

    def _launch(self, cell: int, make_job: Callable[[float], DriveProgram]) -> None:
        """PS: never repeated (a lost Y would make the repeat land on a busy drive), so its one
        try waits as long as the last repeat of another string would: a Y late by a hiccup of
        the adapter or the host is still taken. The job is recorded before PS leaves: a lost
        answer is taken as a started program (the bus then closes with 99EE), §3."""
        self.job = make_job(time.monotonic())
        try:
            answer = self._ask('PS', cell, tries=1, slack_s=self.bus.last_try_slack_s)
        except GarbledAnswer:
            answer = xk.Frame(self.number, 'Y')   # the drive refuses PS only for syntax
        if answer is None:
            raise LinkError(f'drive {self.number:02d} did not answer PS,{cell} on '
                            f'{self.bus.url}; taken as started')
        if answer.code != 'Y':
            self.job = None
            raise DriveError(f'drive {self.number:02d} refused PS,{cell}')
        self.job = make_job(time.monotonic())    # the estimate starts at the drive's Y

    def _superseded(self, epoch: int) -> bool:
        """A stop or a newer command ran between the steps of this one (or another started a
        program): this one writes nothing more."""
        return self.epoch != epoch or self.job is not None

    @property
    def address(self) -> str:
        return f'{self.number:02d}'       # as the manual writes it (status 'address')

    @property
    def in_motion(self) -> bool:
        return self.job is not None

    # ------------------------------------------------------------------------------ life cycle
    def connect(self) -> drive.Operation[dict[str, str]]:
        self.bus.drives[self.name] = self
        if self.job is not None:             # lost with the link: it may have ended at 0
            self.may_end_at_zero = self.job.kind in ('homing', 'program') or self.job.goal == 0
        self.job, self.pending = None, None
        self.epoch += 1
        self.rd_ms = None
        self.cells.clear()                   # RAM cells: unknown after a link loss (§4.1)
        nn = f'{self.number:02d}'
        rs_form = f'{nn}QS,RS,<D0..D3|B0..B3>'
        answer = self._identify('QS', 'RS', expected=rs_form, silence_ok=True)
        if answer is None:
            yield from self._stop_unknown_program()
            answer = self._identify('QS', 'RS', expected=rs_form)
        rs = answer.args[1]
        yield 0.0
        ad = self._identify('QS', 'AD', expected=f'{nn}QS,AD,{nn}').args[1]
        if ad != self.number:
            # The answer has no checksum: a digit garbled into another is asked again.
            yield 0.0
            again = self._identify('QS', 'AD', expected=f'{nn}QS,AD,{nn}').args[1]
            if again != ad:
                raise LinkError(f'drive {nn}: QS,AD answered {ad:02d}, then {again:02d}: '
                                f'garbled answers on {self.bus.url}')
            # §4.2.2.1: a drive answers at the address of its AD preset, and only there
            raise drive.IdentityError(
                f'drive {nn}: QS,AD answered {ad:02d}, expected {nn}: the device answering at '
                f'address {nn} on {self.bus.url} does not have that address preset, so it is '
                'not an X-MIND K')
        if self.resolution and rs != self.resolution:
            logger.warning('%s: drive %s runs RS %s, writing %s (current off >= 200 ms, '
                           '§4.2.2.3)', self.name, nn, rs, self.resolution)
            yield 0.0
            self._command('WS', 'RS', self.resolution)
            yield xk.RS_SILENT_S                 # deaf meanwhile (§4.2.2.3 Note 2)
            yield from self._wait_answering(STOP_WAIT_S)
            rs = self.resolution
        if xk.RESOLUTIONS[rs] != self.steps_per_rev:
            raise drive.IdentityError(
                f'drive {nn}: QS,RS answered {rs} = {xk.RESOLUTIONS[rs]} step/rev but '
                f'drives.{self.name}.steps_per_rev is {self.steps_per_rev:g}: not the '
                f'configured drive; set one of them (resolution: {rs} writes it, §4.2.2.3)')
        presets = {'RS': rs}
        for preset in ('RD', 'CM', *[k for k in self.presets_wanted if k != 'RD']):
            yield 0.0
            value = self._identify('QS', preset, expected=f'{nn}QS,{preset},<value>').args[1]
            want = 0 if preset == 'CM' else self.presets_wanted.get(preset)
            if want is not None and value != want:
                # EEPROM: written only when it differs (§4.2.2: every preset is stored)
                logger.warning('%s: drive %s preset %s is %s, writing %s', self.name, nn,
                               preset, value, want)
                yield 0.0
                self._command('WS', preset, want)
                value = want
            presets[preset] = value
            if preset == 'RD':
                self.rd_ms = int(value)
        yield 0.0
        qe = self._identify('QE', expected=f'{nn}QE,<EC>,<BBB>').args
        self.error = (qe[0], qe[1])
        self.program_alarm = '' if qe[0] == xk.ERROR_NONE else \
            f'last program error {qe[0]:02d} {xk.ERROR_TEXT.get(qe[0], "")} at cell {qe[1]:03d}'
        yield 0.0
        self.fault = self._identify('QO', 'FA', expected=f'{nn}QO,FA,<0|1>').args[1] == 0
        flag_lost = False
        if self.flag:
            yield 0.0
            flag_lost = self._identify('QO', self.flag,
                                       expected=f'{nn}QO,{self.flag},<0|1>').args[1] == 0
            if flag_lost:
                # Flags are 0 at power-on (§8 A17 reading): a new drive or a power cycle.
                # Current is ON (§4.2.3) but not enabled by this node, the counter restarted
                # at 0. Recorded before the flag is set again (a failed connect is retried).
                self.enabled, self.homed, self.homing = False, False, HomingState.IDLE
                if self.connects:
                    self._power_cycled(f'flag {self.flag} was 0 at reconnect')
                yield 0.0
                self._command('SO', self.flag, 1)
        yield 0.0
        position = self._identify('QA', expected=f'{nn}QA,<+-n>').args[0]
        reconnect, self.connects = self.connects > 0, self.connects + 1
        if reconnect and not self.flag and position == 0 and self.position_steps != 0 \
                and not self.may_end_at_zero:
            self._power_cycled(f'the position counter read 0 at reconnect, was '
                               f'{self.position_steps} steps (§4.3.1 counts from power-on)')
        self.position_steps, self.may_end_at_zero = position, False
        self.next_status_s = time.monotonic() + self.status_poll_s
        return {'address': nn,
                **{k: str(v) for k, v in presets.items()},
                'steps_per_rev': str(xk.RESOLUTIONS[rs]),
                'FA': '0 (protection)' if self.fault else '1',
                'QE': f'{qe[0]:02d},{qe[1]:03d}',
                'current': 'ON' if self.enabled else 'not enabled by this node (not readable)'}

    def _power_cycled(self, why: str) -> None:
        """The drive restarted: counter at 0 (§4.3.1), current ON by default (§4.2.3) but not
        enabled by this node; the position reference is gone until the next homing."""
        logger.warning('%s: drive %02d was power-cycled (%s): position reference lost, current '
                       'ON by default (§4.2.3); enable and home again', self.name, self.number,
                       why)
        self.enabled, self.homed, self.homing = False, False, HomingState.IDLE
        self.cells.clear()                   # RAM cells 228-230 lost with the power (§4.1)
        self.power_alarm = f'power cycle detected ({why}): position reference lost, home again'

    def _stop_unknown_program(self) -> drive.Operation[None]:
        """Silent at connect: busy with something we did not start, or absent. EE is answered
        even by a busy drive (§3); after a reconnect nothing may go on moving by itself."""
        answer = self._ask('EE')
        if answer is None:
            raise LinkError(f'drive {self.number:02d} does not answer on {self.bus.url} '
                            '(QS,RS and EE unanswered)')
        logger.warning('%s: drive %02d was busy at connect: sent EE', self.name, self.number)
        yield STOP_POLL_S
        yield from self._wait_answering(STOP_WAIT_S)

    def _wait_answering(self, timeout_s: float) -> drive.Operation[xk.Frame]:
        """Poll QA until the drive answers again (it is silent while busy or after WS,RS)."""
        deadline = time.monotonic() + timeout_s
        while True:
            answer = self._poll_busy()
            if answer is not None and answer.code == 'QA':
                return answer
            if time.monotonic() > deadline:
                raise LinkError(f'drive {self.number:02d} still silent after {timeout_s:g} s')
            yield STOP_POLL_S

    def _wait_idle(self, timeout_s: float) -> drive.Operation[None]:
        """Until the job (being stopped) ends: its estimated end first, then QA polls; a poll
        running between these steps may end it too."""
        deadline = time.monotonic() + timeout_s
        while self.job is not None:
            now = time.monotonic()
            if now > deadline:
                raise LinkError(f'drive {self.number:02d} still silent {timeout_s:g} s after '
                                'the stop')
            yield min(max(self.job.estimate.end_s - now, STOP_POLL_S), deadline - now)
            if self.job is None:
                return
            answer = self._poll_busy()
            if answer is not None and answer.code == 'QA':
                self._job_ended(answer.args[0])

    # ------------------------------------------------------------------------------ read state
    def read_state(self) -> drive.Operation[DriveState]:
        """Up to 7 strings (QA, SA after a homing, QO,FA, QO,flag and SO, WN and PS of a
        pending start), one or two per step; a step that finds another operation in charge
        (a command or stop ran between the steps) ends the poll with what it has."""
        now = time.monotonic()
        epoch = self.epoch
        job = self.job
        if job is not None:
            if now < job.next_poll_s:
                return self._state(now)
            answer = self._poll_busy()
            if answer is None or answer.code != 'QA':
                job.next_poll_s = now + self.busy_poll_s        # silent: still busy (§3)
                if self._overdue(job, now):
                    yield 0.0
                    if self.job is job:
                        self._check_alive(job, now)
                return self._state(time.monotonic())
            self._job_ended(answer.args[0])       # with SA of a homing offset: same step
        else:
            position = self._need('QA').args[0]
            if position == 0 and self.position_steps != 0:
                # §4.3.1: the counter restarts at 0 at power-on, and nothing this node sent
                # moved it: ask the flag now, or without one take it as a power cycle
                if self.flag:
                    self.next_status_s = 0.0
                else:
                    self._power_cycled(f'the position counter read 0, was '
                                       f'{self.position_steps} steps (§4.3.1)')
            self.position_steps = position
        if self.job is None and (now >= self.next_status_s or self.pending is not None):
            yield 0.0
            if self.epoch != epoch or self.job is not None:
                return self._state(time.monotonic())
            yield from self._read_status()
        if self.job is None and self.pending is not None:
            yield 0.0
            if self.epoch == epoch and self.job is None and self.pending is not None:
                yield from self._start_pending()
        return self._state(time.monotonic())

    def _overdue(self, job: DriveProgram, now: float) -> bool:
        """A move long overdue: busy or gone? (not for free runs or homing, see below)"""
        return job.kind == 'move' and not job.stopping and now >= job.estimate.end_s + 1.0 \
            and now >= job.pinged_s + 1.0

    def _check_alive(self, job: DriveProgram, now: float) -> None:
        """ES is answered even when busy and does nothing to an indexed run (§4.2.7), so it
        tells a busy drive from a gone one."""
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
        self.power_alarm = ''

    def _read_status(self) -> drive.Operation[None]:
        """QO,FA and the power-cycle flag (SO,flag,1 when it was lost): the on-the-wire check
        before every start, as current on/off cannot be read (§4.2.3): the drive is not
        blocked by a protection and still runs the power-on session in which it got CY."""
        self.next_status_s = time.monotonic() + self.status_poll_s
        self.fault = self._need('QO', 'FA').args[1] == 0
        if not self.flag:
            return
        yield 0.0
        if self.job is not None:
            return                         # a start between the steps: the drive is busy
        if self._need('QO', self.flag).args[1] == 0:
            # Flags are 0 at power-on: the drive was power-cycled, its counter restarted at 0.
            self._power_cycled(f'flag {self.flag} was 0')
            self._command('SO', self.flag, 1)

    def _require_enabled(self, what: str) -> None:
        self._refuse_in_fault(what)
        if not self.enabled:
            raise DriveError(
                f'{what}: drive {self.number:02d} is not enabled (no CY from this node since it '
                'connected or the drive was power-cycled; current on/off cannot be read back, '
                '§4.2.3): call enable first' + (f'; {self.power_alarm}' if self.power_alarm
                                                else ''))

    def _refuse_in_fault(self, what: str) -> None:
        if self.fault:
            raise DriveError(f'{what}: {FAULT_TEXT}')

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
            alarms=tuple(a for a in (self.power_alarm, self.program_alarm) if a), mode=mode,
            status_word=0, position_steps=int(round(position)), velocity_steps_s=velocity,
            velocity_valid=False, position_estimated=job is not None)

    # -------------------------------------------------------------------------------- power
    def enable(self) -> drive.Operation[None]:
        self._refuse_busy('enable')
        yield from self._read_status()       # a power cycle or a protection shows before CY
        yield 0.0
        self._refuse_busy('enable')
        self._refuse_in_fault('enable')
        self._command('CY')                  # §4.2.3; nothing moves
        self.enabled = True

    def _refuse_busy(self, what: str) -> None:
        if self.job is not None:
            raise DriveError(f'{what}: drive {self.number:02d} is busy ({self.job.kind}); it '
                             'answers only EE and ES until the program ends (§3)')

    def disable(self) -> drive.Operation[None]:
        self.epoch += 1
        self.stops += 1
        self.pending = None
        self.enabled = False                 # refuse motion from now, whatever comes of CN
        if self.job is not None:             # CN is not heard by a busy drive (§3)
            self._stop_job(quick=True)
            yield from self._wait_idle(STOP_WAIT_S)
            yield 0.0
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
        if not math.isfinite(f):
            raise DriveError(f'{v_hz} Hz is not a step frequency (X-MIND K: 1..{RAMPED_MAX_HZ} '
                             'Hz)')
        if f > RAMPED_MAX_HZ:
            raise DriveError(f'{f:.0f} Hz exceeds the X-MIND K maximum of {RAMPED_MAX_HZ} Hz '
                             '(field FFF 030..240 x 100 Hz of instructions 31/32, §4.1.2)')
        if f < 1.0:
            raise DriveError(f'{f:.3g} Hz is below the X-MIND K minimum of 1 Hz (field FFFF '
                             '0001..4800 Hz of instructions 21/22, Table 4)')
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

    def _check_target(self, target_steps: Any) -> int:
        """The node computes targets in relative mode (§5.1): they must be positions the
        32-bit counter can show (QA, §4.3.1), else a chain of index runs would never end."""
        try:
            target = int(target_steps)
        except (OverflowError, ValueError):
            target = None
        if target is None or not xk.COUNTER_MIN <= target <= xk.COUNTER_MAX:
            raise DriveError(f'move to {target_steps} steps: outside the X-MIND K position '
                             f'counter range {xk.COUNTER_MIN}..{xk.COUNTER_MAX} (QA, §4.3.1, '
                             '§5.1)')
        return target

    def move_to(self, target_steps: int, motion: Motion) -> drive.Operation[None]:
        target = self._check_target(target_steps)
        self.run_instruction('move', motion.velocity_steps_s, motion, 1)   # ranges, no wire
        self._require_enabled('move')
        job = self.job
        if self.pending == ('move', target, motion) or (
                job is not None and job.kind == 'move' and not job.stopping
                and job.goal == target and self.pending is None):
            return           # the same target again (a streaming command): nothing to send
        self.epoch += 1
        self.last_target = target
        if job is not None and job.kind == 'move' and not job.stopping and self.pending is None \
                and job.estimate.end_s - time.monotonic() <= QUEUE_BEHIND_S:
            epoch = self.epoch
            ended = yield from self._await_index_end(job, epoch)
            if self.epoch != epoch:
                return                       # a stop or a newer command came meanwhile
            if ended and self.pending is None:
                yield from self._start_move(target, motion, epoch)
                return
            job = self.job                   # still busy well past its end: stop, restart
        if job is not None or self.pending is not None:
            self.pending = ('move', target, motion)
            if job is not None and not job.stopping:
                self._stop_job(quick=False)      # stop, then rewrite and restart (read_state)
            return
        yield from self._start_move(target, motion, self.epoch)

    def until_ready_for_move(self) -> drive.Operation[bool] | None:
        """An index run that ends within QUEUE_BEHIND_S: until it has ended (the next one then
        starts without a stop, §3)."""
        job = self.job
        if job is None or job.kind != 'move' or job.stopping or self.pending is not None \
                or job.estimate.end_s - time.monotonic() > QUEUE_BEHIND_S:
            return None
        return self._await_index_end(job, self.epoch)

    def _await_index_end(self, job: DriveProgram, epoch: int) -> drive.Operation[bool]:
        """Until `job`, an index run about to end, has ended (QA answers again, §3): True; False
        when a stop or another command came meanwhile, or it is still busy QUEUE_BEHIND_S past
        its estimated end."""
        while self.job is job:
            now = time.monotonic()
            if now > job.estimate.end_s + QUEUE_BEHIND_S:
                return False
            yield max(job.estimate.end_s - now, STOP_POLL_S)
            if self.epoch != epoch:
                return False
            if self.job is not job:
                break
            answer = self._poll_busy()
            if answer is not None and answer.code == 'QA':
                self._job_ended(answer.args[0])
        return self.epoch == epoch and self.job is None

    def _start_move(self, target: int, motion: Motion, epoch: int, checked: bool = False
                    ) -> drive.Operation[None]:
        """[FA, flag,] WN 228, PS 228: one index of at most +-8388607 steps (§4.1.2)."""
        if not checked:
            yield from self._read_status()
            yield 0.0
            if self._superseded(epoch):
                return
        self._require_enabled('move')
        start = self.position_steps
        delta = target - start
        if delta == 0:
            return
        chunk = max(-xk.STEPS_MAX, min(xk.STEPS_MAX, delta))
        instr, f, a = self.run_instruction('move', motion.velocity_steps_s, motion, chunk)
        self._store(MOVE_CELL, instr)
        yield 0.0
        if self._superseded(epoch):
            return

        def job(t: float) -> DriveProgram:
            estimate = Estimate.index(t, start, chunk, f, a)
            return DriveProgram('move', instr, estimate, a, estimate.end_s,
                                target_steps=start + chunk,
                       final_target_steps=target if chunk != delta else None, motion=motion)
        self._launch(MOVE_CELL, job)

    def set_velocity(self, velocity_steps_s: float, motion: Motion) -> drive.Operation[None]:
        v = velocity_steps_s
        if not math.isfinite(v):
            raise DriveError(f'velocity {v} steps/s is not a step frequency')
        if abs(v) < 1.0:                     # a stop: always allowed
            self.epoch += 1
            self.pending = None
            if self.job is not None and not self.job.stopping:
                self._stop_job(quick=False)
            return
        instr = self.run_instruction('velocity', v, motion)[0]
        self._require_enabled('velocity')
        job = self.job
        if job is not None and job.kind == 'velocity' and job.instruction == instr \
                and not job.stopping:
            self.pending = None
            return           # already running just so: nothing to send
        self.epoch += 1
        self.last_target = None
        if job is not None or self.pending is not None:
            self.pending = ('velocity', v, motion)
            if job is not None and not job.stopping:
                self._stop_job(quick=False)          # stop, then rewrite and restart
            return
        yield from self._start_run(v, motion, self.epoch)

    def _start_run(self, v: float, motion: Motion, epoch: int, checked: bool = False
                   ) -> drive.Operation[None]:
        """[FA, flag,] WN 229, PS 229: a free run (§4.1.4 / §4.1.8)."""
        if not checked:
            yield from self._read_status()
            yield 0.0
            if self._superseded(epoch):
                return
        self._require_enabled('velocity')
        instr, f, a = self.run_instruction('velocity', v, motion)
        self._store(RUN_CELL, instr)
        yield 0.0
        if self._superseded(epoch):
            return
        start = self.position_steps
        self._launch(RUN_CELL, lambda t: DriveProgram(
            'velocity', instr, Estimate.run(t, start, math.copysign(f, v), a), a,
            t + self.busy_poll_s))

    def _start_pending(self) -> drive.Operation[None]:
        """The command that waited for the stop of the previous job (from read_state, which
        has just read FA and the flag)."""
        kind, value, motion = self.pending
        self.pending = None
        start = self._start_move if kind == 'move' else self._start_run
        try:
            yield from start(value, motion, self.epoch, checked=True)
        except LinkError:
            raise
        except DriveError as e:
            self.last_target = None
            raise DriveError(f'{kind} command not started after the stop: {e}') from None

    def stop(self, quick: bool = False) -> None:
        """One string at most (EE or ES); cancels a start between its steps (epoch)."""
        self.epoch += 1
        self.stops += 1
        self.pending = None
        self.last_target = None              # at rest after a stop = target reached (CiA 402)
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

    # -------------------------------------------------------------------------------- homing
    def start_homing(self, homing: drive.Homing) -> drive.Operation[str]:
        self._refuse_busy('home')
        p = f'drives.{self.name}.homing.'
        offset = homing.offset_steps
        if not xk.COUNTER_MIN <= offset <= xk.COUNTER_MAX:
            raise DriveError(f'{p}offset = {offset} steps is outside the position counter '
                             f'range {xk.COUNTER_MIN}..{xk.COUNTER_MAX} (SA, §4.2.9)')
        if homing.method != 60:
            search, reset, note = self._zero_search(homing, p)
        self._require_enabled('home')
        self.epoch += 1
        epoch = self.epoch
        self.pending = None
        self.last_target = None
        yield from self._read_status()       # on the wire: no protection, no power cycle
        yield 0.0
        if self._superseded(epoch):
            raise DriveError('home: cut short by a stop or a newer command')
        self._require_enabled('home')
        if homing.method == 60:
            if offset:
                self._command('SA', offset)
            else:
                self._command('RA')
            self.position_steps = offset
            self._homed()
            return f'{HOMING_METHODS[60]}' + (f', then SA {offset}' if offset else '')
        self._store(MOVE_CELL, search)        # §7.6: zero search, then counter reset
        yield 0.0
        if self._superseded(epoch):
            raise DriveError('home: cut short by a stop or a newer command')
        self._store(RUN_CELL, reset)
        yield 0.0
        if self._superseded(epoch):
            raise DriveError('home: cut short by a stop or a newer command')
        a = xk.ramp_acceleration_hz_s(search.params[1])
        v = xk.TABLE2_HZ[search.params[0]] * (1 if search.params[2] == '+' else -1)
        start = self.position_steps
        self._launch(MOVE_CELL, lambda t: DriveProgram(
            'homing', search, Estimate.run(t, start, v, a), a, t + self.busy_poll_s,
            target_steps=offset))
        self.homed, self.homing = False, HomingState.RUNNING
        return note

    def _zero_search(self, homing: drive.Homing, p: str
                     ) -> tuple[xk.Instruction, xk.Instruction, str]:
        """Instruction 03 into cell 228 chained to 60 in 229 (§4.1.9, §4.1.20)."""
        ff = int(homing.speed_search_steps_s // 1000) \
            if math.isfinite(homing.speed_search_steps_s) else 0
        if ff not in xk.TABLE2_HZ:
            raise DriveError(f'{p}speed_search = {homing.speed_search_steps_s:.0f} Hz is outside '
                             'the zero search fast speeds 3000..24000 Hz (field FF, Table 2)')
        ll = int(homing.speed_zero_steps_s // 100) \
            if math.isfinite(homing.speed_zero_steps_s) else 0
        if ll not in xk.TABLE3_HZ:
            raise DriveError(f'{p}speed_zero = {homing.speed_zero_steps_s:.0f} Hz is outside the '
                             'zero search approach speeds 200..3000 Hz (field LL, Table 3)')
        rr = self.ramp_code(homing.acceleration_steps_s2)
        direction = '+' if homing.method > 0 else '-'
        search = xk.Instruction.make(3, RUN_CELL, frequency_code=ff, ramp_code=rr,
                                     direction=direction, slow_code=ll)
        reset = xk.Instruction.make(60, xk.END_OF_PROGRAM)
        offset = homing.offset_steps
        note = (f'zero search {direction} at {xk.TABLE2_HZ[ff]} Hz (ramp {rr}), approach '
                f'{xk.TABLE3_HZ[ll]} Hz, then counter reset'
                + (f' and SA {offset}' if offset else ''))
        return search, reset, note

    # --------------------------------------------------------------------------- maintenance
    def fault_reset(self) -> str:
        if self.job is None:
            self.fault = self._need('QO', 'FA').args[1] == 0
        if self.fault:
            raise RefusedError(NO_FAULT_RESET)
        return ''

    def save_params(self) -> drive.Operation[str]:
        if self.job is not None:
            raise DriveError(f'drive {self.number:02d} is busy; presets cannot be read back')
        values = []
        for i, preset in enumerate(xk.PRESETS):
            if i:
                yield 0.0
                if self.job is not None:
                    raise DriveError(f'drive {self.number:02d} became busy; presets read so '
                                     f'far: {", ".join(values)}')
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
            try:
                return xk.encode_answer(answer).decode().rstrip('\r')
            except xk.ProtocolError:       # §8 A12: QS,CM answers 2 without its kkk
                return ','.join([f'{self.number:02d}{code}',
                                 *(str(a) for a in answer.args if a is not None)])
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
        if code == 'WN':
            self.cells.pop(frame.args[0], None)     # written behind the node's back: unknown
        if code == 'PS':                     # a stored program: busy until it answers again
            self.epoch += 1
            self.last_target = None
            position = self.position_steps
            self._launch(frame.args[0], lambda t: DriveProgram(
                'program', None, Estimate.at_rest(t, position), math.inf, t + self.busy_poll_s))
            return
        answer = self._need(frame.code, *frame.args)
        if answer.code != 'Y':
            raise DriveError(f'{text!r} answered {answer.code}')
        if code in xk.BUSY_CODES and self.job is not None:
            self.job.stopping = True
            self.job.estimate.stop(time.monotonic(), self.job.accel_hz_s)
        # what this node tracks because the drive cannot be asked (§4.2.3, §4.3.1)
        if code in ('CY', 'CN'):
            self.enabled = code == 'CY'
        elif code in ('RA', 'SA'):
            self.position_steps = frame.args[0] if code == 'SA' else 0


# ------------------------------------------------------------------------- group start
# The joints of one trajectory on one line start a segment in the same instant: each drive's run
# is stored in its cell MOVE_CELL (WN, each confirmed by Y), then one broadcast stored
# instruction execution 99PS,228 starts them all (§4.2.5 "Broadcast transmission is allowed",
# §2.2.1 "recognized and executed by all X-MIND K series drives connected to serial line",
# no answer: §4.4.3). The broadcast reaches every X-MIND K on the line, driven by this node or
# not, and runs whatever its cell 228 holds: the manual says nothing of an empty cell, of a drive
# with its current off (CN) or blocked by a protection, and cells 228-230 are RAM of unknown
# content after power-on (§4.1). So it is sent only when every drive that can hear it is known
# to hold exactly what this start stored (`broadcast_refusal`); otherwise each drive gets its
# own PS, one after the other, as a single move does.
NULL_INSTRUCTION = xk.Instruction.make(0)      # §4.1.13 null: a drive that stays where it is
PROBE_ADDRESSES = range(xk.ADDRESS_MIN, xk.ADDRESS_MAX + 1)


@dataclasses.dataclass(frozen=True)
class GroupMove:
    """One drive's part of a group start: where to and with which profile (as move_to).
    `stops`: the drive's `stops` when the caller decided on this move (before it queued the
    job): a stop or disable of the drive since leaves it out. The job is queued under one drive
    of the line, so another drive's stop does not drop it as it drops that drive's own jobs."""

    drive: 'XmindKDrive'
    target_steps: int
    motion: Motion
    stops: int | None = None


@dataclasses.dataclass
class GroupStart:
    """What start_together did. `broadcast`: one 99PS started every drive of `started`;
    otherwise `why_not` says what the node could not make sure of, and each got its own PS.
    `skipped`: drive name -> why it was not started (a stop or a newer command between the
    steps, not enabled, in fault, a WN without its Y); `sent_t`: when the string that started
    the (last) drive was on the wire (time.monotonic()); `skew_s`: how far apart the started
    drives begin by their answer delays RD (§4.2.2.5: RD delays the execution too)."""

    broadcast: bool
    why_not: str
    started: tuple[str, ...]
    skipped: dict[str, str]
    sent_t: float | None
    skew_s: float = 0.0


def probe_line(bus: XmindKBus, rd_ms: float = xk.RD_MAX_MS, slack_s: float | None = None,
               addresses: Any = None) -> drive.Operation[frozenset[int]]:
    """Step-wise: ask every address 00..47 that no drive of this node has (QS,AD, §4.3.2, one
    string each, nothing that moves or writes) and return those that answered. A drive's
    answer delay RD is unknown (§4.2.2.5, up to 255 ms): each waits for that by default. Only a
    probe of all of 00..47 counts for broadcasts (bus.line_probe); any answer, full probe or
    not, blocks them until the bus is opened again (bus.foreign). A busy or switched-off drive
    is silent (§4.4.3): the probe cannot prove the line empty, which is why broadcasts also
    need the user's broadcast_start."""
    ours = set(bus.addresses.values())
    full = addresses is None
    todo = [a for a in (PROBE_ADDRESSES if full else addresses) if a not in ours]
    heard = set()
    for i, address in enumerate(todo):
        if i:
            yield 0.0
        try:
            answer = bus.request(xk.Frame(address, 'QS', ('AD',)), rd_ms, tries=1,
                                 retry_silence=False, slack_s=slack_s)
        except GarbledAnswer:
            answer = True                      # something answered at that address
        if answer is not None:
            heard.add(address)
            bus.foreign.add(address)
            logger.warning('%s: address %02d answered, no drive of this node has it: no '
                           'broadcast starts on this line', bus.url, address)
    if full:
        bus.line_probe = frozenset(heard)
    return frozenset(heard)


def line_refusal(bus: XmindKBus, names: Any) -> str:
    """What stops a broadcast on `bus` for a start of the drives `names`, from what is known
    without the wire ('' = nothing): the user's word, the probe, and that every drive this node
    has on the line takes part (a drive of the node left out would run its cell 228 again: its
    last move, relative, §5.1)."""
    if not bus.broadcast_start:
        return ('broadcast_start is false (the line may carry X-MIND K drives this node does not '
                'drive, and a broadcast starts them all, §2.2.1)')
    if bus.foreign:
        return (f'address(es) {", ".join(f"{a:02d}" for a in sorted(bus.foreign))} answered '
                'on this line and no drive of this node has them')
    if bus.line_probe is None:
        return 'the line has not been probed for other drives since it was opened (probe_line)'
    left_out = sorted(set(bus.addresses) - set(names))
    if left_out:
        return (f'drive(s) {", ".join(left_out)} of this line take no part in the start: a '
                'broadcast would run their cell 228 too')
    return ''


def broadcast_refusal(bus: XmindKBus, stored: Mapping[str, xk.Instruction],
                      epochs: Mapping[str, int]) -> str:
    """Checked in the step that sends the broadcast (nothing else reaches the line between):
    line_refusal, and every drive of the line is one of `stored` (name -> the instruction it
    confirmed in MOVE_CELL during this start), connected to this node, idle, enabled, not in
    fault, nothing commanded to it since the start began (`epochs`), and its cell still the
    one confirmed. '' when the broadcast can go."""
    why = line_refusal(bus, stored)
    if why:
        return why
    for name in bus.addresses:
        d = bus.drives.get(name)
        if d is None:
            return f'drive {name} never connected: what it holds is unknown'
        if d.epoch != epochs.get(name) or d.job is not None or d.pending is not None:
            return f'drive {name}: a stop or another command came during the start'
        if not d.enabled or d.fault:
            return f'drive {name} is not enabled or in fault'
        if d.cells.get(MOVE_CELL) != stored[name]:
            return f'drive {name}: cell {MOVE_CELL} is not confirmed to hold this start'
    return ''


def start_together(moves: Any) -> drive.Operation[GroupStart]:
    """Step-wise, for the bus owner (one job): start the GroupMoves, all drives of one line, in
    the same instant where that can be made safe, else one after the other.

    1. As move_to would refuse (no wire): a target outside the counter, a profile outside the
       tables, a drive not enabled or in fault. A drive whose index run ends within
       QUEUE_BEHIND_S is waited for; one still busy then goes the way of move_to (stop, restart)
       and takes no part.
    2. Per drive: FA and the power-cycle flag on the wire (as every start), then WN 228 with its
       run, or the null instruction where it stays put (only when a broadcast is possible: a
       drive left with its last run in 228 would run it again).
    3. One step: broadcast_refusal; '' -> the jobs are recorded, then 99PS,228 (no answer, so
       it is taken as heard: a lost broadcast shows as a drive that did not move). Else PS,228
       to each drive whose run is confirmed, as a single move starts (a lost Y is taken as
       started). A drive that a stop or another command reached between the steps is not
       started; nor one whose WN got no Y (its cell is unknown)."""
    moves = list(moves)
    if not moves:
        return GroupStart(False, 'no moves', (), {}, None)
    bus = moves[0].drive.bus
    if any(m.drive.bus is not bus for m in moves) or \
            len({m.drive.name for m in moves}) != len(moves):
        raise DriveError('start_together: one move per drive, all drives on one line')
    skipped: dict[str, str] = {}
    stops = {m.drive.name: m.drive.stops if m.stops is None else m.stops for m in moves}

    def leave_out_stopped(moves: list) -> list:
        for m in moves:
            if m.drive.stops != stops[m.drive.name]:
                skipped[m.drive.name] = 'stopped or disabled after this start was decided'
        return [m for m in moves if m.drive.name not in skipped]

    moves = leave_out_stopped(moves)
    targets = {}
    for m in moves:                                      # 1. refusals, no wire
        d = m.drive
        targets[d.name] = d._check_target(m.target_steps)
        d.run_instruction('move', m.motion.velocity_steps_s, m.motion, 1)
        d._require_enabled('move')
    for m in moves:
        ready = m.drive.until_ready_for_move()
        if ready is not None:
            yield from ready
    moves = leave_out_stopped(moves)                     # a stop during the waits
    group = [m for m in moves if m.drive.job is None and m.drive.pending is None]
    late = [m for m in moves if m not in group]
    epochs = {}
    for m in group:
        d = m.drive
        d.epoch += 1                                     # a motion command, as move_to
        d.last_target = targets[d.name]
        epochs[d.name] = d.epoch
    # a broadcast is worth it for two drives that move or more; else no null runs are written
    movers = [m for m in group if targets[m.drive.name] != m.drive.position_steps]
    possible = len(movers) >= 2 and not line_refusal(bus, [m.drive.name for m in group])

    def live(d: XmindKDrive) -> bool:
        return d.epoch == epochs[d.name] and d.job is None

    stored: dict[str, xk.Instruction] = {}
    plans = {}
    for i, m in enumerate(group):                        # 2. status and WN, step by step
        d = m.drive
        if i:
            yield 0.0
        try:
            yield from d._read_status()
            yield 0.0
            if not live(d):
                skipped[d.name] = 'a stop or a newer command came first'
                continue
            d._require_enabled('move')
            start = d.position_steps
            chunk = max(-xk.STEPS_MAX, min(xk.STEPS_MAX, targets[d.name] - start))
            if chunk == 0:
                if possible:
                    d._store(MOVE_CELL, NULL_INSTRUCTION)
                    stored[d.name] = NULL_INSTRUCTION
                continue
            instr, f, a = d.run_instruction('move', m.motion.velocity_steps_s, m.motion, chunk)
            d._store(MOVE_CELL, instr)
        except (DriveError, LinkError) as e:             # this drive only; its poll sees a loss
            skipped[d.name] = str(e)
            continue
        stored[d.name] = instr
        plans[d.name] = (d, instr, start, chunk, f, a, targets[d.name], m.motion)
    yield 0.0
    if len(plans) < 2:
        why_not = 'fewer than two drives move' + ''.join(
            f'; {name} not started: {why}' for name, why in skipped.items())
    elif not possible:
        why_not = line_refusal(bus, [m.drive.name for m in group]) or \
            'fewer than two drives move'
    else:
        why_not = broadcast_refusal(bus, stored, epochs)

    def job_for(d, instr, start, chunk, f, a, target, motion):
        def job(t: float) -> DriveProgram:
            estimate = Estimate.index(t, start, chunk, f, a)
            return DriveProgram('move', instr, estimate, a, estimate.end_s,
                                target_steps=start + chunk,
                       final_target_steps=target if start + chunk != target else None,
                       motion=motion)
        return job

    rd_s = [(d.rd_ms or 0) / 1000.0 for d, *_ in plans.values()]
    skew_s = max(rd_s) - min(rd_s) if rd_s else 0.0
    started: list[str] = []
    sent_t = None
    if not why_not:                                      # 3. the broadcast, same step
        t = time.monotonic()
        for d, *plan in plans.values():
            d.job = job_for(d, *plan)(t)                 # recorded before it leaves (§3)
        sent_t = bus.broadcast(xk.Frame(xk.BROADCAST, 'PS', (MOVE_CELL,)))
        for name, (d, *plan) in plans.items():
            d.job = job_for(d, *plan)(sent_t + xk.TURNAROUND_S + (d.rd_ms or 0) / 1000.0)
            d.motion_sent_t = sent_t
            started.append(name)
    else:
        logger.debug('%s: per-drive starts: %s', bus.url, why_not)
        for i, (name, (d, *plan)) in enumerate(plans.items()):
            if i:
                yield 0.0
            if not live(d) or d.fault or not d.enabled or d.cells.get(MOVE_CELL) != plan[0]:
                skipped[name] = 'a stop or a newer command came first, or it is not enabled'
                continue
            try:
                d._launch(MOVE_CELL, job_for(d, *plan))
            except (DriveError, LinkError) as e:
                if d.job is None:                        # refused (N)
                    skipped[name] = str(e)
                    continue
                logger.warning('%s: %s', name, e)        # no Y: taken as started (_launch)
            sent_t = time.monotonic()
            started.append(name)
    for m in late:                                       # busy past its end: as move_to
        yield 0.0
        result = m.drive.move_to(m.target_steps, m.motion)
        if drive.is_operation(result):
            yield from result
    return GroupStart(not why_not, why_not, tuple(started), skipped, sent_t, skew_s)


class XmindKGroupBus(XmindKBus):
    """The line as the node drives it: XmindKBus (protocol/) with this module's group start
    (drive.Bus.group_start: start_together, which decides between one broadcast and per-drive
    starts) and the check it needs (drive.Bus.group_start_check: probe_line, once per opening
    of the line); both only where broadcast_start is true."""

    def __init__(self, params: Mapping[str, Any]):
        super().__init__(params)
        # how long the probe waits for an answer at each address: the largest answer delay RD
        # of a drive on the line (§4.2.2.5, up to 255 ms; unknown: the largest)
        self.probe_wait_ms = float(params.get('broadcast_probe_wait_ms', xk.RD_MAX_MS))
        self.probing = False

    def group_start(self, drives: Any) -> Callable[[Any], drive.Operation[GroupStart]] | None:
        drives = list(drives)
        if not self.broadcast_start or len(drives) < 2 or any(
                not isinstance(d, XmindKDrive) or d.bus is not self for d in drives):
            return None      # not opted in: each joint its own move job, as without this
        stops = {d.name: d.stops for d in drives}     # noted before the job queues

        def starter(moves: Any) -> drive.Operation[GroupStart]:
            return start_together([GroupMove(d, target, motion, stops=stops[d.name])
                                   for d, target, motion in moves])
        return starter

    def group_start_check(self) -> Callable[[], drive.Operation[str]] | None:
        if not self.broadcast_start or self.line_probe is not None or self.probing:
            return None
        return self._probe

    def _probe(self) -> drive.Operation[str]:
        if self.line_probe is not None or self.probing:
            return 'line probe: done already or under way'
        self.probing = True
        try:
            heard = yield from probe_line(self, rd_ms=self.probe_wait_ms)
        finally:
            self.probing = False
        if heard:
            return (f'line probe: address(es) {", ".join(f"{a:02d}" for a in sorted(heard))} '
                    'answered and no drive of this node has them: no broadcast starts on this '
                    'line, each drive is started with its own PS')
        return ('line probe: no answer from the addresses no drive of this node has: the '
                'joints of a trajectory on this line start their segments by one broadcast '
                '99PS where every check of docs/xmind_k.md holds')


# ---------------------------------------------------------------------------------- vendor
def make_bus(params: Mapping[str, Any]) -> XmindKBus:
    return XmindKGroupBus(VENDOR.with_defaults(params))


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
        PS('rs485', False, serial_port.RS485_DESCRIPTION, scope='bus'),
        PS('broadcast_start', False, 'start the trajectory segments of the drives of this line '
           'in one instant by the broadcast stored instruction execution 99PS (§2.2.1, '
           '§4.2.5). A broadcast is executed by EVERY X-MIND K on the line, driven by this node '
           'or not: true only where the line carries no X-MIND K but the drives of this node. '
           'The node then probes the other addresses once the line is open and falls back to '
           'per-drive starts until then, when one answers, or when any check fails '
           '(docs/xmind_k.md)', scope='bus'),
        PS('broadcast_probe_wait_ms', 255, 'how long the line probe of broadcast_start waits '
           'for an answer at each address: the largest answer delay RD of any drive on the '
           'line (§4.2.2.5; 255 = the largest possible, about 15 s for the probe)',
           scope='bus', min_value=1, max_value=255),
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
    # At 9600 baud two axes need segments of 0.85-1.5 s (a move: WN, PS and the status strings
    # per axis): a 3 s MoveIt plan of about 1 rad becomes 2-3 segments that pass 0.15-0.45 rad
    # from its points (docs/moveit.md). The default bound takes such plans and refuses coarser.
    joint_defaults={'path_bound': 0.5},
    validate=validate,
    scanner=xmind_k_scan.SCANNER,
)
