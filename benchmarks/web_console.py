"""The web console's CPU at 1000 PLCs x 10 tags at 1 Hz, as a share of the poller's own CPU.

Setup: 1000 PLCs in another process (one listening socket, 1000 connections; each answers the
E71 word read of its 10 tags with words that all change every second, so every tag changes
every second: the console's worst case, 10,000 changes a second). In this process a real
:class:`~plcstack.poll.engine.Poller` polls them at 1 Hz (10 ``int16`` tags per PLC, merged into
one request each) and the :class:`~plcstack.north.pipeline.North` consumer takes its samples;
the :class:`~plcstack.north.web.server.WebConsole` listens on a free loopback port.

Modes, measured in turns (``--rounds`` rounds, the order rotated each round, ``--window``
seconds each after 2 s to settle), process CPU time (``time.process_time``) of this process
per second of wall time:

* ``poller``: the console is not among the sinks and no browser is connected (the baseline:
  the poller and its consumer alone);
* ``console, 0 browsers``: the console takes every batch (state, trend rings), nobody looks;
* ``console, 1 browser``: a headless Chromium (Debian's, through Playwright, in its own
  process) shows ``/``, the overview: the counts and a page of PLC rows, kept live by its
  event stream (``/events?view=overview``: rows and counts, no tags);
* ``console, 10 clients``: ten clients of ``/events`` (every PLC and every tag: raw sockets
  in another process, reading everything), the heaviest stream a script can ask for.

The console's share = (CPU of the mode - CPU of ``poller``) / CPU of ``poller``, from the
medians. The PLC process, the browser and the stream clients are other processes: not counted.

    python -m benchmarks.web_console [--plcs 1000] [--tags 10] [--window 8] [--rounds 3]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import statistics
import struct
import subprocess
import sys
import time
from typing import Any

from plcstack.bench.cases.fanout import raise_fd_limit
from plcstack.bench.frames import e71_read_words
from plcstack.north.config import NorthConfig
from plcstack.north.pipeline import North
from plcstack.north.web.server import WebConsole
from plcstack.north.web.settings import WebSettings
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.values import INT16

MODES = ("poller", "console, 0 browsers", "console, 1 browser", "console, 10 clients")


# -- the PLCs (another process) -----------------------------------------------------------------
class _Plc(asyncio.Protocol):
    """Answers every complete word read with the current reply."""

    def __init__(self, state: dict[str, Any]) -> None:
        self.state = state
        self.pending = 0
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        self.pending += len(data)
        size = self.state["request_size"]
        if self.pending >= size and self.transport is not None:
            count, self.pending = divmod(self.pending, size)
            self.transport.write(self.state["reply"] * count)


async def _serve_plcs(tags: int) -> None:
    loop = asyncio.get_running_loop()
    state: dict[str, Any] = {"request_size": len(e71_read_words("D", 0, tags))}

    def reply(tick: int) -> bytes:
        words = [(tick * 7 + i) & 0x7FFF for i in range(tags)]
        return b"\x81\x00" + struct.pack(f"<{tags}H", *words)

    state["reply"] = reply(0)
    server = await loop.create_server(lambda: _Plc(state), "127.0.0.1", 0, backlog=4096)
    print(json.dumps({"port": server.sockets[0].getsockname()[1]}), flush=True)
    stop = loop.create_future()

    def end() -> None:
        if not stop.done():
            stop.set_result(None)

    loop.add_reader(sys.stdin.fileno(), end)
    tick = 0
    while not stop.done():
        await asyncio.wait({stop}, timeout=1.0)
        tick += 1
        state["reply"] = reply(tick)  # every word changes every second


# -- one browser (another process) --------------------------------------------------------------
async def _browser(url: str) -> None:
    from playwright.async_api import async_playwright

    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    async with async_playwright() as p:
        browser = await p.chromium.launch(executable_path=chromium)
        page = await browser.new_page()
        await page.goto(url, timeout=120_000)
        await page.wait_for_function(
            "() => document.getElementById('live')?.textContent === 'live'", timeout=60_000
        )
        cell = "#plcs tbody tr td.requests"  # the overview: PLC rows, live
        first = await page.text_content(cell)
        await page.wait_for_function(
            "([s, f]) => document.querySelector(s).textContent !== f",
            arg=[cell, first],
            timeout=60_000,
        )
        print("ready", flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
        last = await page.text_content(cell)
        print(json.dumps({"first": first, "last": last}), flush=True)
        await browser.close()


# -- event-stream clients (another process) -----------------------------------------------------
async def _sse(port: int, n: int) -> None:
    received = [0] * n

    async def client(i: int, ready: asyncio.Future[None]) -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(
            b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\nAccept: text/event-stream\r\n\r\n"
        )
        while chunk := await reader.read(1 << 20):
            received[i] += len(chunk)
            if received[i] > 100_000 and not ready.done():
                ready.set_result(None)

    loop = asyncio.get_running_loop()
    readies = [loop.create_future() for _ in range(n)]
    tasks = [asyncio.create_task(client(i, readies[i])) for i in range(n)]
    await asyncio.wait_for(asyncio.gather(*readies), 60)
    print("ready", flush=True)
    start = list(received)
    began = time.perf_counter()
    await loop.run_in_executor(None, sys.stdin.read)
    seconds = time.perf_counter() - began
    rates = [(r - s) / seconds for r, s in zip(received, start, strict=True)]
    print(json.dumps({"bytes_per_s": rates}), flush=True)
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


# -- the measured side --------------------------------------------------------------------------
def start_helper(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "benchmarks.web_console", *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )


def ready(proc: subprocess.Popen[str], what: str) -> str:
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line:
        raise RuntimeError(f"{what} exited ({proc.wait(5)}) before it was ready")
    return line


def finish(proc: subprocess.Popen[str]) -> dict[str, Any]:
    assert proc.stdin is not None and proc.stdout is not None
    proc.stdin.close()
    out = proc.stdout.read()
    proc.wait(30)
    return json.loads(out) if out.strip() else {}


async def all_answered(poller: Poller, timeout: float = 60.0) -> None:
    """Wait until every PLC answered three requests (connected and polled)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while min(s.requests for s in poller.stats.values()) < 3:
        if loop.time() > deadline:
            raise RuntimeError(f"the PLCs did not all answer within {timeout:.0f} s")
        await asyncio.sleep(0.5)


