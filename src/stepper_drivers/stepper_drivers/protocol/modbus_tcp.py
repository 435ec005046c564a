"""Modbus TCP link on a plain socket: the MBAP header of MODBUS Messaging on TCP/IP
Implementation Guide V1.0b §3.1.3 around the PDUs of protocol/modbus.py.

No rclpy. Raises drive.LinkError when the link is down or a request gets no (valid) answer, and
modbus.ModbusExceptionError (a drive.DriveError) for an exception reply (the link is fine, the
device said no). Reconnecting is the caller's job: after a LinkError it calls close(), later
open().

Why by hand and not pymodbus's ModbusTcpClient: its sync transaction
path (transaction manager, framer, PDU classes, a trace hook per request) costs about 30 us of
Python per transaction on top of the socket calls: 92 us of CPU per FC03 of 21 registers against
64 us for the same exchange on a plain socket (loopback, the project machine). With 8 drives at
50 Hz that was most of the node's distance from its CPU goal (docs/benchmarks.md). The
frame is 7 bytes; pymodbus still provides the exception codes (protocol/modbus.py) and plays
the device in the tests (test_modbus_tcp_bus.py runs against its ModbusTcpServer).
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from typing import Any, Mapping

from ..contract import drive
from ..contract.capabilities import NonblockingPolls
from .modbus import (  # noqa: F401 - re-exported
    MAX_READ_COUNT,
    MAX_WRITE_COUNT,
    ModbusBus,
    ModbusExceptionError,
    ReplyMismatch,
    Request,
    parse_reply_pdu,
)

logger = logging.getLogger(__name__)

MBAP = struct.Struct('>HHHB')     # transaction id, protocol id (0), length, unit id (§3.1.3)
MAX_ADU_BYTES = 260               # §3.1.3: 7 bytes of MBAP + a PDU of at most 253 bytes


# The weight of the newest round trip in ModbusTcpBus.transaction_s.
TRANSACTION_SMOOTHING = 0.1


class _Closed(Exception):
    """The peer closed the connection."""


class ModbusTcpBus(ModbusBus, NonblockingPolls):
    """One TCP connection to a Modbus server; several unit ids may share it. One request at a
    time (the lock): the transaction id of each reply is checked, and a late reply to an earlier
    request that timed out is skipped (counted as `stale_replies`)."""

    def __init__(self, host: str = '127.0.0.1', port: int = 502, timeout_s: float = 0.5):
        self.host = host
        self.port = int(port)
        self.timeout_s = float(timeout_s)
        self.description = f'modbus tcp {host}:{self.port}'
        self.transactions = 0
        self.errors = 0
        self.exceptions = 0
        self.timeouts = 0
        self.stale_replies = 0
        # a transaction's round trip, averaged (TRANSACTION_SMOOTHING) over the answered ones
        self.transaction_s = 0.0
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._rx = bytearray()
        self._tid = 0
        # (request, deadline) of the last send_request() while its reply was not taken
        self._pending: tuple[Request, float] | None = None

    # Life cycle ---------------------------------------------------------------------------------
    def open(self) -> None:
        with self._lock:
            if self._sock is not None:
                return
            try:
                sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
            except OSError as exc:
                raise drive.LinkError(f'cannot connect to {self.host}:{self.port} (modbus tcp, '
                                      f'timeout {self.timeout_s:g} s): '
                                      f'{exc.strerror or exc!r}') from None
            # One small request, then wait for the answer: Nagle would only delay it.
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            # A blocking socket whose kernel timeouts bound every call: recv() is one system
            # call, where Python's own socket timeout adds a poll() before each (a third of
            # the CPU of a transaction on loopback).
            sock.settimeout(None)
            _set_timeouts(sock, self.timeout_s)
            self._sock = sock
            self._rx.clear()
            self._pending = None
            logger.info('connected to %s', self.description)

    def close(self) -> None:
        with self._lock:
            sock, self._sock = self._sock, None
            self._rx.clear()
            self._pending = None
            if sock is not None:
                try:
                    sock.close()
                except OSError as exc:
                    logger.debug('close %s: %s', self.description, exc)

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    def counters(self) -> dict[str, int]:
        return {'transactions': self.transactions, 'errors': self.errors,
                'exceptions': self.exceptions, 'timeouts': self.timeouts,
                'stale_replies': self.stale_replies}

    # Transactions -------------------------------------------------------------------------------
    def transact(self, request: Request) -> list[int]:
        with self._lock:
            sock = self._connected(request)
            if self._pending is not None:
                self._finish_pending(sock)
            reply = b''
            try:
                began = time.monotonic()
                self._send(sock, request)
                reply = self._reply(sock, request)
                took = time.monotonic() - began
                self.transaction_s = took if not self.transaction_s else \
                    self.transaction_s + TRANSACTION_SMOOTHING * (took - self.transaction_s)
                return parse_reply_pdu(reply, request)
            except ModbusExceptionError as exc:
                self.errors += 1
                self.exceptions += 1
                raise exc.within(self._what(request)) from None
            except ReplyMismatch as exc:
                got = f' (reply PDU {reply.hex(" ")})' if reply else ''
                raise self._link_error(request, exc, got) from None
            except (_Closed, OSError) as exc:        # a time-out, reset, broken pipe, ...
                raise self._link_error(request, exc) from None

    def _link_error(self, request: Request, exc: Exception, got: str = '') -> drive.LinkError:
        """(Under _lock) The LinkError of `request`'s failed transaction, counted."""
        self.errors += 1
        what = self._what(request)
        if isinstance(exc, TimeoutError):
            self.timeouts += 1
            return drive.LinkError(f'{what}: no answer within {self.timeout_s:g} s')
        if isinstance(exc, _Closed):
            return drive.LinkError(f'{what}: connection closed by the server')
        if isinstance(exc, ReplyMismatch):
            return drive.LinkError(f'{what}: {exc}{got}')
        return drive.LinkError(f'{what}: {getattr(exc, "strerror", None) or exc!r}')

    def _connected(self, request: Request) -> socket.socket:
        """(Under _lock) The socket, or LinkError while closed."""
        sock = self._sock
        if sock is None:
            self.errors += 1
            raise drive.LinkError(f'{self.description}: not connected ({request.describe()})')
        return sock

    def _send(self, sock: socket.socket, request: Request) -> None:
        """(Under _lock) The request on the wire, with the next transaction id."""
        self.transactions += 1
        self._tid = (self._tid + 1) & 0xFFFF
        pdu = request.pdu()
        sock.sendall(MBAP.pack(self._tid, 0, len(pdu) + 1, request.unit & 0xFF) + pdu)

    def _finish_pending(self, sock: socket.socket) -> None:
        """(Under _lock) The reply to a send_request() nobody took (the poll group gave the link
        back before it came), read and dropped (stale_replies) before the next request goes
        out: one request in flight at a time, as a Modbus server expects (pymodbus answers only
        the first of two requests that arrive together). None within timeout_s of its sending:
        LinkError."""
        request, deadline = self._pending
        self._pending = None
        try:
            self._await_frame(sock, request, deadline)
        except (_Closed, ReplyMismatch, OSError) as exc:
            raise self._link_error(request, exc) from None
        self.stale_replies += 1

    def _what(self, request: Request) -> str:
        return f'{self.host}:{self.port} unit {request.unit}: {request.describe()}'

    def _reply(self, sock: socket.socket, request: Request) -> bytes:
        """The PDU of the reply to the request just sent (transaction id self._tid)."""
        if not self._rx:                     # the usual case: the whole reply in one read
            chunk = _recv(sock)
            if not chunk:
                raise _Closed
            if len(chunk) >= MBAP.size:
                tid, protocol, length, unit = MBAP.unpack_from(chunk)
                if len(chunk) == MBAP.size - 1 + length and tid == self._tid \
                        and protocol == 0 and unit == request.unit & 0xFF:
                    return chunk[MBAP.size:]
            self._rx += chunk
        return self._await_frame(sock, request, time.monotonic() + self.timeout_s)

    def _await_frame(self, sock: socket.socket, request: Request, deadline: float) -> bytes:
        """The PDU of the reply to transaction self._tid, received by `deadline`
        (time.monotonic()), else TimeoutError."""
        while True:
            pdu = self._frame(request)
            if pdu is not None:
                return pdu
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError
            _set_timeouts(sock, remaining)
            try:
                chunk = _recv(sock)
            finally:
                _set_timeouts(sock, self.timeout_s)
            if not chunk:
                raise _Closed
            self._rx += chunk

    def _frame(self, request: Request) -> bytes | None:
        """The PDU of the reply to transaction self._tid from what was received (self._rx),
        or None while it is incomplete; late replies to earlier requests are skipped."""
        while len(self._rx) >= MBAP.size:
            tid, protocol, length, unit = MBAP.unpack_from(self._rx)
            if protocol != 0 or not 2 <= length <= MAX_ADU_BYTES - 6:
                got = bytes(self._rx[:MAX_ADU_BYTES]).hex(' ')
                self._rx.clear()          # the framing is lost: nothing after it is sure
                raise ReplyMismatch(f'not a Modbus TCP header (protocol id {protocol}, '
                                    f'length {length}): received {got}')
            end = MBAP.size - 1 + length
            if len(self._rx) < end:
                return None
            pdu = bytes(self._rx[MBAP.size:end])
            del self._rx[:end]
            if tid != self._tid:      # late answer to a request that timed out
                self.stale_replies += 1
                continue
            if unit != request.unit & 0xFF:
                raise ReplyMismatch(f'reply from unit {unit} (PDU {pdu.hex(" ")})')
            return pdu
        return None

    # Requests whose replies are taken later (poll_group.PollGroup) ------------------------------
    def fileno(self) -> int:
        """The socket's file descriptor (-1 while closed), to wait for a reply with select."""
        sock = self._sock
        return sock.fileno() if sock is not None else -1

    def send_request(self, request: Request) -> None:
        """Send `request` and return at once; take_reply() then gives its reply. The next
        request, whoever sends it, first waits for the reply of one whose reply was not taken
        (bounded by timeout_s from its sending; _finish_pending)."""
        with self._lock:
            sock = self._connected(request)
            if self._pending is not None:
                self._finish_pending(sock)
            try:
                self._send(sock, request)
            except OSError as exc:
                raise self._link_error(request, exc) from None
            self._pending = (request, time.monotonic() + self.timeout_s)

    def take_reply(self, request: Request) -> list[int] | None:
        """The reply to the request of the last send_request(), without blocking: None while
        it has not all come. Raises as transact() does."""
        with self._lock:
            sock = self._connected(request)
            try:
                chunk = sock.recv(MAX_ADU_BYTES, socket.MSG_DONTWAIT)
                if not chunk:
                    raise _Closed
                self._rx += chunk
            except BlockingIOError:
                pass
            except (_Closed, OSError) as exc:
                self._pending = None
                raise self._link_error(request, exc) from None
            try:
                pdu = self._frame(request)
                if pdu is None:
                    return None
                self._pending = None
                return parse_reply_pdu(pdu, request)
            except ModbusExceptionError as exc:
                self.errors += 1
                self.exceptions += 1
                raise exc.within(self._what(request)) from None
            except ReplyMismatch as exc:
                self._pending = None
                raise self._link_error(request, exc) from None


