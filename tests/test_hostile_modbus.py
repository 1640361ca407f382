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
from tests.guard_helpers import ATTACKER, IDLE_SOCKETS, guard_lines, idle_sockets
from tests.runtime_helpers import fed

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
    try:
        async with poller, server, fed(poller, server):
            slot = server.image._by_tag[("p", "block")]
            await eventually(lambda: slot.words is not None, "the first poll reached the image")
            yield server
    finally:
        await sim.aclose()


async def _answered(port: int, source: str | None = None) -> bytes:
    local = None if source is None else (source, 0)
    reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=local)
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
            (connection,) = server.connections
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
        assert server.guard.refused == 5 and server.clients == 3
        reader, writer = held[0]
        writer.write(READ_ALL)
        assert len(await asyncio.wait_for(reader.readexactly(259), 5)) == 259
        for _, w in held + turned:
            w.transport.abort()
        await eventually(lambda: server.clients == 0, "the clients are gone")
        assert len(await _answered(server.port)) == 259
    said = [r.getMessage() for r in caplog.records if "serves 3 clients at once" in r.getMessage()]
    assert len(said) == 2, said  # the first refusal at once, the count of the rest at the end
    assert "refusing 127.0.0.1:" in said[0]
    assert said[1].startswith("Modbus server: 4 more connections of 127.0.0.1 refused since")


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
    assert settings.limits.max_clients == 4 and settings.limits.idle_timeout is None
    assert settings.limits.max_clients_per_host == 3  # three quarters of max_clients
    assert parse_modbus({}) == ModbusSettings()
    assert ModbusSettings().limits.idle_timeout == 600.0
    assert ModbusSettings().limits.first_request_timeout == 10.0
    for table, message in [
        ({"max_clients": 0}, "max_clients must be 1..10000"),
        ({"max_clients": True}, "max_clients must be 1..10000"),
        ({"idle_timeout": -1}, "idle_timeout must be a number of seconds"),
        ({"idle_timeout": float("inf")}, "idle_timeout must be a number of seconds"),
        ({"max_client": 3}, "max_client (did you mean max_clients?)"),
    ]:
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace("?)", r"\?\)")):
            parse_modbus(table)


async def test_64_idle_sockets_of_one_host_lock_no_one_out(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: 64 silent sockets took 32 slots (max_clients) for 600 s each, renewable, and the
    next client was refused. After: one host gets 24 (max_clients_per_host), the rest are
    refused and counted, said in one line; another host is served at once, and the silent
    ones are closed at the first-request deadline, so their host is served again."""
    caplog.set_level(logging.WARNING, "plcstack.north.modbus")
    async with serving(tmp_path, "first_request_timeout = 1") as server:
        guard = server.guard
        counts = guard.counts
        async with idle_sockets(server.port):
            # every socket refused or holding a slot (or, on a slow machine, already closed
            # at its deadline, which let a later one in)
            await eventually(
                lambda: (
                    counts["max_clients_per_host"]
                    + guard.hosts[ATTACKER]
                    + counts["first_request_timeout"]
                    == IDLE_SOCKETS
                ),
                "all sockets seen",
            )
            assert guard.hosts[ATTACKER] <= 24
            assert len(await _answered(server.port)) == 259  # 127.0.0.1: served at once
            await eventually(lambda: not guard.hosts[ATTACKER], "the silent ones closed")
            assert len(await _answered(server.port, source=ATTACKER)) == 259
        refused, closed = counts["max_clients_per_host"], counts["first_request_timeout"]
        assert refused + closed == IDLE_SOCKETS and closed >= 24
    # each kind said once when it began, its count once when the server stopped
    lines = guard_lines(caplog)
    assert len(lines) == 4, lines
    assert "refusing 127.0.0.2:" in lines[0] and "one host may hold 24 connections" in lines[0]
    assert "closed the connection of 127.0.0.2:" in lines[1]
    assert "no complete request within 1 s" in lines[1]
    assert lines[2].startswith(f"Modbus server: {refused - 1} more connections of 127.0.0.2")
    assert lines[3].startswith(f"Modbus server: {closed - 1} more connections of 127.0.0.2")


async def test_one_clients_garbage_is_said_once_per_burst(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: a WARNING line per malformed frame (3,934 lines, 532 KB for 6,000 frames in
    the benchmark), the malformed writes without the client's address. After: the first one,
    naming the client, and the count of the rest once a minute."""
    caplog.set_level(logging.WARNING, "plcstack.north.modbus")
    async with serving(tmp_path) as server:
        bad_write = struct.pack(">HHHBBHHB", 1, 0, 9, 1, 16, 0, 1, 4) + b"\x00\x01"  # 4 != 2 bytes
        unknown = struct.pack(">HHHBB", 2, 0, 2, 1, 0x55)
        broken = struct.pack(">HHHB", 3, 7, 6, 1) + bytes(5)  # protocol id 7
        for _ in range(20):
            reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
            for frame in (bad_write, unknown) * 5:
                writer.write(frame)
                await reader.read(260)
            writer.write(broken)
            assert await reader.read() == b""  # closed
            writer.close()
        assert server.guard.counts["malformed"] == 20 * 11
    lines = guard_lines(caplog, "127.0.0.1")
    assert len(lines) == 2, lines  # the first; the count of the rest when the server stops
    assert "127.0.0.1:" in lines[0] and "malformed request" in lines[0]
    assert lines[1].startswith("Modbus server: 219 more malformed requests from 127.0.0.1")
