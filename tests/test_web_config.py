"""``GET /api/config``, ``POST /api/config/reload`` and ``POST /api/config`` of the web console,
over real HTTP, against a small real :class:`~plcstack.north.control.ConfigControl` that loads
with the product's loader and writes the file as the runtime does (atomically, ``FILE.bak``)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import sys
import tomllib
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp

from plcstack.config import load_config
from plcstack.config.load import read_config
from plcstack.errors import ConfigError
from plcstack.north.audit import Audit, AuditSettings
from plcstack.north.control import ApplyOutcome
from plcstack.north.opcua_config import hash_password
from plcstack.north.web.config_api import MAX_CONFIG_BYTES
from plcstack.north.web.server import WebConsole
from plcstack.north.web.settings import WebSettings
from plcstack.north.writes import WritePath
from plcstack.poll.engine import Poller
from plcstack.sim import e71 as e71_sim
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.tomlfile import TomlFile
from tests.web_helpers import TOKEN, TOKEN_ENV

HASH = hash_password("operator", iterations=1000)
AUTH = {"Authorization": f"Bearer {TOKEN}"}
PLANT = f"""\
# plant 7
[opcua.users.alice]   # the operator
password_hash = '{HASH}'
write = true

[[plc]]
name = "press1"
url = "e71+tcp://127.0.0.1:1?timeout=0.2"
[plc.tags]
strokes = {{ address = "D100" }}
"""
#: a second PLC, as an edit adds it
PRESS2 = '[[plc]]\nname = "press2"\nurl = "e71+tcp://127.0.0.1:1"\ntags = { cycles = "D0" }\n'


class FileControl:
    """The running configuration of one file: loaded with the product's loader, replaced by
    writing the file atomically with the previous one kept as ``FILE.bak``. ``hold``: when
    set, an apply waits for it (a change still running)."""

    def __init__(self, path: Path) -> None:
        self._path = path
        self._text = path.read_text(encoding="utf-8")
        self.changes: list[str] = []
        self.hold: asyncio.Event | None = None
        #: set when an apply waits for ``hold``
        self.waiting = asyncio.Event()

    @property
    def path(self) -> Path:
        return self._path

    def text(self) -> str:
        return self._text

    async def reload(self, *, who: str) -> ApplyOutcome:
        return await self._apply(self._path.read_text(encoding="utf-8"), who, write=False)

    async def replace(self, text: str, *, who: str) -> ApplyOutcome:
        return await self._apply(text, who, write=True)

    async def _apply(self, text: str, who: str, *, write: bool) -> ApplyOutcome:
        try:
            new = read_config(TomlFile.parse(text, str(self._path)))
        except ConfigError as exc:
            return ApplyOutcome(False, errors=(str(exc),))
        if self.hold is not None:
            self.waiting.set()
            await self.hold.wait()
        old = {plc.name for plc in read_config(TomlFile.parse(self._text, "old")).plcs}
        if write:
            self._path.with_name(self._path.name + ".bak").write_bytes(self._path.read_bytes())
            tmp = self._path.with_name(self._path.name + ".tmp")
            tmp.write_text(text, encoding="utf-8")
            os.replace(tmp, self._path)
        self._text = text
        self.changes.append(who)
        added = sorted({plc.name for plc in new.plcs} - old)
        return ApplyOutcome(True, summary=f"PLCs added: {', '.join(added) or 'none'}")


@contextlib.asynccontextmanager
async def console(
    path: Path, *, token: str | None = TOKEN, control: bool = True, audit: Path | None = None
) -> AsyncIterator[tuple[str, FileControl]]:
    path.write_text(PLANT, encoding="utf-8")  # noqa: ASYNC240 (a test's file, written once)
    files = FileControl(path)
    before = os.environ.pop(TOKEN_ENV, None)
    if token is not None:
        os.environ[TOKEN_ENV] = token
    try:
        async with Poller(load_config(path).poll) as poller:
            audited = None if audit is None else Audit(AuditSettings(str(audit)))
            web = WebConsole(
                poller,
                WebSettings(port=0, write_token_env=TOKEN_ENV),
                writes=WritePath(poller, audit=audited),
                control=files if control else None,
            )
            await web.start()
            try:
                yield f"http://127.0.0.1:{web.port}", files
            finally:
                await web.aclose()
    finally:
        os.environ.pop(TOKEN_ENV, None)
        if before is not None:
            os.environ[TOKEN_ENV] = before


async def test_the_running_file_is_shown_with_its_secrets_redacted(tmp_path: Path) -> None:
    async with (
        console(tmp_path / "plant.toml") as (base, _),
        aiohttp.ClientSession() as http,
        http.get(base + "/api/config", headers=AUTH) as r,
    ):
        status, kind, text = r.status, r.content_type, await r.text()
    assert (status, kind) == (200, "application/toml")
    assert HASH not in text
    marker = re.search(r"<redacted:[0-9a-f]{12}>", text)
    assert marker is not None
    assert text == PLANT.replace(HASH, marker.group(0))  # comments and layout as in the file


async def test_without_the_token_nothing_is_shown_reloaded_or_replaced(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    requests = [("GET", "/api/config"), ("POST", "/api/config/reload"), ("POST", "/api/config")]
    async with console(path) as (base, files), aiohttp.ClientSession() as http:
        seen = []
        for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Bearer \udcff"}):
            for method, route in requests:
                async with http.request(
                    method, base + route, headers=headers, data="[[plc]]\n"
                ) as r:
                    seen.append((r.status, await r.json(), r.headers.get("WWW-Authenticate")))
    assert files.changes == [] and path.read_text() == PLANT
    for status, body, challenge in seen:
        assert status == 401 and challenge == 'Bearer realm="plcstack"'
        assert body["ok"] is False
        assert body["errors"][0].startswith("a valid 'Authorization: Bearer TOKEN' is required")
    async with (
        console(path, token=None) as (base, files),
        aiohttp.ClientSession() as http,
        http.get(base + "/api/config", headers=AUTH) as r,
    ):
        assert r.status == 403
        assert "without a write token" in (await r.json())["errors"][0]
    async with console(path, control=False) as (base, _), aiohttp.ClientSession() as http:
        for method, route in requests:
            async with http.request(method, base + route, headers=AUTH, data="x") as r:
                assert r.status == 503, route
                assert (await r.json())["errors"] == [
                    "this run cannot change its configuration (no configuration file)"
                ]


async def test_reload_reads_the_file_again(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    async with console(path) as (base, files), aiohttp.ClientSession() as http:
        path.write_text(PLANT + PRESS2)
        async with http.post(base + "/api/config/reload", headers=AUTH) as r:
            ok = (r.status, await r.json())
        path.write_text(PLANT + "[[plc]]\nname = 7\n")
        async with http.post(base + "/api/config/reload", headers=AUTH) as r:
            broken = (r.status, await r.json())
    assert ok == (200, {"ok": True, "summary": "PLCs added: press2"})
    status, body = broken
    assert status == 400 and body["ok"] is False
    assert re.search(rf"\({re.escape(str(path))}:\d+\)$", body["errors"][0]), body
    assert len(files.changes) == 1 and re.fullmatch(
        r"web 127\.0\.0\.1:\d+ \(token\)", files.changes[0]
    )


async def test_a_shown_text_sent_back_keeps_its_secrets_and_the_file_is_written(
    tmp_path: Path,
) -> None:
    path = tmp_path / "plant.toml"
    async with console(path) as (base, files), aiohttp.ClientSession() as http:
        async with http.get(base + "/api/config", headers=AUTH) as r:
            shown = await r.text()
        edited = shown + PRESS2
        async with http.post(base + "/api/config", headers=AUTH, data=edited.encode()) as r:
            answer = (r.status, await r.json())
    assert answer == (200, {"ok": True, "summary": "PLCs added: press2"})
    written = path.read_text(encoding="utf-8")
    assert written == PLANT + PRESS2
    assert tomllib.loads(written)["opcua"]["users"]["alice"]["password_hash"] == HASH
    assert path.with_name("plant.toml.bak").read_text(encoding="utf-8") == PLANT
    assert files.text() == written


async def test_a_text_that_does_not_load_changes_nothing(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    broken = PLANT + '[[plc]]\nname = "press2"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\nx = {}\n'
    async with console(path) as (base, files), aiohttp.ClientSession() as http:
        async with http.post(base + "/api/config", headers=AUTH, data=broken) as r:
            status, body = r.status, await r.json()
        async with http.post(base + "/api/config", headers=AUTH, data="[[[") as r:
            not_toml = r.status, await r.json()
    assert status == 400 and body["ok"] is False
    assert re.search(rf"{re.escape(str(path))}:15\)$", body["errors"][0]), body
    assert not_toml[0] == 400 and "not valid TOML" in not_toml[1]["errors"][0]
    assert path.read_text() == PLANT and not path.with_name("plant.toml.bak").exists()
    assert files.changes == []


async def test_a_marker_that_stands_for_no_running_secret_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    async with console(path) as (base, files), aiohttp.ClientSession() as http:
        text = PLANT.replace(HASH, "<redacted:0123456789ab>")
        async with http.post(base + "/api/config", headers=AUTH, data=text) as r:
            status, body = r.status, await r.json()
    assert status == 400
    assert body["errors"] == [
        f"{path}:3: <redacted:0123456789ab> stands for no secret of the running configuration"
        " (it was shown by an earlier run, or the secret changed since): read the"
        " configuration again, or write the secret itself"
    ]
    assert path.read_text() == PLANT and files.changes == []


async def test_a_body_too_large_or_not_utf8_is_refused_before_anything_is_read(
    tmp_path: Path,
) -> None:
    path = tmp_path / "plant.toml"
    async with console(path) as (base, files), aiohttp.ClientSession() as http:
        big = b"# " + b"x" * MAX_CONFIG_BYTES + b"\n"
        async with http.post(base + "/api/config", headers=AUTH, data=big) as r:
            too_big = r.status, await r.json()

        async def chunks() -> AsyncIterator[bytes]:  # no Content-Length: counted as it comes
            for _ in range(MAX_CONFIG_BYTES // 65536 + 2):
                yield b"#" * 65535 + b"\n"

        async with http.post(base + "/api/config", headers=AUTH, data=chunks()) as r:
            streamed = r.status
        async with http.post(base + "/api/config", headers=AUTH, data=b"# \xff\xfe\n") as r:
            not_utf8 = r.status, await r.json()
    assert too_big == (
        413,
        {"ok": False, "errors": [f"the body is larger than {MAX_CONFIG_BYTES} bytes"]},
    )
    assert streamed == 413
    assert not_utf8[0] == 400 and not_utf8[1]["errors"] == [
        "the body is not UTF-8 text (invalid start byte at byte 2)"
    ]
    assert files.changes == [] and path.read_text() == PLANT


async def test_one_change_at_a_time(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    async with console(path) as (base, files), aiohttp.ClientSession() as http:
        files.hold = asyncio.Event()
        first = asyncio.create_task(http.post(base + "/api/config/reload", headers=AUTH))
        await asyncio.wait_for(files.waiting.wait(), 10)
        async with http.post(base + "/api/config", headers=AUTH, data=PLANT) as r:
            second = r.status, await r.json()
        files.hold.set()
        async with await first as r:
            assert r.status == 200
    assert second == (
        409,
        {"ok": False, "errors": ["another configuration change is being applied"]},
    )
    assert len(files.changes) == 1


async def test_each_change_refused_here_is_a_record_of_the_audit(tmp_path: Path) -> None:
    """A refused change is audited as a refused write is; a refused read is not a change."""
    audit = tmp_path / "writes.jsonl"
    async with (
        console(tmp_path / "plant.toml", audit=audit) as (base, _),
        aiohttp.ClientSession() as http,
    ):
        wrong = {"Authorization": "Bearer wrong"}
        for method, route, headers, body in [
            ("GET", "/api/config", wrong, b""),
            ("POST", "/api/config/reload", wrong, b""),
            ("POST", "/api/config", AUTH, b"x" * (MAX_CONFIG_BYTES + 1)),
            ("POST", "/api/config", AUTH, b"password = '<redacted:0123456789ab>'\n"),
        ]:
            async with http.request(method, base + route, headers=headers, data=body) as r:
                assert r.status >= 400
    records = [json.loads(line) for line in audit.read_text().splitlines()]
    assert [(r["kind"], r["result"]) for r in records] == [("config", "refused")] * 3
    sources = [re.sub(r":\d+", ":PORT", r["source"]) for r in records]
    assert sources == ["web 127.0.0.1:PORT"] + ["web 127.0.0.1:PORT (token)"] * 2
    assert records[0]["summary"].startswith("a valid 'Authorization: Bearer TOKEN' is required")
    assert records[1]["summary"] == f"the body is larger than {MAX_CONFIG_BYTES} bytes"
    assert records[2]["summary"].startswith(f"{tmp_path / 'plant.toml'}:1: <redacted:0123456789ab>")
    assert {r["file"] for r in records} == {str(tmp_path / "plant.toml")}


# -- end to end: plcstack poll, its runtime's control -------------------------------------------
@contextlib.asynccontextmanager
async def plcstack_poll(path: Path) -> AsyncIterator[str]:
    """``plcstack poll FILE --format none`` as a process, with the write token in its
    environment; the console's base URL, from the line it says on stderr."""
    env = {**os.environ, TOKEN_ENV: TOKEN}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "plcstack", "poll", str(path), "--format", "none",
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE, env=env,
    )  # fmt: skip
    assert proc.stderr is not None
    said: list[str] = []
    try:
        async with asyncio.timeout(20):
            while not (m := re.search(r"web console on (http://\S+)/ ", said[-1] if said else "")):
                line = await proc.stderr.readline()
                assert line, f"plcstack poll ended: {''.join(said)}"
                said.append(line.decode())
        drain = asyncio.create_task(proc.stderr.read())  # the rest of its log, read as it comes
        yield m.group(1)
    finally:
        if proc.returncode is None:
            proc.terminate()
        async with asyncio.timeout(20):
            code = await proc.wait()
    log = (await drain).decode()
    assert code == 0, f"plcstack poll: exit {code}: {''.join(said)}{log}"


