"""/metrics parsed with prometheus_client's own parser; /healthz; bad requests."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from plcstack.clients.base import Client
from plcstack.north.buffer import StoreAndForward
from plcstack.north.metrics import MetricsServer, PlcstackCollector, parse_metrics
from plcstack.north.rbe import ReportByException, ReportPolicy
from plcstack.poll.config import ConfigError, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from tests.poll_fakes import FakeClient


async def http(port: int, request: bytes) -> tuple[int, bytes]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(request)
    try:
        data = await reader.read()
    except ConnectionResetError:  # the server closed with our oversized request unread
        data = b"HTTP/1.1 0 reset\r\n\r\n"
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


class FakeSink:
    def __init__(self) -> None:
        self.buffer = StoreAndForward(None, max_bytes=10_000)
        self.connected = False

        class S:
            sent = 7
            replayed = 3

        self.stats = S()


async def test_metrics_endpoint_parses_and_counts() -> None:
    fakes: dict[str, FakeClient] = {}

    def factory(plc: PlcConfig) -> Client:
        fakes[plc.name] = FakeClient(f"fake://{plc.name}")
        return fakes[plc.name]

    config = PollConfig(
        (
            PlcConfig("a", "e71+tcp://127.0.0.1:1", (TagConfig("t", "D1"),)),
            PlcConfig("b", "e71+tcp://127.0.0.1:1", (TagConfig("t", "D1"),)),
        ),
        {"default": 0.01},
    )
    sink = FakeSink()
    for _ in range(5):
        sink.buffer.put("x/y", b"12345")
    rbe = ReportByException(ReportPolicy())
    async with Poller(config, client_factory=factory) as poller:
        fakes["b"].kill()
        collector = PlcstackCollector(poller, [sink], rbe)
        server = MetricsServer(collector, parse_metrics({"port": 0}))
        await server.start()
        try:
            n = 0
            async for s in poller:
                collector.observe([s])
                rbe.accept(s)
                n += 1
                if n >= 40:
                    break
            status, body = await http(server.port, b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
            assert status == 200
            families = {f.name: f for f in text_string_to_metric_families(body.decode())}
            health = await http(server.port, b"GET /healthz HTTP/1.0\r\n\r\n")
            missing = await http(server.port, b"GET /nope HTTP/1.0\r\n\r\n")
            post = await http(server.port, b"POST /metrics HTTP/1.0\r\n\r\n")
            huge = await http(server.port, b"GET /" + b"x" * 20000 + b" HTTP/1.0\r\n\r\n")
            after = await http(server.port, b"GET /healthz HTTP/1.0\r\n\r\n")
        finally:
            await server.aclose()

    up = {s.labels["plc"]: s.value for s in families["plcstack_plc_up"].samples}
    assert up == {"a": 1.0, "b": 0.0}
    requests = {s.labels["plc"]: s.value for s in families["plcstack_requests"].samples}
    assert requests["a"] >= 1
    errors = {s.labels["plc"]: s.value for s in families["plcstack_connect_failures"].samples}
    assert errors["b"] >= 1
    hist = families["plcstack_request_latency_seconds"]
    count_a = [
        s.value for s in hist.samples if s.name.endswith("_count") and s.labels["plc"] == "a"
    ]
    inf_a = [
        s.value for s in hist.samples if s.labels.get("le") == "+Inf" and s.labels["plc"] == "a"
    ]
    assert count_a == inf_a and count_a[0] >= 1
    backlog = families["plcstack_buffer_backlog_messages"].samples[0]
    assert backlog.value == 5
    assert families["plcstack_mqtt_sent"].samples[0].value == 7
    assert families["plcstack_rbe_suppressed"].samples[0].value == rbe.suppressed > 0
    assert health == (200, b"ok\n")
    assert (missing[0], post[0]) == (404, 405)
    assert huge[0] in (431, 0) and after == (200, b"ok\n")  # refused, and still serving


async def test_healthz_reports_the_reason() -> None:
    class P:
        stats: dict[str, Any] = {}
        dropped = 0

    server = MetricsServer(
        PlcstackCollector(P()), parse_metrics({"port": 0}), lambda: "poller stopped"
    )
    await server.start()
    try:
        assert await http(server.port, b"GET /healthz HTTP/1.0\r\n\r\n") == (
            503,
            b"poller stopped\n",
        )
    finally:
        await server.aclose()


def test_metrics_table() -> None:
    assert parse_metrics({}).host == "127.0.0.1"
    for bad in ({"port": 70000}, {"host": ""}, {"path": "/m"}):
        with pytest.raises(ConfigError):
            parse_metrics(bad)
