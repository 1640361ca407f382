"""The web console in a real browser: Debian's headless Chromium driven by Playwright.

One browser for the module (a browser takes seconds to start) and one console for the tests
that leave it as it was; a test that stops a simulator, needs 200 PLCs or a restart starts its
own. The console polls an E71 simulator every 0.1 s (see tests/web_helpers.py), so a change in
the simulator's memory reaches the page within a second; every wait has a bound of 10 s and
fails with what the page showed. The browser runs in New York time, so a time shown in UTC
(the page without its script) cannot pass for a local one.
"""

from __future__ import annotations

import asyncio
import datetime
import json
import shutil
import sys
import time
import zoneinfo
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import aiohttp
import pytest
import pytest_asyncio

from plcstack.sim import e71 as e71_sim
from plcstack.sim.melsec_memory import MelsecMemory
from tests.web_helpers import HOSTILE, TOKEN, Console, running_console

if TYPE_CHECKING:
    from playwright.async_api._context_manager import PlaywrightContextManager


CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
WAIT_MS = 10_000
ZONE = "America/New_York"

pytestmark = pytest.mark.asyncio(loop_scope="module")


def async_playwright() -> PlaywrightContextManager:
    """Playwright's entry point. Without Playwright every test here FAILS naming it (a skip
    would let the console go untested in a browser and the run still look green)."""
    try:
        from playwright.async_api import async_playwright
    except ImportError as exc:
        pytest.fail(
            f"Playwright cannot be imported ({exc}); the browser tests drive Chromium with it:"
            " pip install -e '.[test]' (no browser download is needed, /usr/bin/chromium is used)",
            pytrace=False,
        )
    return async_playwright()


