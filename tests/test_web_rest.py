"""The web console's REST API, pages and event stream over HTTP, without a browser.

A real E71 simulator polled by the real poller; requests with aiohttp's client over loopback.
"""

from __future__ import annotations

import asyncio
import itertools
import json
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from plcstack.config import parse_config
from plcstack.config.overrides import Overrides, apply_overrides
from plcstack.north.web.events import EventClient, EventHub
from plcstack.north.web.settings import WebSettings, parse_web
from plcstack.north.web.state import ConsoleState
from plcstack.poll.config import ConfigError, PlcConfig, TagConfig
from plcstack.poll.samples import Quality, Sample
from tests.scan_helpers import scan
from tests.web_helpers import HOSTILE, TOKEN, Console, running_console


async def get_json(console: Console, path: str) -> Any:
    async with aiohttp.ClientSession() as http, http.get(console.base + path) as r:
        assert r.status == 200, await r.text()
        return await r.json()


async def post(
    console: Console, plc: str, tag: str, body: object, token: str | None = TOKEN
) -> tuple[int, dict[str, Any]]:
    headers = {} if token is None else {"Authorization": f"Bearer {token}"}
    url = f"{console.base}/api/plcs/{plc}/tags/{tag}"
    async with aiohttp.ClientSession() as http, http.post(url, json=body, headers=headers) as r:
        return r.status, await r.json()


async def tag_value(console: Console, plc: str, tag: str) -> Any:
    rows = await get_json(console, "/api/tags")
    return next((r for r in rows if r["plc"] == plc and r["tag"] == tag), None)


async def wait_value(console: Console, plc: str, tag: str, value: object) -> dict[str, Any]:
    for _ in range(500):
        row = await tag_value(console, plc, tag)
        if row is not None and row["value"] == value:
            return dict(row)
        await asyncio.sleep(0.02)
    raise AssertionError(f"{plc}/{tag} never read {value!r}; last {row!r}")


#: the tags of press1 (tests/web_helpers.py)
TAGS = ("setpoint", "temp", "counter", "status", "valve", "mode", "flow")


async def test_tags_and_plcs_follow_the_simulator() -> None:
    async with running_console() as console:
        row = await wait_value(console, "press1", "setpoint", 1500)
        assert row["quality"] == "good" and row["error"] is None
        assert row["source_time"] > 0
        console.memory.write_words("D", 100, [1234])
        await wait_value(console, "press1", "setpoint", 1234)

        async def dead_is_down() -> bool:
            rows = {r["name"]: r for r in await get_json(console, "/api/plcs")}
            return rows["dead"]["up"] is False

        for _ in range(500):
            if await dead_is_down():
                break
            await asyncio.sleep(0.02)
        rows = {r["name"]: r for r in await get_json(console, "/api/plcs")}
        assert rows["press1"]["up"] is True and rows["press1"]["requests"] > 0
        assert rows["press1"]["state"] == "online" and rows["press1"]["tags"] == 7
        assert rows["press1"]["p50_ms"] is not None
        assert rows["dead"]["up"] is False and rows["dead"]["state"] == "offline"
        assert rows["dead"]["bad_tags"] == 1 and rows["dead"]["since"] > 0
        assert "cannot connect" in rows["dead"]["last_error"]
        dead = await tag_value(console, "dead", "x")
        assert dead["quality"] == "bad" and dead["value"] is None and dead["error"]
        assert dead["text"] == "" and dead["stale_since"] > 0  # never read: nothing to show
        only = await get_json(console, "/api/tags?plc=press1")
        assert {r["tag"] for r in only} == set(TAGS)
        texts = {r["tag"]: r["text"] for r in only}
        assert texts["setpoint"] == "1234 rpm" and texts["status"] == "12AFh"
        assert texts["valve"] == "open" and texts["mode"] == "running"
        trend = await get_json(console, "/api/plcs/press1/tags/setpoint/trend")
        assert trend and trend[-1][1] == 1234


