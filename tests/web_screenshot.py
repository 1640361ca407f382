"""The screenshot of docs/web.md, taken with the browser tests' own set-up.

    python -m tests.web_screenshot docs/web-console.png

Starts the console of tests/web_helpers.py (an E71 simulator polled every 0.1 s), moves the
simulated temperature and setpoint for a few seconds so the trends show something, and saves
the page of ``press1`` as the headless Chromium the browser tests use renders it.
"""

from __future__ import annotations

import asyncio
import math
import shutil
import sys

from playwright.async_api import async_playwright

from tests.web_helpers import TOKEN, float_words, running_console


async def main(path: str) -> None:
    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    async with running_console(trend_seconds=30) as console, async_playwright() as p:
        browser = await p.chromium.launch(executable_path=chromium)
        page = await browser.new_page(viewport={"width": 1360, "height": 420})
        await page.goto(console.base + "/plc/press1")
        for step in range(24):
            temp = 61.5 + 4 * math.sin(step / 4)
            console.memory.write_words("D", 102, float_words(temp))
            console.memory.write_words("D", 100, [1500 if step < 12 else 1800])
            console.memory.write_words("D", 104, [step * 7])
            await asyncio.sleep(1.0)
        await page.fill("#token", TOKEN)
        form = 'tr[data-tag="setpoint"] form.write'
        await page.fill(form + " input", "1800")
        await page.click(form + " button")
        await page.wait_for_function(
            "s => document.querySelector(s).textContent === 'written'", arg=form + " output"
        )
        await page.screenshot(path=path, full_page=True)
        await browser.close()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1] if len(sys.argv) > 1 else "web-console.png"))
