"""The console's two HTML pages: ``/`` (every PLC, every tag) and ``/plc/NAME`` (one PLC).

Rendered on the server with every PLC name, tag name, description, unit, value and error text
passed through :func:`html.escape` (a name holding ``<script>`` is shown as text, never run) and
every name in a link percent-encoded. The pages work as a snapshot without JavaScript; the one
script (``/static/console.js``, no build step, no third-party code) keeps them live from the
server-sent events, writes only through ``textContent``, draws the trend charts (a step line in
an SVG, from the ``data-points`` the server renders and the changes that follow) and sends the
write form as a ``POST`` with the bearer token. The Content-Security-Policy the server sends
allows no inline script at all.
"""

from __future__ import annotations

import datetime
import html
import json
import math
from collections.abc import Iterable
from typing import Any
from urllib.parse import quote

from plcstack.north.web.state import ConsoleState
from plcstack.output import json_safe
from plcstack.poll.config import TagConfig
from plcstack.poll.samples import Sample

__all__ = ["format_time", "format_value", "overview_page", "plc_page"]

_PLC_HEAD = (
    "<tr><th>PLC</th><th>state</th><th>last error</th><th>requests</th><th>errors</th>"
    "<th>reconnects</th><th>p50 ms</th><th>p99 ms</th></tr>"
)
_STAT_CELLS = ("requests", "errors", "reconnects", "p50_ms", "p99_ms")


def esc(text: object) -> str:
    return html.escape(str(text), quote=True)