async def test_write_with_token_reaches_the_plc_and_the_audit(tmp_path: Path) -> None:
    audit = tmp_path / "writes.jsonl"
    async with running_console(audit=audit) as console:
        await wait_value(console, "press1", "setpoint", 1500)
        assert await post(console, "press1", "setpoint", {"value": 42}) == (200, {"ok": True})
        assert console.memory.read_words("D", 100, 1) == [42]
        await wait_value(console, "press1", "setpoint", 42)
        status, _ = await post(console, "press1", "setpoint", {"value": 1}, "wrong")
        assert status == 401
    lines = [json.loads(line) for line in audit.read_text(encoding="utf-8").splitlines()]
    assert [(r["source"], r["tag"], r["value"], r["previous"], r["result"]) for r in lines] == [
        ("web", "setpoint", 42, 1500, "ok"),
        ("web", "setpoint", None, 42, "unauthorized"),
    ]


async def post_from_socket(
    console: Console, plc: str, tag: str, body: bytes, token: str
) -> tuple[int, str]:
    """POST over a socket of our own, so the test knows the client's address exactly: the
    HTTP status and this end's ``host:port``."""
    reader, writer = await asyncio.open_connection("127.0.0.1", console.web.port)
    try:
        host, port = writer.get_extra_info("sockname")[:2]
        head = (
            f"POST /api/plcs/{plc}/tags/{tag} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            f"Authorization: Bearer {token}\r\nContent-Type: application/json\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
        )
        writer.write(head.encode() + body)
        async with asyncio.timeout(10):
            response = await reader.read()  # the server closes after its answer
    finally:
        writer.close()
        await writer.wait_closed()
    return int(response.split(b" ", 2)[1]), f"{host}:{port}"


async def test_the_audit_names_the_http_client_of_each_write(tmp_path: Path) -> None:
    audit = tmp_path / "writes.jsonl"
    async with running_console(audit=audit) as console:
        await wait_value(console, "press1", "setpoint", 1500)
        ok = await post_from_socket(console, "press1", "setpoint", b'{"value": 43}', TOKEN)
        token = await post_from_socket(console, "press1", "setpoint", b'{"value": 1}', "wrong")
        body = await post_from_socket(console, "press1", "setpoint", b"[]", TOKEN)
        tag = await post_from_socket(console, "press1", "counter", b'{"value": 1}', TOKEN)
    assert [status for status, _ in (ok, token, body, tag)] == [200, 401, 400, 403]
    assert console.memory.read_words("D", 100, 1) == [43]
    lines = [json.loads(line) for line in audit.read_text(encoding="utf-8").splitlines()]
    # each line names the connection it came in on: refusals by the token, the body and the
    # write path's allow-list as well as the confirmed write
    assert [(r["result"], r["peer"]) for r in lines] == [
        ("ok", ok[1]),
        ("unauthorized", token[1]),
        ("bad_request", body[1]),
        ("not_writable", tag[1]),
    ]
    assert list(lines[0])[-1] == "peer"  # added last: readers of the older keys are unaffected


async def test_write_refusals() -> None:
    async with running_console() as console:
        for token in (None, "wrong", TOKEN + "x", ""):
            status, answer = await post(console, "press1", "setpoint", {"value": 1}, token)
            assert (status, answer["ok"], answer["error"]) == (401, False, "unauthorized")
        status, answer = await post(console, "press1", "counter", {"value": 1})
        assert (status, answer["error"]) == (403, "not_writable")
        assert "writable = true" in answer["message"]
        status, answer = await post(console, "press1", "nope", {"value": 1})
        assert (status, answer["error"]) == (404, "unknown_tag")
        status, answer = await post(console, "nope", "x", {"value": 1})
        assert (status, answer["error"]) == (404, "unknown_plc")
        status, answer = await post(console, "press1", "setpoint", {"v": 1})
        assert (status, answer["error"]) == (400, "bad_request")
        status, answer = await post(console, "press1", "setpoint", {"value": "many"})
        assert (status, answer["error"], answer["may_have_executed"]) == (
            400,
            "wrong_type",
            False,
        )
        status, answer = await post(console, "dead", "x", {"value": 1})
        assert (status, answer["error"]) == (403, "not_writable")
        async with aiohttp.ClientSession() as http:
            url = f"{console.base}/api/plcs/press1/tags/setpoint"
            async with http.get(url, headers={"Authorization": f"Bearer {TOKEN}"}) as r:
                assert r.status == 405  # no write through GET
            async with http.post(
                url, data=b"{not json", headers={"Authorization": f"Bearer {TOKEN}"}
            ) as r:
                assert r.status == 400
            async with http.post(
                url,
                data=b"x" * 200_000,
                headers={"Authorization": f"Bearer {TOKEN}"},
            ) as r:
                assert r.status == 413
        assert console.memory.read_words("D", 100, 1) == [1500]


