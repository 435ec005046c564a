"""One request at a time on a half-duplex ASCII serial line (RS-485 master side). No ROS.

`AsciiLine` opens any pyserial URL (`/dev/ttyUSB0`, a pty path, `socket://host:port`,
`loop://`) with `serial.serial_for_url` (then `serial_port.prepare`: low-latency mode, and the
kernel's RS-485 mode with `rs485`), writes one terminated string in a single write (the
characters of a string go back to back, X-MIND K manual §3) and reads the one answer:

- the answer's first character must arrive by `first_byte_timeout_s` after the write, else the
  transaction is silent (`None`): a half-duplex slave either answers promptly or not at all;
- the answer must end (terminator) by `reply_timeout_s` after its first character; what came
  until then is returned without a terminator (the caller sees a garbled answer, not silence);
- the next string leaves no earlier than `margin_s` after the end of the answer (§3 margin),
  or after the last transmission when nothing was expected (broadcast).

Stale input (a late answer to an earlier request) is discarded before each write; answers that
do not pass the caller's `accept` check are skipped while time remains. Times come from the
caller (the protocol's timing table); this module only enforces them.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import serial

from . import serial_port

logger = logging.getLogger(__name__)


class LineError(Exception):
    """The port cannot be opened, written or read (device gone, pty closed)."""


class AsciiLine:
    def __init__(self, url: str, *, baudrate: int = 9600, bytesize: int = 8, parity: str = 'N',
                 stopbits: float = 1, terminator: bytes = b'\r', margin_s: float = 0.0,
                 char_time_s: float | None = None, local_echo: bool = False,
                 rs485: bool = False):
        self.url = url
        self.settings = dict(baudrate=baudrate, bytesize=bytesize, parity=parity,
                             stopbits=stopbits)
        self.terminator = terminator
        self.margin_s = margin_s
        self.char_time_s = char_time_s if char_time_s is not None else \
            (1 + bytesize + (parity != 'N') + stopbits) / baudrate
        self.local_echo = local_echo     # adapters that hear their own transmission
        self.rs485 = rs485               # the kernel's RS-485 mode (serial_port.set_rs485)
        self._port: serial.SerialBase | None = None
        self._free_at = 0.0              # time.monotonic() when the next string may leave

    @property
    def description(self) -> str:
        s = self.settings
        return (f"{self.url} {s['baudrate']} {s['bytesize']}{s['parity']}"
                f"{s['stopbits']:g}")

    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def open(self) -> None:
        self.close()
        try:
            self._port = serial.serial_for_url(self.url, timeout=0.1, write_timeout=1.0,
                                               **self.settings)
        except (serial.SerialException, ValueError, OSError) as e:
            self._port = None
            raise LineError(f'cannot open {self.description}: {e}') from None
        try:
            serial_port.prepare(self._port, self.url, rs485=self.rs485)
        except serial_port.PortSetupError as e:
            self.close()
            raise LineError(str(e)) from None
        self._free_at = 0.0

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError) as e:
                logger.debug('close %s: %s', self.url, e)

    def send(self, request: bytes) -> None:
        """Write a string nobody answers (broadcast); the line is held for its length."""
        self._write(request)
        self._free_at = time.monotonic() + len(request) * self.char_time_s + self.margin_s

    def transact(self, request: bytes, *, first_byte_timeout_s: float, reply_timeout_s: float,
                 accept: Callable[[bytes], bool] = lambda _answer: True) -> bytes | None:
        """Write `request`, return the first accepted answer (with terminator) or None."""
        self._write(request)
        t_sent = time.monotonic()
        try:
            answer = self._read_answer(t_sent + first_byte_timeout_s, reply_timeout_s, accept)
        finally:
            self._free_at = time.monotonic() + self.margin_s
        return answer

    # ---------------------------------------------------------------------------------- internal
    def _port_or_fail(self) -> serial.SerialBase:
        if self._port is None:
            raise LineError(f'{self.url} is not open')
        return self._port

    def _write(self, request: bytes) -> None:
        port = self._port_or_fail()
        wait = self._free_at - time.monotonic()
        if wait > 0:
            time.sleep(wait)     # §3 margin: a rate limit, nothing to wait on
        try:
            if port.in_waiting:
                stale = port.read(port.in_waiting)
                logger.debug('%s: discarded stale input %r', self.url, stale)
            port.write(request)
            if self.local_echo:
                port.timeout = len(request) * self.char_time_s + 0.1
                echo = port.read(len(request))
                if echo != request:
                    raise LineError(f'{self.url}: local echo {echo!r} differs from {request!r}')
        except (serial.SerialException, OSError) as e:
            raise LineError(f'{self.description}: write failed: {e}') from None

    def _read_answer(self, first_deadline: float, reply_timeout_s: float,
                     accept: Callable[[bytes], bool]) -> bytes | None:
        port = self._port_or_fail()
        deadline = first_deadline
        buffer = b''
        try:
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    if buffer:
                        logger.debug('%s: incomplete answer %r', self.url, buffer)
                        return buffer
                    return None
                port.timeout = left
                if not buffer:
                    chunk = port.read(1)
                    if not chunk:
                        continue
                    buffer = chunk
                    deadline = time.monotonic() + reply_timeout_s
                    if buffer != self.terminator:
                        continue
                else:
                    buffer += port.read_until(self.terminator)
                if buffer.endswith(self.terminator):
                    if accept(buffer):
                        return buffer
                    logger.debug('%s: skipped answer %r', self.url, buffer)
                    buffer = b''
                    deadline = max(deadline, first_deadline)
        except (serial.SerialException, OSError) as e:
            raise LineError(f'{self.description}: read failed: {e}') from None
