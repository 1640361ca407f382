"""The OPC UA server's client limits: a flood cannot take the process's file descriptors, a
socket that activates no session is closed at the first request's deadline, and refusals and
closes are counted and said once per burst, not once per connection."""

from __future__ import annotations

import asyncio
import logging

import pytest
from asyncua.client.client import Client

from plcstack.north.opcua import OpcUaServer
from plcstack.north.opcua_config import DEFAULT_MAX_CLIENTS, OpcUaConfig, parse_opcua_config
from plcstack.north.opcua_users import AsyncuaSays
from plcstack.poll.config import ConfigError, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from tests.aio_helpers import ended_by_server, eventually
from tests.guard_helpers import IDLE_SOCKETS, guard_lines, idle_sockets

LISTENER = "asyncua.server.binary_server_asyncio"


def _poller() -> Poller:
    # never started: the server only needs its configuration for the address space
    plc = PlcConfig(name="p", url="e71+tcp://127.0.0.1:5000", tags=(TagConfig("a", "D0"),))
    return Poller(PollConfig((plc,)))


async def test_connections_beyond_max_clients_are_closed_at_once_and_said_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = OpcUaConfig(endpoint="opc.tcp://127.0.0.1:0/plcstack", max_clients=2)
    caplog.set_level(logging.WARNING)
    opened: list[asyncio.StreamWriter] = []
    async with OpcUaServer(_poller(), config) as server:
        port = int(server.url.rsplit(":", 1)[1].split("/")[0])
        try:
            kept = [await asyncio.open_connection("127.0.0.1", port) for _ in range(2)]
            opened += [w for _, w in kept]
            for _ in range(3):
                reader, writer = await asyncio.open_connection("127.0.0.1", port)
                opened.append(writer)
                assert await ended_by_server(reader), "a connection beyond the limit stayed open"
            for reader, _ in kept:  # the two within the limit are served (asyncua waits for Hello)
                assert not await ended_by_server(reader, bound=0.2)
        finally:
            for writer in opened:
                writer.close()
        assert server.guard.counts["max_clients"] == 3
        assert not [r for r in caplog.records if "Refusing connection" in r.getMessage()]
    # said by the guard: the first refusal at once, the count of the others when it stops
    said = [r.getMessage() for r in caplog.records if "OPC UA server:" in r.getMessage()]
    assert len(said) == 2, said
    assert "refusing 127.0.0.1:" in said[0] and "serves 2 clients at once" in said[0]
    assert said[1].startswith("OPC UA server: 2 more connections of 127.0.0.1 refused")
    # the filter goes with the server
    assert not any(isinstance(f, AsyncuaSays) for f in logging.getLogger(LISTENER).filters)


def test_max_clients_is_read_and_checked() -> None:
    assert parse_opcua_config({}).max_clients == DEFAULT_MAX_CLIENTS == 64
    assert parse_opcua_config({"max_clients": 5}).max_clients == 5
    for bad in (0, -1, 10_001, "8", True, 2.5):
        with pytest.raises(ConfigError, match="max_clients must be 1..10000"):
            parse_opcua_config({"max_clients": bad})
    with pytest.raises(ConfigError, match="did you mean max_clients"):
        parse_opcua_config({"max_client": 5})


def test_first_request_timeout_is_read_and_checked() -> None:
    assert parse_opcua_config({}).first_request_timeout == 10.0
    assert parse_opcua_config({"first_request_timeout": 2}).first_request_timeout == 2
    assert parse_opcua_config({"first_request_timeout": 0}).first_request_timeout == 30.0
    for bad in (-1, "8", True):
        with pytest.raises(ConfigError, match="first_request_timeout must be a number of seconds"):
            parse_opcua_config({"first_request_timeout": bad})


@pytest.mark.slow  # several seconds: run by the slow run
async def test_64_idle_sockets_are_closed_at_the_first_requests_deadline(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Before: 64 sockets that never sent a byte held all 64 connections for 30 s (asyncua's
    activation watchdog), each close a WARNING line. After: closed at the first request's
    deadline (1 s here), counted and said once with the count; a client that waited for a
    free connection meanwhile is served then."""
    caplog.set_level(logging.WARNING)
    config = OpcUaConfig(
        endpoint="opc.tcp://127.0.0.1:0/plcstack", max_clients=64, first_request_timeout=1.0
    )
    async with OpcUaServer(_poller(), config) as server:
        port = int(server.url.rsplit(":", 1)[1].split("/")[0])
        guard = server.guard
        async with idle_sockets(port):
            await eventually(
                lambda: guard.counts["first_request_timeout"] == IDLE_SOCKETS,
                "the silent sockets closed",
                timeout=10,
            )
            async with Client(server.url, timeout=5) as client:
                assert await client.get_namespace_array()
    lines = guard_lines(caplog)
    assert len(lines) == 2, lines
    assert "closed the connection of 127.0.0.2:" in lines[0]
    assert "no complete request within 1 s" in lines[0]
    assert lines[1].startswith(f"OPC UA server: {IDLE_SOCKETS - 1} more connections of")
