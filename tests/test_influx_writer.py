"""The Influx writer against a real InfluxDB 1.x (influxd): the lines of ``--format influx``,
batched, InfluxDB's answers told apart, held through an outage and replayed in order.

A stand-in HTTP server (aiohttp) plays what influxd cannot be made to say on cue: a 503 from a
proxy in front of it. The 20-PLC outage of a whole ``plcstack poll`` run is in
tests/test_influx_outage.py (slow).
"""

from __future__ import annotations

import asyncio
import json
import logging
import urllib.parse
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from aiohttp import web

from plcstack.errors import ConfigError
from plcstack.north.influx import InfluxFormat
from plcstack.north.influx_config import InfluxSettings, parse_influx
from plcstack.north.influx_sink import InfluxSink, classify
from plcstack.north.mqtt import parse_mqtt
from plcstack.poll.config import parse_poll_config as parse_config
from plcstack.poll.samples import Quality, Sample, Scan
from tests.ports import free_port
from tests.servers import Influxd, _serve

CONFIG = parse_config(
    """
[[plc]]
name = "press1"
url = "e71+tcp://127.0.0.1:5000"
[plc.tags]
strokes = { address = "D100", type = "int16" }
force = { address = "D102", type = "float32" }
[[plc]]
name = "press2"                     # the same tags, force an integer: a type conflict
url = "e71+tcp://127.0.0.1:5001"
[plc.tags]
strokes = { address = "D100", type = "int16" }
force = { address = "D102", type = "int16" }
"""
)


def scan(i: int, plc: str = "press1", force: float = 1.5) -> Scan:
    t = 1_700_000_000.0 + i
    samples = (
        Sample(plc, "strokes", i, Quality.GOOD, t, t + 0.01),
        Sample(plc, "force", force, Quality.GOOD, t, t + 0.01),
    )
    return Scan(plc, "default", t, t + 0.01, samples)


def settings(url: str, **extra: Any) -> InfluxSettings:
    return parse_influx({"url": url, "database": "plant", "batch_wait": 0.05, **extra})


def query(server: Influxd, q: str) -> list[list[Any]]:
    status, text = server.request("GET", "/query?db=plant&q=" + urllib.parse.quote(q))
    assert status == 200, text
    series = json.loads(text)["results"][0].get("series", [])
    return [row for s in series for row in s["values"]]


@pytest.fixture
def influx(influxd: Influxd) -> Influxd:
    influxd.create_database("plant")
    return influxd


@pytest.fixture
def influx_auth() -> Iterator[Influxd]:
    for server in _serve(Influxd(auth=True)):
        assert isinstance(server, Influxd)
        server.create_database("plant")
        yield server


async def running(sink: InfluxSink) -> InfluxSink:
    await sink.start()
    return sink


async def test_the_lines_of_format_influx_are_written(influx: Influxd) -> None:
    sink = await running(InfluxSink(settings(influx.url, batch_size=4), CONFIG.plcs))
    try:
        scans = [scan(i) for i in range(10)]
        for s in scans:
            sink.submit([s])
        await sink.wait_drained(10)
    finally:
        await sink.aclose()
    rows = query(influx, "SELECT strokes, force FROM plc")
    assert [row[1:] for row in rows] == [[i, 1.5] for i in range(10)]
    # exactly what --format influx prints for the same scans
    expected = InfluxFormat(CONFIG.plcs).text(scans).splitlines()
    assert sink.lines(scans) == expected
    # batch_size 4: ten lines in at least three requests, none bigger than four lines
    assert sink.stats.written == 10 and sink.stats.requests >= 3
    assert len(sink.buffer) == 0 and sink.stats.rejected == 0
    assert "10 lines written" in sink.summary()


async def test_lines_wait_for_their_batch(influx: Influxd) -> None:
    """With batch_wait, lines submitted within it go in one request."""
    sink = await running(InfluxSink(settings(influx.url, batch_wait=0.5), CONFIG.plcs))
    try:
        for i in range(5):
            sink.submit([scan(i)])
            await asyncio.sleep(0.01)
        await sink.wait_drained(10)
    finally:
        await sink.aclose()
    assert (sink.stats.written, sink.stats.requests) == (5, 1)


async def test_a_refused_line_is_named_dropped_and_counted(
    influx: Influxd, caplog: pytest.LogCaptureFixture
) -> None:
    """A field whose type differs (press2's force is an integer where InfluxDB has press1's
    float) is refused with 400; InfluxDB stores the others. The refused lines are found, named
    and dropped; the rest arrive."""
    sink = await running(InfluxSink(settings(influx.url, batch_wait=0.3), CONFIG.plcs))
    try:
        sink.submit([scan(0)])
        await sink.wait_drained(10)
        with caplog.at_level(logging.WARNING, "plcstack.north.influx"):
            for i in range(1, 9):
                sink.submit([scan(i, "press2", 7) if i in (4, 6) else scan(i)])
            await sink.wait_drained(10)
    finally:
        await sink.aclose()
    assert sink.stats.rejected == 2 and sink.stats.written == 7
    assert len(sink.buffer) == 0
    assert [row[1] for row in query(influx, "SELECT strokes FROM plc")] == [0, 1, 2, 3, 5, 7, 8]
    assert query(influx, "SELECT strokes FROM plc WHERE plc = 'press2'") == []
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    # said once for the kind of refusal, naming the line and InfluxDB's reason
    assert len(warnings) == 1, warnings
    assert "refused a line, dropped (1 so far): partial write: field type conflict" in warnings[0]
    assert (
        "; the line: plc,plc=press2,group=default strokes=4i,force=7i 1700000004000000000"
        in (warnings[0])
    )


