"""Modbus RTU on a serial line: the frame codec (driver and simulator) and a master (driver).

No rclpy. The codec follows the Modbus over Serial Line V1.02 frame, which the Lika RD4 manual
(§7.2, §7.3.1) describes:

    [ silence >= t3.5 ][ address ][ function code ][ data (0..252 bytes) ][ CRC lo ][ CRC hi ]

CRC-16/Modbus (polynomial 0xA001 reflected, initial 0xFFFF) is sent low byte first; register values
are big-endian (§7.3.1). Characters are 11 bits on the line: start, 8 data, parity (or a second
stop bit when there is no parity), stop (§7.3.1), so a frame of n bytes takes n * 11 / baud s.

`ModbusRtuBus` is the master: one request at a time (§7.1), the reply framed by its length (known
from the function code and byte count), its CRC checked, a bad reply or a timeout retried; it keeps
the t3.5 silence before every request. It is written on pyserial rather than pymodbus because
pymodbus 3.16's RTU framer drops a reply with a bad CRC silently (FramerRTU.decode: "Frame CRC
check failed, possible garbage", debug log only) and then waits for the whole timeout: CRC errors
could be neither counted nor retried at once, and its sync client adds ~4 character times of
polling per transaction (research/transports.md §B1 item 5).
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
from typing import Any, Sequence

from pymodbus.framer import FramerRTU

from ..contract import drive
from . import serial_port
from .modbus import (  # noqa: F401 - re-exported
    EXCEPTION_FLAG,
    FC_READ_HOLDING_REGISTERS,
    FC_READ_INPUT_REGISTERS,
    FC_WRITE_MULTIPLE_REGISTERS,
    FC_WRITE_SINGLE_REGISTER,
    FUNCTION_CODES,
    ILLEGAL_DATA_ADDRESS,
    ILLEGAL_DATA_VALUE,
    ILLEGAL_FUNCTION,
    MAX_READ_COUNT,
    MAX_WRITE_COUNT,
    SERVER_DEVICE_FAILURE,
    ModbusBus,
    ModbusExceptionError,
    ReplyMismatch,
    Request,
    parse_reply_pdu,
    read_request,
    write_multiple_request,
    write_single_request,
)

logger = logging.getLogger(__name__)

MAX_FRAME_BYTES = 256          # §7.3.1 maximum RTU frame
BROADCAST_ADDRESS = 0          # §7.1 (the RD4 does not implement broadcast)
MAX_SLAVE_ADDRESS = 247        # §4.4.1, §7.1
BITS_PER_CHAR = 11             # §7.3.1: 1 start + 8 data + parity (or 2nd stop) + 1 stop
SPIN_S = 0.0002                # last part of the t3.5 wait spent spinning, not sleeping
PARITIES = ('N', 'E', 'O')


# ----------------------------------------------------------------------------------- timing
def char_time_s(baud: int) -> float:
    """One 11-bit RTU character on the line (§7.3.1)."""
    if baud <= 0:
        raise ValueError(f'baud rate must be > 0, got {baud}')
    return BITS_PER_CHAR / baud


def frame_time_s(n_bytes: int, baud: int) -> float:
    return n_bytes * char_time_s(baud)


def t35_s(baud: int) -> float:
    """The silent interval between frames: 3.5 characters (§7.3.1: 4 ms at 9600, 2 ms at 19200).

    Above 19200 baud Modbus over Serial Line V1.02 §2.5.1.1 fixes it at 1.75 ms.
    """
    return 0.00175 if baud > 19200 else 3.5 * char_time_s(baud)


# -------------------------------------------------------------------------------------- CRC
def add_crc(body: bytes) -> bytes:
    """Append the CRC, low byte first (§7.3.1 frame: 'CRC Low, CRC Hi'). pymodbus's
    compute_CRC returns it byte-swapped, i.e. ready to be sent big-endian."""
    return bytes(body) + FramerRTU.compute_CRC(bytes(body)).to_bytes(2, 'big')


def crc_ok(frame: bytes) -> bool:
    return len(frame) >= 4 and FramerRTU.check_CRC(bytes(frame[:-2]),
                                                   int.from_bytes(frame[-2:], 'big'))


# ---------------------------------------------------------------------------------- frames
class FrameError(Exception):
    """A frame that does not parse (the caller treats it like line noise)."""


def encode(request: Request) -> bytes:
    """The RTU frame of a request: slave address, PDU, CRC (§7.3.1)."""
    return add_crc(bytes((request.unit & 0xFF,)) + request.pdu())


def reply_length(request: Request) -> int:
    """Bytes of the normal response frame (§7.4.1)."""
    return request.reply_pdu_length + 3


def request_length(head: bytes) -> int | None:
    """Length of a request frame from its first bytes; None: unknown yet (or unknown FC)."""
    if len(head) < 2:
        return None
    fc = head[1]
    if fc in (FC_READ_HOLDING_REGISTERS, FC_READ_INPUT_REGISTERS, FC_WRITE_SINGLE_REGISTER):
        return 8
    if fc == FC_WRITE_MULTIPLE_REGISTERS:
        return 9 + head[6] if len(head) >= 7 else None
    return None


def response_length(head: bytes) -> int | None:
    """Length of a response frame from its first 3 bytes; None for an unknown function code."""
    if len(head) < 3:
        return None
    fc = head[1]
    if fc & EXCEPTION_FLAG:
        return 5
    if fc in (FC_READ_HOLDING_REGISTERS, FC_READ_INPUT_REGISTERS):
        return 5 + head[2]
    if fc in (FC_WRITE_SINGLE_REGISTER, FC_WRITE_MULTIPLE_REGISTERS):
        return 8
    return None


def parse_request(frame: bytes) -> Request:
    """Decode a request frame whose CRC was checked; ModbusExceptionError for what a slave
    answers with an exception, in the V1.1b §6 order: function code (01), quantity and byte
    count (03). The address range (02) is the device's business."""
    if len(frame) < 4:
        raise FrameError(f'{len(frame)} bytes is too short for a frame')
    unit, fc = frame[0], frame[1]
    pdu = frame[2:-2]
    if fc not in FUNCTION_CODES:
        raise ModbusExceptionError(fc, ILLEGAL_FUNCTION, f'function code 0x{fc:02X}')
    if fc == FC_WRITE_MULTIPLE_REGISTERS:
        if len(pdu) < 5:
            raise ModbusExceptionError(fc, ILLEGAL_DATA_VALUE, 'FC16 request too short')
        address, count, byte_count = (int.from_bytes(pdu[0:2], 'big'),
                                      int.from_bytes(pdu[2:4], 'big'), pdu[4])
        data = pdu[5:]
        if not 1 <= count <= MAX_WRITE_COUNT or byte_count != 2 * count \
                or len(data) != byte_count:
            raise ModbusExceptionError(fc, ILLEGAL_DATA_VALUE,
                                       f'quantity {count}, byte count {byte_count}, '
                                       f'{len(data)} data bytes')
        values = tuple(int.from_bytes(data[i:i + 2], 'big') for i in range(0, len(data), 2))
        return Request(unit, fc, address, count, values)
    if len(pdu) != 4:
        raise ModbusExceptionError(fc, ILLEGAL_DATA_VALUE, f'{len(pdu)}-byte PDU data')
    address, word = int.from_bytes(pdu[0:2], 'big'), int.from_bytes(pdu[2:4], 'big')
    if fc == FC_WRITE_SINGLE_REGISTER:
        return Request(unit, fc, address, 1, (word,))
    if not 1 <= word <= MAX_READ_COUNT:
        raise ModbusExceptionError(fc, ILLEGAL_DATA_VALUE, f'quantity {word}')
    return Request(unit, fc, address, word)


