"""The web console and the metrics endpoint against hostile and broken HTTP clients, over real
loopback sockets: silent and trickling connections, garbage requests, a client that never
reads its answer, a flood."""

from __future__ import annotations

import asyncio
import logging

import prometheus_client
import pytest

from plcstack.north import metrics
from plcstack.north.metrics import MetricsServer, MetricsSettings, PlcstackCollector
from plcstack.poll.config import PollConfig
from plcstack.poll.engine import Poller
from plcstack.transports.guard import Limits
from tests.aio_helpers import ended_by_server, eventually
from tests.guard_helpers import ATTACKER, IDLE_SOCKETS, guard_lines, idle_sockets
from tests.web_helpers import running_console


async def test_web_console_ends_silent_and_trickling_connections(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Before: aiohttp's default keep-alive of 3630 s held a socket that never sent a byte, and
    one sending a header a byte at a time, for an hour. After: the first request's deadline
    (shortened here), counted as such."""
    limits = Limits(max_clients=256, first_request_timeout=0.5, idle_timeout=75)
    async with running_console(limits=limits) as console:
        reader, writer = await asyncio.open_connection("127.0.0.1", console.web.port)
        assert await ended_by_server(reader)
        writer.transport.abort()

        reader, writer = await asyncio.open_connection("127.0.0.1", console.web.port)

        async def trickle() -> None:
            for byte in b"GET /api/tags HTTP/1.1\r\nHost: x\r\n":
                writer.write(bytes([byte]))
                await asyncio.sleep(0.2)

        dripping = asyncio.create_task(trickle())
        try:
            assert await ended_by_server(reader)
            assert not dripping.done()
        finally:
            dripping.cancel()
            await asyncio.gather(dripping, return_exceptions=True)
            writer.transport.abort()
        assert console.web.guard.counts["first_request_timeout"] == 2


GARBAGE = [
    b"\x00" * 4096,
    b"GET /" + b"a" * 70000 + b" HTTP/1.1\r\n\r\n",
    b"POST /api/plcs/p/tags/t HTTP/1.1\r\nHost: x\r\nContent-Length: -1\r\n\r\n",
    b"POST /api/plcs/p/tags/t HTTP/1.1\r\nHost: x\r\nContent-Length: 99999999999999999999\r\n\r\n",
    b"GET / HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\nffffffffffffffffff\r\n",
    b"GET / HTTP/1.1\r\nContent-Length: 5\r\n\r\n",
]


async def test_web_console_answers_garbage_400_without_a_traceback(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Before: every request aiohttp could not parse was an ERROR with a traceback in the log
    ("Error handling request"); then a WARNING line each. After: 400, and one WARNING line
    naming the client for the burst, the count of the rest when the console stops."""
    caplog.set_level(logging.DEBUG)
    async with running_console() as console:
        for request in GARBAGE:
            reader, writer = await asyncio.open_connection("127.0.0.1", console.web.port)
            writer.write(request)
            answer = await asyncio.wait_for(reader.read(64), 5)
            assert answer.startswith(b"HTTP/1.") and b" 400 " in answer, (request[:40], answer)
            writer.transport.abort()
        reader, writer = await asyncio.open_connection("127.0.0.1", console.web.port)
        writer.write(b"GET /api/plcs HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        assert b" 200 " in await asyncio.wait_for(reader.read(64), 5)
        writer.close()
        assert console.web.guard.counts["malformed"] == len(GARBAGE)
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert errors == [], [r.getMessage() for r in errors]
    said = [r.getMessage() for r in caplog.records if "127.0.0.1" in r.getMessage()]
    said = [line for line in said if "bad HTTP request" in line or "more malformed" in line]
    assert len(said) == 2, said
    assert "web console: 127.0.0.1 sent a bad HTTP request, answered 400" in said[0]
    assert said[1].startswith(f"web console: {len(GARBAGE) - 1} more malformed requests from")


def _Poller() -> Poller:
    return Poller(PollConfig((), {"default": 1.0}))


def _handlers() -> list[asyncio.Task[object]]:
    return [
        t
        for t in asyncio.all_tasks()
        if getattr(t.get_coro(), "__qualname__", "") == "MetricsServer._handle"
    ]


async def test_metrics_client_that_never_reads_is_dropped(monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: a scrape whose answer the client never read held its connection, its task and the
    whole answer for ever (the close waited for the answer to be sent), and the task was logged
    as an error at shutdown. After: dropped at the request deadline (shortened here)."""
    monkeypatch.setattr(metrics, "REQUEST_TIMEOUT", 0.5, raising=False)
    big = b"# " + b"x" * (32 * 1024 * 1024) + b"\n"  # beyond what the sockets' buffers hold
    monkeypatch.setattr(prometheus_client, "generate_latest", lambda registry: big)
    server = MetricsServer(PlcstackCollector(_Poller()), MetricsSettings(port=0))
    await server.start()
    _reader, writer = await asyncio.open_connection("127.0.0.1", server.port, limit=1024)
    try:
        writer.write(b"GET /metrics HTTP/1.1\r\n\r\n")
        await eventually(lambda: _handlers(), "the request is taken")
        await eventually(lambda: not _handlers(), "the client that does not read is dropped")
    finally:
        writer.transport.abort()
        await server.aclose()


async def test_metrics_flood_meets_its_limit() -> None:
    """Before: no limit (1000 connections: 1000 served). After: MAX_CLIENTS at once, the next
    ones closed at once and counted; the endpoint answers again once they are gone (all from
    one host here: the per-host cap is another test's)."""
    limits = Limits(max_clients=metrics.MAX_CLIENTS, max_clients_per_host=metrics.MAX_CLIENTS)
    server = MetricsServer(PlcstackCollector(_Poller()), MetricsSettings(port=0, limits=limits))
    await server.start()
    try:
        held = [
            await asyncio.open_connection("127.0.0.1", server.port)
            for _ in range(metrics.MAX_CLIENTS)
        ]
        await eventually(
            lambda: server.guard.current == metrics.MAX_CLIENTS, "the first ones are served"
        )
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        assert await ended_by_server(reader)
        assert server.guard.refused == 1
        writer.transport.abort()
        for _, w in held:
            w.transport.abort()
        await eventually(lambda: server.guard.current == 0, "the held ones are gone")
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(b"GET /healthz HTTP/1.1\r\n\r\n")
        assert (await asyncio.wait_for(reader.read(), 5)).startswith(b"HTTP/1.1 200 OK")
        writer.close()
    finally:
        await server.aclose()


async def test_web_console_flood_meets_its_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: 1000 connections were 1000 served (2000 descriptors; no limit in aiohttp). After:
    max_clients at once (shortened here), the next answered 503 and closed, said once."""
    limits = Limits(max_clients=3, max_clients_per_host=3, idle_timeout=75)
    async with running_console(limits=limits) as console:
        runner = console.web._runner
        assert runner is not None and runner.server is not None
        http = runner.server
        held = [await asyncio.open_connection("127.0.0.1", console.web.port) for _ in range(3)]
        await eventually(lambda: len(http.connections) == 3, "three connections are served")
        reader, writer = await asyncio.open_connection("127.0.0.1", console.web.port)
        answer = await asyncio.wait_for(reader.read(), 5)
        assert answer.startswith(b"HTTP/1.1 503 "), answer
        writer.transport.abort()
        for _, w in held:
            w.transport.abort()
        await eventually(lambda: not http.connections, "the held connections are gone")
        reader, writer = await asyncio.open_connection("127.0.0.1", console.web.port)
        writer.write(b"GET /api/plcs HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        assert b" 200 " in await asyncio.wait_for(reader.read(64), 5)
        writer.close()
        assert console.web.guard.refused == 1


async def test_64_idle_sockets_lock_no_one_out_of_the_console(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """64 silent sockets of one host: the console (256 connections) serves another client at
    once, and closes the silent ones at the first-request deadline, said once with the count."""
    caplog.set_level(logging.WARNING)
    limits = Limits(max_clients=256, first_request_timeout=1.0, idle_timeout=75)
    async with running_console(limits=limits) as console:
        guard = console.web.guard
        async with idle_sockets(console.web.port):
            await eventually(
                lambda: (
                    guard.hosts[ATTACKER] + guard.counts["first_request_timeout"] == IDLE_SOCKETS
                ),
                "every socket holding a slot",
            )
            reader, writer = await asyncio.open_connection("127.0.0.1", console.web.port)
            writer.write(b"GET /api/plcs HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
            assert b" 200 " in await asyncio.wait_for(reader.read(64), 5)
            writer.close()
            await eventually(lambda: not guard.hosts[ATTACKER], "the silent sockets closed")
        assert guard.counts["first_request_timeout"] == IDLE_SOCKETS and guard.refused == 0
    lines = guard_lines(caplog)
    assert len(lines) == 2, lines
    assert "closed the connection of 127.0.0.2:" in lines[0]
    assert lines[1].startswith(f"web console: {IDLE_SOCKETS - 1} more connections of")


async def test_64_idle_sockets_lock_no_one_out_of_the_metrics(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """64 silent sockets of one host: /metrics (16 connections, 12 per host) refuses 52 and
    says so once, serves another host at once, and closes the silent 12 at the first-request
    deadline."""
    caplog.set_level(logging.WARNING)
    limits = Limits(max_clients=16, first_request_timeout=1.0, idle_timeout=None)
    server = MetricsServer(PlcstackCollector(_Poller()), MetricsSettings(port=0, limits=limits))
    await server.start()
    guard = server.guard
    try:
        async with idle_sockets(server.port):
            await eventually(
                lambda: (
                    guard.refused + guard.hosts[ATTACKER] + guard.counts["first_request_timeout"]
                    == IDLE_SOCKETS
                ),
                "every socket refused or holding a slot",
            )
            reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
            writer.write(b"GET /healthz HTTP/1.1\r\n\r\n")
            assert (await asyncio.wait_for(reader.read(), 5)).startswith(b"HTTP/1.1 200 OK")
            writer.close()
            await eventually(lambda: not guard.hosts[ATTACKER], "the silent sockets closed")
        assert guard.refused + guard.counts["first_request_timeout"] == IDLE_SOCKETS
        assert guard.counts["first_request_timeout"] >= 12
    finally:
        await server.aclose()
    lines = guard_lines(caplog)
    assert len(lines) == 4, lines  # the refusals and the closes: each once, then its count
    assert "refusing 127.0.0.2:" in lines[0] and "one host may hold 12 connections" in lines[0]