#: the name a rebinding attacker's page is served under: it resolves to the console's address
#: (a rule of the module's one browser; no other test uses the name)
ATTACKER = "attacker.example"


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def browser() -> AsyncIterator[Any]:
    if not shutil.which(CHROMIUM):
        pytest.fail(f"no Chromium at {CHROMIUM} (Debian's package 'chromium', see .ci/run)")
    rule = f"--host-resolver-rules=MAP {ATTACKER} 127.0.0.1"
    async with async_playwright() as p:
        chromium = await p.chromium.launch(executable_path=CHROMIUM, args=[rule])
        try:
            yield chromium
        finally:
            await chromium.close()


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def audit(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("audit") / "writes.jsonl"


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def console(audit: Path) -> AsyncIterator[Console]:
    async with running_console(audit=audit) as running:
        yield running


@pytest_asyncio.fixture(loop_scope="module")
async def page(browser: Any) -> AsyncIterator[Any]:
    context = await browser.new_context(viewport={"width": 1280, "height": 900}, timezone_id=ZONE)
    page = await context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        yield page
    finally:
        await context.close()
    assert errors == [], f"the page's script failed: {errors}"


def tag(plc: str, name: str, part: str = "td.value .text") -> str:
    """A CSS selector of a part of a tag's row on a PLC's page."""
    return f'#tags tr[data-plc="{css(plc)}"][data-tag="{css(name)}"] {part}'


def css(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"')


async def shows(page: Any, selector: str, text: str) -> None:
    await page.wait_for_function(
        "([s, t]) => document.querySelector(s)?.textContent === t",
        arg=[selector, text],
        timeout=WAIT_MS,
    )


async def count(page: Any, selector: str, n: int) -> None:
    await page.wait_for_function(
        "([s, n]) => document.querySelectorAll(s).length === n", arg=[selector, n], timeout=WAIT_MS
    )


async def rows_are(page: Any, names: list[str]) -> None:
    """Wait until the overview's rows are the PLCs ``names``, in this order."""
    await page.wait_for_function(
        "n => JSON.stringify([...document.querySelectorAll('#plcs tbody tr')]"
        ".map(r => r.dataset.plc)) === n",
        arg=json.dumps(names, separators=(",", ":")),
        timeout=WAIT_MS,
    )


def audit_lines(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines() if path.exists() else []


def local(t: float) -> str:
    """HH:MM:SS of ``t`` in the browser's zone."""
    return datetime.datetime.fromtimestamp(t, zoneinfo.ZoneInfo(ZONE)).strftime("%H:%M:%S")


async def test_overview_counts_the_plcs_and_puts_the_dead_one_first(
    page: Any, console: Console
) -> None:
    await page.goto(console.base + "/")
    await shows(page, "#live", "live")
    await shows(page, "#n-offline", "1")
    await shows(page, "#n-online", "2")
    assert await page.text_content("#counts .total") == "of 3 PLCs"
    first = "#plcs tbody tr:first-child"
    assert await page.get_attribute(first, "data-plc") == "dead"
    await shows(page, first + " td.state", "offline")
    # one line of the error, the whole text on demand
    summary = await page.text_content(first + " td.last_error summary")
    assert summary.startswith("e71+tcp://127.0.0.1:") and "\n" not in summary
    assert await page.is_visible(first + " td.last_error pre") is False
    await page.click(first + " td.last_error summary")
    assert await page.is_visible(first + " td.last_error pre")
    # the time the PLC went offline, in the browser's zone, with its age
    since = first + " td.since time"
    t = float(await page.get_attribute(since, "data-t"))
    text = await page.text_content(since)
    assert text.startswith(local(t)) and text.endswith(" ago)"), text


async def test_values_in_their_display_form_follow_the_plc(page: Any, console: Console) -> None:
    console.memory.write_words("D", 100, [1500])
    await page.goto(console.base + "/plc/press1")
    await shows(page, "#live", "live")
    await shows(page, tag("press1", "temp"), "61.5 °C")
    await shows(page, tag("press1", "status"), "12AFh")
    await shows(page, tag("press1", "valve"), "open")
    await shows(page, tag("press1", "mode"), "running")
    await shows(page, tag("press1", "flow"), "12.3 m³/h")
    await shows(page, tag("press1", "setpoint"), "1500 rpm")
    console.memory.write_words("D", 100, [2718])
    console.memory.write_bits("M", 0, [False])
    await shows(page, tag("press1", "setpoint"), "2718 rpm")  # no reload
    await shows(page, tag("press1", "valve"), "closed")
    changed = tag("press1", "setpoint", "td.time time")
    t = float(await page.get_attribute(changed, "data-t"))
    assert (await page.text_content(changed)).startswith(local(t))


async def test_a_chart_has_a_time_axis_and_a_value_axis_with_the_unit(
    page: Any, console: Console
) -> None:
    await page.goto(console.base + "/plc/press1")
    # beyond every value the other tests write: the axis is -1000..5000 whatever ran
    for value in (-1000, 5000, 2000):
        console.memory.write_words("D", 100, [value & 0xFFFF])
        await shows(page, tag("press1", "setpoint"), f"{value} rpm")
    chart = "figure.chart[data-tags='[\"setpoint\"]']"
    # round steps over -1000..5000, and the unit
    await page.wait_for_function(
        "s => [...document.querySelectorAll(s + ' .axis.y text')].map(e => e.textContent)"
        ".join() === '0,2000,4000,rpm'",
        arg=chart,
        timeout=WAIT_MS,
    )
    line = await page.get_attribute(chart + " path.line", "d")
    assert line.count("V") >= 2, line  # steps: down to -1000, up to 5000, down to 2000
    times = await page.eval_on_selector_all(
        chart + " .axis.x text", "e => e.map(x => x.textContent)"
    )
    # a label a minute over the last five (the console's trend_seconds), in New York time
    now = datetime.datetime.now(zoneinfo.ZoneInfo(ZONE))
    minutes = {(now - datetime.timedelta(minutes=m)).strftime("%H:%M") for m in range(7)}
    assert 4 <= len(times) <= 6 and set(times) <= minutes, (times, minutes)
    # the booleans and states step between their names
    valve = "figure.chart.steps[data-tags='[\"valve\"]'] .axis.y text"
    assert await page.eval_on_selector_all(valve, "e => e.map(x => x.textContent)") == [
        "closed",
        "open",
    ]


async def test_a_write_asks_for_confirmation_and_is_audited(
    page: Any, console: Console, audit: Path
) -> None:
    console.memory.write_words("D", 100, [1500])
    await page.goto(console.base + "/plc/press1")
    await shows(page, tag("press1", "setpoint"), "1500 rpm")
    form = tag("press1", "setpoint", "form.write")
    before = len(audit_lines(audit))
    await page.fill("#token", TOKEN)
    await page.fill(form + " input", "1800")
    await page.click(form + " button")
    dialog = "dialog#confirm"
    await page.wait_for_selector(dialog, state="visible", timeout=WAIT_MS)
    assert await page.text_content(dialog + " .c-tag") == "setpoint"
    assert await page.text_content(dialog + " .c-plc") == "press1"
    assert await page.text_content(dialog + " .c-old") == "1500 rpm"
    assert await page.text_content(dialog + " .c-new") == "1800 rpm"
    await page.click(dialog + " .c-cancel")
    await shows(page, form + " output", "not written")
    assert console.memory.read_words("D", 100, 1) == [1500]
    await page.click(form + " button")
    await page.wait_for_selector(dialog, state="visible", timeout=WAIT_MS)
    await page.click(dialog + " .c-write")
    await shows(page, form + " output", "written")
    assert console.memory.read_words("D", 100, 1) == [1800]
    await shows(page, tag("press1", "setpoint"), "1800 rpm")
    records = [json.loads(line) for line in audit_lines(audit)[before:]]
    assert [(r["source"], r["tag"], r["value"], r["previous"], r["result"]) for r in records] == [
        ("web", "setpoint", 1800, 1500, "ok")  # the cancelled one never left the browser
    ]
    assert await page.query_selector(tag("press1", "counter", "form")) is None  # read-only


async def test_a_hostile_name_is_shown_as_text(page: Any, console: Console) -> None:
    await page.goto(console.base + "/")
    link = f'#plcs tr[data-plc="{css(HOSTILE)}"] td.name a'
    await page.wait_for_selector(link, timeout=WAIT_MS)
    assert await page.text_content(link) == HOSTILE
    assert await page.evaluate("window.pwned") is None
    await page.click(link)
    await page.wait_for_selector("h1", timeout=WAIT_MS)
    assert await page.text_content("h1") == HOSTILE
    await shows(page, tag(HOSTILE, HOSTILE), "7")
    console.memory.write_words("D", 200, [8])
    await shows(page, tag(HOSTILE, HOSTILE), "8")
    assert await page.evaluate("window.pwned") is None


async def test_a_page_rebinding_its_name_to_the_console_reads_nothing(
    page: Any, console: Console
) -> None:
    """DNS rebinding as a browser on the plant network meets it: ``attacker.example`` resolves
    to the console's address, so the attacker's page and the console are one origin to the
    browser. Before: the page and its script read every value (200). Now: 421 for the page and
    for the script's request; the console's own names still work in the same browser."""
    port = console.web.port
    response = await page.goto(f"http://{ATTACKER}:{port}/")
    assert response is not None and response.status == 421
    read = "fetch('/api/tags').then(r => r.status + ' ' + r.headers.get('content-type'))"
    assert await page.evaluate(read) == "421 text/plain; charset=utf-8"
    response = await page.goto(f"http://localhost:{port}/")
    assert response is not None and response.status == 200
    assert (await page.evaluate("fetch('/api/tags').then(r => r.status)")) == 200


async def test_the_last_value_stays_marked_stale_when_the_simulator_stops(page: Any) -> None:
    async with running_console() as console:
        await page.goto(console.base + "/plc/press1")
        await shows(page, tag("press1", "temp"), "61.5 °C")
        await console.sim.aclose()
        await page.wait_for_selector(tag("press1", "temp", "td.value.stale"), timeout=WAIT_MS)
        assert await page.text_content(tag("press1", "temp")) == "61.5 °C"  # still shown
        note = await page.text_content(tag("press1", "temp", "td.value .stale-note"))
        stale = float(await page.get_attribute(tag("press1", "temp", ".stale-note time"), "data-t"))
        assert note.startswith(f"stale since {local(stale)}"), note
        await page.wait_for_selector("#banner.offline", timeout=WAIT_MS)
        assert (await page.text_content("#banner .b-state")) == "offline since "
        # the PLC's error once, in the state line: not in each of its tags' rows
        assert await page.eval_on_selector_all("#tags td.error .err", "e => e.length") == 0
        assert await page.eval_on_selector_all("#banner .err", "e => e.length") == 1


async def test_the_overview_filter_narrows_200_plcs_to_the_one_typed(page: Any) -> None:
    async with running_console(more_plcs=197) as console:
        await page.goto(console.base + "/")
        await shows(page, "#counts .total", "of 200 PLCs")
        await count(page, "#plcs tbody tr", 50)  # a page of them, not 200 rows
        await page.fill('#filter input[name="q"]', "plc137")
        await rows_are(page, ["plc137"])
        await shows(page, "#pager .shown", "PLCs 1-1 of 1")
        assert page.url.endswith("/?q=plc137")
        await page.fill('#filter input[name="q"]', "offline")  # a state is a word too
        await rows_are(page, ["dead"])
        await page.fill('#filter input[name="q"]', "")
        await count(page, "#plcs tbody tr", 50)
        await page.click("#pager a[rel=next]")
        await shows(page, "#pager .shown", "PLCs 51-100 of 200")


async def _start_poll(config: Path) -> tuple[asyncio.subprocess.Process, str, asyncio.Task[bytes]]:
    """``plcstack poll CONFIG`` in a process of its own: the process, the console's address,
    and the task that keeps reading its stderr (so a chatty log never blocks it)."""
    proc = await asyncio.create_subprocess_exec(
        *[sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none"],
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )
    assert proc.stderr is not None
    seen = b""
    async with asyncio.timeout(30):
        while b"web console on " not in seen:
            line = await proc.stderr.readline()
            assert line, f"plcstack poll ended: {seen.decode()}"
            seen += line
    base = seen.decode().split("web console on ", 1)[1].split("/ ", 1)[0]
    return proc, base, asyncio.create_task(proc.stderr.read())


async def _history_has(base: str, value: int) -> None:
    url = f"{base}/api/history?plc=press1&tag=setpoint&from={time.time() - 600}"
    async with aiohttp.ClientSession() as http:
        for _ in range(100):
            async with http.get(url) as r:
                if value in [v for _, v in (await r.json())["points"]]:
                    return
            await asyncio.sleep(0.2)
    raise AssertionError(f"{value} never reached the history")


@pytest.mark.slow  # two starts of plcstack poll and a second of commits: about 6 s
async def test_a_trend_reaches_back_over_a_restart_of_the_process(
    page: Any, tmp_path: Path
) -> None:
    memory = MelsecMemory()
    memory.write_words("D", 100, [1000])
    sim = await e71_sim.start(memory)
    config = tmp_path / "plant.toml"
    config.write_text(
        '[poll]\ninterval = 0.1\n\n[web]\nlisten = "127.0.0.1:0"\n\n'
        '[history]\npath = "history.sqlite"\n\n'
        f'[[plc]]\nname = "press1"\nurl = "{sim.url}"\n[plc.tags]\n'
        'setpoint = { address = "D100", type = "int16", unit = "rpm" }\n',
        encoding="utf-8",
    )
    procs: list[asyncio.subprocess.Process] = []
    try:
        proc, base, _ = await _start_poll(config)
        procs.append(proc)
        for value in (1000, 3000):
            memory.write_words("D", 100, [value])
            await _history_has(base, value)
        proc.terminate()
        assert await asyncio.wait_for(proc.wait(), 20) == 0
        memory.write_words("D", 100, [2000])
        proc, base, _ = await _start_poll(config)  # the same file, a new process
        procs.append(proc)
        await page.goto(base + "/plc/press1")
        await page.click('#trends button[data-range="3600"]')
        chart = "figure.chart[data-loaded='3600']"
        await page.wait_for_function(
            "s => [...document.querySelectorAll(s + ' .axis.y text')].map(e => e.textContent)"
            ".join() === '1000,1500,2000,2500,3000,rpm'",  # 1000 and 3000: before the restart
            arg=chart,
            timeout=WAIT_MS,
        )
        times = await page.eval_on_selector_all(
            chart + " .axis.x text", "e => e.map(x => x.textContent)"
        )
        assert len(times) >= 5 and all(len(t) == 5 and t[2] == ":" for t in times), times
        assert await page.get_attribute("#trends button[data-range='3600']", "aria-pressed") == (
            "true"
        )
    finally:
        for proc in procs:
            if proc.returncode is None:
                proc.terminate()
                await asyncio.wait_for(proc.wait(), 20)
        await sim.aclose()


async def test_a_plcs_page_downloads_its_last_frames_with_a_trace(
    browser: Any, tmp_path: Path
) -> None:
    """With [trace], each PLC's page links its flight recorder's frames; the download is a
    pcapng file of that PLC's connection. Without [trace] there is no link (the module's
    console has none)."""
    from plcstack.wire.streams import conversations, exchanges

    async with running_console(trace=tmp_path / "traces") as running:
        context = await browser.new_context(accept_downloads=True)
        try:
            page = await context.new_page()
            await page.goto(f"{running.base}/plc/press1")
            link = page.locator("p.capture a[download]")
            await link.wait_for(timeout=WAIT_MS)
            async with page.expect_download(timeout=WAIT_MS) as info:
                await link.click()
            download = await info.value
            saved = tmp_path / download.suggested_filename
            await download.save_as(saved)
            # the hostile PLC's name is quoted in its link, never markup
            await page.goto(f"{running.base}/plc/{HOSTILE}")
            href = await page.locator("p.capture a").get_attribute("href")
        finally:
            await context.close()
    assert saved.name.startswith("press1-") and saved.suffix == ".pcapng"
    (conversation,) = conversations(saved.read_bytes())
    assert exchanges(conversation)
    assert href == "/api/plcs/%3Csvg%20onload%3Dpwned%3D1%3E/capture.pcapng"


async def test_without_a_trace_a_plcs_page_has_no_capture_link(page: Any, console: Console) -> None:
    await page.goto(f"{console.base}/plc/press1")
    await page.locator("table#tags").wait_for(timeout=WAIT_MS)
    assert await page.locator("p.capture").count() == 0