def read_response(unit: int, function_code: int, registers: Sequence[int]) -> bytes:
    data = b''.join((r & 0xFFFF).to_bytes(2, 'big') for r in registers)
    return add_crc(bytes((unit, function_code, len(data))) + data)


def write_single_response(request_frame: bytes) -> bytes:
    """§7.4.1 FC06: 'The normal response is an echo of the request'."""
    return bytes(request_frame)


def write_multiple_response(unit: int, address: int, count: int) -> bytes:
    return add_crc(bytes((unit, FC_WRITE_MULTIPLE_REGISTERS)) + address.to_bytes(2, 'big')
                   + count.to_bytes(2, 'big'))


def exception_response(unit: int, function_code: int, code: int) -> bytes:
    return add_crc(bytes((unit, (function_code | EXCEPTION_FLAG) & 0xFF, code)))


def response_for(request: Request, request_frame: bytes, registers: Sequence[int] = ()) -> bytes:
    """The normal response to a request (registers for reads)."""
    fc = request.function_code
    if fc in (FC_READ_HOLDING_REGISTERS, FC_READ_INPUT_REGISTERS):
        return read_response(request.unit, fc, registers)
    if fc == FC_WRITE_SINGLE_REGISTER:
        return write_single_response(request_frame)
    return write_multiple_response(request.unit, request.address, request.count)