def format_value(value: Any) -> str:
    """A value as the page shows it (the script formats the same way)."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(json_safe(value))
        text = repr(value)
        return text[:-2] if text.endswith(".0") else text
    if isinstance(value, list | tuple):
        return json.dumps(json_safe(list(value)), separators=(",", ":"))
    return str(value)


def format_time(t: float | None) -> str:
    """UTC ISO 8601 with milliseconds, as JavaScript's ``Date.toISOString``."""
    if t is None:
        return ""
    moment = datetime.datetime.fromtimestamp(t, datetime.UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _document(title: str, body: str, *, scope: str | None, trend_seconds: int) -> str:
    scope_attr = "" if scope is None else f' data-plc="{esc(scope)}"'
    return (
        "<!doctype html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{esc(title)}</title>"
        '<link rel="stylesheet" href="/static/console.css">'
        '<script src="/static/console.js" defer></script></head>'
        f'<body{scope_attr} data-trend-seconds="{trend_seconds}">'
        '<header><a class="home" href="/">plcstack</a>'
        f"<h1>{esc(title)}</h1>"
        '<span id="live" class="live">not live</span></header>\n'
        f"{body}</body></html>\n"
    )


def _plc_rows(rows: Iterable[dict[str, Any]], *, link: bool) -> str:
    out = []
    for r in rows:
        name = esc(r["name"])
        label = f'<a href="/plc/{esc(quote(r["name"], safe=""))}">{name}</a>' if link else name
        up = r["up"]
        state = "unknown" if up is None else ("online" if up else "offline")
        cells = "".join(
            f'<td class="{c} num">{esc("" if r.get(c) is None else r[c])}</td>' for c in _STAT_CELLS
        )
        out.append(
            f'<tr data-plc="{name}"><td>{label}</td><td class="state {state}">{state}</td>'
            f'<td class="last_error">{esc(r["last_error"] or "")}</td>{cells}</tr>'
        )
    return "".join(out)


def _tag_cells(state: ConsoleState, s: Sample | None) -> str:
    if s is None:
        return (
            '<td class="value num"></td><td class="quality"></td>'
            '<td class="source_time"></td><td class="error"></td>'
        )
    quality = esc(s.quality.value)
    return (
        f'<td class="value num">{esc(format_value(state.shown(s)))}</td>'
        f'<td class="quality {quality}">{quality}</td>'
        f'<td class="source_time">{esc(format_time(s.source_time))}</td>'
        f'<td class="error">{esc(s.error or "")}</td>'
    )


def overview_page(
    state: ConsoleState, plc_rows: list[dict[str, Any]], *, trend_seconds: int
) -> str:
    """``/``: every PLC's health and counters, every tag's latest value."""
    tags = []
    for (plc, tag), config in state.tags.items():
        sample = state.latest.get((plc, tag))
        tags.append(
            f'<tr data-plc="{esc(plc)}" data-tag="{esc(tag)}">'
            f'<td><a href="/plc/{esc(quote(plc, safe=""))}">{esc(plc)}</a></td>'
            f'<td title="{esc(_description(config))}">{esc(tag)}</td>'
            f"{_tag_cells(state, sample)}<td>{esc(config.unit or '')}</td></tr>"
        )
    body = (
        f'<h2>PLCs</h2><table id="plcs"><thead>{_PLC_HEAD}</thead><tbody>'
        f"{_plc_rows(plc_rows, link=True)}</tbody></table>\n"
        '<h2>Tags</h2><table id="tags"><thead><tr><th>PLC</th><th>tag</th><th>value</th>'
        "<th>quality</th><th>source time</th><th>error</th><th>unit</th></tr></thead><tbody>"
        + "".join(tags)
        + "</tbody></table>\n"
    )
    return _document("plcstack console", body, scope=None, trend_seconds=trend_seconds)


def plc_page(
    state: ConsoleState,
    plc: str,
    plc_rows: list[dict[str, Any]],
    *,
    trend_seconds: int,
    writes_enabled: bool,
) -> str:
    """``/plc/NAME``: one PLC's statistics, its tags with trend charts, the write forms."""
    config = state.plcs[plc]
    rows = []
    any_writable = False
    for tag in config.tags:
        sample = state.latest.get((plc, tag.name))
        points = [[round(t, 3), v] for t, v in state.trend(plc, tag.name)]
        trend = (
            f'<svg class="trend" viewBox="0 0 300 60" preserveAspectRatio="none" role="img"'
            f' aria-label="trend of {esc(tag.name)}" data-points="{esc(json.dumps(points))}">'
            "</svg>"
        )
        form = ""
        if tag.writable:
            any_writable = True
            form = (
                '<form class="write" method="post" autocomplete="off">'
                f'<input name="value" aria-label="new value of {esc(tag.name)}" required>'
                '<button type="submit">write</button><output></output></form>'
            )
        rows.append(
            f'<tr data-plc="{esc(plc)}" data-tag="{esc(tag.name)}">'
            f"<td>{esc(tag.name)}</td><td>{esc(_description(tag))}</td>"
            f"<td>{esc(tag.address)}</td>{_tag_cells(state, sample)}<td>{esc(tag.unit or '')}</td>"
            f"<td>{trend}</td><td>{form}</td></tr>"
        )
    token = ""
    if any_writable:
        token = (
            '<p class="token"><label>write token <input id="token" type="password"'
            ' autocomplete="off"></label> '
            + (
                "writes go to the PLC through the poller's connection"
                if writes_enabled
                else "writes are off: the console was started without a write token"
            )
            + "</p>"
        )
    body = (
        f'<table id="plcs"><thead>{_PLC_HEAD}</thead><tbody>'
        f"{_plc_rows(plc_rows, link=False)}</tbody></table>\n{token}"
        f'<p class="url">{esc(config.url)}</p>'
        '<table id="tags"><thead><tr><th>tag</th><th>description</th><th>address</th>'
        "<th>value</th><th>quality</th><th>source time</th><th>error</th><th>unit</th>"
        f"<th>trend (last {trend_seconds} s)</th><th>write</th></tr></thead><tbody>"
        + "".join(rows)
        + "</tbody></table>\n"
    )
    return _document(plc, body, scope=plc, trend_seconds=trend_seconds)


def _description(tag: TagConfig) -> str:
    """The tag's description where the config has one."""
    return tag.description or ""