async def test_writes_are_off_without_a_token() -> None:
    async with running_console(token=None) as console:
        status, answer = await post(console, "press1", "setpoint", {"value": 1})
        assert (status, answer["error"]) == (403, "not_writable")
        assert "without a write token" in answer["message"]
        assert console.memory.read_words("D", 100, 1) == [1500]


async def test_pages_escape_every_name() -> None:
    async with running_console() as console:
        await wait_value(console, HOSTILE, HOSTILE, 7)
        async with aiohttp.ClientSession() as http:
            async with http.get(console.base + "/") as r:
                assert r.status == 200
                page = await r.text()
                assert "script-src 'self'" in r.headers["Content-Security-Policy"]
                assert r.headers["X-Content-Type-Options"] == "nosniff"
            assert HOSTILE not in page
            assert "&lt;svg onload=pwned=1&gt;" in page and "<svg onload" not in page
            assert page.count("<script") == 1  # ours, by src
            async with http.get(console.base + "/plc/press1") as r:
                press = await r.text()
            assert "Oil temperature" in press and "°C" in press
            hostile = "/plc/%3Csvg%20onload%3Dpwned%3D1%3E"
            async with http.get(console.base + hostile) as r:
                assert r.status == 200
                page = await r.text()
            assert HOSTILE not in page and "<svg onload" not in page
            assert page.count("<script") == 1
            async with http.get(console.base + "/plc/%3Cb%3Enope") as r:
                assert r.status == 404
                assert "<b>" not in await r.text()
            async with http.get(console.base + "/static/console.js") as r:
                assert r.status == 200 and "EventSource" in await r.text()
            async with http.get(console.base + "/static/..%2Fserver.py") as r:
                assert r.status == 404


async def read_event(stream: aiohttp.StreamReader, name: str) -> Any:
    """The data of the next event called ``name``."""
    while True:
        block = b""
        while not block.endswith(b"\n\n"):
            block += await stream.readline()
        lines = block.decode().splitlines()
        if f"event: {name}" in lines:
            return json.loads(next(x for x in lines if x.startswith("data: "))[6:])


async def test_event_stream_sends_a_snapshot_then_changes_only() -> None:
    async with running_console() as console:
        await wait_value(console, "press1", "setpoint", 1500)
        async with aiohttp.ClientSession() as http:
            async with http.get(console.base + "/events?plc=press1") as r:
                assert r.headers["Content-Type"] == "text/event-stream"
                snapshot = await asyncio.wait_for(read_event(r.content, "tags"), 10)
                assert {row[1] for row in snapshot} == set(TAGS)
                console.memory.write_words("D", 100, [99])
                for _ in range(100):
                    changes = await asyncio.wait_for(read_event(r.content, "tags"), 10)
                    assert {row[0] for row in changes} == {"press1"}  # this PLC's only
                    if ["press1", "setpoint", 99, "good"] in [row[:4] for row in changes]:
                        break
                console.memory.write_words("D", 104, [5])
                changes = await asyncio.wait_for(read_event(r.content, "tags"), 10)
                # only what changed since: the counter
                assert [row[:4] for row in changes] == [["press1", "counter", 5, "good"]]
            async with http.get(console.base + "/events?plc=nope") as r:
                assert r.status == 404


def _sample(tag: str, value: float) -> Sample:
    return Sample("p", tag, value, Quality.GOOD, 1000.0 + value, 1000.0 + value)