def _set_timeouts(sock: socket.socket, seconds: float) -> None:
    """SO_RCVTIMEO and SO_SNDTIMEO (struct timeval, Linux) of a blocking socket."""
    seconds = max(seconds, 1e-6)               # 0 would mean: wait for ever
    timeval = struct.pack('ll', int(seconds), int(seconds % 1 * 1e6))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, timeval)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, timeval)


def _recv(sock: socket.socket) -> bytes:
    try:
        return sock.recv(MAX_ADU_BYTES)
    except BlockingIOError:                    # EAGAIN: SO_RCVTIMEO ran out
        raise TimeoutError from None


def make_bus(params: Mapping[str, Any]) -> ModbusTcpBus:
    """Bus params 'host', 'port', 'timeout_s'; ValueError naming the parameter when unusable."""
    host = str(params.get('host', '127.0.0.1')).strip()
    if not host:
        raise ValueError("host: '' (allowed: an IP address or host name of the Modbus server)")
    try:
        port = int(params.get('port', 502))
    except (TypeError, ValueError):
        port = 0
    if not 1 <= port <= 65535:
        raise ValueError(f"port: {params.get('port')!r} (allowed: a TCP port 1..65535)")
    return ModbusTcpBus(host=host, port=port, timeout_s=float(params.get('timeout_s', 0.5)))
