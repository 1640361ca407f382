"""TCP/UDP transports and the backoff policy, over real loopback sockets."""

import asyncio
import socket
import typing

import pytest

from plcstack.errors import ConnectFailed, ConnectionLost
from plcstack.transports import Backoff, TcpTransport, UdpTransport
from tests.aio_helpers import ends_quietly
from tests.ports import free_port


async def test_tcp_roundtrip_eof_and_reopen() -> None:
    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        data = await reader.read(100)
        writer.write(data.upper())
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(ends_quietly(handle), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        t = TcpTransport("127.0.0.1", port)
        await t.open(1.0)
        assert t.is_open
        t.write(b"abc")
        assert await t.read() == b"ABC"
        with pytest.raises(ConnectionLost, match="lost"):
            await t.read()
        assert not t.is_open
        with pytest.raises(ConnectionLost, match="not connected"):
            t.write(b"x")
        await t.open(1.0)  # re-openable
        t.write(b"q")
        assert await t.read() == b"Q"
        await t.aclose()
        assert not t.is_open


async def test_tcp_connect_refused_is_connect_failed() -> None:
    t = TcpTransport("127.0.0.1", free_port())
    with pytest.raises(ConnectFailed, match="cannot connect to 127.0.0.1"):
        await t.open(1.0)


class _UdpEcho(asyncio.DatagramProtocol):
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = typing.cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.transport.sendto(b"echo:" + data, addr)


async def test_udp_one_datagram_per_read_and_foreign_sources_ignored() -> None:
    loop = asyncio.get_running_loop()
    echo, _ = await loop.create_datagram_endpoint(_UdpEcho, local_addr=("127.0.0.1", 0))
    port = echo.get_extra_info("sockname")[1]
    t = UdpTransport("127.0.0.1", port)
    await t.open(1.0)
    local = t._transport.get_extra_info("sockname")  # type: ignore[union-attr]
    # A stranger sends to our local port first: it must never be read as the answer.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger:
        stranger.sendto(b"spoofed", local)
    await asyncio.sleep(0.05)
    t.write(b"a")
    t.write(b"b")
    assert await t.read() == b"echo:a"
    assert await t.read() == b"echo:b"
    t.abort()
    await t.open(1.0)
    assert t._transport.get_extra_info("sockname") != local  # type: ignore[union-attr]
    t.abort()
    echo.close()


async def test_udp_port_unreachable_is_reported_not_a_timeout() -> None:
    t = UdpTransport("127.0.0.1", free_port())
    await t.open(1.0)
    t.write(b"hello")
    with pytest.raises(ConnectionLost):
        async with asyncio.timeout(2):
            await t.read()
    t.abort()


def test_backoff_grows_caps_jitters_and_resets() -> None:
    b = Backoff(initial=0.1, maximum=1.0, factor=2.0, jitter=0.0)
    assert [round(b.next_delay(), 6) for _ in range(6)] == [0.1, 0.2, 0.4, 0.8, 1.0, 1.0]
    assert b.failures == 6
    b.reset()
    assert b.next_delay() == pytest.approx(0.1)
    j = Backoff(initial=1.0, maximum=10.0, jitter=0.5)
    delays = [j.next_delay() for _ in range(1)] + [
        Backoff(1.0, 10.0, 2.0, 0.5).next_delay() for _ in range(200)
    ]
    assert all(0.5 <= d <= 1.5 for d in delays)
    assert len({round(d, 6) for d in delays}) > 10  # really jittered
    with pytest.raises(ValueError):
        Backoff(initial=2.0, maximum=1.0)
