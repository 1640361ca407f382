"""/metrics parsed with prometheus_client's own parser; /healthz; bad requests."""

from __future__ import annotations

import asyncio
import time

import pytest
from prometheus_client.parser import text_string_to_metric_families

from plcstack.clients.base import Client
from plcstack.north.buffer import StoreAndForward
from plcstack.north.health import Health
from plcstack.north.metrics import MetricsServer, PlcstackCollector, parse_metrics
from plcstack.north.mqtt import MqttSettings, MqttSink
from plcstack.north.rbe import ReportByException, ReportPolicy
from plcstack.poll.config import ConfigError, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from tests.poll_fakes import FakeClient
from tests.scan_helpers import each, scan


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


def idle_poller() -> Poller:
    """A poller of no PLC, never started."""
    return Poller(PollConfig((), {"default": 1.0}))


def idle_sink() -> MqttSink:
    """An MQTT sink never started, with figures of its own."""
    sink = MqttSink(MqttSettings(port=1), buffer=StoreAndForward(None, max_bytes=10_000))
    sink.stats.sent, sink.stats.replayed = 7, 3
    return sink


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
    sink = idle_sink()
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
                collector.observe([scan(s)])
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
    assert health == (200, b"ok\nmetrics: ok\n")
    assert (missing[0], post[0]) == (404, 405)
    assert huge[0] in (431, 0) and after == health  # refused, and still serving


async def test_healthz_reports_the_reason_and_livez_that_it_lives() -> None:
    since = time.time() - 12
    parts = [
        Health("poller"),
        Health("mqtt", "MQTT broker mqtt://127.0.0.1:1 unreachable", since, (("waiting", 269),)),
    ]
    server = MetricsServer(
        PlcstackCollector(idle_poller()), parse_metrics({"port": 0}), lambda: parts
    )
    await server.start()
    try:
        status, body = await http(server.port, b"GET /healthz HTTP/1.0\r\n\r\n")
        alive = await http(server.port, b"GET /livez HTTP/1.0\r\n\r\n")
        parts[1] = Health("mqtt")
        healthy = await http(server.port, b"GET /healthz HTTP/1.0\r\n\r\n")
    finally:
        await server.aclose()
    assert status == 503
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(since))
    assert body.decode() == (
        f"mqtt: MQTT broker mqtt://127.0.0.1:1 unreachable since {stamp} (12 s ago), 269 waiting\n"
    )
    assert alive == (200, b"alive\n")
    assert healthy == (200, b"ok\npoller: ok\nmqtt: ok\n")


def test_metrics_table() -> None:
    assert parse_metrics({}).host == "127.0.0.1"
    for bad in ({"port": 70000}, {"host": ""}, {"path": "/m"}):
        with pytest.raises(ConfigError):
            parse_metrics(bad)


async def test_failed_requests_have_their_own_latency_histogram_per_error_type() -> None:
    fakes: dict[str, FakeClient] = {}

    def factory(plc: PlcConfig) -> Client:
        fakes[plc.name] = FakeClient(f"fake://{plc.name}", timeout=0.2)
        return fakes[plc.name]

    two_tags = (TagConfig("t", "D1"), TagConfig("u", "D2"))  # one merged request
    config = PollConfig(
        (
            PlcConfig("ok", "e71+tcp://127.0.0.1:1", two_tags),
            PlcConfig("slow", "e71+tcp://127.0.0.1:1", two_tags),
            PlcConfig("off", "e71+tcp://127.0.0.1:1", two_tags),
        ),
        {"default": 0.02},
    )
    async with Poller(config, client_factory=factory) as poller:
        fakes["slow"].delay = 1.0  # never answers within its 0.2 s deadline
        fakes["off"].kill()  # connections refused
        collector = PlcstackCollector(poller)
        n = 0
        async for s in poller:
            collector.observe([scan(s)])
            n += 1
            if n >= 60 and poller.stats["slow"].errors >= 2:
                break
        await poller.aclose()
        collector.observe(poller.drain())  # every failed request's samples seen
        stats = poller.stats

    text = generate_latest_text(collector)
    families = {f.name: f for f in text_string_to_metric_families(text)}
    failed = families["plcstack_failed_request_latency_seconds"].samples

    def series(plc: str, error: str, suffix: str, le: str | None = None) -> float:
        return sum(
            s.value
            for s in failed
            if s.name.endswith(suffix)
            and s.labels["plc"] == plc
            and s.labels["error"] == error
            and (le is None or s.labels.get("le") == le)
        )

    def count(plc: str) -> float:
        return sum(s.value for s in failed if s.name.endswith("_count") and s.labels["plc"] == plc)

    # one observation per failed request (not per tag), and every failed request observed
    assert count("slow") == stats["slow"].errors >= 2
    assert count("off") == stats["off"].errors >= 1
    assert count("ok") == 0 and stats["ok"].errors == 0
    # timeouts took the deadline (0.2 s), not the answer's 1 s: the bucket above the deadline
    # leaves a loaded loop 300 ms to run the timer (0.25 failed under a loaded suite);
    # refused connections next to nothing
    timeouts = series("slow", "PlcTimeout", "_count")
    assert timeouts >= 2
    assert series("slow", "PlcTimeout", "_bucket", le="0.1") == 0
    assert series("slow", "PlcTimeout", "_bucket", le="0.5") == timeouts
    assert series("slow", "PlcTimeout", "_sum") >= 0.2 * timeouts
    refused = series("off", "ConnectFailed", "_count")
    assert refused >= 1 and series("off", "ConnectFailed", "_bucket", le="0.1") == refused
    # the successful-request histogram is unchanged: only what answered
    ok_latency = families["plcstack_request_latency_seconds"].samples
    slow_ok = [s for s in ok_latency if s.name.endswith("_count") and s.labels["plc"] == "slow"]
    assert [s.value for s in slow_ok] == [0.0]


def generate_latest_text(collector: PlcstackCollector) -> str:
    from prometheus_client import CollectorRegistry, generate_latest

    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    return generate_latest(registry).decode()


def test_failures_that_are_no_failed_request_are_not_observed() -> None:
    from plcstack.errors import ConnectionLost, PlcTimeout, ValueDecodeError
    from plcstack.poll.samples import Quality, Sample

    collector = PlcstackCollector(idle_poller())
    t = 1_800_000_000.0
    bad = Quality.BAD
    collector.observe(
        each(
            [
                # the request answered; the value does not decode
                Sample(
                    "p", "bcd", None, bad, t, t + 0.01, "p: read D1 x1: not BCD", ValueDecodeError
                ),
                # never sent: the rest of a scan after the connection was lost
                Sample("p", "x", None, bad, t + 1, t + 1, "p: read D9 x1: lost", ConnectionLost),
                # no type: cannot tell
                Sample("p", "y", None, bad, t, t + 0.5, "remote", None),
                # a timeout, carried by two tags of one request: one observation
                Sample("p", "a", None, bad, t + 2, t + 2.5, "p: read D5 x2: no answer", PlcTimeout),
                Sample("p", "b", None, bad, t + 2, t + 2.5, "p: read D5 x2: no answer", PlcTimeout),
            ]
        )
    )
    text = generate_latest_text(collector)
    families = {f.name: f for f in text_string_to_metric_families(text)}
    counts = {
        (s.labels["plc"], s.labels["error"]): s.value
        for s in families["plcstack_failed_request_latency_seconds"].samples
        if s.name.endswith("_count")
    }
    assert counts == {("p", "PlcTimeout"): 1.0}