async def test_wrong_credentials_stop_the_writer_once(
    influx_auth: Influxd, caplog: pytest.LogCaptureFixture
) -> None:
    env = {"IU": "admin", "IP": "wrong"}
    sink = InfluxSink(
        settings(influx_auth.url, username_env="IU", password_env="IP"), CONFIG.plcs, env=env
    )
    with caplog.at_level(logging.WARNING, "plcstack.north.influx"):
        await sink.start()
        try:
            for i in range(3):
                sink.submit([scan(i)])
                await asyncio.sleep(0.1)
            async with asyncio.timeout(10):
                while not sink.stopped:  # noqa: ASYNC110 - the writer's own state, polled
                    await asyncio.sleep(0.02)
            requests = sink.stats.requests
            await asyncio.sleep(0.3)
            sink.submit([scan(9)])
            await asyncio.sleep(0.2)
            assert sink.stats.requests == requests  # no retry with the same credentials
        finally:
            await sink.aclose(drain=0)
    assert len(sink.buffer) == 4 and sink.stats.written == 0
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(errors) == 2, errors
    assert errors[0].startswith(
        f"influx: InfluxDB at {influx_auth.url} refused the credentials (401"
    )
    assert errors[1].startswith("influx: 4 lines not written are lost as the writer closes")
    assert sink.link.problem is not None and "refused the credentials" in sink.link.problem


async def test_right_credentials_write(influx_auth: Influxd) -> None:
    env = {"IU": Influxd.USER, "IP": Influxd.PASSWORD}
    sink = InfluxSink(
        settings(influx_auth.url, username_env="IU", password_env="IP"), CONFIG.plcs, env=env
    )
    await sink.start()
    try:
        sink.submit([scan(1)])
        await sink.wait_drained(10)
    finally:
        await sink.aclose()
    assert sink.stats.written == 1


async def test_a_missing_variable_stops_the_start() -> None:
    sink = InfluxSink(
        settings("http://127.0.0.1:1", username_env="NO_SUCH_VAR_X", password_env="IP"),
        CONFIG.plcs,
        env={},
    )
    with pytest.raises(ConfigError, match="'NO_SUCH_VAR_X', which is not set"):
        await sink.start()
    await sink.aclose()


@pytest.fixture
async def proxy(influx: Influxd) -> AsyncIterator[dict[str, Any]]:
    """A stand-in in front of influxd: answers the next ``fail`` requests with 503, the rest it
    forwards; ``seen`` counts the requests."""
    import aiohttp

    state: dict[str, Any] = {"fail": 0, "seen": 0}

    async def write(request: web.Request) -> web.Response:
        state["seen"] += 1
        if state["fail"] > 0:
            state["fail"] -= 1
            return web.Response(status=503, text='{"error":"overloaded"}')
        body = await request.read()
        target = f"{influx.url}/write?{request.query_string}"
        async with aiohttp.ClientSession() as session, session.post(target, data=body) as r:
            return web.Response(status=r.status, body=await r.read())

    app = web.Application()
    app.router.add_post("/write", write)
    runner = web.AppRunner(app)
    await runner.setup()
    port = free_port()
    await web.TCPSite(runner, "127.0.0.1", port).start()
    state["url"] = f"http://127.0.0.1:{port}"
    try:
        yield state
    finally:
        await runner.cleanup()


async def test_5xx_is_retried_in_order(
    influx: Influxd, proxy: dict[str, Any], caplog: pytest.LogCaptureFixture
) -> None:
    proxy["fail"] = 3
    sink = InfluxSink(settings(proxy["url"], reconnect_max=0.2), CONFIG.plcs)
    with caplog.at_level(logging.WARNING, "plcstack.north.influx"):
        await sink.start()
        try:
            for i in range(6):
                sink.submit([scan(i)])
                await asyncio.sleep(0.05)
            await sink.wait_drained(10)
        finally:
            await sink.aclose()
    assert sink.stats.failures == 3 and sink.stats.written == 6
    assert sink.stats.replayed == sink.stats.held > 0
    assert [row[1] for row in query(influx, "SELECT strokes FROM plc")] == list(range(6))
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2, said
    assert "cannot be written to: 503: overloaded; retrying with backoff" in said[0]
    assert "takes writes again" in said[1]


