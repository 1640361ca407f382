"""A reload applied to the running runtime: SIGHUP and the web console's ``/api/config`` take one
path (``RuntimeControl``), over real simulators, a real mosquitto and asyncua's client.

Before, SIGHUP re-read the file and said "restart it to apply a change": every new tag cost a
restart, and a restart cost every PLC its connection (an S5-LAN module takes one at a time),
every Sparkplug birth and every OPC UA session of the plant.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import re
import signal
import socket
import sys
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from plcstack.cli.reload import Running, RuntimeControl
from plcstack.config import load_config
from plcstack.errors import ConfigError
from plcstack.north.face import Face
from plcstack.north.pipeline import North
from plcstack.north.stdout import StdoutLines
from plcstack.poll.engine import Poller
from plcstack.sim import e71
from plcstack.sim.base import TcpSimulator
from plcstack.sim.melsec_memory import MelsecMemory
from tests.aio_helpers import eventually

ROOT = Path(__file__).resolve().parent.parent
INTERVAL = 0.05


def _plc(name: str, url: str, *tags: str) -> str:
    body = "".join(f"{t}\n" for t in tags or ('x = "D100"',))
    return f'[[plc]]\nname = "{name}"\nurl = "{url}"\n[plc.tags]\n{body}'


def _file(*plcs: str, head: str = "") -> str:
    return f"[poll]\ninterval = {INTERVAL}\n{head}" + "".join(plcs)


@dataclass
class Run:
    control: RuntimeControl
    poller: Poller
    north: North

    def scans(self, plc: str) -> int:
        return self.poller.stats[plc].scans if plc in self.poller.stats else 0


@contextlib.asynccontextmanager
async def running(path: Path, *faces: Face) -> AsyncIterator[Run]:
    """The runtime's parts as ``plcstack poll`` builds them, on the file at ``path``
    (``faces``: the caller's, as the stdout lines are)."""
    control = RuntimeControl.load(path)
    poller = Poller(control.config.poll)
    north = North(poller, control.config.north, faces=faces, control=control)
    await poller.start()
    try:
        await north.aopen()
        control.attach(Running(poller, north))
        feed = asyncio.create_task(north.run(), name="the consumer")
        try:
            yield Run(control, poller, north)
        finally:
            feed.cancel()
            await asyncio.gather(feed, return_exceptions=True)
            await north.aclose()
    finally:
        await poller.aclose()


@contextlib.asynccontextmanager
async def sims(count: int) -> AsyncIterator[list[TcpSimulator]]:
    started: list[TcpSimulator] = []
    for _ in range(count):
        one = await e71.start(MelsecMemory())
        assert isinstance(one, TcpSimulator)
        started.append(one)
    try:
        yield started
    finally:
        for sim in started:
            await sim.aclose()


async def test_a_reload_adds_removes_and_changes_plcs_and_leaves_the_others_connected(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "plant.toml"
    async with sims(4) as (a, b, c, d):
        path.write_text(
            _file(
                _plc("a", a.url), _plc("b", b.url), _plc("c", c.url),
                head='[audit]\npath = "audit.jsonl"\n',
            )
        )  # fmt: skip
        async with running(path) as run:
            await eventually(lambda: all(run.scans(p) >= 2 for p in "abc"), "scans of a, b, c")
            path.write_text(
                _file(
                    _plc("a", a.url), _plc("c", c.url, 'x = "D100"', 'y = "D200"'),
                    _plc("d", d.url), head='[audit]\npath = "audit.jsonl"\n',
                )
            )  # fmt: skip
            before = {p: run.scans(p) for p in "ac"}
            with caplog.at_level(logging.INFO, "plcstack.reload"):
                outcome = await run.control.reload(who="SIGHUP")
            assert outcome.ok, outcome
            assert outcome.summary == "PLCs added: d; removed: b; changed: c"
            said = [r.getMessage() for r in caplog.records if r.name == "plcstack.reload"]
            assert said == ["reload (SIGHUP): PLCs added: d; removed: b; changed: c"]
            await eventually(
                lambda: run.scans("d") >= 2 and run.scans("c") > before["c"] + 2,
                "scans of the added d and of the replanned c",
            )
            assert run.poller.plcs == ["a", "c", "d"]
            # the unchanged and the replanned PLC kept their one connection all along
            assert (a.connection_count.total, a.connection_count.current) == (1, 1)
            assert (c.connection_count.total, c.connection_count.current) == (1, 1)
            assert run.poller.stats["a"].reconnects == run.poller.stats["c"].reconnects == 0
            assert run.scans("a") > before["a"]
            await eventually(lambda: b.connection_count.current == 0, "b closed")  # removed
            assert {s for s in run.poller.tags("c")} == {"x", "y"}
            assert run.control.text() == path.read_text()
    # one audit record of the change: who, from where, what
    record = json.loads((tmp_path / "audit.jsonl").read_text().splitlines()[-1])
    assert {k: record[k] for k in ("kind", "source", "file", "result", "summary")} == {
        "kind": "config",
        "source": "SIGHUP",
        "file": str(path),
        "result": "ok",
        "summary": "PLCs added: d; removed: b; changed: c",
    }


async def test_a_file_that_does_not_load_changes_nothing_and_says_what_a_start_says(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "plant.toml"
    async with sims(1) as (a,):
        path.write_text(_file(_plc("a", a.url)))
        async with running(path) as run:
            await eventually(lambda: run.scans("a") >= 1, "a scan of a")
            good = path.read_text()
            path.write_text(_file(_plc("a", a.url, 'x = "D100"', 'y = "Q100"')))
            with pytest.raises(ConfigError) as at_start:
                load_config(path)
            with caplog.at_level(logging.INFO, "plcstack.reload"):
                outcome = await run.control.reload(who="SIGHUP")
            assert not outcome.ok
            assert outcome.errors == (str(at_start.value),)
            assert re.search(rf"{re.escape(str(path))}:\d+", outcome.errors[0]), outcome
            errors = [r for r in caplog.records if r.levelno == logging.ERROR]
            assert len(errors) == 1 and "does not load, nothing changed" in errors[0].getMessage()
            # the run goes on as it was: same plan, values keep flowing, same text shown
            assert set(run.poller.tags("a")) == {"x"}
            assert run.control.text() == good
            seen = run.scans("a")
            await eventually(lambda: run.scans("a") >= seen + 3, "scans of a after")
            assert a.connection_count.total == 1


async def test_replace_writes_the_file_atomically_keeps_the_old_one_and_applies_it(
    tmp_path: Path,
) -> None:
    path = tmp_path / "plant.toml"
    async with sims(2) as (a, b):
        first = _file(_plc("a", a.url))
        path.write_text(first)
        async with running(path) as run:
            second = _file(_plc("a", a.url), _plc("b", b.url))
            outcome = await run.control.replace(second, who="web 127.0.0.1 (token)")
            assert outcome.ok and outcome.summary == "PLCs added: b; removed: none; changed: none"
            assert path.read_text() == second
            assert (tmp_path / "plant.toml.bak").read_text() == first
            assert run.control.text() == second
            await eventually(lambda: run.scans("b") >= 1, "a scan of the added b")
            # a text that does not load: refused, the file and its .bak as they were
            refused = await run.control.replace(second + "[[plc]]\nname = 'c'\n", who="web")
            assert not refused.ok and "url" in refused.errors[0]
            assert str(path) in refused.errors[0]
            assert path.read_text() == second
            assert (tmp_path / "plant.toml.bak").read_text() == first
            left = sorted(p.name for p in tmp_path.iterdir())  # noqa: ASYNC240
            assert left == ["plant.toml", "plant.toml.bak"]  # no temporary file left


async def test_poller_wide_keys_are_said_as_waiting_for_a_restart(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    async with sims(1) as (a,):
        path.write_text(_file(_plc("a", a.url)))
        async with running(path) as run:
            path.write_text(
                _file(_plc("a", a.url), head="concurrency = 4\n[report]\non_change = true\n")
            )
            outcome = await run.control.reload(who="SIGHUP")
            assert outcome.ok
            assert outcome.summary == (
                "PLCs added: none; removed: none; changed: none;"
                " not applied (restart needed): [poll] concurrency, [report]"
            )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def test_a_face_whose_table_changed_restarts_alone_and_one_that_cannot_start_is_named(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from plcstack.north.metrics import MetricsServer
    from plcstack.north.modbus.server import ModbusServer

    path = tmp_path / "plant.toml"
    port = _free_port()
    async with sims(1) as (a,):
        faces = f'[modbus]\nlisten = "127.0.0.1:0"\n[metrics]\nlisten = "127.0.0.1:{port}"\n'
        tag = 'x = { address = "D100", modbus = "hr:0" }'
        path.write_text(_file(_plc("a", a.url, tag), head=faces))
        async with running(path) as run:
            modbus, metrics = run.north.face(ModbusServer), run.north.face(MetricsServer)
            assert modbus is not None and metrics is not None
            moved = _free_port()
            path.write_text(
                _file(
                    _plc("a", a.url, tag),
                    head=f'[modbus]\nlisten = "127.0.0.1:0"\n'
                    f'[metrics]\nlisten = "127.0.0.1:{moved}"\n',
                )
            )
            outcome = await run.control.reload(who="SIGHUP")
            assert outcome.ok and "faces restarted: metrics" in outcome.summary, outcome
            assert run.north.face(ModbusServer) is modbus  # untouched
            restarted = run.north.face(MetricsServer)
            assert restarted is not None and restarted is not metrics
            assert f":{moved}" in restarted.url
            # a port another process holds: that face is down and named, the others go on
            with socket_bound() as taken:
                path.write_text(
                    _file(
                        _plc("a", a.url, tag),
                        head=f'[modbus]\nlisten = "127.0.0.1:0"\n'
                        f'[metrics]\nlisten = "127.0.0.1:{taken}"\n',
                    )
                )
                with caplog.at_level(logging.ERROR):
                    outcome = await run.control.reload(who="SIGHUP")
            assert outcome.ok and outcome.errors and "[metrics] cannot start" in outcome.errors[0]
            assert any("[metrics] cannot start" in r.getMessage() for r in caplog.records)
            down = [h for h in run.north.health() if not h.ok]
            assert [h.name for h in down] == ["[metrics]"], down
            assert run.north.face(ModbusServer) is modbus
            seen = run.scans("a")
            await eventually(lambda: run.scans("a") >= seen + 2, "scans of a after")


@contextlib.contextmanager
def socket_bound() -> Iterator[int]:
    """A port another process holds (bound and listening) while the block runs."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


@pytest.mark.slow  # a poll process: a few seconds on a loaded machine
async def test_sighup_applies_the_file_to_a_running_poll(tmp_path: Path) -> None:
    """The whole command: ``plcstack poll`` on stdout, SIGHUP adds a PLC and removes one; the
    unchanged PLC's simulator counts one connection all along."""
    path = tmp_path / "plant.toml"
    async with sims(3) as (a, b, c):
        path.write_text(_file(_plc("a", a.url), _plc("b", b.url)))
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "-v", "poll", str(path), "--duration", "30",
            cwd=tmp_path, env=env, stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        assert proc.stdout is not None and proc.stderr is not None
        plcs: list[str] = []
        err: list[str] = []

        async def out() -> None:
            assert proc.stdout is not None
            while line := await proc.stdout.readline():
                plcs.append(json.loads(line)["plc"])

        async def errs() -> None:
            assert proc.stderr is not None
            while line := await proc.stderr.readline():
                err.append(line.decode())

        readers = [asyncio.create_task(out()), asyncio.create_task(errs())]
        try:
            await eventually(lambda: "b" in plcs, "lines of b", timeout=20)
            path.write_text(_file(_plc("a", a.url), _plc("c", c.url)))
            proc.send_signal(signal.SIGHUP)
            await eventually(
                lambda: any("reload (SIGHUP)" in line for line in err), "the reload line"
            )
            mark = len(plcs)
            await eventually(lambda: plcs[mark:].count("c") >= 2, "lines of the added c")
            assert "b" not in plcs[mark:]
            assert (a.connection_count.total, a.connection_count.current) == (1, 1)
            assert b.connection_count.current == 0
            proc.send_signal(signal.SIGTERM)
            assert await asyncio.wait_for(proc.wait(), 20) == 0
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
            await asyncio.gather(*readers, return_exceptions=True)
    said = [line for line in err if "reload (SIGHUP)" in line]
    assert len(said) == 1 and said[0].rstrip().endswith(
        "reload (SIGHUP): PLCs added: c; removed: b; changed: none"
    ), err


async def test_stdout_lines_print_an_added_plcs_float32_tag_at_float32_precision(
    tmp_path: Path,
) -> None:
    import io
    import struct

    from plcstack.poll.sinks import jsonl_text

    path = tmp_path / "plant.toml"
    memory = MelsecMemory()
    memory.write_words("D", 100, list(struct.unpack("<2H", struct.pack("<f", 0.1))))
    async with sims(1) as (a,):
        b = await e71.start(memory)
        try:
            path.write_text(_file(_plc("a", a.url)))
            out = io.StringIO()
            config = load_config(path)
            lines = StdoutLines(jsonl_text(config.plcs), out, remake=jsonl_text)
            async with running(path, lines) as run:
                tag = 'f = { address = "D100", type = "float32" }'
                path.write_text(_file(_plc("a", a.url), _plc("b", b.url, tag)))
                assert (await run.control.reload(who="SIGHUP")).ok
                await eventually(lambda: '"plc": "b"' in out.getvalue(), "a line of b")
        finally:
            await b.aclose()
    line = next(x for x in out.getvalue().splitlines() if '"plc": "b"' in x)
    assert json.loads(line)["value"] == 0.1, line  # not 0.10000000149011612
