"""The Modbus TCP server against hostile and broken clients, over real loopback sockets: a
client that never reads its answers, a flood of connections, a silent one, a frame trickled
byte by byte, and the ``[modbus]`` keys that bound them."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from plcstack import ConfigError, load_config
from plcstack.north.modbus import server as modbus_server
from plcstack.north.modbus.config import ModbusSettings, parse_modbus
from plcstack.north.modbus.server import ModbusServer
from plcstack.poll.engine import Poller
from plcstack.sim import e71
from tests.aio_helpers import ended_by_server, eventually

PLANT = """
[poll]
interval = 0.2
[modbus]
listen = "127.0.0.1:0"
{extra}
[[plc]]
name = "p"
url = "{url}"
[plc.tags]
block = {{ address = "D0", type = "int16", count = 125, modbus = "hr:0" }}
"""

#: read 125 holding registers: a 12-byte request, a 259-byte answer
READ_ALL = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0, 125)


@contextlib.asynccontextmanager
async def serving(tmp_path: Path, extra: str = "") -> AsyncIterator[ModbusServer]:
    """A Modbus server in front of a polled E71 simulator, once the first poll is in."""
    sim = await e71.start()
    path = tmp_path / "plant.toml"
    path.write_text(PLANT.format(url=sim.url, extra=extra))
    config = load_config(path)
    poller = Poller(config.poll)
    server = ModbusServer.from_config(poller, config.north.modbus)
    feed: asyncio.Task[None] | None = None
    try:
        async with poller, server:
            feed = asyncio.create_task(server.run())
            slot = server.image._by_tag[("p", "block")]
            await eventually(lambda: slot.words is not None, "the first poll reached the image")
            yield server
    finally:
        if feed is not None:
            feed.cancel()
            await asyncio.gather(feed, return_exceptions=True)
        await sim.aclose()


async def _answered(port: int) -> bytes:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(READ_ALL)
        return await asyncio.wait_for(reader.readexactly(259), 5)
    finally:
        writer.close()


async def test_a_client_that_never_reads_is_not_answered_into_memory(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: 5.7 MB of reads never read grew the server's write buffer to 119 MB in 15 s
    (+114 MB RSS). After: the server stops reading from that client at the transport's
    high-water mark, says so once, and serves the next client at once."""
    caplog.set_level(logging.WARNING, "plcstack.north.modbus")
    async with serving(tmp_path) as server:
        _reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        burst = READ_ALL * 1000
        sent = 0
        try:
            while sent < 2 * 1024 * 1024:  # 2 MB of requests = 43 MB of answers
                writer.write(burst)
                sent += len(burst)
                try:
                    await asyncio.wait_for(writer.drain(), 0.5)
                except TimeoutError:
                    break  # the server stopped reading: TCP pushes back on us
            (connection,) = server._connections
            assert connection.transport is not None
            held = connection.transport.get_write_buffer_size() + connection.codec.buffered
            assert held <= 1024 * 1024, f"{held} bytes held for a client that does not read"
            assert server.slow_clients == 1
            assert await _answered(server.port) == await _answered(server.port)
        finally:
            writer.transport.abort()
    said = [r.getMessage() for r in caplog.records if "does not read" in r.getMessage()]
    assert len(said) == 1, said


async def test_a_flood_of_connections_meets_max_clients(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: 1000 connections were 1000 clients (2000 descriptors, no limit). After: the
    clients beyond ``max_clients`` are closed at once, said once, and the limit frees again."""
    caplog.set_level(logging.WARNING, "plcstack.north.modbus")
    async with serving(tmp_path, "max_clients = 3") as server:
        held = [await asyncio.open_connection("127.0.0.1", server.port) for _ in range(3)]
        await eventually(lambda: server.clients == 3, "three clients are served")
        turned = [await asyncio.open_connection("127.0.0.1", server.port) for _ in range(5)]
        for reader, _ in turned:
            assert await ended_by_server(reader)
        assert server.limit.refused == 5 and server.clients == 3
        reader, writer = held[0]
        writer.write(READ_ALL)
        assert len(await asyncio.wait_for(reader.readexactly(259), 5)) == 259
        for _, w in held + turned:
            w.transport.abort()
        await eventually(lambda: server.clients == 0, "the clients are gone")
        assert len(await _answered(server.port)) == 259
    said = [r for r in caplog.records if "the limit" in r.getMessage()]
    assert len(said) == 1, [r.getMessage() for r in said]


async def test_silent_and_trickling_clients_are_ended(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before: a connection that never sent a byte, and one that sent a header byte now and
    then, were held for ever. After: the first is dropped after ``idle_timeout``, the second
    when its frame is not complete :data:`FRAME_TIMEOUT` seconds after its first byte."""
    monkeypatch.setattr(modbus_server, "FRAME_TIMEOUT", 0.5)
    async with serving(tmp_path, "idle_timeout = 0.3") as server:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        assert await ended_by_server(reader)
        assert server.idle_closed == 1
        writer.transport.abort()
    async with serving(tmp_path, "idle_timeout = 30") as server:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)

        async def trickle() -> None:
            for byte in READ_ALL[:-1]:
                writer.write(bytes([byte]))
                await asyncio.sleep(1.0)  # each byte well within idle_timeout

        dripping = asyncio.create_task(trickle())
        try:
            assert await ended_by_server(reader)
        finally:
            dripping.cancel()
            await asyncio.gather(dripping, return_exceptions=True)
            writer.transport.abort()
        assert server.idle_closed == 0 and server.protocol_errors == 1
        assert len(await _answered(server.port)) == 259


def test_modbus_limits_parse_and_refuse_nonsense() -> None:
    settings = parse_modbus({"max_clients": 4, "idle_timeout": 0})
    assert settings.max_clients == 4 and settings.idle_timeout is None
    assert parse_modbus({}) == ModbusSettings()
    assert ModbusSettings().idle_timeout == 600.0
    for table, message in [
        ({"max_clients": 0}, "max_clients must be 1..10000"),
        ({"max_clients": True}, "max_clients must be 1..10000"),
        ({"idle_timeout": -1}, "idle_timeout must be a number of seconds"),
        ({"idle_timeout": float("inf")}, "idle_timeout must be a number of seconds"),
        ({"max_client": 3}, "max_client (did you mean max_clients?)"),
    ]:
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace("?)", r"\?\)")):
            parse_modbus(table)
