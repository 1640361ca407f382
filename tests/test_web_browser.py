"""The web console in a real browser: Debian's headless Chromium driven by Playwright.

One browser and one console for the module (a browser takes seconds to start); each test opens
its own page. The console polls an E71 simulator every 0.1 s (see tests/web_helpers.py), so a
change in the simulator's memory reaches the page within a second; every wait has a bound of
10 s and fails with what the page showed.
"""

from __future__ import annotations

import shutil
from collections.abc import AsyncIterator
from typing import Any

import pytest
import pytest_asyncio

from tests.web_helpers import HOSTILE, TOKEN, Console, running_console

playwright_api = pytest.importorskip("playwright.async_api")

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
WAIT_MS = 10_000

pytestmark = pytest.mark.asyncio(loop_scope="module")


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def browser() -> AsyncIterator[Any]:
    if not shutil.which(CHROMIUM):
        pytest.fail(
            f"no Chromium at {CHROMIUM} (Debian's package 'chromium': scripts/setup-test-machine)"
        )
    async with playwright_api.async_playwright() as p:
        chromium = await p.chromium.launch(executable_path=CHROMIUM)
        try:
            yield chromium
        finally:
            await chromium.close()


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def console() -> AsyncIterator[Console]:
    async with running_console() as running:
        yield running


@pytest_asyncio.fixture(loop_scope="module")
async def page(browser: Any) -> AsyncIterator[Any]:
    context = await browser.new_context(viewport={"width": 1280, "height": 800})
    page = await context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        yield page
    finally:
        await context.close()
    assert errors == [], f"the page's script failed: {errors}"


def cell(plc: str, tag: str, name: str) -> str:
    """A CSS selector of one cell of a tag's row (names as the page has them in data-*)."""
    return f'#tags tr[data-plc="{css(plc)}"][data-tag="{css(tag)}"] td.{name}'


def css(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"')


async def shows(page: Any, selector: str, text: str) -> None:
    await page.wait_for_function(
        "([s, t]) => document.querySelector(s)?.textContent === t",
        arg=[selector, text],
        timeout=WAIT_MS,
    )


async def test_overview_shows_the_value_and_follows_a_change(page: Any, console: Console) -> None:
    console.memory.write_words("D", 100, [1500])
    await page.goto(console.base + "/")
    await shows(page, cell("press1", "setpoint", "value"), "1500")
    await shows(page, "#live", "live")
    await shows(page, '#plcs tr[data-plc="press1"] td.state', "online")
    await shows(page, '#plcs tr[data-plc="dead"] td.state', "offline")
    console.memory.write_words("D", 100, [2718])
    await shows(page, cell("press1", "setpoint", "value"), "2718")  # no reload


async def test_plc_page_draws_the_trend(page: Any, console: Console) -> None:
    await page.goto(console.base + "/plc/press1")
    # beyond every value the other tests write: the chart's scale is -1000..5000 whatever ran
    for value in (-1000, 5000, 2000):
        console.memory.write_words("D", 100, [value & 0xFFFF])
        await shows(page, cell("press1", "setpoint", "value"), str(value))
    svg = '#tags tr[data-tag="setpoint"] svg.trend'
    points = await page.get_attribute(svg + " polyline", "points")
    assert points is not None
    levels: list[
        float
    ] = []  # the step line's levels, in order (each step is two points at one height)
    for point in points.split():
        y = float(point.split(",")[1])
        if not levels or levels[-1] != y:
            levels.append(y)
    assert levels[-3:] == [56.0, 4.0, 30.0], points  # low, high, middle: as written
    assert await page.text_content(svg + " title") == "min -1000, max 5000"


async def test_write_form_needs_the_token(page: Any, console: Console) -> None:
    console.memory.write_words("D", 100, [1500])
    await page.goto(console.base + "/plc/press1")
    form = 'tr[data-tag="setpoint"] form.write'
    await page.fill(form + " input", "321")
    await page.click(form + " button")
    await page.wait_for_function(
        "s => document.querySelector(s).textContent.startsWith('unauthorized')",
        arg=form + " output",
        timeout=WAIT_MS,
    )
    assert console.memory.read_words("D", 100, 1) == [1500]
    await page.fill("#token", TOKEN)
    await page.click(form + " button")
    await shows(page, form + " output", "written")
    assert console.memory.read_words("D", 100, 1) == [321]
    await shows(page, cell("press1", "setpoint", "value"), "321")
    assert await page.query_selector('tr[data-tag="counter"] form') is None  # read-only


async def test_a_hostile_name_is_shown_as_text(page: Any, console: Console) -> None:
    await page.goto(console.base + "/")
    await shows(page, cell(HOSTILE, HOSTILE, "value"), "7")
    assert await page.evaluate("window.pwned") is None
    link = f'#plcs tr[data-plc="{css(HOSTILE)}"] a'
    assert await page.text_content(link) == HOSTILE
    await page.click(link)
    await page.wait_for_selector("h1", timeout=WAIT_MS)
    assert await page.text_content("h1") == HOSTILE
    console.memory.write_words("D", 200, [8])
    await shows(page, cell(HOSTILE, HOSTILE, "value"), "8")
    assert await page.evaluate("window.pwned") is None
