"""``GET /api/history``: one tag's points from the embedded history, for charts and scripts.

```
GET /api/history?plc=P&tag=T[&from=UNIX][&to=UNIX][&points=N]
    -> {"points": [[unix_seconds, value], ...]}
```

``to`` defaults to now, ``from`` to an hour before ``to``, ``points`` to 1000 (4 to 100,000).
Beyond ``points`` the range is cut into buckets and each keeps its minimum and maximum (and its
first gap), so a peak is never averaged away. The first point may be older than ``from``: the
value that held at ``from``. A bad-quality point is ``[t, null]`` (a gap in the line); a
non-finite float is the string ``"NaN"``, ``"Infinity"`` or ``"-Infinity"``. Refusals are
those of the rest of the API: 404 ``no_history`` (no ``[history]`` table), ``unknown_plc``,
``unknown_tag``; 400 ``bad_request`` (a parameter that is not a number, a range that ends
before it starts); 503 ``busy`` (eight queries already running, or the history not open).
"""

from __future__ import annotations

import functools
import json
import math
import time
from typing import Any, Protocol

from aiohttp import web

from plcstack.north.history import History, HistoryBusy
from plcstack.north.web.api import refusal
from plcstack.north.web.state import ConsoleState
from plcstack.output import float32_short, json_safe

__all__ = ["DEFAULT_POINTS", "DEFAULT_SPAN", "MAX_POINTS", "history_routes"]

DEFAULT_POINTS = 1000
MAX_POINTS = 100_000
#: seconds before ``to`` that ``from`` defaults to
DEFAULT_SPAN = 3600.0


_dumps = functools.partial(json.dumps, separators=(",", ":"))


class HistoryConsole(Protocol):
    """What the route needs of the console: its state (names, float32 tags), its history."""

    state: ConsoleState
    history: History | None


class _Bad(ValueError):
    pass


def _number(query: Any, name: str, default: float) -> float:
    text = query.get(name)
    if text is None or text == "":
        return default
    try:
        value = float(text)
    except ValueError:
        raise _Bad(f"{name} must be a Unix time in seconds, not {text[:40]!r}") from None
    if not math.isfinite(value) or abs(value) > 1e11:
        raise _Bad(f"{name} must be a Unix time in seconds, not {text[:40]!r}")
    return value


def history_routes(console: HistoryConsole) -> list[web.RouteDef]:
    state = console.state

    async def history(request: web.Request) -> web.Response:
        store = console.history
        if store is None:
            return refusal(
                "no_history",
                "this gateway keeps no history: add a [history] table to its configuration",
            )
        query = request.query
        plc, tag = query.get("plc", ""), query.get("tag", "")
        if plc not in state.plcs:
            return refusal("unknown_plc", f"no PLC named {plc[:100]!r} here")
        if (plc, tag) not in state.tags:
            return refusal("unknown_tag", f"no tag {tag[:100]!r} of PLC {plc!r} here")
        try:
            end = _number(query, "to", time.time())
            start = _number(query, "from", end - DEFAULT_SPAN)
            if end < start:
                raise _Bad("to must not be before from")
            points_text = query.get("points", str(DEFAULT_POINTS))
            if not points_text.isdigit() or not 4 <= int(points_text) <= MAX_POINTS:
                raise _Bad(f"points must be a whole number from 4 to {MAX_POINTS}")
        except _Bad as exc:
            return refusal("bad_request", str(exc))
        try:
            points = await store.query(plc, tag, start, end, int(points_text))
        except HistoryBusy as exc:
            return refusal("busy", f"{exc}; try again in a moment")
        short = (plc, tag) in state.float32
        rows = [
            [round(t, 3), json_safe(float32_short(v) if short and type(v) is float else v)]
            for t, v in points
        ]
        return web.json_response({"points": rows}, dumps=_dumps)

    return [web.get("/api/history", history)]
