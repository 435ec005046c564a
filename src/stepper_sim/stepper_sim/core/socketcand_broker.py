"""A loopback CAN bus for tests: a socketcand "rawmode" server that relays frames between clients.

Every process (simulated drives, the driver node, a test listening in) opens python-can's stock
`socketcand` interface on 127.0.0.1; the broker forwards each frame one client sends to all other
clients on the same channel, as a CAN bus does (no echo to the sender, order kept per sender).
No kernel module (vcan) is needed, and the driver keeps a normal `can.Bus`, so a user with
hardware only changes `can.interface`/`can.channel`. Only the subset of the socketcand protocol
(linux-can/socketcand, doc/protocol.md) that python-can's client uses is served:

    server: < hi >                 client: < open can0 >      server: < ok >
    client: < rawmode >            server: < ok >
    client: < send 601 8 40 0 10 0 0 0 0 0 >
    others: < frame 601 1700000000.000123 4000100000000000 >

A client that stays in BCM mode (no `< rawmode >`) may send frames the same way and gets none
(the node's SYNC and heartbeat producer, stepper_drivers.protocol.canopen_producers, is one).
python-can compares the whole of one recv() with "< hi >" / "< ok >" during the handshake, so the
broker sends them on their own and holds frames for a new client for `ready_delay_s` after its
"< ok >" to rawmode (they are queued, not dropped). Remote (RTR) frames cannot be carried: the
client sends them as 0-byte data frames (transports.md A4).

Run: `ros2 run stepper_sim socketcand_broker --port 0` (prints the port it got) or
`python -m stepper_sim.core.socketcand_broker`; in-process:
`with SocketcandBroker() as broker: ...`.
Binds to the loopback interface only. No rclpy. It is a stand-in for CAN hardware, like the
simulators it serves, so it lives with them (stepper_sim), not in the driver's protocol layer.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
import threading
import time

logger = logging.getLogger(__name__)

DEFAULT_PORT = 29536                 # socketcand's own default port
LOOPBACK_HOSTS = ('127.0.0.1', 'localhost')
READ_CHUNK = 65536


def check_loopback(host: str) -> str:
    if host not in LOOPBACK_HOSTS:
        raise ValueError(f'socketcand broker host {host!r}: only the loopback interface is '
                         f'allowed ({", ".join(LOOPBACK_HOSTS)})')
    return '127.0.0.1'


class _Client:
    def __init__(self, broker: 'SocketcandBroker', writer: asyncio.StreamWriter):
        self.broker = broker
        self.writer = writer
        self.peer = writer.get_extra_info('peername')
        self.channel: str | None = None
        self.raw = False
        self.ready_at = 0.0
        self.queue: asyncio.Queue[str] = asyncio.Queue()
        self.sender: asyncio.Task | None = None

    def reply(self, text: str) -> None:
        self.writer.write(text.encode('ascii'))

    async def send_frames(self) -> None:
        """Write queued frames, batched, once the client has finished its handshake."""
        delay = self.ready_at - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)
        while True:
            parts = [await self.queue.get()]
            while not self.queue.empty():
                parts.append(self.queue.get_nowait())
            self.writer.write(''.join(parts).encode('ascii'))
            await self.writer.drain()


class SocketcandBroker:
    """The relay; `start()` runs it on an asyncio loop in a thread and returns the port."""

    def __init__(self, host: str = '127.0.0.1', port: int = 0, ready_delay_s: float = 0.05):
        self.host = check_loopback(host)
        self.requested_port = int(port)
        self.port = 0
        self.ready_delay_s = ready_delay_s
        self.frames_in = 0
        self.frames_out = 0
        self._clients: set[_Client] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: asyncio.base_events.Server | None = None
        self._thread: threading.Thread | None = None
        self._stopped: asyncio.Event | None = None

    @property
    def address(self) -> str:
        return f'{self.host}:{self.port}'

    @property
    def clients(self) -> int:
        return len(self._clients)

    # Life cycle --------------------------------------------------------------------------------
    async def open(self) -> None:
        self._stopped = asyncio.Event()
        self._server = await asyncio.start_server(self._handle, self.host, self.requested_port)
        self.port = self._server.sockets[0].getsockname()[1]
        logger.info('socketcand broker listening on %s', self.address)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for client in list(self._clients):
            if client.sender:
                client.sender.cancel()
            client.writer.close()
        if self._server is not None:
            await self._server.wait_closed()
        if self._stopped is not None:
            self._stopped.set()

    async def serve(self) -> None:
        """open(), then run until close() is awaited from another task."""
        if self._server is None:
            await self.open()
        assert self._stopped is not None
        await self._stopped.wait()

    def start(self) -> int:
        """Run in a background thread; return the listening port."""
        started = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            try:
                loop.run_until_complete(self.open())
            except BaseException as exc:   # reported to the caller of start()
                failure.append(exc)
                started.set()
                loop.close()
                return
            started.set()
            loop.run_until_complete(self.serve())
            loop.close()

        self._thread = threading.Thread(target=run, name='socketcand-broker', daemon=True)
        self._thread.start()
        started.wait(10.0)
        if failure:
            raise failure[0]
        return self.port

    def stop(self) -> None:
        if self._loop is not None and self._thread is not None and self._thread.is_alive():
            asyncio.run_coroutine_threadsafe(self.close(), self._loop).result(5.0)
            self._thread.join(5.0)
        self._thread = None

    def __enter__(self) -> 'SocketcandBroker':
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # Protocol ----------------------------------------------------------------------------------
    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = _Client(self, writer)
        self._clients.add(client)
        logger.debug('client %s connected', client.peer)
        buffer = ''
        try:
            client.reply('< hi >')
            await writer.drain()
            while True:
                chunk = await reader.read(READ_CHUNK)
                if not chunk:
                    break
                buffer += chunk.decode('ascii', errors='replace')
                while True:
                    start = buffer.find('<')
                    end = buffer.find('>', start + 1)
                    if start < 0:
                        buffer = ''
                        break
                    if end < 0:
                        buffer = buffer[start:]
                        break
                    self._command(client, buffer[start + 1:end].split())
                    buffer = buffer[end + 1:]
                await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            self._clients.discard(client)
            if client.sender:
                client.sender.cancel()
            writer.close()
            logger.debug('client %s left', client.peer)

    def _command(self, client: _Client, words: list[str]) -> None:
        if not words:
            return
        verb = words[0]
        if verb == 'send' and client.channel is not None and len(words) >= 3:
            # rawmode, or BCM mode (a client that only sends: the node's SYNC producer); a
            # client in BCM mode gets no frames (no `subscribe` here)
            self._relay(client, words)
        elif verb == 'open' and len(words) == 2:
            client.channel = words[1]
            client.reply('< ok >')
        elif verb == 'rawmode' and client.channel is not None:
            client.raw = True
            client.ready_at = time.monotonic() + self.ready_delay_s
            client.reply('< ok >')
            client.sender = asyncio.get_running_loop().create_task(client.send_frames())
        elif verb == 'echo':
            client.reply('< echo >')
        else:
            client.reply(f'< error unsupported command {verb} >')

    def _relay(self, sender: _Client, words: list[str]) -> None:
        try:
            can_id = words[1]
            length = int(words[2], 16)
            data = ''.join(f'{int(b, 16):02X}' for b in words[3:3 + length])
        except ValueError:
            sender.reply('< error bad frame >')
            return
        if len(can_id) <= 3:
            can_id = can_id.rjust(3, '0')
        now = time.time()
        frame = f'< frame {can_id} {int(now)}.{int(now % 1 * 1e6):06d} {data} >'
        self.frames_in += 1
        for client in self._clients:
            if client is not sender and client.raw and client.channel == sender.channel:
                client.queue.put_nowait(frame)
                self.frames_out += 1


    def error_frame(self, error_class: int, channel: str = 'can0') -> None:
        """Send every client on `channel` an error frame, as socketcand forwards the SocketCAN
        controller's (`< error <class> <time> >`; error_class: the CAN_ERR_* bits of
        linux/can/error.h, 0x040 bus-off). From any thread."""
        now = time.time()
        frame = f'< error {error_class:03X} {int(now)}.{int(now % 1 * 1e6):06d} >'

        def put() -> None:
            for client in self._clients:
                if client.raw and client.channel == channel:
                    client.queue.put_nowait(frame)
        if self._loop is None:
            raise RuntimeError('the broker is not running')
        self._loop.call_soon_threadsafe(put)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description='Loopback socketcand (rawmode) CAN broker for tests')
    ap.add_argument('--host', default='127.0.0.1', help='loopback only (default 127.0.0.1)')
    ap.add_argument('--port', type=int, default=DEFAULT_PORT,
                    help=f'TCP port (default {DEFAULT_PORT}; 0 = any free port)')
    ap.add_argument('--verbose', action='store_true')
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format='[socketcand_broker] %(levelname)s %(message)s')
    try:
        broker = SocketcandBroker(args.host, args.port)
    except ValueError as exc:
        print(f'socketcand_broker: {exc}', file=sys.stderr)
        return 2

    async def run() -> None:
        try:
            await broker.open()
        except OSError as exc:
            print(f'socketcand_broker: cannot listen on {args.host}:{args.port}: {exc}',
                  file=sys.stderr, flush=True)
            raise SystemExit(1) from None
        print(f'socketcand_broker: listening on {broker.address}', flush=True)
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, lambda: loop.create_task(broker.close()))
        await broker.serve()

    asyncio.run(run())
    print(f'socketcand_broker: stopped ({broker.frames_in} frames in, '
          f'{broker.frames_out} out)', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
