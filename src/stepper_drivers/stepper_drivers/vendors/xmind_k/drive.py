"""The R.T.A. X-MIND K drive class: `XmindKDrive`, the contract's operations on an X-MIND K
(`link.XmindKLink`: its strings, connect and status check; `maintenance.XmindKMaintenance`:
fault reset, save, raw registers). No ROS.

The drive is silent while it runs a program (§3), so read_state, stop, a velocity change and
homing all work here on the same running DriveProgram, its Estimate (program.py) and the epoch.
"""

from __future__ import annotations

import math
import time

from ...contract import drive
from ...contract.drive import DriveError, DriveState, HomingState, LinkError, Motion, State
from ...protocol import xmind_k as xk
from .link import FAULT_TEXT, STOP_POLL_S, STOP_WAIT_S
from .maintenance import XmindKMaintenance
from .program import DriveProgram, Estimate
from .settings import HOMING_METHODS

MOVE_CELL = 228          # RAM (§4.1): indexed runs, and the zero search of a homing
RUN_CELL = 229           # RAM: free runs, and the counter reset after the zero search
# A new target for an index run that ends within this waits for its end (a trajectory's next
# segment), instead of stopping it and starting again: the drive takes no command while busy (§3).
QUEUE_BEHIND_S = 0.5


class XmindKDrive(XmindKMaintenance):
    """One X-MIND K. Step-wise (contract/drive.py): every operation of more than one string
    yields 0.0 between its strings, and its waits yield; stop() is one string.

    What it adds to its bases (link.py, maintenance.py): the state poll, which takes the end of
    a program, enable and disable, moves, free runs, stops and homing."""

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
