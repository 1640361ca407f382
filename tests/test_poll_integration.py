"""The poller and its CLI against real simulators over loopback sockets.

One good PLC, one dead (a closed port), one slow (behind an asyncio delay proxy) and one that
restarts mid-run, polled together; ``plcstack poll`` over 100 simulated PLCs; ``plcstack demo``.
Protocols whose modules are not in this tree yet are skipped.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import importlib.util
import io
import json
import os
import subprocess
import sys
from argparse import Namespace
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from plcstack import values as vt
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.demo import available_protocols
from plcstack.poll.engine import Poller, Quality, Sample
from tests.aio_helpers import ends_quietly
from tests.ports import free_port

ROOT = Path(__file__).resolve().parent.parent


class DelayProxy:
    """A TCP proxy that holds every chunk from the server for ``delay`` seconds."""

    def __init__(self, target: tuple[str, int], delay: float) -> None:
        self.target = target
        self.delay = delay
        self.server: asyncio.Server | None = None
        self.tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> int:
        self.server = await asyncio.start_server(ends_quietly(self._handle), "127.0.0.1", 0)
        port: int = self.server.sockets[0].getsockname()[1]
        return port

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection(*self.target)

        async def pump(src: asyncio.StreamReader, dst: asyncio.StreamWriter, delay: float) -> None:
            with contextlib.suppress(ConnectionError, asyncio.CancelledError):
                while data := await src.read(4096):
                    if delay:
                        await asyncio.sleep(delay)
                    dst.write(data)
            dst.close()

        for task in (
            asyncio.create_task(pump(reader, up_writer, 0.0)),
            asyncio.create_task(pump(up_reader, writer, self.delay)),
        ):
            self.tasks.add(task)
            task.add_done_callback(self.tasks.discard)

    async def aclose(self) -> None:
        assert self.server is not None
        self.server.close()
        for task in list(self.tasks):
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        await self.server.wait_closed()


@dataclass(frozen=True)
class Proto:
    """How to run one protocol's simulator with a known memory content, for these tests."""

    name: str
    sim_module: str
    scheme: str
    tags: tuple[TagConfig, ...]
    memory: Callable[[int], Any]  # memory whose counter tag holds the argument
    set_counter: Callable[[Any, int], None]
    expected_rest: dict[str, object]  # the values of the other tags
    #: a reply delay that passes the client's deadline (S5-LAN's is at least 1.1 s, spec A.8)
    slow_delay: float

    def sim(self) -> Any:
        return importlib.import_module(self.sim_module)


def e71_memory(counter: int) -> Any:
    mem = importlib.import_module("plcstack.sim.melsec_memory").MelsecMemory()
    mem.write_words("D", 0, [counter, 0, 0x0000, 0x3FC0])  # temp 1.5, low word first
    mem.write_bits("M", 0, [True, False, True, True])
    return mem


def s5_memory(counter: int) -> Any:
    from plcstack.sim.s5memory import Area, S5Memory

    mem = S5Memory(default_dbs={10: 16})
    mem.write_db_words(10, 0, [counter, 0, 0x3FC0, 0x0000])  # temp 1.5, high word first
    mem.write_area(Area.FLAGS, 0, b"\x0d")
    return mem


S5_TAGS = (
    TagConfig("counter", "DB10.DW0", vt.UINT16),
    TagConfig("temp", "DB10.DW2", vt.FLOAT32),
    TagConfig("run", "MB0", vt.UINT8),
)

