"""The OPC UA server's client limit: a flood cannot take the process's file descriptors, and
its refusals are said once per burst, not once per connection."""

from __future__ import annotations

import asyncio
import logging

import pytest

from plcstack.north.opcua import OpcUaServer
from plcstack.north.opcua_config import DEFAULT_MAX_CLIENTS, OpcUaConfig, parse_opcua_config
from plcstack.north.opcua_users import RefusalsOnce
from plcstack.poll.config import ConfigError, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from tests.aio_helpers import ended_by_server

LISTENER = "asyncua.server.binary_server_asyncio"


def _poller() -> Poller:
    # never started: the server only needs its configuration for the address space
    plc = PlcConfig(name="p", url="e71+tcp://127.0.0.1:5000", tags=(TagConfig("a", "D0"),))
    return Poller(PollConfig((plc,)))


async def test_connections_beyond_max_clients_are_closed_at_once_and_said_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = OpcUaConfig(endpoint="opc.tcp://127.0.0.1:0/plcstack", max_clients=2)
    caplog.set_level(logging.WARNING, logger=LISTENER)
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
        refusals = [r for r in caplog.records if "Refusing connection" in r.getMessage()]
        assert len(refusals) == 1, [r.getMessage() for r in refusals]
        filters = [f for f in logging.getLogger(LISTENER).filters if isinstance(f, RefusalsOnce)]
        assert [f.refused for f in filters] == [3]
    # the filter goes with the server
    assert not any(isinstance(f, RefusalsOnce) for f in logging.getLogger(LISTENER).filters)


def test_refusals_are_said_once_per_burst() -> None:
    now = [0.0]
    once = RefusalsOnce(quiet=10.0, clock=lambda: now[0])

    def refused(at: float) -> str | None:
        now[0] = at
        record = logging.LogRecord(
            LISTENER, logging.WARNING, "", 0, "Refusing connection from %s", ("x",), None
        )
        return record.getMessage() if once.filter(record) else None

    said = [refused(t) for t in (0.0, 1.0, 5.0, 14.0, 30.0, 31.0, 50.0)]
    assert said == [
        "Refusing connection from x",
        None,
        None,
        None,  # 9 s after the last one: the same burst
        "Refusing connection from x (and 3 more refused in the burst before)",
        None,
        "Refusing connection from x (and 1 more refused in the burst before)",
    ]
    assert once.refused == 7
    other = logging.LogRecord(LISTENER, logging.INFO, "", 0, "New connection from %s", ("x",), None)
    assert once.filter(other)


def test_max_clients_is_read_and_checked() -> None:
    assert parse_opcua_config({}).max_clients == DEFAULT_MAX_CLIENTS == 64
    assert parse_opcua_config({"max_clients": 5}).max_clients == 5
    for bad in (0, -1, 10_001, "8", True, 2.5):
        with pytest.raises(ConfigError, match="max_clients must be 1..10000"):
            parse_opcua_config({"max_clients": bad})
    with pytest.raises(ConfigError, match="did you mean max_clients"):
        parse_opcua_config({"max_client": 5})
