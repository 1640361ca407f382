"""The pictures of docs/web.md, taken with the browser tests' own set-up.

    python -m tests.web_screenshot docs

Starts the console of tests/web_helpers.py (an E71 simulator polled every 0.1 s, 40 more PLCs
on a second simulator) over a history that already holds the last eight hours of ``press1``
(written here the way the writer writes it), and saves, as the headless Chromium of the browser
tests renders them:

* ``web-overview.png``: the overview (counts, filter, the PLCs, the dead one first);
* ``web-console.png``: the page of ``press1`` with its charts over eight hours;
* ``web-confirm.png``: the confirmation a write asks for;
* ``web-offline.png``: the page once its simulator is stopped (last values kept, marked stale).
"""

from __future__ import annotations

import asyncio
import math
import shutil
import struct
import sys
import tempfile
import time
from pathlib import Path

from playwright.async_api import async_playwright

from plcstack.north.history import HistorySettings
from plcstack.north.history.writer import Writer
from plcstack.poll.samples import Quality, Scan, make_sample
from tests.web_helpers import TOKEN, float_words, running_console

HOURS = 8


def _f32(x: float) -> float:
    return float(struct.unpack("<f", struct.pack("<f", x))[0])


def prefill(path: Path, now: float) -> None:
    """Eight hours of press1, a point every 10 s: a shift's setpoints, the oil warming and
    cooling with them, a valve and a mode switching, a counter counting."""
    writer = Writer(HistorySettings(path=path), clock=lambda: now)
    writer.open()
    start = now - HOURS * 3600
    batch = []
    for i in range(HOURS * 360):
        t = start + 10 * i
        hour = int(i / 360)
        setpoint = 1800 if hour % 3 == 1 else 1500
        values = {
            "setpoint": setpoint,
            "temp": _f32(55 + setpoint / 200 + 2.5 * math.sin(i / 40) + (i % 7) / 10),
            "counter": (i * 3) % 32768,
            "valve": (i // 90) % 2 == 0,
            "mode": 0 if 200 < i % 900 < 260 else 1,
            "flow": _f32(12 + 1.5 * math.sin(i / 25)),
        }
        samples = tuple(
            make_sample("press1", tag, v, Quality.GOOD, t, t + 0.003, None)
            for tag, v in values.items()
        )
        batch.append(Scan("press1", "default", t, t + 0.003, samples))
        if len(batch) == 360:
            writer.write([batch])
            batch = []
    writer.write([batch])
    writer.close()


async def main(folder: Path) -> None:
    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    with tempfile.TemporaryDirectory() as tmp:
        history = Path(tmp) / "history.sqlite"
        prefill(history, time.time())
        async with (
            running_console(history=history, more_plcs=40) as console,
            async_playwright() as p,
        ):
            console.memory.write_words("D", 102, float_words(63.2))
            browser = await p.chromium.launch(executable_path=chromium)
            page = await browser.new_page(viewport={"width": 1360, "height": 860})
            await page.goto(console.base + "/")
            await page.wait_for_function(
                "() => document.getElementById('live').textContent === 'live'"
            )
            await asyncio.sleep(2.5)  # the PLC rows' first push
            await page.screenshot(path=str(folder / "web-overview.png"))

            await page.goto(console.base + "/plc/press1")
            await page.click(f'#trends button[data-range="{HOURS * 3600}"]')
            await page.wait_for_selector(f"figure.chart[data-loaded='{HOURS * 3600}']")
            await asyncio.sleep(1.5)
            await page.screenshot(path=str(folder / "web-console.png"), full_page=True)

            await page.fill("#token", TOKEN)
            form = 'tr[data-tag="setpoint"] form.write'
            await page.fill(form + " input", "1800")
            await page.click(form + " button")
            await page.wait_for_selector("dialog#confirm", state="visible")
            await page.screenshot(path=str(folder / "web-confirm.png"))
            await page.click("dialog#confirm .c-cancel")

            await console.sim.aclose()
            await page.wait_for_selector("#banner.offline")
            await page.wait_for_selector('tr[data-tag="temp"] td.value.stale')
            await asyncio.sleep(1.0)
            await page.screenshot(path=str(folder / "web-offline.png"), full_page=True)
            await browser.close()


if __name__ == "__main__":
    asyncio.run(main(Path(sys.argv[1] if len(sys.argv) > 1 else ".")))
