"""The console's request handling against malformed and hostile requests, over real sockets:
never a 500, every write attempt that reaches the write route audited, only its own host names
answered (DNS rebinding)."""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from plcstack.errors import ConfigError
from plcstack.north.web import hosts as web_hosts
from plcstack.north.web.hosts import HostCheck, host_name
from plcstack.north.web.settings import parse_web
from tests.web_helpers import TOKEN, running_console

WRITE = b"/api/plcs/press1/tags/setpoint"


def request(
    path: bytes,
    *,
    method: bytes = b"POST",
    host: bytes | None = b"127.0.0.1",
    headers: tuple[tuple[bytes, bytes], ...] = (),
    body: bytes = b"",
    version: bytes = b"HTTP/1.1",
) -> bytes:
    lines = [method + b" " + path + b" " + version]
    if host is not None:
        lines.append(b"Host: " + host)
    lines += [name + b": " + value for name, value in headers]
    lines += [b"Content-Length: " + str(len(body)).encode(), b"Connection: close"]
    return b"\r\n".join(lines) + b"\r\n\r\n" + body


async def exchange(port: int, data: bytes) -> tuple[int, bytes]:
    """One request on its own connection: (status, body)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(data)
        answer = await asyncio.wait_for(reader.read(), 10)
    finally:
        writer.close()
    head, _, body = answer.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), body


def bearer(token: bytes) -> tuple[bytes, bytes]:
    return (b"Authorization", b"Bearer " + token)


def audited(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


AUTH = (bearer(TOKEN.encode()),)
BIG = b'{"value": "' + b"x" * 70_000 + b'"}'
#: (what, request headers, body, status, what the answer and the audit say)
MALFORMED = [
    ("token bytes", (bearer(b"\xff\xfe"),), b'{"value": 1}', 401, "unauthorized"),  # was 500
    ("no token, 70 KB", (), BIG, 401, "unauthorized"),
    ("70 KB", AUTH, BIG, 413, "bad_request"),  # was 413 without an audit line
    ("30,000 deep", AUTH, b"[" * 30_000 + b"]" * 30_000, 400, "bad_request"),  # was 500
    ("not UTF-8", AUTH, b'{"value": "\xff"}', 400, "bad_request"),
    ("not an object", AUTH, b"[1]", 400, "bad_request"),
]


async def test_malformed_write_requests_are_4xx_audited_and_no_error_in_the_log(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: the token bytes and the deep body were 500 with a traceback and no audit line,
    the 70 KB body 413 without one."""
    caplog.set_level(logging.DEBUG)
    audit = tmp_path / "writes.jsonl"
    async with running_console(audit=audit) as console:
        port = console.web.port
        for what, headers, body, status, code in MALFORMED:
            got, answer = await exchange(port, request(WRITE, headers=headers, body=body))
            assert got == status, (what, answer[:200])
            assert json.loads(answer)["error"] == code, what
        # a charset Python does not know: the body is UTF-8 JSON all the same (was 500)
        ebcdic = (*AUTH, (b"Content-Type", b"application/json; charset=x-ebc"))
        got, answer = await exchange(port, request(WRITE, headers=ebcdic, body=b'{"value": 9}'))
        assert (got, json.loads(answer)) == (200, {"ok": True})
    lines = audited(audit)
    assert [line["result"] for line in lines] == [c for *_, c in MALFORMED] + ["ok"]
    assert all(line["source"] == "web" and line["peer"] for line in lines)
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert errors == [], [r.getMessage() for r in errors]


async def test_any_authorization_header_or_body_is_never_a_500() -> None:
    async with running_console() as console:
        port = console.web.port

        @settings(max_examples=60, suppress_health_check=[HealthCheck.function_scoped_fixture])
        @given(
            token=st.binary(max_size=40).filter(lambda b: b"\r" not in b and b"\n" not in b),
            body=st.binary(max_size=200),
        )
        def probe(token: bytes, body: bytes) -> None:
            future = asyncio.run_coroutine_threadsafe(
                exchange(port, request(WRITE, headers=(bearer(token.strip()),), body=body)), loop
            )
            status, _ = future.result(15)
            assert status in (400, 401), (token, body[:40], status)

        loop = asyncio.get_running_loop()
        await asyncio.to_thread(probe)


SERVED = [b"127.0.0.1", b"127.0.0.1:8080", b"localhost", b"LOCALHOST:1", b"[::1]:8080",
          b"app.localhost", b"10.1.2.3", b"localhost."]  # fmt: skip
REFUSED = [b"attacker.example", b"attacker.example:8080", b"127.0.0.1.attacker.example",
           b"localhost.attacker.example", b"\xff\xfe", b""]  # fmt: skip


async def test_only_requests_for_a_name_the_console_serves_are_answered(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Before: ``Host: attacker.example`` was answered 200 with every value (a page rebinding
    its name to the gateway reads the plant through a browser on the plant network)."""
    async with running_console() as console:
        port = console.web.port
        for host in SERVED:
            status, _ = await exchange(port, request(b"/api/tags", method=b"GET", host=host))
            assert status == 200, host
        old = request(b"/api/tags", method=b"GET", host=None, version=b"HTTP/1.0")
        assert (await exchange(port, old))[0] == 200  # a tool of HTTP/1.0 may send no Host
        with caplog.at_level(logging.WARNING, "plcstack.web"):
            for host in REFUSED:
                for path, method in ((b"/", b"GET"), (b"/api/tags", b"GET"), (WRITE, b"POST")):
                    status, body = await exchange(port, request(path, method=method, host=host))
                    assert status == 421, (host, path)
                    assert b"[web] hosts" in body
        assert console.web.hosts.refused == 3 * len(REFUSED)
    said = [r.getMessage() for r in caplog.records if "refused a request" in r.getMessage()]
    assert len(said) == 1, said  # once for the burst, not once per request
    assert "attacker.example" in said[0] and "DNS rebinding" in said[0]


def test_the_host_names_served() -> None:
    log = logging.getLogger("test.hosts")
    now = [0.0]
    check = HostCheck("0.0.0.0", ["Gateway01", "gateway01.plant.local"], log, clock=lambda: now[0])
    for header in ("gateway01:8080", "GATEWAY01.plant.local", "192.168.0.5:80", "[fe80::1]"):
        assert check.serves(header), header
    for header in ("gateway02", "plant.local", "gateway01.plant.local.evil", "0.0.0.0.evil"):
        assert not check.serves(header), header
    assert HostCheck("gw.plant.local", [], log).serves("gw.plant.local:8080")  # its own bind
    assert host_name(" Example.COM.:80 ") == "example.com"
    assert host_name("[::1]:80") == "::1"


def test_refusals_are_said_once_per_burst(caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    check = HostCheck("127.0.0.1", [], logging.getLogger("test.hosts"), clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, "test.hosts"):
        for _ in range(5):
            check.refused_request("evil.example", "10.0.0.9:4000", "/")
            now[0] += 1
        now[0] += web_hosts.QUIET_SECONDS
        check.refused_request("evil.example", "10.0.0.9:4000", "/api/tags")
    assert len(caplog.records) == 2 and check.refused == 6
    assert "(5 refused in the burst before)" in caplog.records[1].getMessage()


def test_web_hosts_setting() -> None:
    assert parse_web({"hosts": ["GW01", "gw01.plant.local"]}).hosts == ("gw01", "gw01.plant.local")
    assert parse_web({}).hosts == ()
    for bad in ("gw01", ["gw 01"], ["http://gw01"], ["gw01:8080"], [""], [1]):
        with pytest.raises(ConfigError, match=r"\[web\] hosts"):
            parse_web({"hosts": bad})
