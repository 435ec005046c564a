"""R.T.A. X-MIND K RS-485 transport: `XmindKBus`, one transaction at a time on an `AsciiLine`.

The timing of a transaction comes from the codec (`protocol/xmind_k.py`, §3 of the
*X-MIND K series Programmer's manual*): the first character of an answer within the request's
characters + turnaround + RD, a garbled answer repeated, silence repeated only when asked (a busy
drive is silent). The drive logic (what to send when) is `vendors/xmind_k/`. No ROS.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Mapping

from ..contract import drive
from ..contract.drive import DriveError, LinkError
from . import xmind_k as xk
from .ascii_line import AsciiLine, LineError

logger = logging.getLogger(__name__)

GARBLED_LINK_LOST = 3    # transactions in a row without a valid answer: the link is unusable
RETRY_SLACK_FACTOR = 4   # a repeat waits timeout_s x (1 + 4 k) beyond the manual's timing


class GarbledAnswer(DriveError):
    """Something answered, but not a valid answer to the request (after the retries): the
    drive is there, this transaction failed. `answers`: the raw answers, one per try."""

    def __init__(self, message: str, answers: tuple[bytes, ...] = ()):
        super().__init__(message)
        self.answers = answers


class XmindKBus(drive.Bus):
    """One RS-485 line, 9600 8N1 (§3), strictly one transaction at a time."""

    def __init__(self, params: Mapping[str, Any]):
        self.url = str(params['port'])
        self.line = AsciiLine(self.url, baudrate=int(params['baudrate']),
                              parity=str(params['parity']), stopbits=int(params['stopbits']),
                              margin_s=xk.MARGIN_S, local_echo=bool(params['local_echo']),
                              rs485=bool(params.get('rs485', False)))
        self.char_s = self.line.char_time_s
        self.slack_s = float(params['timeout_s'])
        self.retries = int(params['retries'])
        self.description = f'X-MIND K RS-485 {self.line.description}'
        self.addresses: dict[str, int] = {}          # drive name -> address, for checks
        self.drives: dict[str, Any] = {}   # connected drives, .in_motion (99EE on close)
        self.silences = 0
        self.garbled = 0
        self.broadcasts = 0
        self.failed_in_a_row = 0
        # Group starts by broadcast (vendors/xmind_k/group.py, start_together): a 99PS is
        # executed by every X-MIND K on the line (§2.2.1, §4.2.5), so it needs the user's word
        # that the line carries only this node's drives (bus parameter broadcast_start, false
        # when not given), and a probe of the other addresses that none answered.
        self.broadcast_start = bool(params.get('broadcast_start', False))
        self.line_probe: frozenset[int] | None = None   # addresses that answered a full probe
        self.foreign: set[int] = set()      # addresses not ours that ever answered since open

    def open(self) -> None:
        self.line_probe, self.foreign = None, set()     # a line opened again: probe it again
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

    def broadcast(self, frame: xk.Frame) -> float:
        """A 99 string: executed by every drive, answered by none (§2.2.1). Returns when its
        last character is on the wire (time.monotonic(), estimated from the character time):
        every drive acts from then on, after the turnaround and its RD (§3, §4.2.2.5)."""
        raw = xk.encode_request(frame)
        try:
            self.line.send(raw)
        except LineError as e:
            raise LinkError(str(e)) from None
        self.broadcasts += 1
        return time.monotonic() + len(raw) * self.char_s

    @property
    def last_try_slack_s(self) -> float:
        """The slack of the last repeat of a string sent 1 + retries times: what one string
        that is never repeated (PS) gets at its only try."""
        return self.slack_s * (1 + RETRY_SLACK_FACTOR * self.retries)

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
        answers: list[bytes] = []
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
                answers.append(answer)
                garbled = f'{raw!r} got {answer!r}: {e}'
                logger.debug('%s: garbled answer: %s', self.url, garbled)
        if garbled:
            self.failed_in_a_row += 1
            if self.failed_in_a_row >= GARBLED_LINK_LOST:
                self.failed_in_a_row = 0
                raise LinkError(f'{self.url}: {GARBLED_LINK_LOST} transactions in a row without '
                                f'a valid answer, last: {garbled}')
            raise GarbledAnswer(f'{self.url}: no valid answer: {garbled}', tuple(answers))
        return None