def parse_response(frame: bytes, request: Request) -> list[int]:
    """Registers of a read reply ([] for a write); ModbusExceptionError, ReplyMismatch."""
    if frame[0] != request.unit:
        raise ReplyMismatch(f'reply from address {frame[0]}, asked {request.unit}')
    return parse_reply_pdu(bytes(frame[1:-2]), request)


# ---------------------------------------------------------------------------------- master
class _NoReply(Exception):
    pass


class _BadCrc(Exception):
    pass


class ModbusRtuBus(ModbusBus):
    """The master on one serial line; several slaves (by address) share it.

    Every request waits for t3.5 of silence since the last byte on the line, is written whole,
    and its reply is read by length. A timeout, a CRC error or a reply that does not match the
    request is counted and the request sent again (`retries` times); then LinkError. An exception
    reply is a DriveError (the slave answered: the link is fine), never retried. Any failure of
    the port itself (OSError, termios.error, a port closed under pyserial) is a one-line
    LinkError at once. An opened port gets serial_port.prepare (low-latency mode; with `rs485`
    the kernel's RS-485 mode, or LinkError naming the parameter).
    """

    def __init__(self, port: str, baudrate: int = 9600, parity: str = 'E', stopbits: int = 1,
                 timeout_s: float = 0.5, retries: int = 1, rs485: bool = False):
        self.port = str(port)
        self.baudrate = int(baudrate)
        self.parity = str(parity).upper()
        self.stopbits = int(stopbits)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.rs485 = bool(rs485)        # the kernel's RS-485 mode (serial_port.set_rs485)
        if self.parity not in PARITIES:
            raise ValueError(f'parity: {parity!r} is not allowed (allowed: N, E, O)')
        self.t35_s = t35_s(self.baudrate)
        self.description = (f'modbus rtu {self.port} {self.baudrate} 8{self.parity}'
                            f'{self.stopbits}')
        self.transactions = 0
        self.errors = 0
        self.timeouts = 0
        self.crc_errors = 0
        self.mismatches = 0
        self.exceptions = 0
        self.retried = 0
        self.stale_bytes = 0
        self._lock = threading.Lock()
        self._serial: Any = None
        self._idle_at = 0.0       # monotonic time from which the line has been silent >= t3.5

    # Life cycle ---------------------------------------------------------------------------------
    def open(self) -> None:
        import serial
        with self._lock:
            if self._serial is not None:
                return
            try:
                port = serial.serial_for_url(
                    self.port, baudrate=self.baudrate, bytesize=serial.EIGHTBITS,
                    parity=self.parity, stopbits=self.stopbits, timeout=self.timeout_s,
                    exclusive=True, do_not_open=True)
                port.open()
            except Exception as exc:  # noqa: BLE001 - termios.error too (not an OSError)
                code = getattr(exc, 'errno', None) or (exc.args[0] if exc.args else None)
                hint = (' (a pseudo-terminal may refuse parity E/O: use N there)'
                        if self.parity != 'N' and code == 22 else '')
                raise drive.LinkError(f'cannot open {self.port} at {self.baudrate} baud '
                                      f'8{self.parity}{self.stopbits}: {exc}{hint}') from None
            try:
                serial_port.prepare(port, self.port, rs485=self.rs485)
            except serial_port.PortSetupError as exc:
                port.close()
                raise drive.LinkError(str(exc)) from None
            self._serial = port
            self._idle_at = time.monotonic() + self.t35_s
            logger.info('opened %s', self.description)

    def close(self) -> None:
        with self._lock:
            port, self._serial = self._serial, None
            if port is not None:
                try:
                    port.close()
                except Exception as exc:  # noqa: BLE001 - a dead port may fail any way
                    logger.debug('close %s: %s', self.port, exc)

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def counters(self) -> dict[str, int]:
        return {'transactions': self.transactions, 'errors': self.errors,
                'timeouts': self.timeouts, 'crc_errors': self.crc_errors,
                'mismatches': self.mismatches, 'exceptions': self.exceptions,
                'retries': self.retried, 'stale_bytes': self.stale_bytes}

    # Transactions -------------------------------------------------------------------------------
    def transact(self, request: Request) -> list[int]:
        frame = encode(request)
        what = f'{self.port} unit {request.unit}: {request.describe(hex_address=True)}'
        with self._lock:
            port = self._serial
            if port is None:
                self.errors += 1
                raise drive.LinkError(f'{what}: port not open')
            problems = []
            for attempt in range(1 + self.retries):
                if attempt:
                    self.retried += 1
                self.transactions += 1
                try:
                    reply = self._exchange(port, frame, request)
                    return parse_response(reply, request)
                except ModbusExceptionError as exc:
                    self.errors += 1
                    self.exceptions += 1
                    raise exc.within(what) from None
                except _NoReply as exc:
                    self.errors += 1
                    self.timeouts += 1
                    problems.append(str(exc))
                except _BadCrc as exc:
                    self.errors += 1
                    self.crc_errors += 1
                    problems.append(str(exc))
                except ReplyMismatch as exc:    # (raised by parse_response: `reply` is set)
                    self.errors += 1
                    self.mismatches += 1
                    problems.append(f'{exc}: reply {reply.hex(" ")}')
                except OSError as exc:   # serial.SerialException is an OSError (port gone)
                    self.errors += 1
                    raise drive.LinkError(f'{what}: {exc}') from None
                except Exception as exc:  # noqa: BLE001 - termios.error, or pyserial's
                    # TypeError on a port closed under it: the transport failed, one line.
                    self.errors += 1
                    raise drive.LinkError(f'{what}: {type(exc).__name__}: {exc}') from None
                logger.debug('%s: %s', what, problems[-1])
            raise drive.LinkError(f'{what}: ' + '; '.join(problems))

    def _exchange(self, port: Any, frame: bytes, request: Request) -> bytes:
        self._wait_idle()
        if port.in_waiting:
            stale = port.read(port.in_waiting)     # a late reply to an earlier request
            self.stale_bytes += len(stale)
        port.write(frame)
        # The request and the reply take their time on the line; timeout_s is the slave's part.
        deadline = (time.monotonic() + frame_time_s(len(frame) + reply_length(request),
                                                    self.baudrate) + self.timeout_s)
        reply = self._read_frame(port, deadline)
        self._idle_at = time.monotonic() + self.t35_s
        length = response_length(reply)
        if len(reply) < 3 or (length is not None and len(reply) < length):
            raise _NoReply(f'no reply within {self.timeout_s:g} s' if not reply else
                           f'reply cut short: {reply.hex(" ")}')
        if length is None:
            self._drain(port)
            raise _BadCrc(f'unparsable reply {reply.hex(" ")}...')
        if len(reply) > length:
            self.stale_bytes += len(reply) - length
            reply = reply[:length]
        if not crc_ok(reply):
            self._drain(port)
            raise _BadCrc(f'CRC error in reply {reply.hex(" ")}')
        return reply

    def _wait_idle(self) -> None:
        """§7.3.1: a request only after t3.5 of silence. Sleep, then spin the last 0.2 ms:
        a sleep overshoots by ~0.1 ms, which at 19200 baud is 0.5 % of a poll."""
        wait = self._idle_at - time.monotonic()
        if wait > SPIN_S:
            time.sleep(wait - SPIN_S)
        while time.monotonic() < self._idle_at:
            pass

    @staticmethod
    def _read_frame(port: Any, deadline: float) -> bytes:
        """Bytes until a whole reply (its length known from the first 3) or the deadline."""
        try:
            fd = port.fileno()          # a posix port: select + read what is there
        except (AttributeError, OSError, NotImplementedError, ValueError):
            fd = None
        buf = b''
        while True:
            need = 3 if len(buf) < 3 else response_length(buf)
            if need is None or len(buf) >= need:
                return buf
            left = deadline - time.monotonic()
            if left <= 0:
                return buf
            if fd is None:
                port.timeout = left
                buf += port.read(need - len(buf))
                continue
            readable, _, _ = select.select([fd], [], [], left)
            if readable:
                chunk = os.read(fd, MAX_FRAME_BYTES)
                if not chunk:
                    raise OSError(f'{port.port}: readable but no data (device gone)')
                buf += chunk

    def _drain(self, port: Any) -> None:
        """After garbage: discard bytes until the line has been silent for t3.5."""
        port.timeout = self.t35_s
        while port.read(256):
            pass
        self._idle_at = time.monotonic()
