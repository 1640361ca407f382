"""The console's pages at 1000 PLCs: their size, and how fast Chromium shows them.

1000 PLCs x 10 ``int16`` tags in another process (the PLC process of ``benchmarks.web_console``:
every word changing every second), polled at 1 Hz by a real Poller in this process, the
:class:`~plcstack.north.web.server.WebConsole` on loopback. Measured:

* the bytes of ``/`` (the overview), ``/?q=plc0500`` (filtered), ``/plc/plc0001`` (one PLC) and
  ``GET /api/overview`` as the server sends them (no compression);
* a headless Chromium (Debian's, through Playwright, in its own process) loading ``/``
  ``--loads`` times: wall time of ``page.goto`` until the ``load`` event, and from the page's
  own Navigation and Paint Timing: response end, DOMContentLoaded, load, first contentful
  paint; then until the event stream is live and the counts are shown;
* the filter: from typing a PLC's name into the box to the table showing only it;
* the page of one PLC (with its charts): the same timings.

Medians and maxima of the loads. The PLC process and the browser are other processes.

    python -m benchmarks.console_pages [--plcs 1000] [--tags 10] [--loads 10]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import statistics
import sys
import time
from typing import Any

import aiohttp

from benchmarks.web_console import all_answered, finish, ready, start_helper
from plcstack.bench.cases.fanout import raise_fd_limit
from plcstack.north.config import NorthConfig
from plcstack.north.pipeline import North
from plcstack.north.web.server import WebConsole
from plcstack.north.web.settings import WebSettings
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.values import INT16

_TIMING = """() => {
  const n = performance.getEntriesByType("navigation")[0];
  const paint = performance.getEntriesByName("first-contentful-paint")[0];
  return {
    response_end_ms: n.responseEnd, dom_content_loaded_ms: n.domContentLoadedEventEnd,
    load_ms: n.loadEventEnd, first_contentful_paint_ms: paint ? paint.startTime : null,
    transfer_bytes: n.transferSize, body_bytes: n.decodedBodySize,
  };
}"""


def summary(values: list[float]) -> dict[str, float]:
    return {"median": statistics.median(values), "max": max(values)}


async def sizes(base: str) -> dict[str, int]:
    out = {}
    async with aiohttp.ClientSession() as http:
        for path in ("/", "/?q=plc0500", "/plc/plc0001", "/api/overview"):
            async with http.get(base + path) as r:
                assert r.status == 200, (path, r.status)
                out[path] = len(await r.read())
    return out


async def browse(base: str, loads: int) -> dict[str, Any]:
    from playwright.async_api import async_playwright

    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    result: dict[str, Any] = {}
    async with async_playwright() as p:
        browser = await p.chromium.launch(executable_path=chromium)
        for name, path, ready_js in (
            ("overview", "/", "() => document.getElementById('n-online').textContent !== '0'"),
            ("plc page", "/plc/plc0001", "() => document.querySelector('figure.chart path.line')"),
        ):
            walls, timings, live = [], [], []
            for _ in range(loads):
                page = await browser.new_page()
                t0 = time.perf_counter()
                await page.goto(base + path, wait_until="load")
                walls.append((time.perf_counter() - t0) * 1e3)
                timings.append(await page.evaluate(_TIMING))
                await page.wait_for_function(
                    "() => document.getElementById('live').textContent === 'live'"
                )
                await page.wait_for_function(ready_js)
                live.append((time.perf_counter() - t0) * 1e3)
                await page.close()
            result[name] = {
                "goto_until_load_ms": summary(walls),
                "until_live_and_drawn_ms": summary(live),
                **{
                    key: summary([t[key] for t in timings if t[key] is not None])
                    for key in timings[0]
                    if key.endswith("_ms")
                },
                "body_bytes": timings[0]["body_bytes"],
            }
        page = await browser.new_page()
        await page.goto(base + "/", wait_until="load")
        filters = []
        for i in range(loads):
            name = f"plc{(i * 97) % 1000:04d}"
            t0 = time.perf_counter()
            await page.fill('#filter input[name="q"]', name)
            await page.wait_for_function(
                "n => { const r = document.querySelectorAll('#plcs tbody tr');"
                " return r.length === 1 && r[0].dataset.plc === n; }",
                arg=name,
            )
            filters.append((time.perf_counter() - t0) * 1e3)
        result["filter_typed_to_one_row_ms"] = summary(filters)
        result["filter_note"] = "includes the script's 200 ms wait for typing to pause"
        await browser.close()
    return result


async def measure(args: argparse.Namespace) -> dict[str, Any]:
    raise_fd_limit(args.plcs * 2 + 256)
    plcs = start_helper("plcs", str(args.tags))
    port = json.loads(ready(plcs, "the PLC process"))["port"]
    tags = tuple(TagConfig(f"t{i}", f"D{i}", INT16, unit="mm") for i in range(args.tags))
    config = PollConfig(
        tuple(
            PlcConfig(f"plc{i:04d}", f"e71+tcp://127.0.0.1:{port}", tags) for i in range(args.plcs)
        ),
        {"default": 1.0},
    )
    poller = Poller(config)
    north = North(poller, NorthConfig(web=WebSettings(port=0)))
    try:
        async with poller, north:
            consumer = asyncio.create_task(north.run())
            await all_answered(poller)
            await asyncio.sleep(3.0)  # two pushes of the PLC rows
            console = north.face(WebConsole)
            assert console is not None
            base = console.url.rstrip("/")
            result = {"bytes": await sizes(base), "chromium": await browse(base, args.loads)}
            consumer.cancel()
            await asyncio.gather(consumer, return_exceptions=True)
    finally:
        finish(plcs)
    return {"plcs": args.plcs, "tags": args.plcs * args.tags, **result}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.console_pages")
    parser.add_argument("--plcs", type=int, default=1000)
    parser.add_argument("--tags", type=int, default=10)
    parser.add_argument("--loads", type=int, default=10)
    args = parser.parse_args(argv)
    result = {"load_before": os.getloadavg(), "cpus": os.cpu_count(), **asyncio.run(measure(args))}
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
