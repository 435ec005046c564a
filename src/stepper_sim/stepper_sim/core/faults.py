"""Link faults for simulators: a thread-safe switch the wire servers consult, and a TCP proxy.

`LinkFaults` holds one mode at a time:
  'ok'             replies pass
  'no_reply'       the request reaches the drive (a write takes effect) but the reply is lost
  'late_reply'     replies are delivered delay_s late (in order)
  'corrupt_reply'  reply bytes are garbled (default: every byte XOR 0xFF; `garble_one`: one
                   character of each reply, as line noise does)
  'cut'            every connection is closed and new ones are refused until the mode is 'ok'
Serial simulators check it before answering; TCP simulators put a `FaultyTcpProxy` in front of
their server. Drive faults are vendor-specific and live in each simulator.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import Callable

logger = logging.getLogger(__name__)

OK = 'ok'
NO_REPLY = 'no_reply'
LATE_REPLY = 'late_reply'
CORRUPT_REPLY = 'corrupt_reply'
CUT = 'cut'
MODES = (OK, NO_REPLY, LATE_REPLY, CORRUPT_REPLY, CUT)


def invert_bytes(data: bytes) -> bytes:
    """Default corruption: every bit flipped, so any framed protocol sees a bad frame."""
    return bytes(b ^ 0xFF for b in data)


def garble_one(data: bytes, index: int = 2) -> bytes:
    """One character of a reply replaced by '?' (or 0xBF where it was '?'): the reply keeps its
    length and framing but breaks its protocol's format at byte `index` (2: an X-MIND K code,
    the protocol id of a Modbus TCP header, the index of an SDO answer)."""
    if len(data) <= index:
        return data
    return data[:index] + (b'\xbf' if data[index] == 0x3F else b'?') + data[index + 1:]


class LinkFaults:
    """The current link fault; thread-safe. Listeners hear every change (mode, delay_s)."""

    def __init__(self, corrupt: Callable[[bytes], bytes] = invert_bytes):
        self._lock = threading.Lock()
        self._mode = OK
        self._delay_s = 0.0
        self._corrupt = corrupt
        self._listeners: list[Callable[[str, float], None]] = []
        self.counters = {'dropped': 0, 'delayed': 0, 'corrupted': 0, 'cut': 0}

    def set(self, mode: str, delay_s: float = 0.0) -> None:
        if mode not in MODES:
            raise ValueError(f'unknown link fault {mode!r}; modes: {", ".join(MODES)}')
        if mode == LATE_REPLY and not delay_s > 0:
            raise ValueError(f'late_reply needs a delay > 0 s, got {delay_s}')
        with self._lock:
            self._mode, self._delay_s = mode, float(delay_s) if mode == LATE_REPLY else 0.0
            listeners = list(self._listeners)
        logger.info('link fault: %s%s', mode, f' ({delay_s} s)' if mode == LATE_REPLY else '')
        for listener in listeners:
            listener(mode, delay_s)

    def ok(self) -> None:
        self.set(OK)

    @property
    def mode(self) -> str:
        with self._lock:
            return self._mode

    @property
    def delay_s(self) -> float:
        with self._lock:
            return self._delay_s

    def snapshot(self) -> tuple[str, float]:
        with self._lock:
            return self._mode, self._delay_s

    def count(self, what: str) -> None:
        with self._lock:
            self.counters[what] = self.counters.get(what, 0) + 1

    def corrupt(self, data: bytes) -> bytes:
        return self._corrupt(data)

    def add_listener(self, listener: Callable[[str, float], None]) -> None:
        with self._lock:
            self._listeners.append(listener)

    def remove_listener(self, listener: Callable[[str, float], None]) -> None:
        with self._lock:
            if listener in self._listeners:
                self._listeners.remove(listener)

    def apply_to_reply(self, reply: bytes) -> tuple[bytes | None, float]:
        """For servers without a proxy: (bytes to send or None, delay before sending in s)."""
        mode, delay = self.snapshot()
        if mode in (NO_REPLY, CUT):
            self.count('dropped')
            return None, 0.0
        if mode == CORRUPT_REPLY:
            self.count('corrupted')
            return self.corrupt(reply), 0.0
        if mode == LATE_REPLY:
            self.count('delayed')
            return reply, delay
        return reply, 0.0


class _Connection:
    def __init__(self, client: asyncio.StreamWriter, upstream: asyncio.StreamWriter):
        self.client = client
        self.upstream = upstream
        self.tasks: list[asyncio.Task] = []

    def close(self) -> None:
        for task in self.tasks:
            task.cancel()
        for writer in (self.client, self.upstream):
            try:
                writer.close()
            except Exception:   # already closed by the peer
                pass


class FaultyTcpProxy:
    """TCP proxy on host:port (127.0.0.1) to an internal server, applying a LinkFaults.

    Requests are forwarded unchanged; replies are dropped, delayed, corrupted as the fault says;
    'cut' closes every connection and the listening socket (connects are refused) until the mode
    leaves 'cut'. Create, `await start()` and `await stop()` in one asyncio loop.
    """

    def __init__(self, target_port: int, faults: LinkFaults, *, target_host: str = '127.0.0.1',
                 host: str = '127.0.0.1', port: int = 0):
        self.target = (target_host, int(target_port))
        self.faults = faults
        self.host = host
        self.port = int(port)
        self._server: asyncio.base_events.Server | None = None
        self._connections: set[_Connection] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopped = False

    @property
    def listening(self) -> bool:
        return self._server is not None

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self.faults.add_listener(self._on_fault_threadsafe)
        if self.faults.mode != CUT:
            await self._listen()

    async def stop(self) -> None:
        self._stopped = True
        self.faults.remove_listener(self._on_fault_threadsafe)
        await self._close_all()

    async def _listen(self) -> None:
        if self._server is None and not self._stopped:
            self._server = await asyncio.start_server(self._handle, self.host, self.port,
                                                      reuse_address=True)
            self.port = self._server.sockets[0].getsockname()[1]
            logger.debug('proxy listening on %s:%d -> %s:%d', self.host, self.port, *self.target)

    async def _close_all(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            server.close()
        for conn in list(self._connections):
            conn.close()
        self._connections.clear()
        if server is not None:
            await server.wait_closed()

    def _on_fault_threadsafe(self, mode: str, _delay_s: float) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(lambda: asyncio.ensure_future(self._on_fault(mode)))

    async def _on_fault(self, mode: str) -> None:
        if mode == CUT:
            if self._server is not None or self._connections:
                self.faults.count('cut')
            await self._close_all()
        else:
            await self._listen()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.faults.mode == CUT:
            writer.close()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection(*self.target)
        except OSError as exc:
            logger.warning('proxy: internal server %s:%d unreachable: %s', *self.target, exc)
            writer.close()
            return
        conn = _Connection(writer, up_writer)
        self._connections.add(conn)
        queue: asyncio.Queue = asyncio.Queue()
        conn.tasks = [asyncio.ensure_future(self._pump_requests(reader, up_writer, conn)),
                      asyncio.ensure_future(self._pump_replies(up_reader, queue, conn)),
                      asyncio.ensure_future(self._send_replies(queue, writer, conn))]

    async def _pump_requests(self, reader, up_writer, conn: _Connection) -> None:
        try:
            while data := await reader.read(65536):
                up_writer.write(data)
                await up_writer.drain()
        except (OSError, asyncio.IncompleteReadError):
            pass
        finally:
            self._drop(conn)

    async def _pump_replies(self, up_reader, queue: asyncio.Queue, conn: _Connection) -> None:
        loop = asyncio.get_running_loop()
        try:
            while data := await up_reader.read(65536):
                mode, delay = self.faults.snapshot()
                if mode in (NO_REPLY, CUT):
                    self.faults.count('dropped')
                    continue
                if mode == CORRUPT_REPLY:
                    self.faults.count('corrupted')
                    data = self.faults.corrupt(data)
                if mode == LATE_REPLY:
                    self.faults.count('delayed')
                queue.put_nowait((loop.time() + (delay if mode == LATE_REPLY else 0.0), data))
        except OSError:
            pass
        finally:
            self._drop(conn)

    async def _send_replies(self, queue: asyncio.Queue, writer, conn: _Connection) -> None:
        loop = asyncio.get_running_loop()
        try:
            while True:
                deliver_at, data = await queue.get()
                wait_s = deliver_at - loop.time()
                if wait_s > 0:
                    await asyncio.sleep(wait_s)
                writer.write(data)
                await writer.drain()
        except OSError:
            self._drop(conn)

    def _drop(self, conn: _Connection) -> None:
        if conn in self._connections:
            self._connections.discard(conn)
            conn.close()
