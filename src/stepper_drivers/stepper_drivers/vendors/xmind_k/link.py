"""One X-MIND K address on its line as the node knows it: `XmindKLink`, the base of the drive
class (`drive.XmindKDrive`, through `maintenance.XmindKMaintenance`). No ROS.

The drive cannot be asked for much (current on/off, the program it runs, its RAM cells), so
this class holds what the node tracks of it, next to its strings (a transaction and its
answer, the data requests of connect, WN, PS), the connect sequence, the on-the-wire status
check before every start (FA and the power-cycle flag), and the RAM-cell instruction a move or
a free run takes (§4.1). The operations on a running program are in drive.py.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Callable, Mapping

from ...contract import drive
from ...contract.drive import DriveError, HomingState, LinkError, Motion
from ...protocol import xmind_k as xk
from ...protocol.xmind_k_bus import GarbledAnswer, XmindKBus
from . import settings
from .program import DriveProgram

logger = logging.getLogger(__name__)

# A move on the line (move_time_s): the FA and power-cycle-flag check, WN 228 and PS 228, about 20
# characters a string and its answer, each answered after the turnaround and RD (§3).
MOVE_STRINGS = 4
MOVE_CHARS_PER_STRING = 20
RAMPED_MIN_HZ = min(xk.TABLE2_HZ.values())          # 3000 Hz: below, only unramped runs (§4.1.6)
RAMPED_MAX_HZ = max(xk.HR_RAMPED_X100) * 100        # 24000 Hz (§4.1.2)
FAULT_TEXT = ('FA output OFF: drive blocked by a protection (§2.2.4); X-MIND K has no fault '
              'reset command: clear the cause and power-cycle')
STOP_WAIT_S = 3.0        # bound on waiting for a stopping drive to answer again
STOP_POLL_S = 0.02       # rate limit of that wait (nothing to wait on but the drive's answer)
BUSY_POLL_SLACK_S = 0.03  # a drive that may be busy: a late answer is taken at the next poll


class XmindKLink(drive.Drive):
    """One X-MIND K address: its strings, its connect and what the node tracks of a drive that
    cannot be asked; the base of XmindKDrive (drive.py), which adds the contract's operations.

    `epoch` counts stops and motion commands: a step-wise start checks it before each string it
    writes, so a stop or a newer command that ran between its steps cancels the older start
    (nothing written to the drive after a stop that nobody commanded again)."""

    def __init__(self, bus: XmindKBus, name: str, params: Mapping[str, Any]):
        params = settings.with_defaults(params)
        super().__init__(bus, name, params)
        self.number = int(params['address'])       # the drive address AA (§2.2.1)
        # the rules validate() applies too (settings.py)
        settings._check_address(name, self.number, bus.addresses, bus.url)
        settings._check_drive(name, params)
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

    @property
    def answer_delay_s(self) -> float:
        """The drive's answer delay RD (§4.2.2.5): as read at connect, else as configured,
        else the factory default."""
        rd_ms = self.rd_ms if self.rd_ms is not None else int(self.params['answer_delay_ms'])
        return (rd_ms if rd_ms >= 0 else xk.RD_DEFAULT_MS) / 1000.0

    def move_time_s(self) -> float:
        return (MOVE_STRINGS * (MOVE_CHARS_PER_STRING * self.bus.char_s + xk.TURNAROUND_S
                                + self.answer_delay_s) + xk.TURNAROUND_WN_S)

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

    # ------------------------------------------------------------------ status check, refusals
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

    def _refuse_busy(self, what: str) -> None:
        if self.job is not None:
            raise DriveError(f'{what}: drive {self.number:02d} is busy ({self.job.kind}); it '
                             'answers only EE and ES until the program ends (§3)')

    # ------------------------------------------------------------------------ run instructions
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
