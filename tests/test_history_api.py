"""``GET /api/history`` over HTTP: a real simulator, poller, history file and console."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import aiohttp

from tests.web_helpers import Console, float_words, running_console


async def get(console: Console, query: str) -> tuple[int, Any]:
    async with aiohttp.ClientSession() as http, http.get(console.base + query) as r:
        return r.status, await r.json()


async def test_history_answers_points_of_a_tag(tmp_path: Path) -> None:
    async with running_console(history=tmp_path / "h.sqlite") as console:
        start = time.time()
        for temp in (61.5, 62.25, 70.125):
            console.memory.write_words("D", 102, float_words(temp))
            await asyncio.sleep(0.35)
        assert console.web.history is not None
        await console.web.history.flush()
        status, body = await get(console, f"/api/history?plc=press1&tag=temp&from={start - 1}")
        assert status == 200, body
        points = body["points"]
        assert [v for _, v in points][:1] == [61.5] and points[-1][1] == 70.125
        # every poll is a point (no [report]): in time order, values as the PLC had them
        assert [t for t, _ in points] == sorted(t for t, _ in points)
        assert {v for _, v in points} == {61.5, 62.25, 70.125}
        status, body = await get(
            console, f"/api/history?plc=press1&tag=temp&from={start - 1}&points=4"
        )
        assert status == 200 and len(body["points"]) <= 4
        assert {v for _, v in body["points"]} >= {61.5, 70.125}  # the extremes stay
        status, body = await get(console, "/api/history?plc=dead&tag=x")
        assert status == 200
        assert body["points"] and all(v is None for _, v in body["points"])  # bad: gaps


async def test_history_refusals(tmp_path: Path) -> None:
    async with running_console(history=tmp_path / "h.sqlite") as console:
        cases = {
            "/api/history?plc=nope&tag=temp": (404, "unknown_plc"),
            "/api/history?plc=press1&tag=nope": (404, "unknown_tag"),
            "/api/history?tag=temp": (404, "unknown_plc"),
            "/api/history?plc=press1&tag=temp&from=yesterday": (400, "bad_request"),
            "/api/history?plc=press1&tag=temp&from=nan": (400, "bad_request"),
            "/api/history?plc=press1&tag=temp&from=10&to=5": (400, "bad_request"),
            "/api/history?plc=press1&tag=temp&points=3": (400, "bad_request"),
            "/api/history?plc=press1&tag=temp&points=1e3": (400, "bad_request"),
            "/api/history?plc=press1&tag=temp&points=100001": (400, "bad_request"),
        }
        for query, (status, code) in cases.items():
            got, body = await get(console, query)
            assert (got, body["error"]) == (status, code), (query, body)
    async with running_console() as console:
        got, body = await get(console, "/api/history?plc=press1&tag=temp")
        assert got == 404 and body["error"] == "no_history"
        assert "add a [history] table" in body["message"]