PROTOS = [
    Proto(
        "e71",
        "plcstack.sim.e71",
        "e71+tcp",
        (
            TagConfig("counter", "D0", vt.UINT16),
            TagConfig("temp", "D2", vt.FLOAT32),
            TagConfig("run", "M0", vt.BOOL, 4),
        ),
        e71_memory,
        lambda mem, v: mem.write_words("D", 0, [v]),
        {"temp": 1.5, "run": [True, False, True, True]},
        0.6,
    ),
    Proto(
        "s5lan",
        "plcstack.sim.s5lan",
        "s5lan",
        S5_TAGS,
        s5_memory,
        lambda mem, v: mem.write_db_words(10, 0, [v]),
        {"temp": 1.5, "run": 13},
        1.6,
    ),
    Proto(
        "fetchwrite",
        "plcstack.sim.fetchwrite",
        "fetchwrite",
        S5_TAGS,
        s5_memory,
        lambda mem, v: mem.write_db_words(10, 0, [v]),
        {"temp": 1.5, "run": 13},
        0.6,
    ),
    Proto(
        "as511",
        "plcstack.sim.as511",
        "as511+tcp",
        S5_TAGS,
        s5_memory,
        lambda mem, v: mem.write_db_words(10, 0, [v]),
        {"temp": 1.5, "run": 13},
        1.6,
    ),
]


def _built(proto: Proto) -> bool:
    return all(
        importlib.util.find_spec(m) is not None
        for m in (proto.sim_module, proto.sim_module.replace(".sim.", ".clients."))
    )


AVAILABLE = [p for p in PROTOS if _built(p)]
pytestmark = pytest.mark.skipif(not AVAILABLE, reason="no protocol simulator in this tree yet")


@pytest.fixture(params=PROTOS, ids=[p.name for p in PROTOS])
def proto(request: pytest.FixtureRequest) -> Proto:
    p: Proto = request.param
    if not _built(p):
        pytest.skip(f"{p.name} is not in this tree yet")
    return p


async def gather_until(
    poller: Poller, done: Callable[[list[Sample]], bool], seen: list[Sample], limit: float = 20.0
) -> None:
    async with asyncio.timeout(limit):
        async for sample in poller:
            seen.append(sample)
            if done(seen):
                return


async def test_dead_slow_and_restarting_plcs_do_not_disturb_a_good_one(proto: Proto) -> None:
    sim, tags = proto.sim(), proto.tags
    good = await sim.start(proto.memory(1))
    slow_sim = await sim.start(proto.memory(2))
    proxy = DelayProxy(("127.0.0.1", slow_sim.port), delay=proto.slow_delay)
    slow_port = await proxy.start()
    restart_mem = proto.memory(3)
    restart = await sim.start(restart_mem)
    restart_port = restart.port
    plcs = (
        PlcConfig("good", good.url, tags),
        PlcConfig("dead", f"{proto.scheme}://127.0.0.1:{free_port()}", tags),
        PlcConfig("slow", f"{proto.scheme}://127.0.0.1:{slow_port}", tags),
        PlcConfig("restart", restart.url, tags),
    )
    config = PollConfig(
        tuple(
            PlcConfig(p.name, p.url, p.tags, timeout=0.3, connect_timeout=0.3, backoff_max=0.2)
            for p in plcs
        ),
        {"default": 0.05},
    )
    seen: list[Sample] = []

    def by(plc: str, quality: Quality | None = None) -> list[Sample]:
        return [s for s in seen if s.plc == plc and (quality is None or s.quality is quality)]

    try:
        async with Poller(config) as poller:
            await gather_until(poller, lambda s: len(by("restart", Quality.GOOD)) >= 6, seen)
            await restart.aclose()
            await gather_until(poller, lambda s: len(by("restart", Quality.BAD)) >= 6, seen)
            proto.set_counter(restart_mem, 33)
            restart = await sim.start(restart_mem, port=restart_port)
            await gather_until(
                poller,
                lambda s: s[-1].plc == "restart" and s[-1].quality is Quality.GOOD,
                seen,
            )
            await gather_until(poller, lambda s: len(by("slow")) >= 3, seen)
            stats = poller.stats
    finally:
        await asyncio.gather(good.aclose(), slow_sim.aclose(), restart.aclose(), proxy.aclose())

    # the good PLC: every sample good, values right, and it kept scanning through it all
    assert by("good") and all(s.quality is Quality.GOOD for s in by("good"))
    last = {s.tag: s.value for s in by("good")}
    assert last == {"counter": 1, **proto.expected_rest}
    assert len(by("good")) > 3 * len(by("slow"))
    # dead: bad from the start, the message names the PLC's URL and why
    dead = by("dead")
    assert dead and all(s.quality is Quality.BAD for s in dead)
    assert all(f"{proto.scheme}://127.0.0.1:" in (s.error or "") for s in dead)
    assert stats["dead"].connect_failures >= 1 and stats["dead"].requests >= 1
    # slow: answers come after the deadline, so every scan times out
    assert all(s.quality is Quality.BAD for s in by("slow"))
    assert any("within" in (s.error or "") for s in by("slow"))  # a deadline, per protocol
    # restart: good, then bad, then good again with the new value; the reconnect is counted
    qualities = [s.quality for s in by("restart") if s.tag == "counter"]
    first_bad = qualities.index(Quality.BAD)
    assert Quality.GOOD in qualities[:first_bad] and qualities[-1] is Quality.GOOD
    assert [s.value for s in by("restart") if s.tag == "counter"][-1] == 33
    assert stats["restart"].reconnects >= 1
    assert stats["good"].errors == 0 and stats["good"].reconnects == 0