async def window(poller: Poller, seconds: float) -> tuple[float, float]:
    """After 2 s to settle, ``seconds`` measured: (process CPU per wall second, requests/s)."""
    await asyncio.sleep(2.0)
    requests = sum(s.requests for s in poller.stats.values())
    c0, w0 = time.process_time(), time.perf_counter()
    await asyncio.sleep(seconds)
    c1, w1 = time.process_time(), time.perf_counter()
    done = sum(s.requests for s in poller.stats.values()) - requests
    return (c1 - c0) / (w1 - w0), done / (w1 - w0)


async def _measure(args: argparse.Namespace) -> dict[str, Any]:
    raise_fd_limit(args.plcs * 2 + 256)
    plcs = start_helper("plcs", str(args.tags))
    port = json.loads(ready(plcs, "the PLC process"))["port"]
    tags = tuple(TagConfig(f"t{i}", f"D{i}", INT16) for i in range(args.tags))
    config = PollConfig(
        tuple(
            PlcConfig(f"plc{i:04d}", f"e71+tcp://127.0.0.1:{port}", tags) for i in range(args.plcs)
        ),
        {"default": 1.0},
    )
    poller = Poller(config)
    north = North(poller, NorthConfig())
    console = WebConsole(poller, WebSettings(port=0))
    cpu: dict[str, list[float]] = {m: [] for m in MODES}
    rates: dict[str, list[float]] = {m: [] for m in MODES}
    notes: dict[str, Any] = {}
    loop = asyncio.get_running_loop()
    try:
        async with poller, north:
            await console.start()
            consumer = asyncio.create_task(north.run())
            await all_answered(poller)
            for r in range(args.rounds):
                order = MODES[r % len(MODES) :] + MODES[: r % len(MODES)]
                for mode in order:
                    helper = None
                    if mode == "poller":
                        north.faces = [f for f in north.faces if f is not console]
                    elif console not in north.faces:
                        north.faces.append(console)
                    if mode == "console, 1 browser":
                        helper = start_helper("browser", console.url)
                        await loop.run_in_executor(None, ready, helper, "the browser")
                    elif mode == "console, 10 clients":
                        helper = start_helper("sse", str(console.port), "10")
                        await loop.run_in_executor(None, ready, helper, "the stream clients")
                    share, rate = await window(poller, args.window)
                    cpu[mode].append(share)
                    rates[mode].append(rate)
                    if helper is not None:
                        notes.setdefault(mode, []).append(
                            await loop.run_in_executor(None, finish, helper)
                        )
                    print(
                        f"round {r + 1} {mode:22s} cpu {cpu[mode][-1] * 100:5.1f} % of a core,"
                        f" {rates[mode][-1]:6.0f} requests/s",
                        file=sys.stderr,
                        flush=True,
                    )
            consumer.cancel()
            await asyncio.gather(consumer, return_exceptions=True)
            await console.aclose()
            overruns = sum(s.overruns for s in poller.stats.values())
    finally:
        finish(plcs)
    base = statistics.median(cpu["poller"])
    return {
        "plcs": args.plcs,
        "tags": args.tags,
        "window_s": args.window,
        "rounds": args.rounds,
        "cpu_share_of_a_core": {m: statistics.median(v) for m, v in cpu.items()},
        "requests_per_s": {m: statistics.median(v) for m, v in rates.items()},
        "console_share_of_poller": {
            m: (statistics.median(v) - base) / base for m, v in cpu.items() if m != "poller"
        },
        "dropped_clients": console.hub.dropped,
        "overruns": overruns,
        "helpers": notes,
        "cpus": os.cpu_count(),
        "load_before": os.getloadavg(),
    }


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "plcs":
        asyncio.run(_serve_plcs(int(argv[1])))
        return 0
    if argv and argv[0] == "browser":
        asyncio.run(_browser(argv[1]))
        return 0
    if argv and argv[0] == "sse":
        asyncio.run(_sse(int(argv[1]), int(argv[2])))
        return 0
    parser = argparse.ArgumentParser(prog="python -m benchmarks.web_console")
    parser.add_argument("--plcs", type=int, default=1000)
    parser.add_argument("--tags", type=int, default=10)
    parser.add_argument("--window", type=float, default=8.0)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    load = os.getloadavg()
    result = asyncio.run(_measure(args))
    result["load_before"] = load
    print(json.dumps(result, indent=2))
    share = result["console_share_of_poller"]
    print(
        f"\npoller alone: {result['cpu_share_of_a_core']['poller'] * 100:.1f} % of a core;"
        " console: "
        + ", ".join(f"{m.split(', ')[1]} +{v * 100:.1f} %" for m, v in share.items())
        + " of the poller's CPU",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
