"""LinkFaults and FaultyTcpProxy against a real TCP echo server on 127.0.0.1."""

import asyncio
import contextlib
import time

import pytest
from stepper_sim.core.faults import MODES, FaultyTcpProxy, LinkFaults, invert_bytes


@contextlib.asynccontextmanager
async def echo_and_proxy(faults: LinkFaults):
    async def echo(reader, writer):
        try:
            while data := await reader.read(1024):
                writer.write(data)
                await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(echo, '127.0.0.1', 0)
    proxy = FaultyTcpProxy(server.sockets[0].getsockname()[1], faults)
    await proxy.start()
    try:
        yield proxy
    finally:
        await proxy.stop()
        server.close()
        await server.wait_closed()


async def connect(port):
    return await asyncio.wait_for(asyncio.open_connection('127.0.0.1', port), 2.0)


async def ask(reader, writer, data: bytes, timeout_s: float = 2.0) -> bytes:
    writer.write(data)
    await writer.drain()
    return await asyncio.wait_for(reader.readexactly(len(data)), timeout_s)


async def wait_for(cond, timeout_s: float = 2.0):
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError('condition not met')
        await asyncio.sleep(0.005)


def test_link_faults_validates_and_notifies():
    faults = LinkFaults()
    seen = []
    faults.add_listener(lambda mode, delay: seen.append((mode, delay)))
    with pytest.raises(ValueError, match='unknown link fault .*modes: ok, no_reply'):
        faults.set('lost')
    with pytest.raises(ValueError, match='late_reply needs a delay > 0 s'):
        faults.set('late_reply')
    faults.set('late_reply', 0.25)
    assert faults.snapshot() == ('late_reply', 0.25)
    assert faults.apply_to_reply(b'ab') == (b'ab', 0.25)
    faults.set('corrupt_reply')
    assert faults.apply_to_reply(b'\x00\x0f') == (b'\xff\xf0', 0.0)
    faults.set('no_reply')
    assert faults.apply_to_reply(b'x') == (None, 0.0)
    faults.ok()
    assert faults.apply_to_reply(b'x') == (b'x', 0.0)
    assert seen[0] == ('late_reply', 0.25) and seen[-1] == ('ok', 0.0)
    assert faults.counters['dropped'] == 1 and faults.counters['corrupted'] == 1
    assert MODES == ('ok', 'no_reply', 'late_reply', 'corrupt_reply', 'cut')


def test_proxy_passes_delays_drops_and_corrupts():
    async def scenario():
        faults = LinkFaults()
        async with echo_and_proxy(faults) as proxy:
            reader, writer = await connect(proxy.port)
            assert await ask(reader, writer, b'hello') == b'hello'

            faults.set('late_reply', 0.3)
            t0 = time.monotonic()
            assert await ask(reader, writer, b'late') == b'late'
            assert time.monotonic() - t0 >= 0.29

            faults.set('no_reply')
            with pytest.raises(asyncio.TimeoutError):
                await ask(reader, writer, b'lost', timeout_s=0.3)
            faults.ok()
            # the dropped reply never shows up later: the next answer is the next request's
            assert await ask(reader, writer, b'next') == b'next'

            faults.set('corrupt_reply')
            assert await ask(reader, writer, b'\x01\x02\xff') == invert_bytes(b'\x01\x02\xff')
            faults.ok()
            assert await ask(reader, writer, b'clean') == b'clean'
            writer.close()
            assert faults.counters['delayed'] == 1 and faults.counters['dropped'] == 1
    asyncio.run(scenario())


def test_cut_closes_connections_refuses_new_ones_until_ok():
    async def scenario():
        faults = LinkFaults()
        async with echo_and_proxy(faults) as proxy:
            port = proxy.port
            reader, writer = await connect(port)
            assert await ask(reader, writer, b'ping') == b'ping'
            faults.set('cut')
            # the open connection is closed by the proxy: EOF (or a reset)
            try:
                data = await asyncio.wait_for(reader.read(10), 2.0)
                assert data == b''
            except ConnectionError:
                pass
            await wait_for(lambda: not proxy.listening)
            with pytest.raises(ConnectionRefusedError):
                await connect(port)
            faults.ok()
            await wait_for(lambda: proxy.listening)
            assert proxy.port == port                      # same address as before
            reader, writer = await connect(port)
            assert await ask(reader, writer, b'back') == b'back'
            writer.close()
            assert faults.counters['cut'] == 1
    asyncio.run(scenario())


def test_proxy_set_from_another_thread_applies():
    async def scenario():
        faults = LinkFaults()
        async with echo_and_proxy(faults) as proxy:
            reader, writer = await connect(proxy.port)
            await asyncio.to_thread(faults.set, 'cut')      # e.g. a ROS service thread
            await wait_for(lambda: not proxy.listening)
            await asyncio.to_thread(faults.ok)
            await wait_for(lambda: proxy.listening)
            writer.close()
    asyncio.run(scenario())