async def test_merged_reads_and_writes_through_the_poller(proto: Proto) -> None:
    mem = proto.memory(5)
    sim = await proto.sim().start(mem)
    config = PollConfig((PlcConfig("p", sim.url, proto.tags),), {"default": 0.02})
    try:
        async with Poller(config) as poller:
            plan = poller.plan("p", "default")
            # counter and temp in one request (4 words), the bits in another
            assert len(plan.requests) == 2 and plan.requests[0].count == 4
            await poller.write_tag("p", "temp", -2.25)
            await poller.write_tag("p", "counter", 65535)
            seen: list[Sample] = []
            await gather_until(
                poller,
                lambda s: (
                    any(x.tag == "temp" and x.value == -2.25 for x in s)
                    and any(x.tag == "counter" and x.value == 65535 for x in s)
                ),
                seen,
            )
    finally:
        await sim.aclose()


async def make_plant(proto: Proto, n: int) -> list[Any]:
    sim = proto.sim()
    return [await sim.start(proto.memory(i)) for i in range(n)]


def write_config(path: Path, proto: Proto, urls: list[str], interval: float) -> None:
    lines = [f"[poll]\ninterval = {interval}\ntimeout = 2.0\n"]
    for i, url in enumerate(urls):
        lines.append(
            f'[[plc]]\nname = "plc{i:03d}"\nurl = "{url}"\n[plc.tags]\n'
            + "".join(
                f'{t.name} = {{ address = "{t.address}", type = "{t.type.name}", '
                f"count = {t.count} }}\n"
                for t in proto.tags
            )
        )
    path.write_text("\n".join(lines))


@pytest.mark.slow
async def test_cli_poll_100_simulated_plcs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from plcstack.cli.poll import run_poll

    proto = AVAILABLE[0]  # E71 when built: its simulators are the cheapest
    sims = await make_plant(proto, 100)
    try:
        cfg = tmp_path / "plant.toml"
        write_config(cfg, proto, [s.url for s in sims], interval=0.2)
        out = io.StringIO()
        code = await run_poll(Namespace(config=str(cfg), format="jsonl", duration=2.0), out)
    finally:
        await asyncio.gather(*(s.aclose() for s in sims))
    assert code == 0
    records = [json.loads(line) for line in out.getvalue().splitlines()]
    assert {r["plc"] for r in records} == {f"plc{i:03d}" for i in range(100)}
    assert all(r["quality"] == "good" for r in records)
    assert {r["value"] for r in records if r["plc"] == "plc007" and r["tag"] == "counter"} == {7}
    err = capsys.readouterr().err
    assert "TOTAL (100 PLCs)" in err and "p99 ms" in err
    total = next(line for line in err.splitlines() if line.startswith("TOTAL"))
    assert int(total.split()[-3]) == len(records)  # every sample taken was written out


