"""``[trace]``: the flight recorder of a running poller: the table, the rings on each PLC's
connection, the capture file when a PLC goes offline (once), the capture on request."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import sys
from pathlib import Path

import aiohttp
import pytest

from plcstack.errors import ConfigError
from plcstack.north.trace import TraceSettings, TraceSink, parse_trace
from plcstack.poll.config import DEFAULT_GROUP, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.sim import e71 as e71_sim
from plcstack.wire.streams import conversations, exchanges
from tests.aio_helpers import eventually
from tests.web_helpers import running_console

ROOT = Path(__file__).resolve().parent.parent


def test_the_table_and_its_checks(tmp_path: Path) -> None:
    assert parse_trace({}) == TraceSettings()
    settings = parse_trace({"ring": 16, "dir": "t", "interval": "10m"}, base=tmp_path)
    assert settings == TraceSettings(16, tmp_path / "t", 600.0)
    cases: list[tuple[dict[str, object], str]] = [
        ({"ring": 0}, "[trace] ring must be 1..4096, not 0"),
        ({"ring": True}, "[trace] ring must be 1..4096, not True"),
        ({"ring": 5000}, "[trace] ring must be 1..4096, not 5000"),
        ({"dir": ""}, "[trace] dir must name a folder, not ''"),
        ({"interval": "soon"}, "[trace] interval must be a number of seconds (greater than 0)"),
        ({"rings": 4}, "unknown key(s) rings (did you mean ring?)"),
    ]
    for table, message in cases:
        with pytest.raises(ConfigError) as raised:
            parse_trace(table)
        assert message in str(raised.value)


async def test_an_offline_plc_leaves_its_last_frames_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    sim = await e71_sim.start()
    sim.memory.write_words("D", 100, [7])
    trace = TraceSink(TraceSettings(ring=8, directory=tmp_path / "traces"))
    config = PollConfig(
        plcs=(
            PlcConfig(
                name="press",
                url=sim.url,
                timeout=2.0,  # a loaded machine must not time a request out here
                connect_timeout=0.3,
                backoff_max=0.2,
                tags=(TagConfig(name="strokes", address="D100"),),
            ),
        ),
        groups={DEFAULT_GROUP: 0.05},
    )
    poller = Poller(config)
    trace.attach(poller)
    seen: list[object] = []

    async def consume() -> None:
        async for batch in poller.scans():
            trace.submit(batch)
            seen.extend(s.value for scan in batch for s in scan.samples)

    await poller.start()
    consumer = asyncio.create_task(consume())
    try:
        await eventually(lambda: seen.count(7) >= 3, "three scans of the PLC")
        # what the REST route hands out: the ring as pcapng, the last exchanges of the poll
        (conversation,) = conversations(trace.capture("press"))
        answered = [e.answers for e in exchanges(conversation) if e.answers]
        assert answered and all(a == (bytes.fromhex("8100 0700"),) for a in answered)
        await sim.aclose()  # the PLC goes away: offline, once
        await eventually(lambda: trace.written, "the capture of the PLC gone offline")
        await asyncio.sleep(0.5)  # further failed scans: no second file
    finally:
        consumer.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await consumer
        await poller.aclose()
    (path,) = trace.written
    assert path.parent == tmp_path / "traces" and path.suffix == ".pcapng"
    assert any(e.request for c in conversations(path.read_bytes()) for e in exchanges(c))
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert sum("press went offline: its last" in m for m in said) == 1
    assert conversations(trace.capture("oven")) == []  # no frames: a file without packets


async def test_the_console_hands_out_a_plcs_capture(tmp_path: Path) -> None:
    """GET /api/plcs/NAME/capture.pcapng: the ring of that PLC as a pcapng attachment; an
    unknown PLC is 404 unknown_plc, a console without [trace] 404 no_trace."""
    async with running_console(trace=tmp_path / "traces") as console:
        await eventually(lambda: console.poller.stats["press1"].requests >= 3, "three scans")
        async with aiohttp.ClientSession() as session:
            url = f"{console.base}/api/plcs/press1/capture.pcapng"
            async with session.get(url) as response:
                assert response.status == 200
                assert response.headers["Content-Type"] == "application/x-pcapng"
                assert 'filename="press1-' in response.headers["Content-Disposition"]
                body = await response.read()
            async with session.get(f"{console.base}/api/plcs/nosuch/capture.pcapng") as gone:
                assert gone.status == 404 and (await gone.json())["error"] == "unknown_plc"
    (conversation,) = conversations(body)
    assert exchanges(conversation) and all(e.answers for e in exchanges(conversation)[:-1])
    async with running_console() as console, aiohttp.ClientSession() as session:
        url = f"{console.base}/api/plcs/press1/capture.pcapng"
        async with session.get(url) as response:
            assert response.status == 404 and (await response.json())["error"] == "no_trace"


async def test_poll_with_a_trace_table_writes_the_offline_plcs_frames_beside_its_config(
    tmp_path: Path,
) -> None:
    sim = await e71_sim.start()
    config = tmp_path / "plant.toml"
    config.write_text(
        f"""
[poll]
interval = 0.05
timeout = 0.3
connect_timeout = 0.3
backoff_max = 0.2

[trace]
ring = 8

[[plc]]
name = "press"
url = "{sim.url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16" }}
""",
        encoding="utf-8",
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "plcstack", "poll", str(config),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=env,
    )  # fmt: skip
    try:
        assert proc.stdout is not None and proc.stderr is not None
        await asyncio.wait_for(proc.stdout.readline(), 30)  # polling: a first sample
        await sim.aclose()  # the PLC goes away while it is polled
        # until it said so, then stopped as a service is (SIGTERM): a fixed --duration could
        # end first on a loaded machine
        said_offline = b""
        async with asyncio.timeout(30):
            while b"press went offline" not in said_offline:
                line = await proc.stderr.readline()
                assert line, f"poll ended before saying the PLC went offline: {said_offline!r}"
                said_offline += line
        proc.terminate()
        _, rest = await asyncio.wait_for(proc.communicate(), 30)
        err = said_offline + rest
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 0, err.decode()
    (written,) = (tmp_path / "traces").iterdir()  # beside the config, once
    assert written.name.startswith("press-") and written.suffix == ".pcapng"
    said = err.decode()
    assert re.search(
        rf"press went offline: its last \d+ frames are in {re.escape(str(written))}", said
    ), said
    assert conversations(written.read_bytes())
