"""The X-MIND K's maintenance services: `XmindKMaintenance`, the layer of the drive class
(`drive.XmindKDrive`) over `link.XmindKLink` for fault reset, save, and the raw data requests
and commands of read_register / write_register (§4.2, §4.3). No ROS.
"""

from __future__ import annotations

import math
import time

from ...contract import drive
from ...contract.drive import DriveError, RefusedError
from ...protocol import xmind_k as xk
from .link import XmindKLink
from .program import DriveProgram, Estimate

NO_FAULT_RESET = 'X-MIND K has no fault reset command; clear the cause and power-cycle'


class XmindKMaintenance(XmindKLink):
    """An X-MIND K's maintenance: what the node can do besides motion (the drive has no fault
    reset and no save command; every preset is stored when written)."""

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