async def test_cli_poll_influx_and_config_error_exit_codes(tmp_path: Path) -> None:
    proto = AVAILABLE[0]  # the CLI is protocol-agnostic: one protocol is enough here
    sim = await proto.sim().start(proto.memory(9))
    try:
        cfg = tmp_path / "one.toml"
        write_config(cfg, proto, [sim.url], interval=0.05)
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "plcstack",
            "poll",
            str(cfg),
            "--format",
            "influx",
            "--duration",
            "1",
            "--stats-every",
            "0.4",
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        stdout, stderr = await proc.communicate()
    finally:
        await sim.aclose()
    assert proc.returncode == 0, stderr.decode()
    lines = stdout.decode().splitlines()
    # the default fields layout: one line per PLC and scan group, a field per tag
    assert any(
        line.startswith("plc,plc=plc000,group=default ") and "counter=9i" in line.split(" ")[1]
        for line in lines
    )
    assert "plc000" in stderr.decode() and "requests" in stderr.decode()
    assert stderr.decode().count("p99 ms") >= 2  # --stats-every, then the final statistics

    bad = tmp_path / "bad.toml"
    bad.write_text(
        f'[[plc]]\nname = "p"\nurl = "{proto.scheme}://127.0.0.1:1"\n[plc.tags]\nx = "Q99"\n'
    )
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "plcstack",
        "poll",
        str(bad),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    out_bytes, err_bytes = await proc.communicate()
    result = Namespace(
        returncode=proc.returncode, stdout=out_bytes.decode(), stderr=err_bytes.decode()
    )
    assert result.returncode == 2
    assert "p" in result.stderr and "'x'" in result.stderr and result.stdout == ""


@pytest.mark.slow  # several seconds: run by the slow run
def test_demo_in_a_pipe_prints_samples_of_every_protocol_and_exits_0() -> None:
    protocols, _ = available_protocols()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    result = subprocess.run(
        [sys.executable, "-m", "plcstack", "demo", "--duration", "3"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert result.returncode == 0, result.stderr
    good = {
        line.split()[1].rsplit("-", 1)[0] for line in result.stdout.splitlines() if " good " in line
    }
    assert good == {p.label for p in protocols}
    assert "\x1b[" not in result.stdout  # plain lines, no ANSI, when stdout is not a terminal
    assert "p99 ms" in result.stderr  # the statistics at the end


async def test_demo_live_table_on_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    """On a terminal the demo redraws a table in place: ANSI escapes, every PLC on a row.
    (A terminal that calls itself dumb gets plain lines: whatever TERM the suite runs under,
    this one is a terminal that draws.)"""
    from plcstack.cli.demo import run_demo

    monkeypatch.setenv("TERM", "xterm")

    protocols, _ = available_protocols()
    master, slave = os.openpty()
    chunks: list[bytes] = []
    loop = asyncio.get_running_loop()

    def drain() -> None:
        try:
            chunks.append(os.read(master, 65536))
        except OSError:  # EIO once the terminal side is closed: nothing more will come
            loop.remove_reader(master)

    loop.add_reader(master, drain)
    try:
        with os.fdopen(slave, "w", closefd=True) as term:
            args = Namespace(plcs=None, duration=1.5, interval=0.1)
            assert await run_demo(args, term) == 0
        await asyncio.sleep(0.05)
    finally:
        loop.remove_reader(master)
        os.close(master)
    screen = b"".join(chunks).decode(errors="replace")
    assert "\x1b[H" in screen and "plcstack demo" in screen
    for proto in protocols:
        assert f"{proto.label}-1" in screen
    assert "\x1b[32m" in screen  # good values are drawn in green