def test_a_client_that_does_not_read_is_dropped() -> None:
    state = ConsoleState([PlcConfig("p", "e71+tcp://127.0.0.1:1", (TagConfig("t", "D0"),))])
    hub = EventHub(state, lambda plc: [])
    aborted: list[bool] = []

    async def scenario() -> EventClient:
        client = hub.connect(None)
        assert client is not None
        client.on_drop = lambda: aborted.append(True)
        for i in range(client.limit + 5):
            state.submit([scan(_sample("t", float(i)))])
            hub.push()
        return client

    client = asyncio.run(scenario())
    assert client.dropped and aborted == [True]
    hub.disconnect(client)
    assert hub.clients == set() and hub.dropped == 1


def test_trend_ring_is_bounded_and_spaced() -> None:
    state = ConsoleState(
        [PlcConfig("p", "e71+tcp://127.0.0.1:1", (TagConfig("t", "D0"),))],
        trend_seconds=10,
        clock=lambda: 1000.0,
    )
    for i in range(100):  # 10 samples a second for 10 s: one point a second kept
        state.submit([scan(Sample("p", "t", float(i), Quality.GOOD, 1000.0 + i / 10, 0.0))])
    points = state.trend("p", "t")
    assert len(points) == 10
    # one point a second, each holding the latest value of its second
    values = [v for _, v in points]
    assert values[-1] == 99.0
    assert [b - a for a, b in itertools.pairwise(values)] == [10.0] * 9
    for i in range(100, 200):
        state.submit([scan(Sample("p", "t", float(i), Quality.GOOD, 1000.0 + i, 0.0))])
    assert len(state.trend("p", "t")) == 10 and state.trend("p", "t")[-1][1] == 199.0


@pytest.mark.parametrize(
    ("table", "problem"),
    [
        ({"port": 70000}, "port must be 0..65535"),
        ({"host": ""}, "host must be a non-empty string"),
        ({"write_token_env": ""}, "write_token_env must name"),
        ({"trend_seconds": 5}, "trend_seconds must be"),
        ({"token": "x"}, r"unknown key\(s\) token"),
    ],
)
def test_web_table_errors(table: dict[str, Any], problem: str) -> None:
    with pytest.raises(ConfigError, match=problem):
        parse_web(table)


def test_web_table_defaults_and_port_override() -> None:
    assert parse_web({}) == WebSettings("127.0.0.1", 8080, None, 300)
    plc = '[[plc]]\nname = "p"\nurl = "e71+tcp://127.0.0.1:1"\ntags = { t = "D0" }\n'
    bare = parse_config(plc)
    assert apply_overrides(bare, Overrides()) is bare
    assert apply_overrides(bare, Overrides(web_port=0)).north.web == WebSettings(port=0)
    placed = parse_config('[web]\nlisten = "0.0.0.0:1"\n' + plc)
    moved = apply_overrides(placed, Overrides(web_port=2))
    assert moved.north.web == WebSettings("0.0.0.0", 2)
    with pytest.raises(ConfigError, match="--web-port must be 0..65535"):
        Overrides(web_port=-1)


async def test_poll_command_serves_the_console(
    tmp_path: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    from plcstack.cli import build_parser
    from plcstack.sim import e71 as e71_sim

    sim = await e71_sim.start()
    try:
        config = tmp_path / "plant.toml"
        config.write_text(
            f'[web]\nlisten = "127.0.0.1:1"\n\n[[plc]]\nname = "p"\nurl = "{sim.url}"\n'
            '[plc.tags]\nt = "D0"\n',
            encoding="utf-8",
        )
        args = build_parser().parse_args(
            ["poll", str(config), "--web-port", "0", "--duration", "0.3", "--format", "none"]
        )
        assert await args.func(args) == 0
        err = capsys.readouterr().err
        assert "plcstack: web console on http://127.0.0.1:" in err
        assert ":1/" not in err  # --web-port won over [web] listen's port
        with pytest.raises(SystemExit):  # the parser refuses it, one line, exit 2
            build_parser().parse_args(["poll", str(config), "--web-port", "70000"])
    finally:
        await sim.aclose()