async def test_an_outage_is_held_and_replayed(
    influx: Influxd, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """influxd stopped: lines wait; a stop of the writer keeps them on disk; the next writer
    on the same file writes them first, then its own (as a reload restarting the writer does).
    Scans handed to the closed writer in between are counted and said once (before: queued in
    the memory of a closed queue, lost without a word)."""
    path = tmp_path / "influx.sqlite"
    first = await running(
        InfluxSink(settings(influx.url, reconnect_max=0.2, buffer_path=str(path)), CONFIG.plcs)
    )
    try:
        first.submit([scan(0)])
        await first.wait_drained(10)
        influx.stop()
        for i in range(1, 5):
            first.submit([scan(i)])
        await asyncio.sleep(0.3)
    finally:
        await first.aclose()
    with caplog.at_level(logging.WARNING, logger="plcstack.north.influx"):
        first.submit([scan(90)])
        first.submit([scan(91)])
    assert first.stats.late == 2 and len(first.buffer) == 4  # the 4 kept on disk, no more
    late = [r.getMessage() for r in caplog.records if "after the writer closed" in r.getMessage()]
    assert late == [
        "influx: lines arrive after the writer closed (a reload restarts it): they are not"
        " written; counted"
    ]
    assert first.stats.written == 1 and first.stats.held == 4
    assert "4 not delivered (kept in" in first.summary()
    influx.start()
    second = await running(InfluxSink(settings(influx.url, buffer_path=str(path)), CONFIG.plcs))
    try:
        second.submit([scan(5)])
        await second.wait_drained(10)
    finally:
        await second.aclose()
    assert [row[1] for row in query(influx, "SELECT strokes FROM plc")] == list(range(6))


def test_answers_are_told_apart() -> None:
    assert classify(204, "").kind == "written"
    assert (
        classify(400, '{"error":"partial write: x dropped=1"}').reason
        == "partial write: x dropped=1"
    )
    assert classify(413, "").kind == "split"
    assert classify(401, '{"error":"authorization failed"}').kind == "stop"
    assert classify(403, "").kind == "stop"
    assert classify(404, '{"error":"database not found: \\"plant\\""}').reason == (
        '404: database not found: "plant" (CREATE DATABASE it?)'
    )
    assert classify(500, "<html>oops</html>").reason == "500: <html>oops</html>"
    assert classify(503, "").kind == "retry"


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ({"url": "http://h:8086"}, 'url needs database = "NAME"'),
        ({"database": "x"}, "database needs url ="),
        ({"url": "udp://h:8089", "database": "x"}, "url must be http://HOST:PORT"),
        ({"url": "http://u:p@h:8086", "database": "x"}, "must not carry credentials"),
        ({"url": "http://h:8086", "database": "x", "username_env": "U"}, "go together"),
        ({"url": "http://h:8086", "database": "x", "batch_size": 0}, "batch_size must be"),
        ({"url": "http://h:8086", "database": "x", "ca_file": "ca.pem"}, "needs an https"),
        ({"url": "http://h:8086", "database": "x", "bufer_path": "q"}, "did you mean buffer_path"),
    ],
)
def test_config_errors(table: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_influx(table)


def test_config_paths_and_write_url(tmp_path: Path) -> None:
    parsed = parse_influx(
        {"url": "http://h:8086/", "database": "plant 1", "retention_policy": "a&b",
         "buffer_path": "q.sqlite"},
        base=tmp_path,
    )  # fmt: skip
    assert parsed.buffer_path == str(tmp_path / "q.sqlite")
    assert parsed.write_url == "http://h:8086/write?db=plant%201&precision=ns&rp=a%26b"
    assert parse_influx({}) == InfluxSettings()


def test_config_reads_durations_and_sizes_as_mqtt_does() -> None:
    """[influx] and [mqtt] take the same spellings: durations with units, sizes with units."""
    parsed = parse_influx(
        {"url": "http://h:8086", "database": "p", "batch_wait": "250ms", "timeout": "1m",
         "buffer_memory": "1 MiB", "buffer_max": "2 GiB"}
    )  # fmt: skip
    assert (parsed.batch_wait, parsed.timeout) == (0.25, 60.0)
    assert (parsed.buffer_memory, parsed.buffer_max) == (1 << 20, 2 << 30)
    assert parse_influx({"url": "http://h", "database": "p", "batch_wait": 0}).batch_wait == 0
    mqtt = parse_mqtt({"buffer_memory": "1 MiB", "buffer_max": "2 GiB"})
    assert (mqtt.buffer_memory, mqtt.buffer_max) == (parsed.buffer_memory, parsed.buffer_max)


async def test_a_close_without_buffer_path_says_what_it_loses(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Before: the lines left in memory went with the closed writer without a word (the run's
    summary said it at the end of a run, but a reload restarting the writer prints none)."""
    sink = await running(InfluxSink(settings(f"http://127.0.0.1:{free_port()}"), CONFIG.plcs))
    sink.submit([scan(0), scan(1)])
    with caplog.at_level(logging.WARNING, logger="plcstack.north.influx"):
        await sink.aclose(drain=0)
    lost = [r.getMessage() for r in caplog.records if "lost as the writer closes" in r.getMessage()]
    assert lost == [
        "influx: 2 lines not written are lost as the writer closes ([influx] buffer_path would"
        " keep them for the next writer)"
    ]