async def test_plcstack_poll_takes_a_new_plc_over_rest_and_refuses_a_broken_file(
    tmp_path: Path,
) -> None:
    """One ``plcstack poll`` with ``[web]``: ``POST /api/config`` adding a PLC starts polling
    it (its value on ``/api/tags``), the file written and the old one kept as ``FILE.bak``;
    a text that does not load is 400 with its FILE:LINE and changes nothing."""
    memory = MelsecMemory()
    memory.write_words("D", 100, [1500])
    memory.write_words("D", 200, [4711])
    path = tmp_path / "plant.toml"
    start = (
        f'[poll]\ninterval = 0.1\n[web]\nlisten = "127.0.0.1:0"\nwrite_token_env = "{TOKEN_ENV}"\n'
    )
    async with await e71_sim.start(memory) as sim:
        first = (
            start + f'[[plc]]\nname = "press1"\nurl = "{sim.url}"\ntags = {{ speed = "D100" }}\n'
        )
        second = (
            first + f'[[plc]]\nname = "press2"\nurl = "{sim.url}"\ntags = {{ level = "D200" }}\n'
        )
        broken = (
            second + f'[[plc]]\nname = "press3"\nurl = "{sim.url}"\ntags = {{ x = "DB1.DW0" }}\n'
        )
        path.write_text(first)
        async with plcstack_poll(path) as base, aiohttp.ClientSession() as http:
            async with http.get(base + "/api/config", headers=AUTH) as r:
                shown = await r.text()
            async with http.post(base + "/api/config", headers=AUTH, data=second) as r:
                added = r.status, await r.json()

            async def level() -> object:
                async with http.get(base + "/api/tags?plc=press2") as r:
                    rows = await r.json()
                return rows[0]["value"] if rows else None

            for _ in range(200):  # polled every 0.1 s: its value within 10 s
                if await level() == 4711:
                    break
                await asyncio.sleep(0.05)
            else:
                raise AssertionError("press2 was not polled within 10 s of its POST")
            async with http.post(base + "/api/config", headers=AUTH, data=broken) as r:
                refused = r.status, await r.json()
            async with http.get(base + "/api/plcs") as r:
                plcs = sorted(row["name"] for row in await r.json())
            written, kept = path.read_text(), path.with_name("plant.toml.bak").read_text()
    assert shown == first
    assert added == (
        200,
        {"ok": True, "summary": "PLCs added: press2; removed: none; changed: none"},
    )
    status, body = refused
    assert status == 400 and body["ok"] is False, body
    assert body["errors"][0].endswith(f"({path}:14)"), body
    assert "S5" in body["errors"][0], body
    assert plcs == ["press1", "press2"]
    assert (written, kept) == (second, first)
